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
