"""The workbench installs as a wheel: built from this checkout, installed (not editable)
into a fresh venv, it makes, builds and analyses a project in a temporary folder."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest
from conftest import ROOT

pytestmark = pytest.mark.slow


def _run(cmd: list[str], cwd: Path, env: dict[str, str], timeout: float = 900) -> str:
    out = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, f"{' '.join(cmd)} -> {out.returncode}\n{out.stdout}\n{out.stderr}"
    return out.stdout


def _fresh_venv(venv: Path, wheel: Path, env: dict[str, str]) -> tuple[Path, Path]:
    """A new venv with the wheel installed (not editable); its python and ``payload``.

    By default the dependencies are this test environment's, reached through a ``.pth``
    line after the new venv's own site-packages (a plain path: the editable install's
    hooks in this environment are not run), so only the package itself comes from the
    wheel. ``PAYLOAD_WHEEL_TEST_DEPS=install`` installs every dependency into the venv
    instead (from pip's cache and the local wheel folders; minutes on 2 cores).
    """
    # no pip of its own (ensurepip's 3 to 4 s): this environment's pip installs into it
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], venv.parent, env)
    py = venv / "bin" / "python"
    pip = [sys.executable, "-m", "pip", "--python", str(py), "install", "-q"]
    if os.environ.get("PAYLOAD_WHEEL_TEST_DEPS") == "install":
        _run([*pip, str(wheel)], venv.parent, env, 3600)
    else:
        site = Path(
            _run(
                [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                venv.parent,
                env,
            ).strip()
        )
        ours = sorted({sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]})
        # first on the path (.pth files run in name order), then this environment's other
        # .pth hooks (cmeel's puts Pinocchio on the path), never the editable install's
        (site / "aa_test_dependencies.pth").write_text("\n".join(ours) + "\n")
        for folder in ours:
            for pth in Path(folder).glob("*.pth"):
                if not pth.name.startswith("__editable__") and not (site / pth.name).exists():
                    (site / pth.name).write_text(pth.read_text())
        _run([*pip, "--no-deps", "--ignore-installed", str(wheel)], venv.parent, env)
    return py, venv / "bin" / "payload"


def test_wheel_in_a_fresh_venv_runs_a_project(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("PAYLOAD_PROJECT", "PYTHONPATH")}
    # the suite's PAYLOAD_CACHE_DIR (conftest): compiled solvers and calibrations are keyed
    # by content, so the new project (the default design) reuses them; compiling from an
    # empty cache is tested in test_retarget.py
    assert "PAYLOAD_CACHE_DIR" in env
    dist = tmp_path / "dist"
    _run(
        [sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "-q", "-w", str(dist)],
        tmp_path,
        env,
    )
    (wheel,) = dist.glob("astrobee_payload-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert {"payload/data/design.toml", "payload/retarget/hands/payload.toml"} <= set(names)
    assert not any(n.startswith(("urdf/", "cad/", "analyses/", "tests/")) for n in names)
    venv = tmp_path / "venv"
    py, payload = _fresh_venv(venv, wheel, env)
    work = tmp_path / "work"
    work.mkdir()
    where = _run([str(py), "-c", "import payload; print(payload.__file__)"], work, env)
    assert Path(where.strip()).is_relative_to(venv), where  # not this checkout

    _run([str(payload), "new", "variant"], work, env)
    proj = work / "variant"
    assert (proj / "urdf" / "payload.xml").is_file()
    out = _run([str(payload), "build"], proj, env)
    assert out.splitlines()[0] == f"project: {proj.resolve()}"
    _run([str(payload), "build", "--check"], proj / "cad", env)
    env_json = json.loads(_run([str(payload), "report", "envelope", "--json"], proj, env))
    assert env_json["project"] == str(proj.resolve()) and env_json["passed"] is True
    assert env_json["provenance"]["git_commit"] is None
    reach = json.loads(
        _run([str(payload), "report", "reach", "--samples", "2000", "--json"], proj, env)
    )
    assert reach["pairs"]["L"]["span_max_mm"] > 0
    assert (proj / "analyses" / "envelope.json").is_file()
    assert (proj / "analyses" / "reach.png").is_file()
    bench = json.loads(
        _run([str(payload), "bench", "retarget", "--steps", "20", "--json"], proj, env)
    )
    assert bench["project"] == str(proj.resolve()) and bench["steps"] == 20
    trial = json.loads(
        _run([str(payload), "trial", "--seed", "0", "--max-time", "20", "--json"], proj, env)
    )
    assert trial["project"] == str(proj.resolve())
    assert trial["provenance"]["design"] == "cad/design.toml"
    assert (proj / "runs" / "trial-0000" / "log.mcap").is_file()
