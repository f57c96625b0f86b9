"""Export trial recordings as a LeRobot v3 dataset (``codebase_version`` ``v3.0``).

One episode per recording, 50 frames per second, calibration steps left out (the
demonstration starts at the first step after calibration; ``frame_index`` 0 is that step
and ``timestamp = frame_index / fps``). No videos: the payload has no camera.

Layout written under ``out``::

    meta/info.json                            schema, fps 50, path templates, totals
    meta/stats.json                           min/max/mean/std/count/q01..q99 per feature
    meta/tasks.parquet                        task strings (pandas index) -> task_index
    meta/episodes/chunk-000/file-000.parquet  per-episode lengths, offsets, tasks, stats
    data/chunk-000/file-000.parquet           the frames (further files past 100 MB)

Frame features (float32 vectors; the names are in ``meta/info.json``):

* ``observation.state`` (38): the 17 measured manipulation coordinates (paper order,
  rad / rail m), the measured deployment coordinate (m), Astrobee position (3, m),
  orientation (4, w x y z, body -> world), twist (world linear 3 m/s, body angular
  3 rad/s), CTB position (3, m) and orientation (4, w x y z).
* ``action`` (24): the 17 commanded manipulation coordinates, the commanded deployment
  coordinate, and the base-channel twist command (linear 3 m/s, angular 3 rad/s, body).
* ``timestamp`` (float32 s), ``frame_index``, ``episode_index``, ``index`` (global frame
  counter), ``task_index`` (int64).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from payload.errors import PayloadError
from payload.folders import METRICS, RECORDING
from payload.trials.reading import cut_reason
from payload.trials.recorder import Recording, RecordingError, read_recording
from payload.trials.records import CALIBRATION
from payload.trials.setup_options import MAX_SEED

log = logging.getLogger(__name__)

CODEBASE_VERSION = "v3.0"
FPS = 50
CHUNKS_SIZE = 1000
DATA_FILE_SIZE_MB = 100
VIDEO_FILE_SIZE_MB = 200
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
DEFAULT_TASK = "Carry the cargo transfer bag from Kibo into Node 2 with the four-finger payload"
ROBOT_TYPE = "astrobee_four_finger_payload"
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}


def _joint_names() -> list[str]:
    from payload.design.tree import MANIPULATION_JOINTS

    return list(MANIPULATION_JOINTS)


def state_names() -> list[str]:
    """Names of the 38 ``observation.state`` entries, in order."""
    return [
        *_joint_names(),
        "stage",
        *(f"astrobee_{a}" for a in ("x", "y", "z", "qw", "qx", "qy", "qz")),
        *(f"astrobee_{a}" for a in ("vx", "vy", "vz", "wx", "wy", "wz")),
        *(f"ctb_{a}" for a in ("x", "y", "z", "qw", "qx", "qy", "qz")),
    ]


def action_names() -> list[str]:
    """Names of the 24 ``action`` entries, in order."""
    return [
        *_joint_names(),
        "stage",
        *(f"twist_{a}" for a in ("vx", "vy", "vz", "wx", "wy", "wz")),
    ]


class LeRobotExportError(PayloadError):
    """Recordings cannot be exported (missing, wrong rate, output folder not empty)."""


def state_matrix(rec: Recording) -> np.ndarray:
    """``observation.state`` rows of a recording, shape (N, 38), float64."""
    return np.concatenate(
        [
            rec.q_meas,
            rec.deploy_meas[:, None],
            rec.astrobee_pos,
            rec.astrobee_quat,
            rec.astrobee_twist,
            rec.ctb_pos,
            rec.ctb_quat,
        ],
        axis=1,
    )


def action_matrix(rec: Recording) -> np.ndarray:
    """``action`` rows of a recording, shape (N, 24), float64."""
    return np.concatenate([rec.q_cmd, rec.deploy_cmd[:, None], rec.twist_cmd], axis=1)


def resolve_runs(runs: Sequence[str | Path]) -> list[Path]:
    """Recording files for the given runs.

    Each run is a ``.mcap`` file, a trial folder holding ``log.mcap``, or a folder of
    runs (a campaign's, or a project's ``runs/``) whose subfolders' ``log.mcap`` files
    (``trial-*``, ``replay-*``, ``hw-*``) are taken in name order.

    Raises:
        LeRobotExportError: A run does not exist or holds no recording, or a recording is
            given twice (as a file and in its trial or campaign folder, say).
    """
    if not runs:
        raise LeRobotExportError("no runs given")
    out: list[Path] = []
    for run in runs:
        p = Path(run)
        if p.is_file():
            out.append(p)
        elif (p / RECORDING).is_file():
            out.append(p / RECORDING)
        elif p.is_dir():
            found = sorted(p.glob(f"*/{RECORDING}"))  # a replay's or hw run's too (only trial-*
            if not found:  # were taken: `export lerobot runs` left replays out without a word)
                raise LeRobotExportError(f"{p}: no {RECORDING} and no */{RECORDING} inside")
            out.extend(found)
        else:
            raise LeRobotExportError(f"{p}: no such recording or folder")
    seen: dict[Path, Path] = {}
    for path in out:  # one episode a recording: the same one twice would train on it twice
        first = seen.setdefault(path.resolve(), path)
        if first is not path:
            raise LeRobotExportError(
                f"{path}: the recording {first} is given twice (each recording is one episode)"
            )
    return out


NO_STEPS = "no steps after calibration"
"""Why a recording whose session ended during its calibration has no episode."""


def _episode_frames(rec: Recording, source: Path, fps: int) -> tuple[np.ndarray, np.ndarray]:
    keep = rec.phase != CALIBRATION
    if not np.any(keep):
        raise LeRobotExportError(f"{source}: {NO_STEPS}")
    first = int(np.flatnonzero(keep)[0])
    sel = np.arange(first, len(rec))
    t = rec.t[sel]
    if len(t) > 1:
        dt = np.diff(t)
        period = 1.0 / fps
        if abs(float(np.median(dt)) - period) > 0.01 * period or float(dt.max()) > 1.5 * period:
            raise LeRobotExportError(
                f"{source}: steps are not at {fps} Hz (median {1e3 * np.median(dt):.2f} ms, "
                f"longest gap {1e3 * dt.max():.2f} ms)"
            )
    return state_matrix(rec)[sel], action_matrix(rec)[sel]


def _stats(values: np.ndarray) -> dict[str, list[float]]:
    """LeRobot feature statistics of rows ``values`` (N, D) (as stored, float32 or int)."""
    v = np.asarray(values, dtype=np.float64)
    out = {
        "min": v.min(axis=0).tolist(),
        "max": v.max(axis=0).tolist(),
        "mean": v.mean(axis=0).tolist(),
        "std": v.std(axis=0).tolist(),
        "count": [int(v.shape[0])],
    }
    for key, q in QUANTILES.items():
        out[key] = np.quantile(v, q, axis=0).tolist()
    return out


def _fixed_list(values: np.ndarray, width: int) -> Any:
    import pyarrow as pa

    flat = pa.array(np.ascontiguousarray(values, dtype=np.float32).reshape(-1), type=pa.float32())
    return pa.FixedSizeListArray.from_arrays(flat, width)


def _tasks_table(tasks: list[str]) -> Any:
    """``meta/tasks.parquet`` as pandas would write ``DataFrame({"task_index": ...},
    index=Index(tasks, name="task"))``: LeRobot reads it with pandas and looks tasks up
    by index."""
    import pyarrow as pa

    pandas_meta = {
        "index_columns": ["task"],
        "column_indexes": [
            {
                "name": None,
                "field_name": None,
                "pandas_type": "unicode",
                "numpy_type": "object",
                "metadata": {"encoding": "UTF-8"},
            }
        ],
        "columns": [
            {
                "name": "task_index",
                "field_name": "task_index",
                "pandas_type": "int64",
                "numpy_type": "int64",
                "metadata": None,
            },
            {
                "name": "task",
                "field_name": "task",
                "pandas_type": "unicode",
                "numpy_type": "object",
                "metadata": None,
            },
        ],
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.0",
    }
    schema = pa.schema(
        [("task_index", pa.int64()), ("task", pa.string())],
        metadata={b"pandas": json.dumps(pandas_meta).encode()},
    )
    return pa.table(
        {"task_index": np.arange(len(tasks), dtype=np.int64), "task": tasks}, schema=schema
    )


def _prepare_out(out: Path, overwrite: bool) -> Path:
    """Check ``out`` and return a fresh staging folder beside it to write the dataset in."""
    if out.exists() and not out.is_dir():
        raise LeRobotExportError(f"{out}: exists and is not a folder")
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise LeRobotExportError(
            f"{out}: already holds files; pass --force to replace the dataset in it or choose "
            "another --out"
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f".{out.name}.new-", dir=out.parent))


def _swap_in(stage: Path, out: Path) -> None:
    """Move the finished dataset from ``stage`` into ``out``; the dataset it replaces is
    set aside first and deleted only once the new one is in place."""
    out.mkdir(parents=True, exist_ok=True)
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
    for sub in ("meta", "data"):
        if (out / sub).exists():
            os.replace(out / sub, old / sub)
    for sub in ("meta", "data"):
        os.replace(stage / sub, out / sub)
    shutil.rmtree(old)
    shutil.rmtree(stage, ignore_errors=True)


def _trial_success(recording: Path) -> bool | None:
    """The trial's success from the ``metrics.json`` beside its recording, or None (no
    such file, or not a trial's: a replay's file given alone, an unscored run)."""
    from payload.trials.trial_results import read_metrics  # checks `success` is a bool

    path = Path(recording).parent / METRICS
    if not path.is_file():
        return None
    try:
        return read_metrics(path)["success"]
    except PayloadError:  # unreadable, or not a trial's metrics
        return None


UNFINISHED = "unfinished"
"""A ``left_out`` entry's ``kind`` for the recording of a run that ended before its task."""

