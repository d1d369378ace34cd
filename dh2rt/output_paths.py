"""The one rule for where a command may write, checked before the command does any work
(``dh2rt capture -o``, ``dh2rt wireshark -o``, ``dh2rt image -o``, ``dh2rt topo --png-dir``):

* ``-`` is standard output, where the command allows it;
* a file must not be a folder (and a folder option must not name a file), its suffix must be
  one the command writes, and it must be writable: tried now, not found out after a run;
* a capture or a key that exists is never overwritten without ``--force`` (a dissector, an
  image or a picture written again is what the command is for);
* a missing folder is created only inside the current one: a path elsewhere names folders
  that exist, so that a typo never makes ``/nonexistent/`` as root.

Every refusal is an :class:`~dh2rt.errors.OutputError` (exit 2) naming the option and the path.
It lives in the core because ``dh2rt image`` is a core command; the tools use it as it is.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

from dh2rt.errors import OutputError

#: What ``-`` stands for in an output option: standard output.
STDOUT = Path("-")
#: Names a capture is written under (pcapng, pcap, python-can's logs) and the first bytes of
#: the binary ones (pcapng's section header, pcap both ways and in ns, BLF).
CAPTURE_SUFFIXES = (".pcapng", ".pcap", ".log", ".blf", ".asc", ".csv", ".trc")
CAPTURE_MAGICS = (
    b"\x0a\x0d\x0d\x0a",
    b"\xd4\xc3\xb2\xa1",
    b"\xa1\xb2\xc3\xd4",
    b"\x4d\x3c\xb2\xa1",
    b"\xa1\xb2\x3c\x4d",
    b"LOGG",
)
#: A key file (``dh2rt keys new``): PEM, or its public half beside it.
KEY_SUFFIXES = (".pem", ".key", ".pub")


def check_output(
    path: Path,
    option: str,
    suffixes: tuple[str, ...] = (),
    *,
    stdout: bool = False,
    force: bool = False,
    folder: bool = False,
) -> Path:
    """``path`` if ``option`` may write it under the rule above (``folder``: a folder that
    the command fills, made here when missing); raises OutputError naming what is wrong."""
    if path == STDOUT:
        if stdout:
            return path
        raise OutputError(f"{option} -: this output cannot go to standard output; name a file")
    try:
        if folder:
            if path.exists() and not path.is_dir():
                raise OutputError(f"{option} {path}: is a file; name a folder")
            _make_folder(path, option, path)
            _try_writing_in(path, option, path)
            return path
        if path.is_dir():
            raise OutputError(f"{option} {path}: is a folder; name a file")
        if suffixes and path.suffix.lower() not in suffixes:
            raise OutputError(
                f"{option} {path}: the file is written as {suffixes[0][1:].upper()}; "
                f"give it a name ending in {' or '.join(suffixes)}"
            )
        if path.exists():
            kind = precious(path)
            if kind and not force:
                raise OutputError(f"{option} {path}: is {kind} that exists; it is not overwritten without --force")
            _try_opening(path, option)
        else:
            _make_folder(path.parent, option, path)
            _try_writing_in(path.parent, option, path)
    except OSError as exc:  # a name too long, a loop of links, a folder not to be read
        raise OutputError(f"{option} {shown_path(path)}: {exc.strerror or exc}") from None
    return path


def precious(path: Path) -> str | None:
    """``"a capture"`` or ``"a key"`` when the existing file ``path`` is one (by its name or
    its first bytes), else None."""
    suffix = path.suffix.lower()
    try:
        with path.open("rb") as fh:
            head = fh.read(16)
    except OSError:
        head = b""
    if suffix in CAPTURE_SUFFIXES or path.name.endswith(".programs.json") or head.startswith(CAPTURE_MAGICS):
        return "a capture"
    if suffix in KEY_SUFFIXES or (head.startswith(b"-----BEGIN") and b"KEY" in head + _first_line(path)):
        return "a key"
    return None


def _first_line(path: Path) -> bytes:
    try:
        with path.open("rb") as fh:
            return fh.readline(80)
    except OSError:
        return b""


def _make_folder(folder: Path, option: str, path: Path) -> None:
    """Make ``folder`` if it is missing and inside the current folder; refuse otherwise."""
    if folder.is_dir():
        return
    if folder.exists():
        raise OutputError(f"{option} {shown_path(path)}: {folder} is not a folder")
    if not folder.resolve().is_relative_to(Path.cwd().resolve()):
        raise OutputError(
            f"{option} {shown_path(path)}: the folder {folder} does not exist, and a folder outside the current one "
            f"is not made unasked: make it first (mkdir -p {folder})"
        )
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(
            f"{option} {shown_path(path)}: cannot make the folder {folder} ({exc.strerror or exc})"
        ) from None


def _try_opening(path: Path, option: str) -> None:
    """Open the existing ``path`` for writing without changing a byte of it."""
    try:
        os.close(os.open(path, os.O_WRONLY))
    except OSError as exc:
        raise OutputError(f"{option} {shown_path(path)}: cannot be written ({exc.strerror or exc})") from None


def _try_writing_in(folder: Path, option: str, path: Path) -> None:
    """Create and remove a file in ``folder``: the one sure test that it takes new files
    (permissions, read-only mounts, /proc)."""
    probe = folder / f".dh2rt-write-test-{os.getpid()}"
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    except FileExistsError:
        return
    except OSError as exc:
        why = exc.strerror or str(exc)
        if exc.errno in (errno.ENOENT, errno.EACCES, errno.EPERM, errno.EROFS):
            why = f"the folder {folder} takes no new files ({why})"
        raise OutputError(f"{option} {shown_path(path)}: cannot be written: {why}") from None
    probe.unlink(missing_ok=True)


def shown_path(path: Path) -> str:
    """``path`` for a message: a name of thousands of characters shown by its ends."""
    text = str(path)
    return text if len(text) <= 120 else f"{text[:60]}...{text[-40:]} ({len(text)} characters)"
