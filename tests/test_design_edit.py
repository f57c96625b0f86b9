"""Editing a design file's text in place (``payload.design.edit.set_in_text``): the key
set, every other value and line kept. Checked by parsing with ``tomllib`` (a TOML parser
the editor does not use) against the file before."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from payload.cli import main
from payload.design.edit import set_in_text

DESIGN = Path(__file__).resolve().parents[1] / "cad" / "design.toml"


def _leaves(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(_leaves(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _stowed_line(text: str) -> str:
    """The design's ``[stowed]`` ``finger = [...]`` line as committed, whole."""
    table = text[text.index("\n[stowed]") :]
    return re.search(r"^finger\s*=.*\n", table, re.M).group(0)


STOWED = _stowed_line(DESIGN.read_text())
_A, _B, _C, _D = (repr(v) for v in tomllib.loads(DESIGN.read_text())["stowed"]["finger"])
LAYOUTS = {  # the design's own four values, laid out as a designer might
    "as committed": STOWED,
    "no comment": f"finger = [{_A}, {_B}, {_C}, {_D}]\n",
    "no blank before the comment": f"finger = [{_A}, {_B}, {_C}, {_D}]# found\n",
    "over several lines": f"finger = [\n  {_A}, {_B},  # A, B\n  {_C}, {_D},\n]  # found\n",
    "tabs": f"finger\t=\t[{_A}, {_B}, {_C}, {_D}]\t# found\n",
}


@pytest.mark.parametrize("layout", list(LAYOUTS), ids=list(LAYOUTS))
@pytest.mark.parametrize("comment", [None, "written by a test"])
@pytest.mark.parametrize("newline", ["\n", "\r\n"], ids=["LF", "CRLF"])
def test_the_stowed_finger_set_in_any_layout_keeps_the_rest(layout, comment, newline) -> None:
    """``--write-stowed``'s edit: the finger posture set whether its line has a comment or
    not and however its array is laid out; every other value parses as before and every
    line outside the value is the same text (a line without a comment lost its line end,
    running the next key into the new comment)."""
    text = DESIGN.read_text()
    assert STOWED in text
    text = text.replace(STOWED, LAYOUTS[layout]).replace("\n", newline)
    before = _leaves(tomllib.loads(text))
    out = set_in_text(text, "stowed.finger", [1.5, -0.25, 1.25, 1.75], comment)
    after = _leaves(tomllib.loads(out))
    assert after.pop("stowed.finger") == [1.5, -0.25, 1.25, 1.75]
    before.pop("stowed.finger")
    assert after == before
    edited = [ln for ln in out.splitlines(keepends=True) if re.match(r"finger\s*=\s*\[1.5", ln)]
    assert len(edited) == 1 and edited[0].endswith(newline)
    if comment is not None:
        assert edited[0].rstrip("\r\n").endswith(f"  # {comment}")
    # every line outside the value's is the same text, in the same order
    head, _, tail = text.partition(LAYOUTS[layout].replace("\n", newline))
    assert out == head + edited[0] + tail


def test_every_number_of_the_design_is_set_alone() -> None:
    """What a sweep does: each numeric leaf of the design set on its own, nothing else
    changed."""
    text = DESIGN.read_text()
    before = _leaves(tomllib.loads(text))
    numbers = {k: v for k, v in before.items() if isinstance(v, float)}
    assert len(numbers) > 20
    for key, value in numbers.items():
        after = _leaves(tomllib.loads(set_in_text(text, key, value * 1.5 + 1.0)))
        assert after == {**before, key: value * 1.5 + 1.0}, key


def test_write_stowed_keeps_a_design_without_the_comment_valid(tmp_path) -> None:
    """``report envelope --search --write-stowed`` on a project whose ``finger`` line has
    no comment (it wrote ``...  # written by ...rail = 0.0`` and the design no longer
    loaded)."""
    root = tmp_path / "p"
    assert main(["new", str(root)]) == 0
    design = root / "cad" / "design.toml"
    design.write_text(design.read_text().replace(STOWED, LAYOUTS["no comment"]))
    argv = ["--project", str(root), "report", "envelope", "--write-stowed", "--json"]
    assert main(argv) in (0, 1)  # the verdict's exit; the design must stay valid
    stowed = tomllib.loads(design.read_text())["stowed"]
    assert set(stowed) == {"finger", "rail", "stage"} and len(stowed["finger"]) == 4


@pytest.mark.parametrize("newline", ["\n", "\r\n"], ids=["LF", "CRLF"])
def test_a_key_added_after_a_nested_array_lands_in_its_table(newline) -> None:
    """A key the table lacks is added at the table's end: the lines of another key's
    value over several lines (``[0.5],`` items) are not read as table headers, and the
    added line ends as the file's lines do."""
    text = "[stowed]\nfinger = [\n  [0.5],  # one\n  [1.0],\n]\nrail = 0.0\n[home]\nx = 1\n"
    text = text.replace("\n", newline)
    out = set_in_text(text, "stowed.stage", 0.25)
    assert tomllib.loads(out) == {
        "stowed": {"finger": [[0.5], [1.0]], "rail": 0.0, "stage": 0.25},
        "home": {"x": 1},
    }
    assert out == text.replace(f"rail = 0.0{newline}", f"rail = 0.0{newline}stage = 0.25{newline}")
    added = set_in_text(text, "extra.k", 1.5)  # a table the file lacks, at its end
    assert tomllib.loads(added)["extra"] == {"k": 1.5}
    assert added.startswith(text) and added.count(newline) == added.count("\n")
