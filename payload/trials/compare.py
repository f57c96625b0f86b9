"""``payload trials compare RUN_A RUN_B``: two runs of the same seeds, seed by seed.

A run is a campaign folder (``trial-NNNN`` folders), one trial folder, or a campaign's
summary kept without its trials (``summary.json`` alone, as ``analyses/campaign/*``
commits it: its per-trial rows, at full precision, and its set-up). Trials are matched
by folder name (the seed). Per seed the change ``B - A`` of every metric the
paper summarises, and per metric the largest change over the seeds; with ``steps``,
every recorded step of both recordings compared field by field (every field of
:data:`~payload.trials.records.FIELD_SPECS`; ``seq`` and ``wall_time`` are not
compared), counting the steps that differ in any bit, every message of the other
channels (hand frames, Foxglove, safety records; the wall-clock timestamps aside) and
every other metric of ``metrics.json`` but the provenance and what ended the session
(:data:`NOT_RESULTS`).

Uses: the validation of ``--physics-dt 0.002`` (the ``single`` campaign at 2 ms against
1 ms), and the bit-for-bit check of a speed change (the same seeds before and after).
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path
from typing import Any

import numpy as np

from payload.errors import PayloadError
from payload.folders import METRICS, RECORDING, SUMMARY, trial_dir
from payload.schema import ENDED_BY_CAP
from payload.teleop.live import SIMULATOR
from payload.trials.records import FIELD_SPECS, HANDS_TOPIC, STEP_TOPIC, RecordingError
from payload.trials.scoring import same_value
from payload.trials.setup_options import RUN_SETTINGS
from payload.trials.summary_fields import CAP_STOPPED, METRIC_KEYS, METRIC_LABELS
from payload.trials.trial_results import read_metrics

NOT_RESULTS = ("provenance", "ended_by", "device", "replay", "loop_overruns")
"""``metrics.json`` fields a step comparison leaves out: where and with what a run was
made (a hardware run's serial device and the path of the recording it replayed among
them, and how often its paced loop ran late: the host's timing), and what ended its
session (a replay of a trial cut off by ``--max-time`` ends
with its source's last frame at the same step: the recorded steps say where it ended)."""


class CompareError(PayloadError):
    """A run to compare is missing or unreadable, or two runs share no seed."""


def _trials(run: Path) -> dict[str, Path | dict[str, Any]]:
    """Trials of a run by name: a campaign's ``trial-*`` folders, the folder itself, or a
    summary's rows (each its metrics, with the summary's set-up) where the campaign's
    folder holds its ``summary.json`` without trial folders."""
    if run.is_file() and run.name in (METRICS, RECORDING):
        raise CompareError(f"{run}: a trial's file; give its folder, {run.parent}")
    if run.is_file() and run.name == SUMMARY:
        raise CompareError(f"{run}: a campaign's summary; give its folder, {run.parent}")
    if not run.is_dir():
        raise CompareError(f"{run}: no such trial or campaign folder")
    if (run / METRICS).is_file() or (run / RECORDING).is_file():
        return {run.name: run}
    found: dict[str, Path | dict[str, Any]] = {
        p.name: p for p in sorted(run.glob("trial-*")) if p.is_dir()
    }
    if not found and (run / SUMMARY).is_file():
        found = _summary_rows(run / SUMMARY)
    if not found:
        raise CompareError(f"{run}: no {METRICS}, no trial-* folders and no {SUMMARY}")
    return found


def _summary_rows(path: Path) -> dict[str, dict[str, Any]]:
    """A campaign summary's trials as metrics by trial folder name: each row (the metrics
    at full precision) with the campaign's set-up (:data:`RUN_SETTINGS`, the summary's;
    a setting the trials did not share, or none recorded, is left out: no row's own)."""
    try:
        summary = json.loads(path.read_text(encoding="utf-8"))
        rows = summary["trials"]
        known = (k for k in RUN_SETTINGS if k in summary)  # a mixed or unknown one is no row's
        setup = {k: summary[k] for k in known if not isinstance(summary[k], (dict, type(None)))}
        station = summary.get("station") or {}
        for key in ("base_filter", "link_delay"):  # the station block's, written as text
            if key not in setup and isinstance(station.get(key), str):
                setup[key] = _setting_value(station[key])
        return {trial_dir("", int(r["seed"])).name: {**setup, **r} for r in rows}
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
        why = exc.strerror if isinstance(exc, OSError) else f"not a campaign summary ({exc!r})"
        raise CompareError(f"{path}: {why}") from None


def _setting_value(text: str) -> Any:
    """A setting a summary's station block writes as the text of its value (``"False"``,
    ``"[1.0, 0.2]"``) as that value; a mixed one as its text."""
    if text in ("True", "False"):
        return text == "True"
    try:
        return json.loads(text)
    except ValueError:
        return text


def _trial_metrics(trial: Path | dict[str, Any]) -> dict[str, Any]:
    """A trial's ``metrics.json`` (or its summary row); a trial that has none but a
    recording is said to be unscored, with why (aborted, killed) where its recording says.

    Raises:
        CompareError: No metrics to compare (one line naming the trial and why).
        CampaignError: The metrics file is unreadable (:func:`read_metrics`).
    """
    if isinstance(trial, dict):
        return trial
    if not (trial / METRICS).is_file() and (trial / RECORDING).is_file():
        from payload.trials.reading import recording_meta, unfinished_reason

        meta = recording_meta(trial / RECORDING)
        why = unfinished_reason(meta or {}, meta is not None)
        state = f"an unfinished run ({why})" if why else "a run not scored"
        raise CompareError(f"{trial}: {state}: it has no {METRICS} to compare")
    return read_metrics(trial / METRICS)


def _setup_value(metrics: dict[str, Any], key: str) -> Any:
    """A trial's setting as compared: its recorded value; the driver of a trial that
    records none is the simulator's (only a hardware run records one)."""
    if key == "driver":
        return metrics.get("driver") or SIMULATOR
    return metrics.get(key)


def _change(a: Any, b: Any) -> float | None:
    """``b - a`` for two numbers; None where either is missing or not finite."""
    if not isinstance(a, (int, float)) or not isinstance(b, (int, float)):
        return None
    if isinstance(a, bool) or isinstance(b, bool):
        return None
    d = float(b) - float(a)
    return d if math.isfinite(d) else None


def compare_steps(log_a: Path, log_b: Path) -> dict[str, Any]:
    """Every recorded step of two recordings, field by field, bit for bit.

    Args:
        log_a: The first ``log.mcap``.
        log_b: The second.

    Returns:
        ``{"steps_a", "steps_b", "identical" (same step count and every field's bits),
        "differing_steps" (steps of the common length where any field differs),
        "first_differing_step" (index or None), "fields": {name: largest absolute
        difference (numbers; NaN where one side is NaN and the other not) or the count
        of differing steps (text and flags)}}`` with only the differing fields listed.
    """
    from payload.trials.reading import read_recording

    a, b = read_recording(log_a), read_recording(log_b)
    n = min(len(a), len(b))
    differs = np.zeros(n, dtype=bool)
    fields: dict[str, float | int] = {}
    for name, (_shape, kind) in FIELD_SPECS.items():
        x, y = getattr(a, name)[:n], getattr(b, name)[:n]
        if isinstance(kind, tuple) or kind == "bool":
            row = x != y
        else:  # bits: NaN equals NaN, -0.0 differs from 0.0
            xb = np.ascontiguousarray(x, dtype=np.float64).view(np.uint64)
            yb = np.ascontiguousarray(y, dtype=np.float64).view(np.uint64)
            row = (xb != yb).reshape(n, -1).any(axis=1)
        row = np.asarray(row).reshape(n, -1).any(axis=1)
        if row.any():
            differs |= row
            if isinstance(kind, tuple) or kind == "bool":
                fields[name] = int(row.sum())
            else:
                with np.errstate(invalid="ignore"):
                    gap = np.abs(np.asarray(x, float) - np.asarray(y, float))
                fields[name] = float(np.nanmax(gap)) if not np.isnan(gap).all() else math.nan
    first = int(np.argmax(differs)) if differs.any() else None
    return {
        "steps_a": len(a),
        "steps_b": len(b),
        "identical": len(a) == len(b) and not differs.any(),
        "differing_steps": int(differs.sum()),
        "first_differing_step": first,
        "fields": fields,
    }


def _without_timestamps(message: Any) -> Any:
    """``message`` with every ``google.protobuf.Timestamp`` in it cleared, at any depth
    (the Foxglove channels stamp their messages with the wall clock at the start plus the
    step time; the message's log time, compared relative to the recording's first, keeps
    the step)."""
    for field, value in message.ListFields():
        if field.message_type is None:
            continue
        if field.message_type.full_name == "google.protobuf.Timestamp":
            message.ClearField(field.name)
        elif field.is_repeated:  # a repeated message field (maps are not used here)
            for item in value:
                _without_timestamps(item)
        else:
            _without_timestamps(value)
    return message


def _hand_sample(sample: dict[str, Any]) -> bytes:
    """A decoded hand sample as comparable bytes (the joints' bits, NaN rows included)."""
    head = struct.pack(
        "<qd??", sample["seq"], sample["stamp"], sample["left_tracked"], sample["right_tracked"]
    )
    return head + np.asarray(sample["left"]).tobytes() + np.asarray(sample["right"]).tobytes()


def _channel_messages(log: Path) -> dict[str, list[bytes]]:
    """Every message of every channel but the steps', in order, as comparable bytes: its
    log time relative to the recording's first message (the wall clock at the start
    cancels), then its content: the raw hand samples decoded (their delta encoding
    restarts at each flush, which the wall clock decides), the other protobuf messages
    re-serialised without their timestamps, the rest as written."""
    from google.protobuf.message import DecodeError
    from mcap_protobuf.decoder import DecoderFactory

    from payload.trials.codec import StepCodec
    from payload.trials.reading import read_messages

    try:
        messages = read_messages(log)
    except RecordingError as exc:
        raise CompareError(str(exc)) from None
    decoders, hands = DecoderFactory(), StepCodec()
    t0 = messages[0][2].log_time if messages else 0
    out: dict[str, list[bytes]] = {}
    for channel, schema, message in messages:
        if channel.topic == STEP_TOPIC:
            continue  # compare_steps compares them (their wall_time is the clock's)
        data = message.data
        try:
            if channel.topic == HANDS_TOPIC:
                data = _hand_sample(hands.decode_hands(data))
            elif channel.message_encoding == "protobuf" and schema is not None:
                decode = decoders.decoder_for(channel.message_encoding, schema)
                if decode is not None:
                    data = _without_timestamps(decode(data)).SerializeToString()
        except (DecodeError, ValueError) as exc:
            raise CompareError(f"{log}: {channel.topic}: a corrupt message ({exc})") from None
        out.setdefault(channel.topic, []).append(struct.pack("<q", message.log_time - t0) + data)
    return out


def compare_channels(log_a: Path, log_b: Path) -> dict[str, Any]:
    """Every message of every other channel of two recordings (the raw hand frames, the
    Foxglove channels, the safety records), in order, bit for bit, at the same time
    relative to the recording's start, their wall-clock timestamps aside.

    Returns:
        ``{"identical", "channels": {topic: {"messages_a", "messages_b",
        "differing"}}}`` (``differing``: messages of the common length whose bytes
        differ; a channel in one recording only counts all its messages).
    """
    a, b = _channel_messages(log_a), _channel_messages(log_b)
    channels = {}
    for topic in sorted(set(a) | set(b)):
        ma, mb = a.get(topic, []), b.get(topic, [])
        n = min(len(ma), len(mb))
        differing = sum(x != y for x, y in zip(ma[:n], mb[:n])) + abs(len(ma) - len(mb))
        channels[topic] = {"messages_a": len(ma), "messages_b": len(mb), "differing": differing}
    return {
        "identical": all(c["differing"] == 0 for c in channels.values()),
        "channels": channels,
    }


def compare_runs(run_a: str | Path, run_b: str | Path, *, steps: bool = False) -> dict[str, Any]:
    """Two runs of the same seeds, seed by seed.

    Args:
        run_a: Campaign or trial folder (the reference).
        run_b: Campaign or trial folder (the one compared with it).
        steps: Also compare every recorded step (:func:`compare_steps`), every message of
            the recordings' other channels (:func:`compare_channels`) and every metric
            in ``metrics.json`` but :data:`NOT_RESULTS`.

    Returns:
        ``{"a", "b", "trials": [{"trial", "seed_a", "seed_b", "setup_differs" ({setting:
        [a, b]} where the two differ), "success_a", "success_b", "physics_dt_a",
        "physics_dt_b", "metrics": {key: {"a", "b", "change"}}, "steps"?}],
        "largest_change": {key: {"change" (signed, largest in size), "trial"}},
        "only_a", "only_b" (trial names in one run only), "identical" (with ``steps``:
        the same trials in both, every trial's metrics the same as written, its steps
        and its other channels' messages bit for bit)}``; with ``steps`` each trial also
        has ``"channels"`` and ``"other_metrics"`` (the names of the other metrics that
        differ).

    Raises:
        CompareError: A run is missing, a metrics file unreadable, or no trial in common.
    """
    a_dir, b_dir = Path(run_a), Path(run_b)
    ta, tb = _trials(a_dir), _trials(b_dir)
    for run, trials in ((a_dir, ta), (b_dir, tb)):
        if steps and any(isinstance(t, dict) for t in trials.values()):
            raise CompareError(
                f"{run}: a campaign's summary without its trials' recordings: its steps "
                "cannot be compared (--steps and --require-identical need the recordings; "
                "without either its metrics are compared)"
            )
    if len(ta) == 1 and len(tb) == 1:  # two single trials: compare them whatever their names
        common = [(next(iter(ta)), next(iter(tb)))]
    elif 1 in (len(ta), len(tb)):  # one trial against a campaign: its seed's, whatever the
        one, many = (ta, tb) if len(ta) == 1 else (tb, ta)  # folder's name (a --force rerun
        alone = next(iter(one))  # of runs/trial-0003 may hold another seed); no seed: its name
        seed = _trial_metrics(one[alone]).get("seed")
        name = trial_dir("", seed).name if isinstance(seed, int) else None
        if name in many:
            common = [(alone, name) if one is ta else (name, alone)]
        else:
            common = [(n, n) for n in ta if n in tb]
    else:
        common = [(name, name) for name in ta if name in tb]
    if not common:
        raise CompareError(f"{a_dir} and {b_dir} have no trial (seed) in common")
    rows = []
    largest: dict[str, dict[str, Any]] = {}
    identical = True
    for name_a, name_b in common:
        ma, mb = _trial_metrics(ta[name_a]), _trial_metrics(tb[name_b])
        metrics = {}
        for key in METRIC_KEYS:
            change = _change(ma.get(key), mb.get(key))
            metrics[key] = {"a": ma.get(key), "b": mb.get(key), "change": change}
            if not same_value(ma.get(key), mb.get(key)):
                identical = False
            best = largest.get(key)
            if change is not None and (best is None or abs(change) > abs(best["change"])):
                largest[key] = {"change": change, "trial": name_b}
        row: dict[str, Any] = {
            "trial": name_b,
            "trial_a": name_a,  # another name only when two single trials are compared
            "seed_a": ma.get("seed"),
            "seed_b": mb.get("seed"),
            "setup_differs": {
                k: [_setup_value(ma, k), _setup_value(mb, k)]
                for k in (*RUN_SETTINGS, "driver")
                if (k in ma or k in mb) and not same_value(_setup_value(ma, k), _setup_value(mb, k))
            },
            "success_a": ma.get("success"),
            "success_b": mb.get("success"),
            "physics_dt_a": ma.get("physics_dt"),
            "physics_dt_b": mb.get("physics_dt"),
            "ended_by_a": ma.get("ended_by"),
            "ended_by_b": mb.get("ended_by"),
            "metrics": metrics,
        }
        if ma.get("success") != mb.get("success"):
            identical = False
        if steps:
            log_a, log_b = Path(ta[name_a]) / RECORDING, Path(tb[name_b]) / RECORDING  # type: ignore[arg-type]
            row["steps"] = compare_steps(log_a, log_b)
            row["channels"] = compare_channels(log_a, log_b)
            row["other_metrics"] = sorted(
                key
                for key in (set(ma) | set(mb)) - {*NOT_RESULTS, *METRIC_KEYS}
                if not same_value(ma.get(key), mb.get(key))
            )
            identical = (
                identical
                and row["steps"]["identical"]
                and row["channels"]["identical"]
                and not row["other_metrics"]
            )
        rows.append(row)
    names_a = {x for x, _ in common}
    names_b = {y for _, y in common}
    return {
        "a": str(a_dir),
        "b": str(b_dir),
        "trials": rows,
        "largest_change": largest,
        "only_a": sorted(set(ta) - names_a),
        "only_b": sorted(set(tb) - names_b),
        # a trial in one run only is a difference too
        "identical": (identical and names_a == set(ta) and names_b == set(tb)) if steps else None,
    }


def _num(value: Any) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, bool):
        return "yes" if value else "no"
    return f"{value:.3f}" if isinstance(value, (int, float)) else str(value)


def _setting(value: Any) -> str:
    """A setup setting as given (a physics step of 0.0001 s is not "0.000")."""
    if isinstance(value, float):
        return f"{value:g}"
    return _num(value)


COMPARISON_OPENING = "Comparison of "
"""How a comparison's Markdown begins (``trials compare --out F --force`` replaces only
a file that begins so)."""


def comparison_notes(result: dict[str, Any]) -> list[str]:
    """What a reader must know before the table: trials of different seeds put side by
    side (two single trials are compared whatever their names), trials the ``--max-time``
    cap cut short, and the settings the two runs' trials ran with where they differ
    (``setting A / B``)."""
    notes = []
    for row in result["trials"]:
        a, b = row.get("seed_a"), row.get("seed_b")
        if a is not None and b is not None and a != b:
            notes.append(
                f"Trial `{shown_name(row)}` is seed {b} in B and seed {a} in A: different "
                "operator sessions, so its changes are not the setup's alone."
            )
    for row in result["trials"]:
        cut = [side for side in ("A", "B") if row.get(f"ended_by_{side.lower()}") == ENDED_BY_CAP]
        if cut:
            notes.append(
                f"Trial `{shown_name(row)}` was {CAP_STOPPED} in "
                f"{' and '.join(cut)}: a session cut short, so its metrics are not a whole "
                "trial's."
            )
    differ: dict[str, set[str]] = {}
    for row in result["trials"]:
        for key, (a, b) in row.get("setup_differs", {}).items():
            differ.setdefault(key, set()).add(f"{_setting(a)} / {_setting(b)}")
    if differ:
        said = "; ".join(f"{k} {', '.join(sorted(v))}" for k, v in differ.items())
        notes.append(f"Setup, A / B, where it differs: {said}.")
    return notes


def shown_name(row: dict[str, Any]) -> str:
    """A row's trial as the tables show it: its name, or ``A's / B's`` where two single
    trials of different names are compared."""
    a = row.get("trial_a", row["trial"])
    return row["trial"] if a == row["trial"] else f"{a} / {row['trial']}"


def compare_markdown(result: dict[str, Any]) -> str:
    """The comparison as a Markdown table: per seed each metric's A, B and change, then
    the largest change of each metric (and the step comparison when it was made)."""
    keys = METRIC_KEYS
    head = ["trial", "success A/B", *(f"{k} A / B (change)" for k in keys)]
    lines = [
        f"{COMPARISON_OPENING}`{result['b']}` (B) against `{result['a']}` (A), seed by seed.",
        "",
        *(f"{note}\n" for note in comparison_notes(result)),
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for row in result["trials"]:
        cells = [shown_name(row), f"{_num(row['success_a'])} / {_num(row['success_b'])}"]
        for k in keys:
            m = row["metrics"][k]
            change = "n/a" if m["change"] is None else f"{m['change']:+.3f}"
            cells.append(f"{_num(m['a'])} / {_num(m['b'])} ({change})")
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "| metric | largest change (B - A) | trial |", "|---|---|---|"]
    for k in keys:
        best = result["largest_change"].get(k)
        if best is None:
            lines.append(f"| {METRIC_LABELS[k]} | n/a | |")
        else:
            lines.append(f"| {METRIC_LABELS[k]} | {best['change']:+.4g} | {best['trial']} |")
    with_steps = [r for r in result["trials"] if "steps" in r]
    if with_steps:
        lines += [
            "",
            "| trial | steps A / B | differing steps | first "
            "| fields (largest difference; text and flags: differing steps) |",
            "|---|---|---|---|---|",
        ]
        for r in with_steps:
            s = r["steps"]
            fields = ", ".join(f"{k} {v:.3g}" for k, v in s["fields"].items()) or "none"
            differing = f"{s['differing_steps']}"
            if s["steps_a"] != s["steps_b"]:  # compared over the shorter run's steps only
                differing += f" of the first {min(s['steps_a'], s['steps_b'])}"
            lines.append(
                f"| {shown_name(r)} | {s['steps_a']} / {s['steps_b']} | {differing} | "
                f"{s['first_differing_step'] if s['first_differing_step'] is not None else '-'}"
                f" | {fields} |"
            )
    with_channels = [r for r in result["trials"] if "channels" in r]
    if with_channels:
        lines += ["", "| trial | other channels: differing messages | other metrics differing |"]
        lines += ["|---|---|---|"]
        for r in with_channels:
            chans = r["channels"]["channels"]
            counts = ", ".join(
                f"{t} {c['differing']} of {max(c['messages_a'], c['messages_b'])}"
                for t, c in chans.items()
                if c["differing"]
            )
            total = sum(max(c["messages_a"], c["messages_b"]) for c in chans.values())
            counts = counts or f"none ({len(chans)} channels, {total} messages)"
            lines.append(
                f"| {shown_name(r)} | {counts} | {', '.join(r['other_metrics']) or 'none'} |"
            )
    if result["only_a"] or result["only_b"]:
        only = [
            f"only in {side}: {', '.join(result[key])}"
            for side, key in (("A", "only_a"), ("B", "only_b"))
            if result[key]
        ]
        lines += ["", f"Not compared, {'; '.join(only)}."]
    return "\n".join(lines) + "\n"


__all__ = [
    "COMPARISON_OPENING",
    "CompareError",
    "compare_channels",
    "compare_markdown",
    "compare_runs",
    "compare_steps",
    "shown_name",
]
