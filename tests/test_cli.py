"""The command line's entry points: ``payload --version`` and ``python -m payload``."""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import version

from payload.cli import main


def test_version_matches_installed_distribution(capsys) -> None:
    try:
        main(["--version"])
    except SystemExit as exc:
        assert exc.code == 0
    out = capsys.readouterr().out.strip()
    assert out == f"payload {version('astrobee-payload')}"


def test_python_dash_m_runs_the_same_cli() -> None:
    res = subprocess.run(
        [sys.executable, "-m", "payload", "--version"], capture_output=True, text=True, check=False
    )
    assert res.returncode == 0
    assert res.stdout.strip() == f"payload {version('astrobee-payload')}"
    bad = subprocess.run(
        [sys.executable, "-m", "payload", "no-such-command"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert bad.returncode == 2
    assert "invalid choice" in bad.stderr
