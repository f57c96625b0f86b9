"""LeRobot v3 export: read back with pyarrow (and pandas) and compare with the recordings;
LeRobot's own loader when it is installed."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from payload.trials.lerobot import (
    DEFAULT_TASK,
    LeRobotExportError,
    action_names,
    export_lerobot,
    state_names,
)
from payload.trials.recorder import TrialRecorder, random_step, read_recording

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")

DT = 0.02


def _write_run(path: Path, seed: int, n: int, n_cal: int, dt: float = DT, task=None) -> Path:
    """A seeded recording with ``n_cal`` calibration steps then ``n - n_cal`` others."""
    rng = np.random.default_rng(seed)
    with TrialRecorder(path) as rec:
        meta = {"seed": seed}
        if task:
            meta["task"] = task
        rec.write_meta(meta)
        for k in range(n):
            phase = "calibration" if k < n_cal else "translation"
            rec.write(random_step(rng, k * dt, phase=phase, contact=bool(k % 2)))
    return path


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> list[Path]:
    root = tmp_path_factory.mktemp("runs")
    # a trial folder, a bare .mcap file, and a campaign folder with one trial
    (root / "trial-0000").mkdir()
    a = _write_run(root / "trial-0000" / "log.mcap", seed=0, n=140, n_cal=20)
    b = _write_run(root / "b.mcap", seed=1, n=75, n_cal=0, task="Hand the CTB over")
    (root / "camp" / "trial-0002").mkdir(parents=True)
    c = _write_run(root / "camp" / "trial-0002" / "log.mcap", seed=2, n=60, n_cal=10)
    # the trials' scores beside their recordings (the bare file has none)
    (root / "trial-0000" / "metrics.json").write_text('{"success": true}')
    (root / "camp" / "trial-0002" / "metrics.json").write_text('{"success": false}')
    return [a, b, c]


@pytest.fixture(scope="module")
def dataset(runs, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("ds") / "astrobee_cargo"
    info = export_lerobot([runs[0].parent, runs[1], runs[2].parent.parent], out)
    return out, info


def _expected_rows(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """State and action rows built field by field from the documented layout."""
    rec = read_recording(path)
    keep = rec.phase != "calibration"
    state = np.column_stack(
        [
            rec.q_meas,
            rec.deploy_meas,
            rec.astrobee_pos,
            rec.astrobee_quat,
            rec.astrobee_twist,
            rec.ctb_pos,
            rec.ctb_quat,
        ]
    )[keep]
    action = np.column_stack([rec.q_cmd, rec.deploy_cmd, rec.twist_cmd])[keep]
    return state.astype(np.float32), action.astype(np.float32)


def test_info_and_layout(dataset) -> None:
    out, info = dataset
    meta = json.loads((out / "meta" / "info.json").read_text())
    assert meta["codebase_version"] == "v3.0" and meta["fps"] == 50
    assert meta["total_episodes"] == 3 == info["episodes"]
    assert meta["total_frames"] == 120 + 75 + 50 == info["frames"]
    assert meta["total_tasks"] == 2
    assert meta["splits"] == {"train": "0:3"}
    assert meta["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    feats = meta["features"]
    assert feats["observation.state"]["shape"] == [38] and feats["action"]["shape"] == [24]
    assert feats["observation.state"]["names"][:4] == [
        "A_mcp_flex",
        "A_mcp_abd",
        "A_pip",
        "A_dip",
    ]
    assert feats["observation.state"]["names"][16:18] == ["rail", "stage"]
    assert len(set(state_names())) == 38 and len(set(action_names())) == 24
    for key in ("timestamp", "frame_index", "episode_index", "index", "task_index"):
        assert feats[key]["shape"] == [1]
    for rel in (
        "meta/stats.json",
        "meta/tasks.parquet",
        "meta/episodes/chunk-000/file-000.parquet",
        "data/chunk-000/file-000.parquet",
    ):
        assert (out / rel).is_file(), rel


def test_frames_match_recordings(dataset, runs) -> None:
    out, _ = dataset
    table = pq.read_table(out / "data" / "chunk-000" / "file-000.parquet")
    assert table.schema.field("observation.state").type == pa.list_(pa.float32(), 38)
    assert table.schema.field("action").type == pa.list_(pa.float32(), 24)
    assert table.schema.field("timestamp").type == pa.float32()
    cols = table.to_pydict()
    state = np.array(cols["observation.state"], dtype=np.float32)
    action = np.array(cols["action"], dtype=np.float32)
    ep = np.array(cols["episode_index"])
    frame = np.array(cols["frame_index"])
    np.testing.assert_array_equal(np.array(cols["index"]), np.arange(245))
    np.testing.assert_array_equal(np.bincount(ep), [120, 75, 50])
    for e, path in enumerate(runs):
        exp_state, exp_action = _expected_rows(path)
        sel = ep == e
        np.testing.assert_array_equal(state[sel], exp_state)
        np.testing.assert_array_equal(action[sel], exp_action)
        np.testing.assert_array_equal(frame[sel], np.arange(sel.sum()))
    np.testing.assert_allclose(np.array(cols["timestamp"]), frame / 50.0, atol=1e-6)
    assert set(np.array(cols["task_index"])[ep == 1]) == {1}
    assert set(np.array(cols["task_index"])[ep != 1]) == {0}


def test_episodes_tasks_and_stats(dataset, runs) -> None:
    out, _ = dataset
    eps = pq.read_table(out / "meta" / "episodes" / "chunk-000" / "file-000.parquet").to_pylist()
    assert [e["episode_index"] for e in eps] == [0, 1, 2]
    assert [e["length"] for e in eps] == [120, 75, 50]
    assert [e["dataset_from_index"] for e in eps] == [0, 120, 195]
    assert [e["dataset_to_index"] for e in eps] == [120, 195, 245]
    assert eps[1]["tasks"] == ["Hand the CTB over"] and eps[0]["tasks"] == [DEFAULT_TASK]
    assert [e["payload/seed"] for e in eps] == [0, 1, 2]
    assert [e["payload/success"] for e in eps] == [True, None, False]
    assert [e["payload/ended_by"] for e in eps] == [None, None, None]  # none recorded
    assert all(e["data/chunk_index"] == 0 and e["data/file_index"] == 0 for e in eps)

    states = [_expected_rows(p)[0].astype(np.float64) for p in runs]
    np.testing.assert_allclose(eps[2]["stats/observation.state/mean"], states[2].mean(axis=0))
    assert eps[2]["stats/observation.state/count"] == [50]

    stats = json.loads((out / "meta" / "stats.json").read_text())
    allstate = np.concatenate(states)
    s = stats["observation.state"]
    np.testing.assert_allclose(s["min"], allstate.min(axis=0))
    np.testing.assert_allclose(s["max"], allstate.max(axis=0))
    np.testing.assert_allclose(s["mean"], allstate.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(s["std"], allstate.std(axis=0), rtol=1e-12)
    np.testing.assert_allclose(s["q50"], np.median(allstate, axis=0))
    assert s["count"] == [245]
    allaction = np.concatenate([_expected_rows(p)[1].astype(np.float64) for p in runs])
    np.testing.assert_allclose(stats["action"]["std"], allaction.std(axis=0), rtol=1e-12)
    assert stats["frame_index"]["max"] == [119] and stats["episode_index"]["mean"] == [
        pytest.approx((75 * 1 + 50 * 2) / 245)
    ]
    # the global statistics are the count-weighted merge of the per-episode ones
    counts = np.array([e["stats/action/count"][0] for e in eps], dtype=float)
    means = np.array([e["stats/action/mean"] for e in eps])
    np.testing.assert_allclose(stats["action"]["mean"], counts @ means / counts.sum())

    tasks = pq.read_table(out / "meta" / "tasks.parquet").to_pydict()
    assert tasks == {"task_index": [0, 1], "task": [DEFAULT_TASK, "Hand the CTB over"]}


def test_tasks_parquet_reads_as_lerobot_expects(dataset) -> None:
    """LeRobot reads tasks with pandas and looks a task up by its index label."""
    pd = pytest.importorskip("pandas", reason="pandas is not installed")
    out, _ = dataset
    tasks = pd.read_parquet(out / "meta" / "tasks.parquet")
    assert tasks.index.name == "task"
    assert tasks.iloc[1].name == "Hand the CTB over"
    assert int(tasks.loc[DEFAULT_TASK].task_index) == 0


def test_export_errors(runs, tmp_path: Path) -> None:
    out = tmp_path / "ds"
    export_lerobot([runs[1]], out)
    with pytest.raises(LeRobotExportError, match="already holds files; pass --force"):
        export_lerobot([runs[1]], out)
    info = export_lerobot([runs[1], runs[2]], out, overwrite=True, task="Task X")
    assert info["episodes"] == 2 and info["tasks"] == ["Task X"]
    # a recording given twice (here as a file and inside its campaign folder, and by a
    # path with a detour) would be two identical episodes: refused, the dataset kept
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    detour = runs[1].parent / "camp" / ".." / runs[1].name
    for twice in ([runs[2], runs[2].parent.parent], [runs[1], detour]):
        with pytest.raises(LeRobotExportError, match="given twice"):
            export_lerobot(twice, out, overwrite=True)
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before
    with pytest.raises(LeRobotExportError, match="no such recording"):
        export_lerobot([tmp_path / "missing"], tmp_path / "ds2")
    slow = _write_run(tmp_path / "slow.mcap", seed=3, n=20, n_cal=0, dt=0.1)
    with pytest.raises(LeRobotExportError, match="not at 50 Hz"):
        export_lerobot([slow], tmp_path / "ds3")
    # a folder of runs takes every run's recording in it, a replay's and a hw run's too
    folder = tmp_path / "runs"
    for name, seed in (("trial-0000", 5), ("replay-0001", 6), ("hw-0001", 7)):
        (folder / name).mkdir(parents=True)
        _write_run(folder / name / "log.mcap", seed=seed, n=30, n_cal=5)
    info = export_lerobot([folder], tmp_path / "ds5")
    assert info["episodes"] == 3
    cal_only = _write_run(tmp_path / "cal.mcap", seed=4, n=10, n_cal=10)
    with pytest.raises(LeRobotExportError, match="no steps after calibration"):
        export_lerobot([cal_only], tmp_path / "ds4")


def test_cli_export(runs, tmp_path: Path, capsys) -> None:
    from payload.cli import main

    out = tmp_path / "cli_ds"
    assert main(["export", "lerobot", str(runs[0]), str(runs[2]), "--out", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["episodes"] == 2 and info["frames"] == 170 and info["fps"] == 50
    # the folder under the trials' and campaigns' name, and the one it had
    assert Path(info["out_dir"]) == Path(info["path"]) == out
    assert main(["export", "lerobot", str(runs[0]), "--out", str(out)]) == 2
    assert "already holds files; pass --force" in capsys.readouterr().err


def test_lerobot_loader_reads_the_export(dataset, runs) -> None:
    """Optional: LeRobot's own loader (skipped when the ``lerobot`` package is absent)."""
    pytest.importorskip(
        "lerobot", reason="the lerobot package is not installed; LeRobot's loader not run"
    )
    try:
        from lerobot.datasets.lerobot_dataset import LeRobotDataset
    except ImportError:  # older layout
        from lerobot.common.datasets.lerobot_dataset import LeRobotDataset

    out, _ = dataset
    ds = LeRobotDataset("local/astrobee_cargo", root=out)
    assert len(ds) == 245 and ds.meta.fps == 50 and ds.num_episodes == 3
    item = ds[130]
    exp_state, _ = _expected_rows(runs[1])
    np.testing.assert_allclose(item["observation.state"].numpy(), exp_state[10], rtol=1e-6)
    assert tuple(item["action"].shape) == (24,)
    assert item["task"] == "Hand the CTB over"
    assert math.isclose(float(item["timestamp"]), 10 / 50, abs_tol=1e-6)


