"""Result folders: no command writes over a recording, into a file, or among another
command's results; ``--force`` replaces only its own kind; an interrupted ``trial --force``
keeps the trial it was to replace.

Each case checks the exit code, that stderr is one line naming the problem, and that the
files already there are byte for byte what they were."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from payload.cli import main


def _snapshot(root: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _one_line(capsys: pytest.CaptureFixture[str], *words: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and all(w in err[0] for w in words), err
    return err[0]


OUT_COMMANDS = [
    ["trial", "--max-time", "1"],
    ["trials", "run", "--n", "1", "--workers", "0"],
    ["bench", "trial", "--seconds", "1"],
    ["report", "envelope"],
    ["report", "reach", "--samples", "1000"],
    ["sweep", "--set", "rail.travel=0.04,0.05"],
    ["export", "lerobot", "analyses"],
]
"""Commands that write their results into an ``--out`` folder (short settings)."""


@pytest.mark.parametrize("argv", OUT_COMMANDS, ids=lambda argv: " ".join(argv[:2]))
def test_an_out_that_is_a_file_is_one_line_and_exit_2(argv, tmp_path, capsys) -> None:
    """``--out`` naming a regular file: one line naming it, exit 2, the file untouched
    (the commands used to fail with a traceback, most after their work)."""
    afile = tmp_path / "notes.txt"
    afile.write_text("mine")
    assert main([*argv, "--out", str(afile)]) == 2
    _one_line(capsys, str(afile), "not a folder")
    assert afile.read_text() == "mine" and sorted(tmp_path.iterdir()) == [afile]


@pytest.mark.parametrize(
    "argv",
    [
        ["trial", "--max-time", "1"],
        ["trials", "run", "--n", "1", "--workers", "0"],
        ["report", "envelope"],
        ["report", "reach", "--samples", "1000"],
        ["sweep", "--set", "rail.travel=0.04,0.05"],
        ["export", "lerobot", "analyses"],
    ],
    ids=lambda argv: " ".join(argv[:2]),
)
def test_an_out_that_cannot_be_made_is_one_line_before_the_work(argv, capsys) -> None:
    """``--out`` where no folder can be made (``/proc`` takes none, even from root): one
    line naming it and why, exit 2, before any work (the reports failed with a traceback
    after their analysis)."""
    where = "/proc/payload-no-such/results"
    assert main([*argv, "--out", where]) == 2
    _one_line(capsys, where, "cannot make the folder")


UNWRITABLE = "/sys"
"""A folder that exists and takes no new file, even from root (sysfs)."""


@pytest.mark.parametrize(
    "argv",
    [
        ["trial", "--max-time", "1", "--out", UNWRITABLE],
        ["trials", "run", "--n", "1", "--workers", "0", "--out", UNWRITABLE],
        ["bench", "trial", "--seconds", "1", "--out", UNWRITABLE],
        ["report", "envelope", "--out", UNWRITABLE],
        ["sweep", "--set", "rail.travel=0.04,0.05", "--out", UNWRITABLE],
        ["export", "lerobot", "analyses", "--out", UNWRITABLE],
        ["hw", "run", "--emulator", "--replay", __file__, "--out", UNWRITABLE],
        [
            "trials",
            "compare",
            "analyses/campaign/single",
            "analyses/campaign/single",
            "--out",
            f"{UNWRITABLE}/c.md",
        ],
        ["review", "--static", f"{UNWRITABLE}/review.html", "--reach-samples", "0"],
        ["teleop", "serve", "--port", "0", "--seconds", "1", "--record", UNWRITABLE],
    ],
    ids=lambda argv: " ".join(argv[:2]),
)
def test_an_out_that_takes_no_file_is_one_line_before_the_work(argv, capsys) -> None:
    """An ``--out`` folder (or a file's folder) that exists but takes no file (a
    read-only mount, another user's folder): one line naming it and why, exit 2, before
    any work (they failed with a traceback, a trial after its session, a hardware run
    after the servos' bring-up)."""
    import tempfile

    with pytest.raises(OSError):  # the premise: nothing can be written there
        tempfile.mkstemp(dir=UNWRITABLE)
    assert main(argv) == 2
    _one_line(capsys, UNWRITABLE, "cannot write in")


def test_an_out_checked_for_being_makeable_is_left_as_it_was(tmp_path) -> None:
    """The check makes the missing folders and removes them again: nothing is left, and
    a folder that was there stays with what it holds."""
    from payload.cliutil import out_folder

    deep = tmp_path / "a" / "b" / "c"
    assert out_folder(str(deep)) == deep and sorted(tmp_path.iterdir()) == []
    (tmp_path / "kept").mkdir()
    (tmp_path / "kept" / "notes.txt").write_text("mine")
    assert out_folder(str(tmp_path / "kept" / "new")) == tmp_path / "kept" / "new"
    assert sorted(p.name for p in (tmp_path / "kept").iterdir()) == ["notes.txt"]


@pytest.mark.parametrize(
    "argv",
    [
        ["sweep", "--set", "rail.travel=0.04,0.05", "--out"],
        ["export", "lerobot", "analyses", "--force", "--out"],
        ["teleop", "serve", "--port", "0", "--seconds", "1", "--record"],
    ],
    ids=lambda argv: " ".join(argv[:2]),
)
@pytest.mark.parametrize("held", ["metrics.json", "hands.jsonl", "summary.md"])
def test_no_command_writes_among_a_trials_or_a_campaigns_files(argv, held, tmp_path, capsys):
    """A sweep, a dataset or a live session never goes into a folder holding a trial's or a
    campaign's files, ``--force`` or not: one line naming the file, exit 2."""
    folder = tmp_path / "results"
    folder.mkdir()
    (folder / held).write_text("recorded")
    before = _snapshot(tmp_path)
    assert main([*argv, str(folder)]) == 2
    _one_line(capsys, held)
    assert _snapshot(tmp_path) == before


def test_trials_compare_force_replaces_only_an_earlier_comparison(tmp_path, capsys) -> None:
    """``trials compare --out F --force`` replaces an earlier comparison; a recording, a
    summary or a folder given as F is refused with one line, exit 2."""
    runs = []
    for name in ("a", "b"):
        trial = tmp_path / name / "trial-0000"
        trial.mkdir(parents=True)
        (trial / "metrics.json").write_text('{"success": true, "rms_mm": 30.0}')
        runs.append(str(tmp_path / name))
    table = tmp_path / "compare.md"
    assert main(["trials", "compare", *runs, "--out", str(table)]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == f"wrote {table}"  # said where it went
    first = table.read_text()
    assert main(["trials", "compare", *runs, "--out", str(table)]) == 2  # exists: --force
    _one_line(capsys, str(table))
    assert main(["trials", "compare", *reversed(runs), "--out", str(table), "--force"]) == 0
    capsys.readouterr()
    assert table.read_text() != first  # B and A swapped: the new comparison
    recording = tmp_path / "a" / "trial-0000" / "log.mcap"
    recording.write_bytes(b"\x89MCAP0\r\nrecorded")
    before = _snapshot(tmp_path)
    folders = [(str(tmp_path / "a"), ("is a folder",)), (f"{tmp_path}/new/", ("is a folder",))]
    for out, words in [(str(recording), ("not a comparison",)), *folders]:
        assert main(["trials", "compare", *runs, "--out", out, "--force"]) == 2  # new/: made
        _one_line(capsys, out, *words)  # by nothing, not a file named new either
    assert _snapshot(tmp_path) == before


def test_review_static_replaces_only_an_earlier_page(tmp_path, capsys) -> None:
    """``review --static F`` never writes over a file that is not an HTML page (a
    recording, say): one line, exit 2, the file untouched."""
    recording = tmp_path / "log.mcap"
    recording.write_bytes(b"\x89MCAP0\r\nrecorded")
    assert main(["review", "--static", str(recording), "--reach-samples", "0"]) == 2
    _one_line(capsys, str(recording), "not an HTML page")
    assert recording.read_bytes() == b"\x89MCAP0\r\nrecorded"


def test_trial_force_replaces_a_trial_not_a_live_session(tmp_path, capsys, monkeypatch) -> None:
    """``trial --force`` replaces a trial only: a folder with a live session's or a
    hardware run's ``hands.jsonl`` beside a current recording is refused; an older
    trial's (schema 1 wrote its hands there; converted, its backup is beside it) is
    replaced, its ``hands.jsonl`` with it."""
    from payload.trials import runner

    live = tmp_path / "live"
    live.mkdir()
    for name, data in (("log.mcap", b"rec"), ("hands.jsonl", b"{}\n"), ("metrics.json", b"{}")):
        (live / name).write_bytes(data)
    before = _snapshot(tmp_path)
    assert main(["trial", "--max-time", "1", "--out", str(live), "--force"]) == 2
    _one_line(capsys, "hands.jsonl", "replaces only a trial")
    assert _snapshot(tmp_path) == before
    older = tmp_path / "older"
    _old_trial(older)
    (older / "hands.jsonl").write_text("{}\n")
    (older / "log.v1.mcap").write_bytes(b"the schema-1 original")
    monkeypatch.setattr(runner, "_run_trial", _finished)
    runner.run_trial(0, out_dir=older, force=True, max_time=1.0)
    assert sorted(p.name for p in older.iterdir()) == ["log.mcap", "log.v1.mcap"]


def _finished(seed, source, out, **kwargs):
    """A trial that ran (its recording a stand-in: the runner only moves it)."""
    (out / "log.mcap").write_bytes(b"new")
    return {"seed": seed}


def test_rerunning_a_campaigns_trial_says_its_summary_no_longer_matches(
    tmp_path, capsys, monkeypatch
) -> None:
    """``trial --out camp/trial-NNNN --force`` reruns one trial of a campaign (a crashed
    one, say) and says, in one warning line, that the campaign's summary needs
    ``trials summarize --force``."""
    from payload.trials import runner

    camp = tmp_path / "campaign"
    camp.mkdir()
    _old_trial(camp / "trial-0003")
    (camp / "summary.json").write_text("{}")
    monkeypatch.setattr(runner, "_run_trial", _finished)
    argv = ["trial", "--seed", "3", "--out", str(camp / "trial-0003"), "--force", "--json"]
    assert main(argv) == 0
    warning = _one_line(capsys, "summary no longer matches", "trials summarize")
    assert str(camp) in warning
    assert (camp / "trial-0003" / "log.mcap").read_bytes() == b"new"


def _old_trial(out: Path) -> dict[Path, bytes]:
    out.mkdir()
    for name in ("log.mcap", "metrics.json", "fig_ctb_body_frame.png", "fig_route.png"):
        (out / name).write_bytes(f"old {name}".encode())
    return _snapshot(out)


def _recording(path: Path, steps: int) -> None:
    """A recorder's file with ``steps`` steps (none: opened and closed, as by a trial that
    failed before its first step)."""

    from payload.trials.recorder import TrialRecorder, random_step

    rng = np.random.default_rng(1)
    with TrialRecorder(path) as rec:
        rec.write_meta({"seed": 0})
        for k in range(steps):
            rec.write(random_step(rng, 0.02 * k))


def test_an_interrupted_or_failed_trial_force_keeps_the_old_trial(tmp_path, monkeypatch) -> None:
    """``run_trial(force=True)``: the old trial is replaced only by a new recording that
    holds a step (a finished trial, or one its own error aborted: its message then names
    the recording where it now is), its rescorings removed with it; an interrupt (Ctrl-C),
    an error before the recorder opened, or one before the first step keeps the old trial
    whole and leaves no staging folder."""
    from payload.trials import runner
    from payload.trials.reading import read_recording

    def interrupted(seed, source, out, **kwargs):
        _recording(out / "log.mcap", 3)
        raise KeyboardInterrupt

    def failed_early(seed, source, out, **kwargs):
        raise RuntimeError("no world")

    def failed_at_first_step(seed, source, out, **kwargs):
        _recording(out / "log.mcap", 0)
        raise runner.TrialAborted(f"trial 0 aborted at t = 0.00 s; kept: {out / 'log.mcap'}")

    def aborted(seed, source, out, **kwargs):
        _recording(out / "log.mcap", 3)
        raise runner.TrialAborted(f"trial 0 aborted at t = 0.04 s; kept: {out / 'log.mcap'}")

    for name, fake, raised in (
        ("interrupted", interrupted, KeyboardInterrupt),
        ("failed", failed_early, RuntimeError),
        ("first step", failed_at_first_step, runner.TrialAborted),
    ):
        out = tmp_path / name
        old = _old_trial(out)
        monkeypatch.setattr(runner, "_run_trial", fake)
        with pytest.raises(raised) as caught:
            runner.run_trial(0, out_dir=out, force=True, max_time=1.0)
        assert _snapshot(out) == old, name
        assert sorted(out.iterdir()) == sorted(old), name
        if raised is KeyboardInterrupt:  # the CLI's "payload: interrupted" line says so
            assert caught.value.__notes__ == [
                f"nothing recorded: the trial already in {out} is kept whole"
            ]
    # into a folder holding no trial, the note does not speak of one
    monkeypatch.setattr(runner, "_run_trial", interrupted)
    with pytest.raises(KeyboardInterrupt) as caught:
        runner.run_trial(0, out_dir=tmp_path / "fresh", force=True, max_time=1.0)
    assert caught.value.__notes__ == [
        "nothing recorded (an interrupted --force run keeps no partial recording)"
    ]
    out = tmp_path / "aborted"
    _old_trial(out)
    tag = "contact-min0s-gap0.1s"  # the old trial's rescoring, and a file of the user's
    for name in (f"metrics.{tag}.json", f"fig_route.{tag}.png", "metrics.contact-notes.json"):
        (out / name).write_text("old")
    monkeypatch.setattr(runner, "_run_trial", aborted)
    with pytest.raises(runner.TrialAborted) as caught:
        runner.run_trial(0, out_dir=out, force=True, max_time=1.0)
    assert str(caught.value).endswith(f"kept: {out / 'log.mcap'}")  # not the staging folder
    # the aborted run's record, without the rescorings of the trial it replaced
    assert sorted(p.name for p in out.iterdir()) == ["log.mcap", "metrics.contact-notes.json"]
    assert len(read_recording(out / "log.mcap")) == 3


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["new"], ("a file, not a folder",)),
        (["trials", "summarize"], ("a file, not a campaign folder",)),
    ],
    ids=lambda v: " ".join(v) if isinstance(v, list) else "",
)
def test_a_file_where_a_folder_is_expected_is_named_so(argv, words, tmp_path, capsys) -> None:
    """A regular file given where a folder is expected is called a file (it was "not an
    empty folder" and "no such campaign folder"), one line, exit 2, the file untouched."""
    afile = tmp_path / "notes.txt"
    afile.write_text("mine")
    assert main([*argv, str(afile)]) == 2
    _one_line(capsys, str(afile), *words)
    assert afile.read_text() == "mine"


