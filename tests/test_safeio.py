"""Writing results without losing or silently replacing any (payload.safeio)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from payload.safeio import (
    OverwriteError,
    check_new,
    new_folder,
    replace_file,
    replacing,
    write_unless_changed,
)


def test_replace_file_goes_through_a_temporary_file_and_a_rename(tmp_path: Path) -> None:
    target = tmp_path / "a.json"
    target.write_text("old")
    inode = os.stat(target).st_ino
    replace_file(target, "new")
    assert target.read_text() == "new" and os.stat(target).st_ino != inode
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json"]  # nothing left over


def test_a_failed_write_leaves_the_old_file(tmp_path: Path) -> None:
    target = tmp_path / "fig.png"
    target.write_bytes(b"old figure")
    with pytest.raises(RuntimeError), replacing(target) as tmp:
        assert tmp.suffix == ".png" and tmp.parent == tmp_path
        tmp.write_bytes(b"half a fig")
        raise RuntimeError("plotting failed")
    assert target.read_bytes() == b"old figure"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig.png"]


def test_write_unless_changed(tmp_path: Path) -> None:
    target = tmp_path / "summary.md"
    assert write_unless_changed(target, "one") is True
    mtime = target.stat().st_mtime_ns
    assert write_unless_changed(target, "one") is False and target.stat().st_mtime_ns == mtime
    with pytest.raises(OverwriteError, match="--force"):
        write_unless_changed(target, "two")
    assert target.read_text() == "one"
    assert write_unless_changed(target, "two", force=True) is True
    assert target.read_text() == "two"


def test_check_new_and_new_folder(tmp_path: Path) -> None:
    (tmp_path / "log.mcap").write_bytes(b"x")
    check_new([tmp_path / "other"])
    check_new([tmp_path / "log.mcap"], force=True)
    with pytest.raises(OverwriteError, match="already holds a trial"):
        check_new([tmp_path / "log.mcap"], what="trial")
    names = [new_folder(tmp_path / "runs", "trial-0000").name for _ in range(3)]
    assert names == ["trial-0000", "trial-0000-2", "trial-0000-3"]


# -- file modes: every writer honours the umask (issue 30) -----------------------------
@pytest.fixture(params=[0o022, 0o027])
def umask(request):
    """Run the test under this umask; the expected file mode is 0o666 less it."""
    old = os.umask(request.param)
    yield request.param
    os.umask(old)


def _modes(paths: list[Path]) -> dict[str, str]:
    return {p.name: oct(p.stat().st_mode & 0o777) for p in paths}


def _expect(paths: list[Path], umask: int) -> None:
    # what a plain open() gives under this umask, found by creating a file the plain way
    probe = paths[0].parent / ".probe"
    probe.write_bytes(b"")
    want = oct(probe.stat().st_mode & 0o777)
    probe.unlink()
    assert want == oct(0o666 & ~umask)
    assert _modes(paths) == {p.name: want for p in paths}


def test_replace_file_and_replacing_honour_the_umask(tmp_path: Path, umask: int) -> None:
    replace_file(tmp_path / "a.json", "{}")
    with replacing(tmp_path / "b.png") as tmp:
        tmp.write_bytes(b"png")
    write_unless_changed(tmp_path / "c.md", "x")
    _expect([tmp_path / "a.json", tmp_path / "b.png", tmp_path / "c.md"], umask)


def test_a_reports_files_honour_the_umask(tmp_path: Path, umask: int) -> None:
    from payload.envelope.writer import _write_report

    out = tmp_path / "analyses"
    _write_report(
        out, "envelope", "# r\n", {"a": 1, "seconds": 2.0}, lambda p: p.write_bytes(b"x"), False
    )
    _expect(sorted(out.iterdir()), umask)


def test_a_trials_files_honour_the_umask(tmp_path: Path, umask: int) -> None:
    from test_trials import fixture_synthetic_trial

    fixture_synthetic_trial(5, tmp_path / "t")
    files = sorted((tmp_path / "t").iterdir())
    assert {p.name for p in files} >= {"log.mcap", "metrics.json", "fig_route.png"}
    _expect(files, umask)


def test_a_campaign_summary_honours_the_umask(tmp_path: Path, umask: int) -> None:
    from test_trials import fixture_synthetic_trial

    from payload.trials.campaign import run_campaign
    from payload.trials.summary import write_summary

    results = run_campaign(fixture_synthetic_trial, [4, 6], tmp_path, workers=0, progress=False)
    write_summary(results, tmp_path)
    files = sorted(p for p in tmp_path.iterdir() if p.is_file())
    assert {"summary.md", "summary.json"} <= {p.name for p in files}
    _expect(files, umask)


def test_the_generated_models_honour_the_umask(tmp_path: Path, umask: int, design) -> None:
    from payload.design.build import write

    result = write(design, tmp_path)
    _expect([tmp_path / rel for rel in result.files], umask)


def test_no_trial_file_is_written_in_place() -> None:
    """A trial's scored files (``metrics.json``, written again by the runner, the live
    session and the hardware run after scoring) are replaced through a temporary file
    and a rename: no module writes one with ``Path.write_text``/``write_bytes``, which
    truncate the file first (a crash there leaves half a ``metrics.json``)."""
    import ast

    from payload.folders import SCORED

    root = Path(__file__).resolve().parents[1]
    names = {"METRICS", "CTB_FIGURE", "ROUTE_FIGURE", "SCORED", *SCORED}
    found = []
    for package in ("payload", "firmware_interface"):
        for path in sorted((root / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if not (
                    isinstance(node, ast.Call)
                    and isinstance(node.func, ast.Attribute)
                    and node.func.attr in ("write_text", "write_bytes")
                ):
                    continue
                target = ast.unparse(node.func.value)
                if any(name in target for name in names):
                    found.append(f"{path.relative_to(root)}:{node.lineno}: {target}")
    assert found == []
