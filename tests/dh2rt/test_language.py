"""The text parser and the Python API build the same AST; images are stable."""

from __future__ import annotations

from pathlib import Path

import pytest

from dh2rt.compiler import compile_program, load_image
from dh2rt.errors import ImageError
from dh2rt.lang import api, ast
from dh2rt.lang.api import DOF1, ClockCycle, H, LocalTimer, T, emit, hormone, keep_alive, program, receptor
from dh2rt.lang.image import from_image, image_hash, to_image
from dh2rt.lang.parser import parse, parse_file


def caterpillar_by_api() -> ast.Program:
    def head(name: str, when: object, angle: int, phase: str) -> ast.Receptor:
        return receptor(
            name, (T == "T1") & (LocalTimer == when), [DOF1(angle), emit("X", phase, via="back"), keep_alive()]
        )

    def body(name: str, got: str, angle: int, phase: str) -> ast.Receptor:
        return receptor(
            name,
            (T == ["T16", "T2"]) & (("X", got) == H),  # type: ignore[operator]  # reflected ==: tuple's is bool to mypy
            [DOF1(angle), emit("X", phase, via="back"), keep_alive()],
        )

    return program(
        "caterpillar",
        consts={"ClockCycle": 40},
        hormones=[hormone("X", phase=["A", "B", "C", "D"])],
        receptors=[
            head("head_a", 0, +45, "A"),
            head("head_b", ClockCycle / 4, -45, "B"),
            head("head_c", ClockCycle / 2, -45, "C"),
            head("head_d", 3 * ClockCycle / 4, +45, "D"),
            body("body_a", "A", -45, "B"),
            body("body_b", "B", -45, "C"),
            body("body_c", "C", +45, "D"),
            body("body_d", "D", +45, "A"),
        ],
    )


def test_api_and_text_build_the_same_program(examples: Path) -> None:
    text = parse_file(examples / "caterpillar.dh2")
    built = caterpillar_by_api()
    assert built == text
    assert to_image(built) == to_image(text)


def test_table_one_has_eight_receptors_and_four_hormones(examples: Path) -> None:
    p = parse_file(examples / "caterpillar.dh2")
    assert len(p.receptors) == 8
    x = p.hormones[0]
    assert x.name == "X" and x.params[0].domain == ("A", "B", "C", "D")
    cp = compile_program(p)
    assert cp.clock_cycle == 40
    timers = sorted(k for d in cp.index.by_timer for k in d)
    assert set(timers) == {0, 10, 20, 30}  # the quarters of ClockCycle


def test_api_covers_fig5_constructs() -> None:
    p = program(
        "fig5",
        consts={"ClockCycle": 8},
        variables={"waiting": 0},
        hormones=[hormone("RCT"), hormone("TAR")],
        receptors=[
            receptor("a", (T == ["T5", "T6"]) & (H == "RCT"), [api.periodic("RCT", via="all", every=4)]),
            receptor("b", (T == "T2") & (H == "RCT").as_("p"), [emit("TAR", via=api.reply("p")), api.terminate()]),
            receptor(
                "c", (api.V.waiting > 0) & ~(api.R.b == 1), [api.set_var("waiting", api.V.waiting - 1), api.create("b")]
            ),
            receptor(
                "d",
                (H != "TAR") | (api.S.light >= 3),
                [api.stop("RCT"), api.inhibit("a"), api.activate("a")],
                status="passive",
            ),
        ],
        sensors=["light"],
    )
    text = parse(
        """
        program fig5
        const ClockCycle = 8
        var waiting = 0
        sensor light
        hormone RCT
        hormone TAR
        receptor a when T == {T6, T5} and H == RCT { periodic RCT via all every 4 }
        receptor b when T == T2 and H == RCT as p { emit TAR via p-1; terminate self }
        receptor c when V.waiting > 0 and not R.b == 1 { V.waiting = V.waiting - 1; create b }
        receptor d passive when H != TAR or S.light >= 3 { stop RCT; inhibit a; activate a }
        """
    )
    assert p == text
    compile_program(p)


def test_image_round_trip_and_hash_stability(examples: Path) -> None:
    cp = compile_program(parse_file(examples / "legs_to_snake.dh2"))
    again = load_image(cp.image)
    assert again.image == cp.image and again.hash == cp.hash
    assert image_hash(cp.image) == cp.hash and len(cp.hash) == 64
    # the hash does not depend on where the file is or on whitespace and comments
    src = (examples / "caterpillar.dh2").read_text()
    moved = parse("# moved\n\n" + src.replace("    ", "\t"), "/elsewhere/x.dh2")
    assert to_image(moved) == to_image(parse_file(examples / "caterpillar.dh2"))


@pytest.mark.parametrize(
    "blob",
    [
        b"",
        b"garbage",
        b"DH2IMG1\n{not json",
        b'DH2IMG1\n{"":"Nope"}',
        b'DH2IMG1\n{"":"Program","bogus":1}',
        b"DH2IMG1\n[1]",
    ],
)
def test_corrupt_images_raise_image_error(blob: bytes) -> None:
    with pytest.raises(ImageError):
        from_image(blob)