def test_bench_trial_never_writes_over_a_trial(tmp_path, capsys) -> None:
    """``bench trial --out`` a folder holding a trial's files: one line naming them (the
    bench has no ``--force``, so the runner's "pass --force" would mislead), exit 2."""
    trial = tmp_path / "trial"
    _old_trial(trial)
    before = _snapshot(tmp_path)
    assert main(["bench", "trial", "--seconds", "1", "--out", str(trial)]) == 2
    assert "--force" not in _one_line(capsys, "already holds log.mcap")
    assert _snapshot(tmp_path) == before


def test_a_results_folder_made_for_a_failing_command_is_removed_again(tmp_path) -> None:
    """``cliutil.results_folder``: a folder the command made (the numbered default, for an
    ``--out`` left out or empty, or a new ``--out``) is removed when the command fails
    before writing in it, and kept once written in; a folder that was there stays."""
    from payload.cliutil import results_folder
    from payload.design.cli import new_project

    project, _ = new_project(tmp_path / "p")

    def fails(value: object) -> Path:
        with pytest.raises(RuntimeError), results_folder(value, project, "demo") as out:
            made = out
            out.mkdir(parents=True, exist_ok=True)  # what the command makes of an --out
            raise RuntimeError("the command failed")
        return made

    for value in (None, ""):  # left out, and given empty: the numbered default
        made = fails(value)
        assert made.parent == project.runs_dir and not made.exists()
    new = tmp_path / "new" / "out"
    assert fails(str(new)) == new and not new.exists()
    there = tmp_path / "there"
    there.mkdir()
    assert fails(str(there)) == there and there.is_dir()
    with pytest.raises(RuntimeError), results_folder(None, project, "demo") as out:
        (out / "summary.md").write_text("written")
        raise RuntimeError("failed after writing")
    assert (out / "summary.md").read_text() == "written"
    with results_folder("", project, "demo") as ok:  # a command that succeeds keeps it
        pass
    assert ok.is_dir() and ok.parent == project.runs_dir