def test_an_export_of_nothing_leaves_no_numbered_folder(tmp_path, capsys):
    """A run that is not there is one line and exit 2, and no ``runs/lerobot-NNNN`` is made
    (nor its number used up) for it."""
    from payload.cli import main
    from payload.design.cli import new_project

    project, _ = new_project(tmp_path / "p")
    argv = ["--project", str(project.root), "export", "lerobot", str(tmp_path / "nothing")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no such recording or folder" in err[0], err
    assert not list(project.runs_dir.glob("lerobot-*"))


def test_unfinished_runs_are_left_out_unless_asked_for(
    runs, tmp_path: Path, capsys, caplog
) -> None:
    """An aborted run's recording (its ``aborted`` metadata) and a killed one's (never
    closed: its summary and footer lost) end wherever the run stopped: the export leaves
    them out, names each in a warning and under ``left_out``; ``--include-unfinished``
    exports them; a set of unfinished runs alone exports nothing (exit 2)."""
    from payload.cli import main

    aborted = tmp_path / "aborted.mcap"
    rng = np.random.default_rng(9)
    with TrialRecorder(aborted) as rec:
        for k in range(30):
            rec.write(random_step(rng, k * DT, phase="translation"))
        rec.write_meta({"aborted": "KeyboardInterrupt: "})
    cut = _write_run(tmp_path / "cut.mcap", seed=4, n=200, n_cal=0)
    whole = cut.read_bytes()
    cut.write_bytes(whole[: len(whole) * 3 // 4])
    assert not read_recording(cut).complete and len(read_recording(cut)) > 0
    # closed recordings whose sessions stopped early: the --max-time cap, and a replay of
    # an aborted run's hands
    capped, replayed = tmp_path / "capped.mcap", tmp_path / "replayed.mcap"
    for path, meta in (
        (capped, {"ended_by": "max_time"}),
        (replayed, {"ended_by": "source", "replay": {"source_unfinished": "aborted (x)"}}),
    ):
        with TrialRecorder(path) as rec:
            for k in range(40):
                rec.write(random_step(rng, k * DT, phase="translation"))
            rec.write_meta(meta)
        assert read_recording(path).complete
    unfinished = [aborted, cut, capped, replayed]
    argv = ["export", "lerobot", str(runs[0]), *map(str, unfinished), "--json"]
    assert main([*argv, "--out", str(tmp_path / "ds")]) == 0
    out = capsys.readouterr()
    info = json.loads(out.out)
    assert info["episodes"] == 1 and info["frames"] == 120 and info["sources"] == [str(runs[0])]
    assert [x["source"] for x in info["left_out"]] == list(map(str, unfinished))
    why = [x["why"] for x in info["left_out"]]
    assert [x["kind"] for x in info["left_out"]] == ["unfinished"] * 4
    assert why[0].startswith("aborted") and "cut short" in why[1], why
    assert "--max-time" in why[2] and "replay of an unfinished run" in why[3], why
    warned = [r.getMessage() for r in caplog.records if "left out" in r.getMessage()]
    assert len(warned) == 4 and all(str(p) in w for p, w in zip(unfinished, warned))
    assert main([*argv, "--out", str(tmp_path / "all"), "--include-unfinished"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["episodes"] == 5 and info["left_out"] == []
    assert info["frames"] == 120 + 30 + len(read_recording(cut)) + 40 + 40
    eps = pq.read_table(tmp_path / "all" / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    ended = eps.to_pydict()["payload/ended_by"]
    assert ended == [None, None, None, "max_time", "source"]
    assert main(["export", "lerobot", str(aborted), str(cut), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "--include-unfinished exports them" in err[-1] and not (tmp_path / "x").exists()


def test_a_session_that_ended_in_its_calibration_is_left_out(runs, tmp_path: Path, capsys):
    """A recording with no step after its calibration (an ``hw run`` of a trial capped
    early) stopped a whole folder's export ("no steps after calibration", exit 2). It has
    no episode: left out with why, with or without ``--include-unfinished``; given alone it
    is still that one line."""
    from payload.cli import main

    rng = np.random.default_rng(3)
    calibrating = tmp_path / "calibrating.mcap"
    with TrialRecorder(calibrating) as rec:
        for k in range(20):
            rec.write(random_step(rng, k * DT, phase="calibration"))
        rec.write_meta({})
    for extra in ([], ["--include-unfinished"]):
        out = tmp_path / f"ds{len(extra)}"
        argv = ["export", "lerobot", str(runs[0]), str(calibrating), "--json", "--out", str(out)]
        assert main([*argv, *extra]) == 0
        info = json.loads(capsys.readouterr().out)
        assert info["episodes"] == 1 and info["sources"] == [str(runs[0])]
        assert info["left_out"] == [
            {"source": str(calibrating), "why": "no steps after calibration", "kind": "empty"}
        ]
    assert main(["export", "lerobot", str(calibrating), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"payload: error: {calibrating}: no steps after calibration"], err
    # two such, with or without --include-unfinished: said as what they are (it advised
    # --include-unfinished, which exports nothing of them)
    twice = tmp_path / "calibrating2.mcap"
    twice.write_bytes(calibrating.read_bytes())
    for extra in ([], ["--include-unfinished"]):
        argv = ["export", "lerobot", str(calibrating), str(twice), "--out", str(tmp_path / "y")]
        assert main([*argv, *extra]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1] == (
            "payload: error: no recording to export: all 2 given are without steps after "
            "calibration"
        ), err


def test_an_empty_task_text_is_refused(runs, tmp_path: Path, capsys) -> None:
    """A LeRobot episode's task is the policy's instruction: `--task ""` is one line, exit
    2, and no dataset."""
    from payload.cli import main

    out = tmp_path / "ds"
    assert main(["export", "lerobot", str(runs[0]), "--task", " ", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--task" in err[0] and "empty" in err[0], err
    assert not out.exists()


def test_a_damaged_recording_is_left_out_and_the_rest_exported(
    runs, tmp_path: Path, capsys, caplog
) -> None:
    """In a campaign whose one trial's file is damaged (not MCAP at all), the export writes
    the other trials' episodes and names the damaged file in a warning and under
    ``left_out`` (``--include-unfinished`` or not); the episodes are those of the good
    files exported alone. Nothing readable given: one line, exit 2, no dataset."""
    from payload.cli import main

    camp = tmp_path / "camp"
    for i, src in enumerate(runs):
        (camp / f"trial-000{i}").mkdir(parents=True)
        shutil.copy(src, camp / f"trial-000{i}" / "log.mcap")
    bad = camp / "trial-0001" / "log.mcap"
    bad.write_bytes(b"not an mcap file at all")
    for extra in ([], ["--include-unfinished"]):
        out = tmp_path / f"ds{len(extra)}"
        assert main(["export", "lerobot", str(camp), "--out", str(out), "--json", *extra]) == 0
        info = json.loads(capsys.readouterr().out)
        good = [read_recording(r) for r in (runs[0], runs[2])]  # their steps after calibration
        assert info["episodes"] == 2, info
        assert info["frames"] == sum(int((r.phase != "calibration").sum()) for r in good), info
        assert [x["source"] for x in info["left_out"]] == [str(bad)], info["left_out"]
        assert info["left_out"][0]["why"].startswith("unreadable: "), info["left_out"]
        assert info["left_out"][0]["kind"] == "unreadable", info["left_out"]
        assert str(bad) not in info["left_out"][0]["why"]  # the path said once
        warned = [r.getMessage() for r in caplog.records if "left out" in r.getMessage()]
        assert warned[-1].startswith(f"{bad}: left out (unreadable: "), warned
        assert "--include-unfinished" not in warned[-1]  # it would not export this one
    assert export_lerobot([runs[0], runs[2]], tmp_path / "good")["episodes"] == 2
    frames = "data/chunk-000/file-000.parquet"  # the same frames as the good files alone
    assert pq.read_table(tmp_path / "ds0" / frames).equals(
        pq.read_table(tmp_path / "good" / frames)
    )
    assert main(["export", "lerobot", str(camp), "--out", str(tmp_path / "ds2")]) == 0
    assert capsys.readouterr().out.rstrip().endswith("; 1 unreadable run(s) left out")
    cut = tmp_path / "cut.mcap"  # a killed run's file: unfinished, not unreadable
    cut.write_bytes(runs[0].read_bytes()[: runs[0].stat().st_size * 3 // 4])
    argv = ["export", "lerobot", str(runs[2]), str(cut), str(bad), "--out"]
    assert main([*argv, str(tmp_path / "ds3")]) == 0
    said = capsys.readouterr().out.rstrip()
    assert said.endswith("; 1 unfinished run(s) and 1 unreadable run(s) left out"), said
    other = tmp_path / "other.mcap"
    other.write_bytes(b"\x89MCAP0\r\n but torn")
    for given, says in (
        ([bad], f"{bad}: "),  # the one recording given: its own error
        ([bad, other], "no recording to export: all 2 given are unreadable (the first: "),
        ([cut, bad], "no recording to export: of the 2 given, 1 unreadable (the first: "),
    ):
        assert main(["export", "lerobot", *map(str, given), "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0], err
        assert not (tmp_path / "x").exists()


def test_a_seed_beyond_64_bits_is_refused_and_the_largest_exported(tmp_path: Path) -> None:
    """A recording whose seed does not fit a signed 64-bit integer (the commands refuse
    such seeds now; an older recording may hold one) is one error naming it, nothing
    written; the largest seed that fits is exported and reads back exact."""
    big = _write_run(tmp_path / "big.mcap", seed=2**63, n=12, n_cal=2)
    with pytest.raises(LeRobotExportError, match=f"{big}: seed {2**63} does not fit .*signed"):
        export_lerobot([big], tmp_path / "ds")
    assert not (tmp_path / "ds").exists()
    edge = _write_run(tmp_path / "edge.mcap", seed=2**63 - 1, n=12, n_cal=2)
    export_lerobot([edge], tmp_path / "ds2")
    (episodes,) = (tmp_path / "ds2" / "meta" / "episodes").rglob("*.parquet")
    assert pq.read_table(episodes).column("payload/seed").to_pylist() == [2**63 - 1]


def test_an_export_to_a_named_folder_needs_no_project(
    runs, tmp_path: Path, monkeypatch, capsys
) -> None:
    """``export lerobot RUNS --out DIR`` from a folder in no project: the recordings and
    the dataset are named, so it exports (it failed, "not inside a design project"); left
    without ``--out``, the numbered folder needs a project, and that is the one line."""
    from payload.cli import main

    nowhere = tmp_path / "nowhere"
    nowhere.mkdir()
    monkeypatch.delenv("PAYLOAD_PROJECT", raising=False)
    monkeypatch.chdir(nowhere)
    out = tmp_path / "named"
    assert main(["export", "lerobot", str(runs[0]), "--out", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["episodes"] == 1
    assert main(["export", "lerobot", str(runs[0])]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "not inside a design project" in err, err
    assert sorted(nowhere.iterdir()) == []
