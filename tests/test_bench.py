"""payload.trials.bench: the worker import figure of ``payload bench trial``."""

from __future__ import annotations

import math
import subprocess

import pytest

from payload.trials import bench


def test_worker_import_seconds_imports_this_payload_in_a_fresh_process(
    monkeypatch, tmp_path
) -> None:
    """The figure comes from a fresh interpreter that imports what it names (a missing
    module fails it) from this process's package, wherever the command runs from."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("PYTHONPATH", raising=False)
    seconds = bench.worker_import_seconds()
    assert math.isfinite(seconds) and seconds > 0.0
    monkeypatch.setattr(bench, "WORKER_MODULES", ("payload.trials.no_such_module",))
    with pytest.raises(subprocess.CalledProcessError):
        bench.worker_import_seconds()