def test_a_sweep_that_fails_before_its_first_point_leaves_no_folder(
    tmp_path, monkeypatch, capsys
) -> None:
    """A sweep whose points cannot run (here: the scheduler does not answer, raised where
    ``run_points`` raises it) removes the numbered folder it made: the failing sweeps of a
    wrong ``--scheduler`` left an empty ``runs/sweep-NNNN`` each."""
    from payload.design.cli import new_project
    from payload.sweep import run
    from payload.sweep.grid import SweepError

    project, _ = new_project(tmp_path / "p")

    def unreachable(*args: object, **kwargs: object) -> list:
        raise SweepError("cannot reach Dask scheduler tcp://127.0.0.1:1: timed out")

    monkeypatch.setattr(run, "run_points", unreachable)
    argv = ["--project", str(project.root), "sweep", "--set", "rail.travel=0.04,0.05"]
    assert main(argv) == 2
    _one_line(capsys, "cannot reach Dask scheduler")
    assert not project.runs_dir.exists() or list(project.runs_dir.iterdir()) == []


def test_a_sweep_never_writes_into_a_design_project(tmp_path, capsys) -> None:
    """``sweep --out`` naming a design project's folder (its own, say): one line, exit 2,
    nothing written (its points, projects themselves, went among the project's files)."""
    from payload.design.cli import new_project

    project, _ = new_project(tmp_path / "p")
    before = _snapshot(project.root)
    argv = ["--project", str(project.root), "sweep", "--set", "rail.travel=0.04,0.05"]
    assert main([*argv, "--out", str(project.root)]) == 2
    _one_line(capsys, "already holds cad/design.toml")
    assert _snapshot(project.root) == before


