"""A campaign's per-trial results read from its ``trial-*`` folders: each trial's
``metrics.json`` read and checked field by field, or its recording scored (or rescored
with another contact definition); a trial whose recording is not a finished run's is an
error row.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from payload.errors import PayloadError
from payload.folders import METRICS, RECORDING, SUMMARY, held
from payload.safeio import OverwriteError
from payload.trials.scoring import finish_trial
from payload.trials.summary_fields import METRIC_KEYS, CampaignError


def _unfinished(meta: dict[str, Any] | None, complete: bool) -> str | None:
    """The error row's text of a trial whose recording is not a finished run's
    (:func:`~payload.trials.reading.unfinished_reason`), or ``None``."""
    from payload.trials.reading import unfinished_reason

    why = unfinished_reason(meta or {}, complete)
    return None if why is None else f"{RECORDING}: {why}; not scored"


def read_metrics(path: Path) -> dict[str, Any]:
    """A trial's ``metrics.json``.

    Raises:
        CampaignError: Unreadable, not JSON (cut short, binary) or not a JSON object: one
            line naming the file; or a field a summary reads has a value of the wrong
            kind (``success`` missing or not true or false, a figure that is not a number
            or null...): one line naming the file, the field and what was expected.
    """
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:  # JSON and UTF-8 errors are ValueErrors
        raise CampaignError(f"{path}: cannot read the trial's metrics ({exc})") from None
    if not isinstance(data, dict):
        raise CampaignError(f"{path}: cannot read the trial's metrics (not a JSON object)")
    if "success" not in data:
        raise CampaignError(f"{path}: success: missing (not a trial's metrics)")
    _check_metrics(data, str(path))
    _check_metrics(data.get("literal") or {}, f"{path}: literal")
    return data


_METRIC_KINDS: dict[str, Any] = {
    **dict.fromkeys(("success", "acquired", "complete"), "bool"),
    **dict.fromkeys(
        (*METRIC_KEYS, "min_interval_s", "max_gap_s", "physics_dt", "wall_s"), "float_nan"
    ),
    **dict.fromkeys(("final_module", "ctb", "propulsion", "error"), "text"),
}
"""The type of each field a summary or a comparison reads from ``metrics.json`` (null is
allowed for every number and text; older files may leave any of them out)."""


def _check_metrics(data: Any, where: str) -> None:
    """Raise :class:`CampaignError` naming the file and field of the first value that a
    summary cannot use (a metrics file edited by hand, or written by another tool)."""
    from payload.trials.stepcheck import field_problem

    if not isinstance(data, dict):
        raise CampaignError(f"{where}: expected a JSON object, got {type(data).__name__}")
    seed = data.get("seed")
    if seed is not None and (not isinstance(seed, int) or isinstance(seed, bool) or seed < 0):
        raise CampaignError(f"{where}: seed: expected an integer >= 0 or null, got {seed!r}")
    for key, kind in _METRIC_KINDS.items():
        value = data.get(key)
        if value is None:
            continue
        if kind == "text":
            problem = None if isinstance(value, str) else f"got {value!r}"
            problem = problem and f"expected text or null, {problem}"
        else:
            problem = field_problem(value, (), kind)
        if problem is not None:
            raise CampaignError(f"{where}: {key}: {problem}")


def _one_campaign(root: Path, dirs: list[Path], recording_meta: Any) -> None:
    """Refuse a folder whose trials are not one campaign's: two of them of one seed (a
    campaign runs each seed once; a project's ``runs/`` holds separate runs, and their
    summary would say "seeds 0 to 0" of a mix). Each trial's seed as it recorded it
    (``metrics.json``, else its recording's metadata), else its folder's number."""
    seen: dict[int, list[str]] = {}
    for d in dirs:
        seed: Any = None
        if (d / METRICS).is_file():
            try:
                seed = read_metrics(d / METRICS).get("seed")
            except CampaignError:
                seed = None  # refused with its own words below
        elif (d / RECORDING).is_file():
            seed = (recording_meta(d / RECORDING) or {}).get("seed")
        if not isinstance(seed, int) or isinstance(seed, bool):
            number = d.name.split("-", 1)[1]
            seed = int(number) if number.isdigit() else None
        if seed is not None:
            seen.setdefault(seed, []).append(d.name)
    twice = sorted((s, names) for s, names in seen.items() if len(names) > 1)
    if twice:
        seed, names = twice[0]
        named = f"{', '.join(names[:-1])} and {names[-1]}"
        raise CampaignError(
            f"{root}: not one campaign: {named} are {'both' if len(names) == 2 else 'all'} "
            f"seed {seed} (a campaign "
            "runs each seed once; give a campaign's folder, or set runs side by side with "
            "`payload trials compare`)"
        )


def load_trial_results(
    out_dir: str | Path,
    recompute: bool = False,
    *,
    min_interval_s: float | None = None,
    max_gap_s: float | None = None,
    force: bool = False,
) -> list[dict[str, Any]]:
    """Per-trial results from a campaign folder's ``trial-*`` folders, ordered by seed.

    Args:
        out_dir: The campaign folder.
        recompute: Rescore every trial from its ``log.mcap`` instead of reading
            ``metrics.json``, writing the results beside the originals, named by the
            contact definition (see :func:`finish_trial`); a trial without
            ``metrics.json`` is scored, unless its recording is an aborted trial's or was
            cut short (never closed): that trial is an ``error`` row, a failure.
        min_interval_s: Contact-interval definition used when rescoring (0 = paper;
            None = the one each recording was made with).
        max_gap_s: Same for the bridged indicator dropouts.
        force: Replace rescoring files that exist with other content.

    Raises:
        CampaignError: The folder does not exist or holds no trial folders.
        OverwriteError: A rescoring file exists with other content and ``force`` is false.
        DamagedRecordingError: A recording read for scoring is damaged.
        CampaignError: A trial's ``metrics.json`` cannot be read (:func:`read_metrics`).
    """
    root = Path(out_dir)
    if root.exists() and not root.is_dir():
        raise CampaignError(f"{root}: a file, not a campaign folder")
    if not root.is_dir():
        raise CampaignError(f"{root}: no such campaign folder")
    dirs = sorted(p for p in root.glob("trial-*") if p.is_dir())
    if not dirs:
        if held(root, (RECORDING, METRICS)):  # a trial's own folder, given for a campaign's
            raise CampaignError(
                f"{root}: a trial's folder, not a campaign's (no trial-* folders); give the "
                "campaign folder that holds it"
            )
        if held(root, (SUMMARY,)):  # a kept summary (analyses/campaign/*): no trials
            raise CampaignError(
                f"{root}: a campaign's summary without its trial-* folders: nothing to "
                "summarize again (`payload trials run` makes a campaign with its trials)"
            )
        raise CampaignError(f"{root}: no trial-* folders")
    from payload.trials.reading import read_recording, recording_meta
    from payload.trials.records import DamagedRecordingError

    _one_campaign(root, dirs, recording_meta)

    # every recording to be scored is read first: a damaged one stops the summary before
    # anything is written (a re-scoring beside an earlier trial's metrics, say)
    reads: dict[Path, Any] = {}
    for d in dirs:
        if (recompute or not (d / METRICS).exists()) and (d / RECORDING).exists():
            try:
                reads[d] = read_recording(d / RECORDING)
            except DamagedRecordingError:
                raise  # damage is not a trial's failure: nothing is scored from it
            except PayloadError as exc:
                reads[d] = exc
    results = []
    for d in dirs:
        try:
            seed: int | None = int(d.name.split("-", 1)[1])
        except ValueError:
            seed = None
        metrics_path = d / METRICS
        if recompute or not metrics_path.exists():
            if not (d / RECORDING).exists():
                why = f"no {RECORDING} to rescore" if metrics_path.exists() else (
                    f"no {RECORDING} and no {METRICS}")  # fmt: skip
                results.append({"seed": seed, "out_dir": str(d), "error": why})
                continue
            rec = reads[d]
            if isinstance(rec, PayloadError):
                results.append({"seed": seed, "out_dir": str(d), "error": str(rec)})
                continue
            try:
                unfinished = _unfinished(rec.meta, rec.complete)
                if unfinished:  # as the runner leaves it: a record, not a scored trial
                    results.append({"seed": seed, "out_dir": str(d), "error": unfinished})
                    continue
                row = finish_trial(
                    d,
                    d / RECORDING,
                    min_interval_s=min_interval_s,
                    max_gap_s=max_gap_s,
                    beside=recompute,
                    force=force,
                    recording=rec,
                )
            except OverwriteError:
                raise
            except PayloadError as exc:
                results.append({"seed": seed, "out_dir": str(d), "error": str(exc)})
                continue
        else:
            row = read_metrics(metrics_path)
            # scored before summaries checked: an aborted run's metrics.json does not say
            # so, its recording's metadata does (read through the file's index)
            meta = recording_meta(d / RECORDING)
            unfinished = _unfinished(meta, row.get("complete", True))
            if unfinished:
                results.append({"seed": seed, "out_dir": str(d), "error": unfinished})
                continue
        row.setdefault("error", None)
        if row.get("seed") is None:
            row["seed"] = seed
        row["out_dir"] = str(d)
        results.append(row)
    return sorted(results, key=lambda r: (r.get("seed") is None, r.get("seed") or 0))


__all__ = ["load_trial_results", "read_metrics"]
