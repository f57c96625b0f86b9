"""Result folders: no command writes over a recording, into a file, or among another
command's results; ``--force`` replaces only its own kind; an interrupted ``trial --force``
keeps the trial it was to replace.

Each case checks the exit code, that stderr is one line naming the problem, and that the
files already there are byte for byte what they were."""

from __future__ import annotations

from pathlib import Path

import pytest

from payload.cli import main


def _snapshot(root: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _one_line(capsys: pytest.CaptureFixture[str], *words: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and all(w in err[0] for w in words), err
    return err[0]


@pytest.mark.parametrize(
    "argv",
    [
        ["trial", "--max-time", "1"],
        ["trials", "run", "--n", "1", "--workers", "0"],
        ["bench", "trial", "--seconds", "1"],
        ["report", "envelope"],
        ["report", "reach", "--samples", "1000"],
        ["sweep", "--set", "rail.travel=0.04,0.05"],
        ["export", "lerobot", "analyses"],
    ],
    ids=lambda argv: " ".join(argv[:2]),
)
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
        ["sweep", "--set", "rail.travel=0.04,0.05", "--out"],
        ["export", "lerobot", "analyses", "--force", "--out"],
        ["teleop", "serve", "--port", "0", "--record"],
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
    capsys.readouterr()
    first = table.read_text()
    assert main(["trials", "compare", *runs, "--out", str(table)]) == 2  # exists: --force
    _one_line(capsys, str(table))
    assert main(["trials", "compare", *reversed(runs), "--out", str(table), "--force"]) == 0
    capsys.readouterr()
    assert table.read_text() != first  # B and A swapped: the new comparison
    recording = tmp_path / "a" / "trial-0000" / "log.mcap"
    recording.write_bytes(b"\x89MCAP0\r\nrecorded")
    before = _snapshot(tmp_path)
    for out, words in ((recording, ("not a comparison",)), (tmp_path / "a", ("is a folder",))):
        assert main(["trials", "compare", *runs, "--out", str(out), "--force"]) == 2
        _one_line(capsys, str(out), *words)
    assert _snapshot(tmp_path) == before


def test_review_static_replaces_only_an_earlier_page(tmp_path, capsys) -> None:
    """``review --static F`` never writes over a file that is not an HTML page (a
    recording, say): one line, exit 2, the file untouched."""
    recording = tmp_path / "log.mcap"
    recording.write_bytes(b"\x89MCAP0\r\nrecorded")
    assert main(["review", "--static", str(recording), "--reach-samples", "0"]) == 2
    _one_line(capsys, str(recording), "not an HTML page")
    assert recording.read_bytes() == b"\x89MCAP0\r\nrecorded"


def test_trial_force_replaces_neither_a_live_session_nor_a_campaigns_trial(
    tmp_path, capsys
) -> None:
    """``trial --force`` replaces a trial only: a folder with a live session's or a
    hardware run's ``hands.jsonl``, or a campaign's ``trial-NNNN``, is refused."""
    live = tmp_path / "live"
    live.mkdir()
    for name, data in (("log.mcap", b"rec"), ("hands.jsonl", b"{}\n"), ("metrics.json", b"{}")):
        (live / name).write_bytes(data)
    camp = tmp_path / "campaign"
    (camp / "trial-0000").mkdir(parents=True)
    (camp / "summary.json").write_text("{}")
    (camp / "trial-0000" / "log.mcap").write_bytes(b"the campaign's")
    before = _snapshot(tmp_path)
    assert main(["trial", "--max-time", "1", "--out", str(live), "--force"]) == 2
    _one_line(capsys, "hands.jsonl", "replaces only a trial")
    assert main(["trial", "--max-time", "1", "--out", str(camp / "trial-0000"), "--force"]) == 2
    _one_line(capsys, "a campaign's trial", "summary.json")
    assert _snapshot(tmp_path) == before


def _old_trial(out: Path) -> dict[Path, bytes]:
    out.mkdir()
    for name in ("log.mcap", "metrics.json", "fig_ctb_body_frame.png", "fig_route.png"):
        (out / name).write_bytes(f"old {name}".encode())
    return _snapshot(out)


def test_an_interrupted_or_failed_trial_force_keeps_the_old_trial(tmp_path, monkeypatch) -> None:
    """``run_trial(force=True)``: the old trial is replaced only by a new recording (a
    finished trial, or one its own error aborted), its rescorings removed with it; an
    interrupt (Ctrl-C) or an error before anything was recorded keeps the old trial whole
    and leaves no staging folder."""
    from payload.trials import runner

    def interrupted(seed, source, out, **kwargs):
        (out / "log.mcap").write_bytes(b"half a trial")
        raise KeyboardInterrupt

    def failed_early(seed, source, out, **kwargs):
        raise RuntimeError("no world")

    def aborted(seed, source, out, **kwargs):
        (out / "log.mcap").write_bytes(b"an aborted trial")
        raise runner.TrialAborted("aborted at t = 1 s")

    for name, fake, raised in (
        ("interrupted", interrupted, KeyboardInterrupt),
        ("failed", failed_early, RuntimeError),
    ):
        out = tmp_path / name
        old = _old_trial(out)
        monkeypatch.setattr(runner, "_run_trial", fake)
        with pytest.raises(raised):
            runner.run_trial(0, out_dir=out, force=True, max_time=1.0)
        assert _snapshot(out) == old and sorted(p.name for p in out.iterdir()) == sorted(
            p.name for p in old
        )
    out = tmp_path / "aborted"
    _old_trial(out)
    tag = "contact-min0s-gap0.1s"  # the old trial's rescoring, and a file of the user's
    for name in (f"metrics.{tag}.json", f"fig_route.{tag}.png", "metrics.mine.json"):
        (out / name).write_text("old")
    monkeypatch.setattr(runner, "_run_trial", aborted)
    with pytest.raises(runner.TrialAborted):
        runner.run_trial(0, out_dir=out, force=True, max_time=1.0)
    # the aborted run's record, without the rescorings of the trial it replaced
    assert sorted(p.name for p in out.iterdir()) == ["log.mcap", "metrics.mine.json"]
    assert (out / "log.mcap").read_bytes() == b"an aborted trial"


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
