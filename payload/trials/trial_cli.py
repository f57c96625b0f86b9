"""``payload trial``: one trial, synthetic or a replay of a recording's hands (contract in
docs/cli.md; registered by :mod:`payload.trials.cli`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from payload.cliutil import check_seconds, command_project, emit_json, out_folder, replay_file, warn
from payload.folders import CAMPAIGN_FILES, TRIAL_FILES, held, other_results
from payload.profiles import PROFILE_SETTINGS
from payload.trials.setup_options import (
    _SETUP,
    TrialsCliError,
    _check_ctb,
    _check_physics_dt,
    _link_and_zones,
    _setup_defaults,
    cap_before_teleoperation,
    seed_problem,
)


def _parse_operator(args: argparse.Namespace) -> tuple[str, Path | None]:
    """The operator of ``payload trial``: ``--replay FILE``, else synthetic; or the
    deprecated ``--operator synthetic|replay FILE``.

    Raises:
        TrialsCliError: Both spellings, a bad ``--operator`` or no such file.
    """
    values = getattr(args, "operator", None)
    if values is None:
        if args.replay is None:
            return "synthetic", None
        return "replay", replay_file("--replay", Path(args.replay))
    if args.replay is not None:
        raise TrialsCliError("--replay and --operator (its deprecated spelling): give one")
    if values == ["synthetic"]:
        return "synthetic", None
    if len(values) == 2 and values[0] == "replay":
        return "replay", replay_file("--operator replay", Path(values[1]))
    raise TrialsCliError(
        f"--operator: expected 'synthetic' or 'replay FILE', got {' '.join(values)!r}"
    )


def _cmd_trial(args: argparse.Namespace) -> int:
    from payload.design import models_follow_design
    from payload.envelope.stowed_fit import stowed_fit_warning
    from payload.trials.runner import run_trial

    if args.seed is not None and (problem := seed_problem(args.seed)) is not None:
        raise TrialsCliError(f"--seed {problem}")
    check_seconds("--max-time", args.max_time, cap=True)
    _check_physics_dt(args.physics_dt)
    operator, replay = _parse_operator(args)
    if operator == "synthetic":
        _setup_defaults(args)
    if args.ctb is not None:
        _check_ctb(args.ctb)
    project = command_project(args)
    models_follow_design(project.design_path, project.root, json=args.json)
    out = out_folder(args.out, holding=other_results("trial"))  # its own: --force
    extra: dict[str, Any] = {"project": project, **_link_and_zones(args)}
    for name in _SETUP:
        if getattr(args, name) is not None:  # a replay: the others are its recording's
            extra[name] = getattr(args, name)
    if not args.json and sys.stderr.isatty():
        extra["progress"] = True
    if args.max_time is not None:
        extra["max_time"] = args.max_time
    if args.force:
        extra["force"] = True
    campaign = None
    if out is not None and out.name.startswith("trial-"):
        campaign = held(out.parent, CAMPAIGN_FILES) or None
    seed = args.seed if args.seed is not None or operator == "replay" else 0
    result = dict(run_trial(seed=seed, operator=operator, replay=replay, out_dir=out, **extra))
    out = Path(result.get("out_dir") or out)
    seed = result.get("seed", seed)
    cap_before_teleoperation(args.max_time)  # after the run: no bad input follows it
    if (unfit := stowed_fit_warning(project.design_path, "the trial ran")) is not None:
        warn(unfit)
    if campaign:  # a campaign's trial, rerun: its summary describes what was there before
        warn(
            f"{out} is a trial of the campaign in {out.parent} ({', '.join(campaign)}), whose "
            f"summary no longer matches it: `payload trials summarize {out.parent} --force` "
            "brings it up to date"
        )
    if args.json:
        emit_json({**result, "project": str(project.root)})
        return 0
    print(f"trial seed {seed} ({operator}) -> {out}")
    given = ""
    if operator == "replay":
        names = [n for n in _SETUP if getattr(args, n) is not None]
        names += ["zones"] if args.zones is not None else []  # else the recording's
        named = result.get("replay_setup_recorded", _SETUP)
        # a controller given: its profile's settings not given apart are the profile's own
        own = [n for n in PROFILE_SETTINGS if "controller" in names and n not in names]
        defaults = [n for n in _SETUP if n not in names and n not in named and n not in own]
        if own:
            names = [f"controller ({', '.join(own)}: its own)" if n == "controller" else n
                     for n in names]  # fmt: skip
        rest = "the recording's"
        if defaults and any(n not in names and n in named for n in _SETUP):
            rest = f"the recording's; {', '.join(defaults)}: the defaults (not in the recording)"
        elif defaults:
            rest = "the defaults: the recording names none"
        given = f" (given: {', '.join(names)}; the rest {rest})" if names else f" ({rest})"
    from payload.trials.summary import print_trial_summary

    print_trial_summary(result, given)
    wrote = [name for name in TRIAL_FILES if (out / name).is_file()]
    print(f"wrote {', '.join(wrote)} in {out}")
    import shlex

    folder = shlex.quote(str(out))
    export = (  # a run the cap stopped is no episode unless asked for (export's rule)
        f"; `payload export lerobot {folder}` makes it a LeRobot dataset"
        if not result.get("ended_by")
        else ""
    )
    print(f"next: `payload review {folder}` replays it in the browser{export}")
    return 0
