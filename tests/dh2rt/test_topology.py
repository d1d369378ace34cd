"""Built-in topologies, TOML files, the CONRO profile as data, and their errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from dh2rt.errors import TopologyError
from dh2rt.profile import CONRO, Profile
from dh2rt.topology import parse_spec


def test_conro_profile_has_32_local_topologies_and_the_papers_aliases() -> None:
    assert sum(len(t.statuses) for t in CONRO.types) == 32
    f, b, left, right = (CONRO.connector_index(c) for c in ("front", "back", "left", "right"))
    assert CONRO.type_of((0, f, 0, 0)).alias == 1 and CONRO.type_of((0, 0, 0, 0)).name == "head"
    assert CONRO.type_of((b, 0, 0, 0)).alias == 2
    assert CONRO.type_of((b, f, 0, 0)).alias == 16
    assert CONRO.type_of((left, 0, 0, 0)).alias == 5 and CONRO.type_of((right, 0, 0, 0)).alias == 6
    assert CONRO.type_by_name("T16") is CONRO.type_by_name("body")
    assert CONRO.type_of((left, f, 0, 0)).name == "t_lf00"  # systematic names for the rest
    with pytest.raises(TopologyError, match="not legal"):
        CONRO.type_of((f, 0, 0, 0))  # female to female


def test_profile_from_data_for_another_robot() -> None:
    p = Profile.from_dict(
        {
            "name": "pair",
            "connectors": {"a": "female", "b": "male"},
            "types": [{"name": "end", "alias": 1, "statuses": [["0", "a"]]}],
        }
    )
    assert [t.name for t in p.types] == ["end", "t_00", "t_b0", "t_ba"]
    with pytest.raises(TopologyError, match="unknown connector"):
        Profile.from_dict({"connectors": {"a": "female"}, "types": [{"name": "x", "statuses": [["zz"]]}]})


@pytest.mark.parametrize(
    ("spec", "size", "links"),
    [
        ("snake:1", 1, 0),
        ("snake:8", 8, 7),
        ("tripod", 4, 3),
        ("quadruped", 6, 5),
        ("hexapod", 9, 8),
        ("octopod", 12, 11),
        ("dragon", 11, 10),
        ("t-shape", 8, 7),
        ("ring:6", 6, 6),
    ],
)
def test_builtins(spec: str, size: int, links: int) -> None:
    t = parse_spec(spec)
    assert (t.size, len(t.links)) == (size, links)


@pytest.mark.parametrize("spec", ["snake", "snake:x", "snake:0", "blob", "ring:2", "octopod:3"])
def test_bad_specs(spec: str) -> None:
    with pytest.raises(TopologyError):
        parse_spec(spec)


def test_toml_topology(tmp_path: Path) -> None:
    f = tmp_path / "y.toml"
    f.write_text('modules = ["a", "b", "c"]\nlinks = ["a.back <-> b.front", "a.left <-> c.front"]\n')
    t = parse_spec(str(f))
    assert t.names == ("a", "b", "c") and len(t.links) == 2


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('modules = 2\nlinks = ["0.back <-> 1.bak"]', "links[0]: unknown connector 'bak'"),
        ('modules = 2\nlinks = ["0.back -> 1.front"]', "links[0]: expected"),
        ('modules = 2\nlinks = ["0.back <-> 7.front"]', "links[0]: no module '7'"),
        ('modules = 2\nlinks = ["0.back <-> 1.left"]', "joins two male connectors"),
        ('modules = 3\nlinks = ["0.back <-> 1.front", "0.back <-> 2.front"]', "docked twice"),
        ("modules = true", "field 'modules'"),
        ("modules = [", "y.toml"),
    ],
)
def test_toml_errors_name_file_and_field(tmp_path: Path, text: str, message: str) -> None:
    f = tmp_path / "y.toml"
    f.write_text(text)
    with pytest.raises(TopologyError) as info:
        parse_spec(str(f))
    assert message in str(info.value) and str(f) in str(info.value)