EMPTY = "empty"
"""A ``left_out`` entry's ``kind`` for a recording with no step after its calibration."""

UNREADABLE = "unreadable"
"""A ``left_out`` entry's ``kind`` (and how its ``why`` starts) for a recording that could
not be read."""


def _nothing_to_export(given: int, unreadable: dict[Path, str], empty: int = 0) -> str:
    """Why an export of ``given`` recordings has none left: every one unfinished, ``empty``
    of them with no step after calibration, or ``unreadable`` (source -> why) among them."""
    unfinished = "--include-unfinished exports them"
    left = given - len(unreadable) - empty  # of unfinished runs
    if not (unreadable or empty):
        return (
            "every recording given is of an unfinished run (aborted, cut short or stopped "
            f"early); {unfinished}"
        )
    kinds = []  # (how many, what they are)
    if unreadable:
        src, why = next(iter(unreadable.items()))
        kinds.append((len(unreadable), f"unreadable (the first: {src}: {why})"))
    if empty:
        kinds.append((empty, "without steps after calibration"))
    if left:
        kinds.append((left, f"of unfinished runs ({unfinished})"))
    if len(kinds) == 1:
        return f"no recording to export: all {given} given are {kinds[0][1]}"
    listed = ", ".join(f"{n} {what}" for n, what in kinds)
    return f"no recording to export: of the {given} given, {listed}"