def test_an_interrupted_recording_says_it_was_kept(tmp_path) -> None:
    """Ctrl-C or SIGTERM inside a recording: the file is kept, marked aborted, and the
    interrupt carries a note naming it (printed by the CLI after "payload: interrupted"
    or "payload: terminated (SIGTERM)"); other errors get no such note (their own
    messages name the recording)."""
    from payload.errors import Terminated
    from payload.trials.reading import read_recording, unfinished_reason
    from payload.trials.recorder import TrialRecorder, random_step

    rng = np.random.default_rng(2)
    path = tmp_path / "log.mcap"
    with pytest.raises(Terminated) as caught, TrialRecorder(path) as rec:
        rec.write(random_step(rng, 0.0))
        raise Terminated(15)
    assert caught.value.__notes__ == [f"recording kept, marked aborted (not scored): {path}"]
    kept = read_recording(path)
    assert len(kept) == 1 and unfinished_reason(kept.meta, kept.complete).startswith("aborted")
    other = tmp_path / "other.mcap"
    with pytest.raises(RuntimeError) as failed, TrialRecorder(other) as rec:
        rec.write(random_step(rng, 0.0))
        raise RuntimeError("a bug")
    assert not getattr(failed.value, "__notes__", None)


def _project_with_stale_models(tmp_path: Path) -> Path:
    """A new project whose design's distal link was then made 2 mm shorter (its own value
    less 2 mm, written as a designer would): its models no longer match it."""
    from payload.design import load_design, stale_files
    from payload.design.edit import set_in_text

    root = tmp_path / "p"
    assert main(["new", str(root)]) == 0
    design = root / "cad" / "design.toml"
    distal = load_design(design).finger.lengths.distal
    design.write_text(set_in_text(design.read_text(), "finger.lengths.distal", distal - 0.002))
    assert stale_files(load_design(design), root)  # the premise: the models are stale
    return root


