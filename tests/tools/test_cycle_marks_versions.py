"""The cycle marks file's versions: version 2 adds unlink marks; version 1 files (none) are
still read; a version this dh2rt does not know is refused naming the file and line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dh2rt.errors import CaptureError
from tools.capture_cycles import FORMAT, LinkMark, UnlinkMark, line, link_mark_json, marks_path, read_marks

ENDS = ((3, 2), (4, 1))


def write_marks(capture: Path, version: int, *marks: dict[str, object]) -> None:
    text = json.dumps({"format": FORMAT, "version": version}) + "\n"
    marks_path(capture).write_text(text + "".join(line(m, 100.0 + i) for i, m in enumerate(marks)), encoding="utf-8")


def test_a_link_docked_then_undocked_reads_back_as_a_link_and_an_unlink_mark(tmp_path: Path) -> None:
    capture = tmp_path / "robot.pcapng"
    write_marks(capture, 2, link_mark_json(3, ENDS), link_mark_json(3, ENDS, docked=False))
    assert list(read_marks(capture)) == [LinkMark(100.0, 3, ENDS), UnlinkMark(101.0, 3, ENDS)]


def test_a_version_1_file_is_read(tmp_path: Path) -> None:
    capture = tmp_path / "old.pcapng"
    write_marks(capture, 1, link_mark_json(0, ENDS))
    assert list(read_marks(capture)) == [LinkMark(100.0, 0, ENDS)]


def test_a_version_this_dh2rt_does_not_know_is_refused(tmp_path: Path) -> None:
    capture = tmp_path / "new.pcapng"
    write_marks(capture, 3, link_mark_json(0, ENDS))
    with pytest.raises(CaptureError, match=r"new\.pcapng\.cycles\.jsonl:1: .*version 3, this dh2rt reads 1, 2"):
        list(read_marks(capture))


def test_a_mark_of_an_unknown_kind_is_refused_naming_its_line(tmp_path: Path) -> None:
    capture = tmp_path / "odd.pcapng"
    write_marks(capture, 2, link_mark_json(0, ENDS), {"kind": "dock", "link": 0})
    with pytest.raises(CaptureError, match=r"odd\.pcapng\.cycles\.jsonl:3: not a cycle mark .*'dock'"):
        list(read_marks(capture))
