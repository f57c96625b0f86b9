"""Design projects: finding them, ``payload new``, building and reporting on the project
in front of the command (never the package's or this checkout's), and provenance."""

from __future__ import annotations

import hashlib
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
import tomllib
from conftest import DESIGN, ROOT

from payload.cli import main
from payload.project import (
    Project,
    ProjectError,
    default_design_text,
    find_project,
    project_of,
    provenance,
)


def _digest(root: Path) -> dict[str, str]:
    """SHA-256 of every file of a project's design, models and reports."""
    files = [root / "cad" / "design.toml", *sorted((root / "urdf").glob("*"))]
    files += sorted((root / "cad" / "meshes").glob("*.stl"))
    files += sorted((root / "analyses").glob("*.*"))
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


@pytest.fixture(scope="module")
def checkout_before() -> dict[str, str]:
    return _digest(ROOT)


@pytest.fixture(scope="module")
def new_project(tmp_path_factory, checkout_before) -> Path:
    """A project made by ``payload new`` in a temporary folder (built once per module)."""
    root = tmp_path_factory.mktemp("proj") / "variant"
    assert main(["new", str(root)]) == 0
    return root


@pytest.fixture
def outside(tmp_path, monkeypatch) -> Path:
    """Stand in a folder that is in no project, with ``PAYLOAD_PROJECT`` unset."""
    monkeypatch.delenv("PAYLOAD_PROJECT", raising=False)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _set(text: str, table: str, key: str, value: float) -> str:
    """``text`` with ``key = value`` in ``[table]`` (checked by re-parsing)."""
    pattern = rf"(\[{re.escape(table)}\][^\[]*?\n{key}\s*=\s*)[-0-9.eE]+"
    out, n = re.subn(pattern, rf"\g<1>{value!r}", text, count=1)
    assert n == 1
    node = tomllib.loads(out)
    for part in table.split("."):
        node = node[part]
    assert node[key] == value
    return out


# ------------------------------------------------------------------ finding one
def test_find_project_order_explicit_env_cwd(tmp_path, monkeypatch):
    a, b = Project.at(tmp_path / "a"), Project.at(tmp_path / "b")
    for p in (a, b):
        p.design_path.parent.mkdir(parents=True)
        p.design_path.write_text(default_design_text())
    deep = a.root / "x" / "y"
    deep.mkdir(parents=True)
    monkeypatch.delenv("PAYLOAD_PROJECT", raising=False)
    assert find_project(cwd=deep) == a  # upward from the cwd
    monkeypatch.setenv("PAYLOAD_PROJECT", str(b.root))
    assert find_project(cwd=deep) == b  # the variable beats the cwd
    assert find_project(a.root, cwd=deep) == a  # --project beats both
    monkeypatch.setenv("PAYLOAD_PROJECT", str(tmp_path))
    with pytest.raises(ProjectError, match=r"PAYLOAD_PROJECT .*not a design project"):
        find_project(cwd=deep)
    assert project_of(b.design_path) == b
    assert project_of(tmp_path / "loose.toml") is None