def test_models_or_reports_that_cannot_be_written_are_one_line_and_nothing_written(
    tmp_path, capsys
) -> None:
    """A project whose ``urdf/`` or ``analyses/`` takes no file (here a link to sysfs,
    which refuses even root; a read-only mount alike): ``build`` and ``report envelope``
    say so in one line, exit 2, before writing anything (they failed with a traceback,
    the build after rewriting the meshes, the report after its analysis)."""
    import shutil

    root = _project_with_stale_models(tmp_path)
    meshes = _snapshot(root / "cad" / "meshes")
    shutil.rmtree(root / "urdf")
    (root / "urdf").symlink_to(UNWRITABLE)
    capsys.readouterr()
    assert main(["--project", str(root), "build"]) == 2
    _one_line(capsys, f"{root / 'urdf'}: cannot write the generated models there", "nothing")
    assert _snapshot(root / "cad" / "meshes") == meshes
    (root / "urdf").unlink()
    # models to be made in folders that do not exist yet, under one that takes none: said
    # of that one, before any folder is made (a traceback from mkdir before)
    assert main(["build", "--root", f"{UNWRITABLE}/payload-models"]) == 2
    _one_line(capsys, f"{UNWRITABLE}: cannot write the generated models there")
    assert main(["--project", str(root), "build"]) == 0  # the models follow the design
    shutil.rmtree(root / "analyses", ignore_errors=True)
    (root / "analyses").symlink_to(UNWRITABLE)
    capsys.readouterr()
    assert main(["--project", str(root), "report", "envelope", "--no-search"]) == 2
    _one_line(capsys, f"{root / 'analyses'}: cannot write the report there", "--out DIR")