def export_lerobot(
    runs: list[Path],
    out: Path,
    *,
    task: str | None = None,
    fps: int = FPS,
    overwrite: bool = False,
    progress: bool = False,
    unfinished: bool = False,
) -> dict[str, Any]:
    """Write recordings as a LeRobot v3 dataset (layout in the module docstring).

    A recording whose session ended before its task did (aborted by an error or Ctrl-C,
    cut short by a kill, stopped by the ``--max-time`` cap, or a replay of such a run's
    hands: :func:`~payload.trials.reading.cut_reason`) is left out with a warning naming
    it, unless ``unfinished``: its episode would end where the session stopped. A
    recording that cannot be read (damaged, not a trial recording) is left out the same
    way, ``unfinished`` or not, so one bad file does not stop a campaign's export. Each
    episode carries ``payload/ended_by`` (``"source"``, ``"max_time"``, or null: not
    recorded) and ``payload/success`` (the trial's ``metrics.json`` beside the recording;
    null where there is none).

    Args:
        runs: Recordings: ``.mcap`` files, trial folders or campaign folders (see
            :func:`resolve_runs`); one episode each, in the given order.
        out: Dataset root folder (created; must be empty unless ``overwrite``).
        task: Task text for every episode; default: the recording's ``task`` metadata, or
            :data:`DEFAULT_TASK`.
        fps: Frame rate the recordings were taken at [Hz]; checked against them.
        overwrite: Replace ``meta/`` and ``data/`` of an existing dataset at ``out``.
        progress: Show a rich progress bar while reading recordings.
        unfinished: Export the recordings of unfinished runs too.

    Returns:
        ``{"path", "episodes", "frames", "fps", "tasks", "files", "sources", "left_out"}``
        (``left_out``: the unfinished and unreadable recordings not exported, in the order
        given, each ``{"source", "why", "kind"}``, ``kind`` :data:`UNFINISHED` or
        :data:`UNREADABLE`).

    Raises:
        LeRobotExportError: A run is missing or empty, not at ``fps``, every run is
            unfinished (and ``unfinished`` is not set) or unreadable, or ``out`` is not
            empty.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    if fps <= 0:
        raise LeRobotExportError(f"fps must be positive, got {fps}")
    sources = resolve_runs(runs)
    out = Path(out)

    episodes: list[dict[str, Any]] = []
    tasks: list[str] = []
    data_tables: dict[tuple[int, int], list[Any]] = {}
    chunk, file, file_bytes = 0, 0, 0
    index = 0
    all_state, all_action = [], []
    all_idx: dict[str, list[np.ndarray]] = {
        k: [] for k in ("timestamp", "frame_index", "episode_index", "index", "task_index")
    }
    n_state, n_action = len(state_names()), len(action_names())

    def read(src: Path) -> Recording | str:
        """The recording, or why it cannot be read (one damaged file does not stop the
        others; the one recording given alone raises its own error)."""
        try:
            return read_recording(src)
        except RecordingError as exc:
            if len(sources) == 1:
                raise
            return f"{UNREADABLE}: {str(exc).removeprefix(f'{src}: ')}"

    items: Any = sources
    if progress:
        from rich.console import Console
        from rich.progress import track

        items = track(sources, description="reading runs", console=Console(stderr=True))
    read_out = {src: read(src) for src in items}
    unreadable = {src: r for src, r in read_out.items() if isinstance(r, str)}
    loaded = [(src, r) for src, r in read_out.items() if not isinstance(r, str)]
    why = {src: None if unfinished else cut_reason(rec.meta, rec.complete) for src, rec in loaded}
    why.update(unreadable)
    # a session that ended during its calibration has no episode, unfinished or not (one
    # such recording given alone raises its own error, below)
    empty = {
        src for src, rec in loaded if len(sources) > 1 and not np.any(rec.phase != CALIBRATION)
    }
    why.update({src: NO_STEPS for src in empty})
    left_out = [
        {
            "source": str(src),
            "why": why[src],
            "kind": UNREADABLE if src in unreadable else EMPTY if src in empty else UNFINISHED,
        }
        for src in sources
        if why.get(src) is not None
    ]
    if len(left_out) == len(sources):
        raise LeRobotExportError(_nothing_to_export(len(sources), unreadable, len(empty)))
    for item in left_out:
        hint = "; --include-unfinished exports it" if item["kind"] == UNFINISHED else ""
        log.warning("%s: left out (%s%s)", item["source"], item["why"], hint)
    loaded = [(src, rec) for src, rec in loaded if why[src] is None]
    # check every recording before touching an existing dataset at ``out``
    frames = [_episode_frames(rec, src, fps) for src, rec in loaded]
    for src, rec in loaded:  # a seed beyond int64 (typed before the commands refused it)
        seed = rec.meta.get("seed")
        if isinstance(seed, int) and seed > MAX_SEED:
            raise LeRobotExportError(
                f"{src}: seed {seed} does not fit the dataset's seed column (a signed "
                f"64-bit integer, at most {MAX_SEED}); nothing written"
            )
    final, out = out, _prepare_out(out, overwrite)
    for ep, ((src, rec), (state, action)) in enumerate(zip(loaded, frames)):
        n = state.shape[0]
        ep_task = task or str(rec.meta.get("task") or DEFAULT_TASK)
        if ep_task not in tasks:
            tasks.append(ep_task)
        task_index = tasks.index(ep_task)
        frame_index = np.arange(n, dtype=np.int64)
        cols = {
            "observation.state": state.astype(np.float32),
            "action": action.astype(np.float32),
            "timestamp": (frame_index / fps).astype(np.float32),
            "frame_index": frame_index,
            "episode_index": np.full(n, ep, dtype=np.int64),
            "index": np.arange(index, index + n, dtype=np.int64),
            "task_index": np.full(n, task_index, dtype=np.int64),
        }
        ep_bytes = sum(c.nbytes for c in cols.values())
        if file_bytes and file_bytes + ep_bytes > DATA_FILE_SIZE_MB * 1024**2:
            file += 1
            if file == CHUNKS_SIZE:
                chunk, file = chunk + 1, 0
            file_bytes = 0
        file_bytes += ep_bytes
        table = pa.table(
            {
                "observation.state": _fixed_list(cols["observation.state"], n_state),
                "action": _fixed_list(cols["action"], n_action),
                **{k: pa.array(cols[k]) for k in all_idx},
            }
        )
        data_tables.setdefault((chunk, file), []).append(table)
        ep_stats = {
            "observation.state": _stats(cols["observation.state"]),
            "action": _stats(cols["action"]),
            **{k: _stats(cols[k][:, None]) for k in all_idx},
        }
        row: dict[str, Any] = {
            "episode_index": ep,
            "tasks": [ep_task],
            "length": n,
            "data/chunk_index": chunk,
            "data/file_index": file,
            "dataset_from_index": index,
            "dataset_to_index": index + n,
            "meta/episodes/chunk_index": 0,
            "meta/episodes/file_index": 0,
            "payload/source": str(src),
            "payload/seed": rec.meta.get("seed"),
            "payload/ended_by": rec.meta.get("ended_by"),
            "payload/success": _trial_success(src),
        }
        for feat, st in ep_stats.items():
            for key, val in st.items():
                row[f"stats/{feat}/{key}"] = val
        episodes.append(row)
        all_state.append(cols["observation.state"])
        all_action.append(cols["action"])
        for k in all_idx:
            all_idx[k].append(cols[k])
        index += n

    files = []
    for (c, f), tables in sorted(data_tables.items()):
        path = out / DATA_PATH.format(chunk_index=c, file_index=f)
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.concat_tables(tables), path)
        files.append(str(path.relative_to(out)))

    ep_path = out / EPISODES_PATH.format(chunk_index=0, file_index=0)
    ep_path.parent.mkdir(parents=True, exist_ok=True)
    ep_table = pa.Table.from_pylist(episodes)
    pq.write_table(ep_table, ep_path)
    pq.write_table(_tasks_table(tasks), out / "meta" / "tasks.parquet")

    stats = {
        "observation.state": _stats(np.concatenate(all_state)),
        "action": _stats(np.concatenate(all_action)),
        **{k: _stats(np.concatenate(v)[:, None]) for k, v in all_idx.items()},
    }
    (out / "meta" / "stats.json").write_text(json.dumps(stats, indent=2, allow_nan=False) + "\n")

    scalar = {"shape": [1], "names": None}
    info = {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": ROBOT_TYPE,
        "total_episodes": len(episodes),
        "total_frames": index,
        "total_tasks": len(tasks),
        "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": DATA_FILE_SIZE_MB,
        "video_files_size_in_mb": VIDEO_FILE_SIZE_MB,
        "fps": fps,
        "splits": {"train": f"0:{len(episodes)}"},
        "data_path": DATA_PATH,
        "video_path": None,
        "features": {
            "observation.state": {"dtype": "float32", "shape": [n_state], "names": state_names()},
            "action": {"dtype": "float32", "shape": [n_action], "names": action_names()},
            "timestamp": {"dtype": "float32", **scalar},
            "frame_index": {"dtype": "int64", **scalar},
            "episode_index": {"dtype": "int64", **scalar},
            "index": {"dtype": "int64", **scalar},
            "task_index": {"dtype": "int64", **scalar},
        },
    }
    (out / "meta" / "info.json").write_text(json.dumps(info, indent=4) + "\n")
    _swap_in(out, final)
    return {
        "path": str(final),
        "episodes": len(episodes),
        "frames": index,
        "fps": fps,
        "tasks": tasks,
        "files": files,
        "sources": [str(src) for src, _ in loaded],
        "left_out": left_out,
        "duration_s": index / fps,
    }


__all__ = [
    "CODEBASE_VERSION",
    "DEFAULT_TASK",
    "FPS",
    "LeRobotExportError",
    "action_matrix",
    "action_names",
    "export_lerobot",
    "resolve_runs",
    "state_matrix",
    "state_names",
]