def test_outside_any_project_commands_say_so_in_one_line(outside, capsys):
    for argv in (["build", "--check"], ["report", "envelope"], ["summary", "--json"]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "not inside a design project" in err, err
    assert main(["--project", str(outside), "build"]) == 2
    assert "--project" in capsys.readouterr().err


def test_packaged_default_design_is_this_checkouts_design():
    """The wheel's default design and the checkout's cad/design.toml are the same bytes."""
    assert default_design_text().encode() == DESIGN.read_bytes()


# ------------------------------------------------------------------ payload new
def test_new_project_is_built_and_checks_clean(new_project, capsys):
    p = Project.at(new_project)
    assert p.design_path.read_bytes() == DESIGN.read_bytes()
    assert p.urdf.is_file() and p.mjcf.is_file() and any(p.meshes_dir.glob("*.stl"))
    # the same design gives the same models as this checkout's committed ones
    assert p.urdf.read_bytes() == (ROOT / "urdf" / "payload.urdf").read_bytes()
    assert main(["--project", str(new_project), "build", "--check"]) == 0
    assert capsys.readouterr().out.splitlines()[0] == f"project: {p.root}"


def test_new_refuses_a_non_empty_folder_and_copies_from(tmp_path, new_project, capsys):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("mine")
    assert main(["new", str(tmp_path / "full")]) == 2
    assert "not an empty folder" in capsys.readouterr().err
    assert (tmp_path / "full" / "notes.txt").read_text() == "mine"
    variant = Project.at(new_project)
    edited = _set(variant.design_path.read_text(), "rail", "travel", 0.045)
    src = tmp_path / "src"
    assert main(["new", str(src)]) == 0
    Project.at(src).design_path.write_text(edited)
    assert main(["new", str(tmp_path / "copy"), "--from", str(src)]) == 0
    assert Project.at(tmp_path / "copy").design_path.read_text() == edited


def test_new_where_no_folder_can_be_made_is_one_line(tmp_path, capsys):
    """A path below a regular file cannot become a folder (as a read-only or someone
    else's folder cannot): one line naming the folder, exit 2, not a traceback."""
    blocker = tmp_path / "notes.txt"
    blocker.write_text("mine")
    target = blocker / "variant"
    assert main(["new", str(target)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(target) in err and "cannot" in err, err
    assert blocker.read_text() == "mine" and sorted(tmp_path.iterdir()) == [blocker]


def test_new_refuses_a_project_option_it_would_ignore(tmp_path, capsys):
    """``payload new DIR --project P`` (or ``payload --project P new DIR``) made DIR and
    ignored P; the user meant another project's design, which is ``--from``: one line,
    exit 2, nothing made."""
    for argv in (
        ["new", str(tmp_path / "a"), "--project", str(ROOT)],
        ["--project", str(ROOT), "new", str(tmp_path / "a")],
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "use --from PROJECT" in err, err
    assert not (tmp_path / "a").exists()
    # and its help does not offer it (it listed `--project DIR  design project to work on`)
    with pytest.raises(SystemExit):
        main(["new", "--help"])
    shown = capsys.readouterr().out
    assert "--from PROJECT" in shown and "--project" not in shown, shown


# ------------------------------------------------- the project in front of the command
def test_edited_project_is_stale_and_a_long_proximal_fails(
    new_project, tmp_path, monkeypatch, capsys, checkout_before
):
    p = Project.at(tmp_path / "edit")
    assert main(["new", str(p.root), "--from", str(new_project)]) == 0
    capsys.readouterr()
    monkeypatch.delenv("PAYLOAD_PROJECT", raising=False)
    monkeypatch.chdir(p.meshes_dir)  # found from a subfolder, like git
    text = p.design_path.read_text()
    lengths = tomllib.loads(text)["finger"]["lengths"]
    p.design_path.write_text(_set(text, "finger.lengths", "proximal", lengths["proximal"] + 0.150))
    assert main(["build", "--check"]) == 1
    captured = capsys.readouterr()
    assert captured.out.splitlines()[0] == f"project: {p.root}"
    assert "stale: " in captured.err and "urdf/payload.urdf" in captured.err
    assert captured.err.rstrip().endswith("; run `payload build`)")  # the project's own design
    assert main(["build"]) == 0
    assert main(["build", "--check"]) == 0
    capsys.readouterr()
    assert main(["report", "envelope", "--no-search", "--json"]) == 1
    data = json.loads(capsys.readouterr().out)
    assert data["project"] == str(p.root)
    assert data["fits"] is False and data["passed"] is False
    assert (
        data["provenance"]["design_sha256"]
        == hashlib.sha256(p.design_path.read_bytes()).hexdigest()
    )
    written = json.loads((p.analyses_dir / "envelope.json").read_text())
    assert written["fits"] is False
    assert "project" not in written["provenance"]  # no absolute path in project files
    # the protruding part is the longer finger: the report measured this project
    assert any(q["protrusion_mm"] and q["protrusion_mm"] > 100 for q in data["parts"])
    assert _digest(ROOT) == checkout_before  # the package's own design untouched


def test_build_design_f_writes_fs_project(new_project, tmp_path, capsys, checkout_before):
    p = Project.at(tmp_path / "other")
    assert main(["new", str(p.root), "--from", str(new_project)]) == 0
    p.design_path.write_text(_set(p.design_path.read_text(), "rail", "travel", 0.040))
    before = p.urdf.read_bytes()
    # standing in this checkout (PAYLOAD_PROJECT = ROOT), naming the other project's design
    assert main(["build", "--design", str(p.design_path)]) == 0
    assert capsys.readouterr().out.splitlines()[0] == f"project: {p.root}"
    assert p.urdf.read_bytes() != before
    assert 'upper="0.04"' in p.urdf.read_text() or "0.04" in p.urdf.read_text()
    # stale again, checked from here: the hint builds that project's, not this one's
    p.design_path.write_text(_set(p.design_path.read_text(), "rail", "travel", 0.045))
    capsys.readouterr()
    assert main(["build", "--check", "--design", str(p.design_path)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.endswith(f"; run `payload build --design {p.design_path}`)"), err
    assert main(["build", "--design", str(p.design_path)]) == 0
    assert main(["build", "--design", str(p.design_path), "--project", str(ROOT)]) == 2
    assert "belongs to project" in capsys.readouterr().err
    # a design file in no project is checked against the project found as usual
    loose = tmp_path / "loose.toml"
    loose.write_text(p.design_path.read_text())
    assert main(["build", "--check", "--design", str(loose), "--project", str(p.root)]) == 0
    capsys.readouterr()
    assert main(["build", "--check", "--design", str(loose)]) == 1  # this checkout's
    assert capsys.readouterr().out.splitlines()[0] == f"project: {ROOT}"
    assert _digest(ROOT) == checkout_before


def test_build_notes_reports_made_from_another_version_of_the_design(tmp_path, capsys):
    """`build` follows the models only; a report made before a design edit then carried
    the old design's digest while `build --check` said all matched. `build` and `build
    --check` now say which reports were made from another version of the design file
    (their provenance's digest against the file's own, by hashlib), and stop once the
    report is run again."""
    p = Project.at(tmp_path / "p")
    assert main(["new", str(p.root)]) == 0
    assert main(["--project", str(p.root), "report", "envelope", "--no-search"]) == 0
    capsys.readouterr()
    note = "note: analyses/envelope.json made from another version of"

    def made_from_the_file() -> bool:
        made = json.loads((p.analyses_dir / "envelope.json").read_text())
        return made["provenance"]["design_sha256"] == (
            hashlib.sha256(p.design_path.read_bytes()).hexdigest()
        )

    assert made_from_the_file()
    assert main(["--project", str(p.root), "build", "--check"]) == 0
    assert note not in capsys.readouterr().out
    p.design_path.write_text(_set(p.design_path.read_text(), "rail", "travel", 0.045))
    assert not made_from_the_file()
    for argv in (["build"], ["build", "--check"]):
        assert main(["--project", str(p.root), *argv]) == 0
        out = capsys.readouterr().out
        assert f"{note} {p.design_path}: `payload report all`" in out, out
        assert "reach.json" not in out  # never made: nothing to follow
    assert main(["--project", str(p.root), "report", "envelope", "--no-search"]) == 0
    assert made_from_the_file()
    capsys.readouterr()
    assert main(["--project", str(p.root), "build", "--check"]) == 0
    assert note not in capsys.readouterr().out


def test_models_come_from_the_project(new_project, monkeypatch):
    from payload.kinematics import Kinematics
    from payload.retarget.hand import load_hand
    from payload.sim.world import WorldConfig

    p = Project.at(new_project)
    assert load_hand(project=p).urdf == p.urdf
    assert WorldConfig.for_project(p).payload_mjcf == p.mjcf
    monkeypatch.setenv("PAYLOAD_PROJECT", str(p.root))
    assert load_hand().urdf == p.urdf
    assert Kinematics().urdf == p.urdf
    config = WorldConfig()
    assert (config.payload_mjcf, config.design) == (p.mjcf, p.design_path)
    # a config naming one project's design takes that project's MJCF
    assert WorldConfig(design=DESIGN).payload_mjcf == ROOT / "urdf" / "payload.xml"


# ------------------------------------------------------------------ provenance
def test_provenance_of_a_git_checkout_and_of_a_plain_folder(new_project):
    prov = provenance(find_project(ROOT))
    assert prov["design_sha256"] == hashlib.sha256(DESIGN.read_bytes()).hexdigest()
    assert prov["design"] == "cad/design.toml"
    head = subprocess.run(
        ["git", "log", "-1", "--format=%H"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.strip()
    assert prov["git_commit"] == head
    changed = subprocess.run(
        ["git", "diff", "HEAD", "--quiet"], cwd=ROOT, capture_output=True, check=False
    ).returncode
    assert prov["git_dirty"] is (changed != 0)
    from importlib.metadata import version

    assert prov["package_version"] == version("astrobee-payload")
    plain = provenance(Project.at(new_project))
    assert (plain["git_commit"], plain["git_dirty"]) == (None, None)


def test_a_design_the_commit_does_not_hold_is_dirty(new_project, tmp_path):
    """A project made inside another's git work tree (a sweep's points under the ignored
    ``runs/``) or a design file from outside it: the commit is the work tree's, but it
    does not hold the design a result was computed from, so the result is dirty. Before,
    such a point, with its own proximal length, claimed the clean commit of its parent."""

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", "-c", "user.name=t", "-c", "user.email=t@t", *args],
            cwd=repo,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()

    repo = tmp_path / "repo"
    assert main(["new", str(repo), "--from", str(new_project)]) == 0
    (repo / ".gitignore").write_text("runs/\n")
    git("init", "-q")
    git("add", "-A")
    git("commit", "-q", "-m", "a design project")
    head = git("rev-parse", "HEAD")
    tracked = provenance(Project.at(repo))
    assert (tracked["git_commit"], tracked["git_dirty"]) == (head, False)

    point = Project.at(repo / "runs" / "sweep-0001" / "point-000")
    assert main(["new", str(point.root), "--from", str(repo)]) == 0
    text = point.design_path.read_text()
    proximal = tomllib.loads(text)["finger"]["lengths"]["proximal"]
    point.design_path.write_text(_set(text, "finger.lengths", "proximal", proximal + 0.01))
    assert git("status", "--porcelain", "--untracked-files=no") == ""  # the tree is clean
    inner = provenance(point)
    assert (inner["git_commit"], inner["git_dirty"]) == (head, True)
    # the same file once committed is clean again
    git("add", "-f", str(point.design_path))
    git("commit", "-q", "-m", "the point's design")
    assert provenance(point)["git_dirty"] is False
    # a design file from outside the work tree, reported on in this project
    outside = provenance(Project.at(repo), Path(new_project) / "cad" / "design.toml")
    assert outside["git_dirty"] is True
    assert provenance(Project.at(repo))["git_dirty"] is False


def test_summary_names_the_project_first_and_in_json(new_project, capsys):
    assert main(["--project", str(new_project), "summary"]) == 0
    assert capsys.readouterr().out.splitlines()[0] == f"project: {Path(new_project).resolve()}"
    assert main(["summary", "--project", str(new_project), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["project"] == str(Path(new_project).resolve())


def test_cli_subprocess_in_a_project_folder(new_project):
    """The console entry point finds the project from its working directory."""
    env = {k: v for k, v in __import__("os").environ.items() if k != "PAYLOAD_PROJECT"}
    out = subprocess.run(
        [sys.executable, "-m", "payload.cli", "build", "--check"],
        cwd=Path(new_project) / "cad",
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[0] == f"project: {Path(new_project).resolve()}"


def test_a_design_in_no_project_is_reported_into_its_out_from_anywhere(outside, capsys):
    """``report envelope --design F --out DIR`` with F in no project, from a folder in no
    project: the report needs none (no models on disk to follow), so it is written into
    DIR with F's provenance (it failed, "not inside a design project"); without ``--out``
    one line says to give one."""
    loose = outside / "variant.toml"
    loose.write_bytes(DESIGN.read_bytes())
    out = outside / "report"
    # named as typed, relative: the provenance names it absolute, traceable from anywhere
    argv = ["report", "envelope", "--design", "variant.toml", "--no-search", "--json"]
    assert main([*argv, "--out", str(out)]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["project"] is None and data["provenance"]["design"] == str(loose.resolve())
    assert data["provenance"]["design_sha256"] == hashlib.sha256(DESIGN.read_bytes()).hexdigest()
    assert json.loads((out / "envelope.json").read_text())["passed"] == data["passed"]
    assert sorted(p.name for p in outside.iterdir()) == ["report", "variant.toml"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--design variant.toml: in no design project" in err, err
    assert "give --out DIR" in err
    # a --project that is wrong is said, not passed over because --out was given
    typo = outside / "typo"
    assert main(["--project", str(typo), *argv, "--out", str(outside / "r2")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"--project {typo}: no such folder" in err, err