@pytest.mark.parametrize("command", ["envelope", "reach"])
def test_a_bad_bay_size_writes_nothing_not_even_the_models(command, tmp_path, capsys) -> None:
    """A report's bad ``--bay-size`` is refused before the stale models are rebuilt (the
    models were rebuilt, then the error said; "nothing written" held only for the
    report)."""
    root = _project_with_stale_models(tmp_path)
    before = _snapshot(root)
    capsys.readouterr()
    argv = ["--project", str(root), "report", command, "--bay-size", "0.2", "0.1", "-0.1"]
    assert main(argv) == 2
    _one_line(capsys, "bay")
    assert _snapshot(root) == before


@pytest.mark.parametrize("where", ["root", "cad"])
@pytest.mark.parametrize(
    "argv",
    # (a sweep refuses a project's folder as holding cad/design.toml, said its own way)
    [
        *(a for a in OUT_COMMANDS if a[0] != "sweep"),
        ["hw", "run", "--emulator", "--replay", __file__],
    ],
    ids=lambda argv: " ".join(argv[:2]),
)
def test_no_command_writes_its_results_among_a_projects_own_files(argv, where, tmp_path, capsys):
    """An ``--out`` naming a design project's folder or its ``cad/`` (beside its
    ``design.toml``): one line, exit 2, nothing written (``bench trial --out proj/cad``
    wrote a trial beside the design)."""
    root = tmp_path / "p"
    assert main(["new", str(root)]) == 0
    out = root if where == "root" else root / "cad"
    before = _snapshot(root)
    capsys.readouterr()
    assert main([*argv, "--out", str(out)]) == 2
    _one_line(capsys, f"--out {out}: is a design project's", "folder of their own")
    assert _snapshot(root) == before


def test_a_live_sessions_record_folder_is_checked_before_the_server_starts(
    tmp_path, capsys
) -> None:
    """``teleop serve --record`` under a file (``review.html/x``) or in a sweep's folder
    started the server, and the first the operator heard was a traceback after their
    calibration (``NotADirectoryError``): one line, exit 2, nothing served or written."""
    page = tmp_path / "review.html"
    page.write_text("<html></html>")
    sweep = tmp_path / "sweep-0001"
    sweep.mkdir()
    (sweep / "sweep.json").write_text("{}")
    before = _snapshot(tmp_path)
    for record, words in (
        (page / "x", (f"{page} is a file",)),
        (sweep, ("already holds sweep.json",)),
    ):
        argv = ["teleop", "serve", "--port", "0", "--seconds", "1", "--record", str(record)]
        assert main(argv) == 2
        _one_line(capsys, f"--record {record}", *words)
    assert _snapshot(tmp_path) == before


@pytest.mark.parametrize(
    ("argv", "held"),
    [
        (["trial", "--max-time", "1", "--out"], "envelope.json"),
        (["trial", "--max-time", "1", "--out"], "summary.json"),
        (["trial", "--max-time", "1", "--out"], "sweep.md"),
        (["trials", "run", "--n", "1", "--workers", "0", "--out"], "metrics.json"),
        (["trials", "run", "--n", "1", "--workers", "0", "--out"], "reach.json"),
        (["report", "envelope", "--out"], "log.mcap"),
        (["report", "reach", "--samples", "1000", "--out"], "summary.md"),
        (["report", "envelope", "--out"], "sweep.json"),
    ],
    ids=lambda v: v if isinstance(v, str) else " ".join(v[:2]),
)
def test_no_command_writes_among_another_kind_of_results(argv, held, tmp_path, capsys):
    """A trial into the reports' folder (``payload trial --out analyses``), a report into a
    trial's or a campaign's: each wrote its files beside the others'. One line naming what
    the folder holds, exit 2, nothing written."""
    folder = tmp_path / "results"
    folder.mkdir()
    (folder / held).write_text("recorded")
    before = _snapshot(tmp_path)
    assert main([*argv, str(folder)]) == 2
    _one_line(capsys, f"already holds {held}")
    assert _snapshot(tmp_path) == before
