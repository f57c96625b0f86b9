"""``payload trials summarize`` of a campaign holding a trial that did not finish: a
recording cut short (its process killed: the file never closed) or marked aborted (an
error, Ctrl-C) is a failed row that says so, never a scored trial; and rescoring options
that are not numbers are bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from test_trials import fixture_synthetic_trial

from payload.cli import main
from payload.schema import CONTROL_DT, ENDED_BY_CAP
from payload.trials.reading import read_recording
from payload.trials.recorder import TrialRecorder, random_step


def _campaign(root: Path, seeds: list[int]) -> Path:
    for seed in seeds:
        fixture_synthetic_trial(seed, root / f"trial-{seed:04d}")
    return root


def test_a_recording_cut_short_is_not_scored_as_a_trial(tmp_path: Path, capsys) -> None:
    """A trial killed after its last step but before its file was closed: every step is
    readable and would score as a success, but the summary counts it as a failure, names
    it, and takes the medians over the finished trials only."""
    camp = _campaign(tmp_path / "camp", [1, 2, 3])
    torn = camp / "trial-0003"
    log = torn / "log.mcap"
    whole = read_recording(log)
    data = log.read_bytes()
    for name in ("metrics.json", "fig_ctb_body_frame.png", "fig_route.png"):
        (torn / name).unlink()  # as a killed run leaves its folder
    log.write_bytes(data[: len(data) - 40])  # the footer lost: the file was never closed
    cut = read_recording(log)
    assert not cut.complete and len(cut) == len(whole)  # every step is still there

    assert main(["trials", "summarize", str(camp), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    finished = [json.loads((camp / f"trial-{s:04d}/metrics.json").read_text()) for s in (1, 2)]
    assert all(m["success"] for m in finished)
    assert (out["n"], out["success"], out["errors"]) == (3, 2, 1)
    row = out["trials"][2]
    assert row["seed"] == 3 and not row["success"] and "cut short" in row["error"]
    for key in ("duration_s", "rms_mm", "peak_mm", "contact_s"):
        values = [m[key] for m in finished]
        assert out[key]["median"] == pytest.approx(float(np.median(values)), abs=0)
        assert (out[key]["min"], out[key]["max"], out[key]["count"]) == (
            min(values),
            max(values),
            2,
        )
    assert not (torn / "metrics.json").exists()  # nothing scored into the torn trial
    text = (camp / "summary.md").read_text()
    assert "- seed 3: log.mcap: cut short (never closed" in text
    assert "| 3 | error |" in text


def test_an_aborted_recording_is_not_scored_as_a_trial(tmp_path: Path, capsys) -> None:
    """A run interrupted by Ctrl-C: its recorder marks the file aborted, the runner
    leaves no metrics.json; the summary names it instead of scoring it."""
    camp = _campaign(tmp_path / "camp", [1, 2])
    src = read_recording(camp / "trial-0002" / "log.mcap")
    shutil.rmtree(camp / "trial-0002")
    path = camp / "trial-0002" / "log.mcap"
    with pytest.raises(KeyboardInterrupt), TrialRecorder(path) as rec:
        rec.write_meta({"seed": 2})
        for k in range(120):  # the steps of the fixture trial, up to an interrupt
            rec.write(src.step(k))
        raise KeyboardInterrupt
    assert read_recording(path).meta["aborted"].startswith("KeyboardInterrupt")

    assert main(["trials", "summarize", str(camp), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["n"], out["success"], out["errors"]) == (2, 1, 1)
    assert "aborted (KeyboardInterrupt)" in out["trials"][1]["error"]
    one = json.loads((camp / "trial-0001/metrics.json").read_text())
    assert out["duration_s"]["median"] == one["duration_s"]
    assert not (camp / "trial-0002" / "metrics.json").exists()
    # a metrics.json an earlier summarize scored into it (it does not say "aborted"; the
    # recording's metadata does): still an error row, its figures out of the medians
    stale = {**one, "seed": 2, "duration_s": one["duration_s"] + 50.0, "success": True}
    (camp / "trial-0002" / "metrics.json").write_text(json.dumps(stale))
    assert main(["trials", "summarize", str(camp), "--json", "--force"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["success"], out["errors"]) == (1, 1)
    assert "aborted (KeyboardInterrupt)" in out["trials"][1]["error"]
    assert out["duration_s"]["median"] == one["duration_s"]


def test_a_recording_marked_aborted_by_the_runner_alone_is_unfinished_everywhere(
    tmp_path: Path,
) -> None:
    """A closed file whose only mark is the runner's ``aborted_by`` (the recorder's own
    ``aborted`` note missing): not a success, an error row, left out of an export."""
    from payload.trials.lerobot import export_lerobot
    from payload.trials.metrics import compute_metrics, recorded_definition
    from payload.trials.summary import load_trial_results

    camp = _campaign(tmp_path / "camp", [1, 2])
    src = read_recording(camp / "trial-0002" / "log.mcap")
    assert compute_metrics(src, "node2", *recorded_definition(src)).success
    shutil.rmtree(camp / "trial-0002")
    path = camp / "trial-0002" / "log.mcap"
    with TrialRecorder(path) as rec:
        rec.write_meta(src.meta)
        for k in range(len(src)):
            rec.write(src.step(k))
        rec.write_meta({"aborted_by": "SimError: unstable", "aborted_at_s": 5.9})
    marked = read_recording(path)
    assert "aborted" not in marked.meta and marked.complete
    assert not compute_metrics(marked, "node2", *recorded_definition(marked)).success
    rows = load_trial_results(camp)
    assert "aborted (SimError: unstable)" in rows[1]["error"]
    info = export_lerobot([camp], tmp_path / "ds")
    assert info["episodes"] == 1 and info["left_out"][0]["source"] == str(path)


@pytest.mark.parametrize("option", ["--min-contact-s", "--max-gap-s"])
@pytest.mark.parametrize("value", ["nan", "inf"])
def test_summarize_refuses_a_contact_definition_that_is_not_a_number(
    tmp_path: Path, capsys, option: str, value: str
) -> None:
    camp = _campaign(tmp_path / "camp", [1])
    before = sorted(p.name for p in camp.iterdir())
    assert main(["trials", "summarize", str(camp), option, value]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{option} must be a number >= 0, got {value}" in err[0], err
    assert sorted(p.name for p in camp.iterdir()) == before  # no summary written


def test_summarize_of_a_trials_own_folder_says_so(tmp_path: Path, capsys) -> None:
    """A trial's folder given where a campaign's is wanted is named as such (one line,
    exit 2); an empty folder still says it holds no trial-* folders."""
    trial = tmp_path / "trial-0001"
    fixture_synthetic_trial(1, trial)
    assert main(["trials", "summarize", str(trial)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "a trial's folder, not a campaign's" in err[0], err
    (tmp_path / "empty").mkdir()
    assert main(["trials", "summarize", str(tmp_path / "empty")]) == 2
    assert "no trial-* folders" in capsys.readouterr().err


def test_a_damaged_recording_stops_the_summary_with_one_line(tmp_path: Path, capsys) -> None:
    """A rescoring (or a trial without ``metrics.json``) reads the recording: a damaged
    one is bad input named in one line (exit 2, nothing written: no summary, nor a scoring
    of another trial read before it), never a trial counted as a failure that the campaign
    did not have (issue 30)."""
    from payload.trials.records import RecordingError

    camp = _campaign(tmp_path / "camp", [1, 2])
    log = camp / "trial-0002" / "log.mcap"
    data = bytearray(log.read_bytes())
    data[len(data) // 2] ^= 0x55
    log.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="damaged"):
        read_recording(log)
    capsys.readouterr()
    for argv, drop_metrics in (
        (["trials", "summarize", str(camp), "--recompute"], False),
        (["trials", "summarize", str(camp)], True),  # no metrics.json: scored from the file
    ):
        if drop_metrics:
            (log.parent / "metrics.json").unlink()
            (camp / "trial-0001" / "metrics.json").unlink()  # an undamaged one to score too
        before = sorted(p.relative_to(camp) for p in camp.rglob("*"))
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"payload: error: {log}: "), err
        assert "damaged" in err[0]
        # nothing written: no summary, and no scoring of the trial before the damaged one
        assert sorted(p.relative_to(camp) for p in camp.rglob("*")) == before


def test_an_empty_recording_is_a_trial_cut_short_not_damage(tmp_path: Path, capsys) -> None:
    """A trial killed between creating its ``log.mcap`` and its first write leaves an empty
    file: the summary lists it as that trial's error and goes on (exit 0), as a trial cut
    short; only bytes that are there and wrong stop it as damage."""
    camp = _campaign(tmp_path / "camp", [1, 2])
    (camp / "trial-0002" / "metrics.json").unlink()
    (camp / "trial-0002" / "log.mcap").write_bytes(b"")
    capsys.readouterr()
    assert main(["trials", "summarize", str(camp), "--json"]) == 0
    rows = {r["seed"]: r for r in json.loads((camp / "summary.json").read_text())["trials"]}
    assert "cut short before its first write" in rows[2]["error"]
    assert rows[1]["error"] is None


@pytest.mark.parametrize(
    "content",
    [b'{"seed": 2, "success": tr', b"\xc3\x28 not text", b"[1, 2]"],
    ids=["cut-short", "binary", "not-an-object"],
)
def test_a_damaged_metrics_file_is_one_line_in_summarize_and_compare(
    tmp_path: Path, capsys, content: bytes
) -> None:
    """A trial's metrics.json cut short, binary or not a JSON object: `trials summarize`
    and `trials compare` name it in one line, exit 2, and write no summary."""
    camp = _campaign(tmp_path / "camp", [1, 2])
    metrics = camp / "trial-0002" / "metrics.json"
    metrics.write_bytes(content)
    capsys.readouterr()
    for argv in (["trials", "summarize", str(camp)], ["trials", "compare", str(camp), str(camp)]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"payload: error: {metrics}: "), err
    assert not list(camp.glob("summary*"))


def test_compare_says_why_a_trial_cannot_be_compared_and_when_seeds_differ(
    tmp_path: Path, capsys
) -> None:
    """`trials compare`: a killed trial (a recording, no metrics) is named as unfinished in
    one line, not as a missing file; a trial's file given for its folder names the folder
    to give; two single trials of different seeds are compared, but the table and a
    warning say the sessions differ."""
    camp = _campaign(tmp_path / "camp", [1, 2])
    one, two = camp / "trial-0001", camp / "trial-0002"
    killed = tmp_path / "killed"
    shutil.copytree(one, killed)
    (killed / "metrics.json").unlink()
    log = killed / "log.mcap"
    log.write_bytes(log.read_bytes()[:-40])  # never closed
    capsys.readouterr()
    assert main(["trials", "compare", str(killed), str(one)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "an unfinished run (cut short" in err[0], err
    assert main(["trials", "compare", str(one / "log.mcap"), str(one)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"give its folder, {one}" in err[0], err
    assert main(["trials", "compare", str(one), str(two)]) == 0
    out = capsys.readouterr()
    assert "Trial `trial-0001 / trial-0002` is seed 2 in B and seed 1 in A" in out.out
    assert "warning: trial-0001 / trial-0002: seed 1 in A and seed 2 in B" in out.err
    assert "\n| trial-0001 / trial-0002 | " in out.out  # the row names both trials
    assert main(["trials", "compare", str(one), str(two), "--json"]) == 0
    row = json.loads(capsys.readouterr().out)["trials"][0]
    assert (row["trial_a"], row["trial"]) == ("trial-0001", "trial-0002")
    # the same seed: no such note
    assert main(["trials", "compare", str(one), str(one)]) == 0
    out = capsys.readouterr()
    assert "seed" not in out.err and "different operator sessions" not in out.out


def test_an_interrupted_campaign_says_what_it_kept_and_summarises_with_its_setup(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    """Ctrl-C during `trials run` names the finished trials it kept and the command that
    summarises them; that summary (no campaign summary before it) is titled with the setup
    the scored trials record, and the aborted trial, which records none, does not make
    the self-collision setting "mixed"."""
    import payload.trials.campaign as campaign
    from payload.design.cli import new_project

    project, _ = new_project(tmp_path / "p")
    out = tmp_path / "camp"
    setup = {
        "ctb": "single",
        "propulsion": "nozzles",
        "controller": "paper",
        "retarget_budget": "paper",
        "retarget_collisions": False,
        "base_filter": False,
        "link_delay": None,
        "physics_dt": 0.001,
    }

    def interrupted(trial_fn, seeds, out_dir, **kw):  # trial 0 ends, then Ctrl-C in trial 1
        fixture_synthetic_trial(seeds[0], out_dir / f"trial-{seeds[0]:04d}")
        metrics = out_dir / f"trial-{seeds[0]:04d}" / "metrics.json"
        metrics.write_text(json.dumps({**json.loads(metrics.read_text()), **setup}))
        rng = np.random.default_rng(1)
        with TrialRecorder(out_dir / f"trial-{seeds[1]:04d}" / "log.mcap") as rec:
            for k in range(10):
                rec.write(random_step(rng, k * 0.02))
            rec.write_meta({"seed": seeds[1], "aborted": "KeyboardInterrupt: "})
        raise KeyboardInterrupt

    monkeypatch.setattr(campaign, "run_campaign", interrupted)
    argv = ["--project", str(project.root), "trials", "run", "--n", "2", "--out", str(out)]
    assert main(argv) == 130
    err = capsys.readouterr().err
    assert f"1 finished trial(s) kept in {out}: `payload trials summarize {out}`" in err, err
    assert main(["trials", "summarize", str(out)]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith(f"wrote {out / 'summary.md'}, ") and str(out / "summary.json") in last
    text = (out / "summary.md").read_text()
    assert text.startswith(
        "# Cargo-transport campaign (2 trials, CTB single, nozzles, controller paper, "
        "retargeting budget paper)\n"
    ), text[:200]
    assert json.loads((out / "summary.json").read_text())["retarget_collisions"] is False
    assert "mixed" not in text
    # summarised again with nothing changed: no file is said to be written
    files = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in out.glob("summary*")}
    assert main(["trials", "summarize", str(out)]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in out.glob("summary*")} == files
    assert last.startswith("unchanged (already what the trials give): "), last
    assert all(str(p) in last for p in files if p.suffix in (".md", ".json")), last
    assert not any(line.startswith("wrote") for line in capsys.readouterr().out.splitlines())


def test_a_campaign_of_unscored_trials_claims_no_setting_and_mixed_definitions_say_so(
    tmp_path: Path,
) -> None:
    """A summary whose every trial raised says nothing of the self-collision setting (no
    trial recorded one); a summary of trials scored under different contact definitions
    heads its column "mixed", not "confirmed contact"."""
    from payload.trials.summary import write_summary
    from payload.trials.summary_markdown import summary_markdown

    failed = write_summary([{"seed": 0, "success": False, "error": "boom"}], tmp_path / "a")
    assert "retarget_collisions" not in failed
    camp = _campaign(tmp_path / "camp", [1, 2])
    assert main(["trials", "summarize", str(camp), "--json"]) == 0
    mixed = {**json.loads((camp / "summary.json").read_text())}
    mixed["contact_definition"] = {"mixed": [[0.5, 0.1], [0.0, 0.0]]}
    text = summary_markdown(mixed)
    assert "| this campaign, mixed contact definitions |" in text
    assert "confirmed contact |" not in text


def test_ctrl_c_counts_only_the_interrupted_runs_trials(tmp_path: Path, capsys, monkeypatch):
    """A --force run into a folder of an earlier campaign, interrupted before any of its
    own trials ended: the earlier trials (other seeds, and its own seed's older result)
    are not said to be this run's."""
    import os

    import payload.trials.campaign as campaign
    from payload.design.cli import new_project

    project, _ = new_project(tmp_path / "p")
    out = _campaign(tmp_path / "camp", [0, 5])  # an earlier campaign's trials
    old = out / "trial-0000" / "metrics.json"
    os.utime(old, (old.stat().st_atime - 60, old.stat().st_mtime - 60))

    def interrupted(trial_fn, seeds, out_dir, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(campaign, "run_campaign", interrupted)
    argv = ["--project", str(project.root), "trials", "run", "--n", "2", "--out", str(out)]
    assert main([*argv, "--force"]) == 130
    err = capsys.readouterr().err
    assert "interrupted" in err and "finished trial(s) kept" not in err, err


def test_ctrl_c_after_the_last_trial_names_the_trials_kept(tmp_path: Path, capsys, monkeypatch):
    """Ctrl-C after every trial ended, while the summary is being written (its figure
    takes a moment): the finished trials are named as kept, with the command that
    summarises them (only "interrupted" was said before)."""
    import payload.trials.campaign as campaign
    from payload.design.cli import new_project

    project, _ = new_project(tmp_path / "p")
    out = tmp_path / "camp"

    def finished(trial_fn, seeds, out_dir, **kw):
        return [fixture_synthetic_trial(seed, out_dir / f"trial-{seed:04d}") for seed in seeds]

    def interrupted_summary(*args, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(campaign, "run_campaign", finished)
    monkeypatch.setattr(campaign, "write_summary", interrupted_summary)
    argv = ["--project", str(project.root), "trials", "run", "--n", "2", "--out", str(out)]
    assert main(argv) == 130
    err = capsys.readouterr().err
    assert f"2 finished trial(s) kept in {out}: `payload trials summarize {out}`" in err, err


def test_compare_names_the_trials_only_one_side_has(tmp_path: Path, capsys) -> None:
    """Two campaigns of partly different seeds: the trials compared are the shared ones,
    and the table ends naming the others by side (it printed Python lists, an empty one
    included)."""
    a = _campaign(tmp_path / "a", [1, 2])
    b = tmp_path / "b"
    shutil.copytree(a / "trial-0002", b / "trial-0002")
    _campaign(b, [3])
    assert main(["trials", "compare", str(a), str(b)]) == 0
    out = capsys.readouterr().out
    assert out.rstrip().endswith("Not compared, only in A: trial-0001; only in B: trial-0003.")
    shutil.rmtree(b / "trial-0003")  # one side's extra alone: no empty list beside it
    assert main(["trials", "compare", str(a), str(b)]) == 0
    assert capsys.readouterr().out.rstrip().endswith("Not compared, only in A: trial-0001.")


def test_compare_takes_a_campaign_kept_as_its_summary_and_a_trial_by_its_seed(
    tmp_path: Path, capsys
) -> None:
    """``analyses/campaign/*`` keeps a campaign's summary without its trials: compare reads
    its per-trial rows (it said "no metrics.json and no trial-* folders"), matches a single
    trial folder to the campaign's trial of its seed, and refuses --steps for the summary
    in one line (no recordings). The rows are the trials' own metrics (each metrics.json,
    read here), so the comparison with the trials themselves finds no change."""
    from payload.trials.campaign import load_trial_results, write_summary

    camp = _campaign(tmp_path / "camp", [1, 2])
    kept = tmp_path / "kept"
    write_summary(load_trial_results(camp), kept)
    assert sorted(p.name for p in kept.iterdir() if p.is_dir()) == []  # the summary alone
    assert main(["trials", "summarize", str(kept)]) == 2  # nothing to summarize: one line
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "a campaign's summary without its trial-* folders" in err[0], err
    assert main(["trials", "compare", str(camp), str(kept), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert [r["trial"] for r in result["trials"]] == ["trial-0001", "trial-0002"]
    for row in result["trials"]:
        own = json.loads((camp / row["trial"] / "metrics.json").read_text())
        for key, m in row["metrics"].items():
            assert m["a"] == own[key] and m["b"] == own[key] and m["change"] == 0.0, key
        assert row["setup_differs"] == {}, row
    # one trial against the kept campaign: matched by its seed, whatever its folder's name
    single = tmp_path / "mine"
    shutil.copytree(camp / "trial-0002", single)
    assert main(["trials", "compare", str(kept), str(single), "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)["trials"]
    assert (row["trial_a"], row["trial"]) == ("trial-0002", "mine")
    # a folder named as a campaign's trial but holding another seed (a --force rerun of
    # runs/trial-0001 with seed 2) is matched by its seed, not by its name
    renamed = tmp_path / "runs" / "trial-0001"
    shutil.copytree(camp / "trial-0002", renamed)
    assert main(["trials", "compare", str(kept), str(renamed), "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)["trials"]
    assert (row["trial_a"], row["seed_a"], row["seed_b"]) == ("trial-0002", 2, 2), row
    # a trial the --max-time cap cut short is said to be so before the table
    metrics = single / "metrics.json"
    metrics.write_text(json.dumps({**json.loads(metrics.read_text()), "ended_by": ENDED_BY_CAP}))
    assert main(["trials", "compare", str(kept), str(single)]) == 0
    out = capsys.readouterr().out
    said = "Trial `trial-0002 / mine` was stopped by the --max-time cap in B: a session cut"
    assert said in out.split("| trial |")[0], out
    # a setting the campaign's trials did not share is no trial's: not a difference
    summary = json.loads((kept / "summary.json").read_text())
    (kept / "summary.json").write_text(
        json.dumps({**summary, "ctb": {"mixed": ["rigid", "single"]}, "propulsion": None})
    )
    assert main(["trials", "compare", str(kept), str(camp), "--json"]) == 0
    assert all(r["setup_differs"] == {} for r in json.loads(capsys.readouterr().out)["trials"])
    for option in ("--steps", "--require-identical"):  # the refusal names the option given
        assert main(["trials", "compare", str(kept), str(camp), option]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "its steps cannot be compared" in err[0], err
        assert option in err[0].split("cannot be compared")[1], err


def test_compare_steps_of_a_cut_trial_says_over_which_steps(tmp_path: Path, capsys) -> None:
    """A trial against a copy cut short: no step of the shorter one differs, and the
    table says that is over the first steps only (it read "differing steps 0" beside two
    step counts)."""
    a = _campaign(tmp_path / "a", [1])
    b = tmp_path / "b"
    shutil.copytree(a, b)
    log = b / "trial-0001" / "log.mcap"
    data = log.read_bytes()
    log.write_bytes(data[: len(data) * 2 // 3])
    n_a, n_b = len(read_recording(a / "trial-0001" / "log.mcap")), len(read_recording(log))
    assert 0 < n_b < n_a
    assert main(["trials", "compare", str(a), str(b), "--steps"]) == 0
    out = capsys.readouterr().out
    assert f"| trial-0001 | {n_a} / {n_b} | 0 of the first {n_b} | - |" in out, out


def test_a_campaign_capped_by_max_time_says_so(tmp_path: Path, capsys) -> None:
    """``trials run --max-time S`` caps each trial's session as ``payload trial
    --max-time`` does (it had no such option): each trial records the cap as its end, its
    line says so, and the summary states the cap."""
    out = tmp_path / "camp"
    argv = ["trials", "run", "--n", "1", "--seed", "3", "--workers", "0", "--max-time", "1"]
    assert main([*argv, "--out", str(out)]) == 0
    said = capsys.readouterr().out
    metrics = json.loads((out / "trial-0003" / "metrics.json").read_text())
    # the control steps of 0 to 1 s, both ends included
    assert metrics["ended_by"] == ENDED_BY_CAP and metrics["steps"] == round(1 / CONTROL_DT) + 1
    assert "[1/1] seed 3: failed (stopped by the --max-time cap)" in said
    summary = json.loads((out / "summary.json").read_text())
    assert summary["run"]["max_time_s"] == 1.0
    line = "Each trial's session was capped at 1 s (--max-time)"
    assert line in said and line in (out / "summary.md").read_text()
    # the summary counts and flags the capped trial: its row, the headline, the figures
    assert summary["capped"] == 1 and summary["trials"][0]["ended_by"] == ENDED_BY_CAP
    table = (out / "summary.md").read_text()
    assert "| 3 | no (capped) |" in table
    assert "1 of the trials was stopped by the --max-time cap" in table
    assert "; 1 stopped by the --max-time cap" in said
    from payload.trials.campaign_figure import campaign_figure
    from payload.trials.summary_fields import METRIC_LABELS

    fig = campaign_figure(summary, METRIC_LABELS)
    assert "succeeded, 1 stopped by the --max-time cap" in fig.get_suptitle()
    assert main([*argv[:-2], "--max-time", "nan", "--out", str(tmp_path / "x")]) == 2
    assert "--max-time" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_compare_steps_leaves_out_where_a_hardware_run_ran_and_what_it_read(
    tmp_path: Path, capsys
) -> None:
    """Two hardware runs of one recording, kept in different places and run on different
    serial devices, are the same run: ``device`` and ``replay`` (paths) are where it ran
    and what it read, as ``provenance`` is, not results that differ."""
    a = tmp_path / "a"
    fixture_synthetic_trial(4, a)
    b = tmp_path / "b"
    shutil.copytree(a, b)
    for folder, device in ((a, "/dev/pts/3"), (b, "/dev/ttyUSB0")):
        metrics = folder / "metrics.json"
        extra = {"device": device, "replay": str(folder / "src" / "log.mcap")}
        metrics.write_text(json.dumps({**json.loads(metrics.read_text()), **extra}))
    assert main(["trials", "compare", str(a), str(b), "--steps", "--require-identical"]) == 0
    capsys.readouterr()


def test_compare_says_a_differing_setting_as_it_was_given() -> None:
    """A 0.1 ms physics step against 1 ms read "physics_dt 0.000 / 0.001" (three decimals,
    as the metrics are shown); a setting is said as given."""
    from payload.trials.compare import comparison_notes

    row = {"trial": "trial-0000", "setup_differs": {"physics_dt": [0.0001, 0.001]}}
    notes = comparison_notes({"trials": [row], "only_a": [], "only_b": []})
    assert "Setup, A / B, where it differs: physics_dt 0.0001 / 0.001." in notes, notes


def test_the_route_figure_of_a_capped_trial_says_so(tmp_path: Path, monkeypatch) -> None:
    """``fig_route.png``'s title says when the ``--max-time`` cap stopped the session (Fig.
    3 says it in a label); a trial that ran to its end says nothing of a cap."""
    from payload.trials import figures

    fixture_synthetic_trial(4, tmp_path / "t")
    rec = read_recording(tmp_path / "t" / "log.mcap")
    titles: list[str] = []
    monkeypatch.setattr(
        figures, "save_figure", lambda fig, path, *a: titles.append(fig.axes[0].get_title())
    )
    figures.plot_route(rec, tmp_path / "a.png")
    rec.meta["ended_by"] = ENDED_BY_CAP
    figures.plot_route(rec, tmp_path / "b.png")
    assert figures.CAP_LABEL not in titles[0] and titles[1].endswith(f"; {figures.CAP_LABEL})")


def test_compare_reads_a_summarys_station_settings_as_values(tmp_path: Path) -> None:
    """A campaign kept as its summary writes its filter setting as text in the station
    block (``"False"``); compare read it back through the wrong of two functions of one
    name (the table's formatter), so every trial with the filter off was said to differ:
    "base_filter False / no". Read as the value, only a real difference is said."""
    from payload.trials.compare import compare_runs, comparison_notes

    camp = tmp_path / "camp"
    camp.mkdir()
    row = {"seed": 0, "success": True, "rms_mm": 30.0, "duration_s": 80.0}
    summary = {"n": 1, "trials": [row], "station": {"base_filter": "False", "link_delay": None}}
    (camp / "summary.json").write_text(json.dumps(summary))
    for name, on in (("off", False), ("on", True)):
        trial = tmp_path / name / "trial-0000"
        trial.mkdir(parents=True)
        (trial / "metrics.json").write_text(json.dumps({**row, "base_filter": on}))
    same = compare_runs(camp, tmp_path / "off")
    assert same["trials"][0]["setup_differs"] == {}
    assert not [n for n in comparison_notes(same) if n.startswith("Setup")]
    other = compare_runs(camp, tmp_path / "on")
    assert other["trials"][0]["setup_differs"] == {"base_filter": [False, True]}
    assert "Setup, A / B, where it differs: base_filter no / yes." in comparison_notes(other)
    # a hardware run against a simulated trial: the driver differs (a trial records none)
    hw = tmp_path / "hw" / "trial-0000"
    hw.mkdir(parents=True)
    (hw / "metrics.json").write_text(
        json.dumps({**row, "base_filter": False, "driver": "hardware"})
    )
    against = compare_runs(tmp_path / "off", tmp_path / "hw")
    assert against["trials"][0]["setup_differs"] == {"driver": ["simulator", "hardware"]}


def test_summarize_refuses_a_folder_of_separate_runs(tmp_path: Path, capsys) -> None:
    """``trials summarize runs`` summarised a project's runs/ as a campaign: two trials of
    seed 0 (``trial-0000`` and a ``payload trial --out runs/trial-35``) as "seeds 0 to 0",
    writing the summary and its figure there. A folder with one seed twice is not one
    campaign: one line naming them, exit 2, nothing written."""
    from payload.cli import main

    runs = tmp_path / "runs"
    fixture_synthetic_trial(0, runs / "trial-0000")
    fixture_synthetic_trial(0, runs / "trial-35")
    fixture_synthetic_trial(1, runs / "trial-0001")
    before = sorted(p.name for p in runs.iterdir())
    assert main(["trials", "summarize", str(runs)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"payload: error: {runs}: not one campaign: trial-0000 and trial-35 are both seed 0 (a "
        "campaign runs each seed once; give a campaign's folder, or set runs side by side "
        "with `payload trials compare`)"
    ], err
    assert sorted(p.name for p in runs.iterdir()) == before
