"""``payload trials run|summarize``: a campaign of seeded trials and its summary, and the
summary rebuilt (or rescored) from a campaign's folders (contract in docs/cli.md;
registered by :mod:`payload.trials.cli`)."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

from payload.cliutil import (
    CheckFailed,
    check_seconds,
    command_project,
    emit_json,
    out_folder,
    results_folder,
    warn,
)
from payload.folders import (
    CAMPAIGN_FIGURE,
    CAMPAIGN_FILES,
    METRICS,
    RECORDING,
    SUMMARY,
    SUMMARY_TEXT,
    held,
    other_results,
    tagged,
)
from payload.trials.setup_options import (
    _SETUP,
    RUN_SETTINGS,
    TrialsCliError,
    _check_ctb,
    _check_physics_dt,
    _link_and_zones,
    _setup_defaults,
    cap_before_teleoperation,
    seed_problem,
)


def _cmd_trials_run(args: argparse.Namespace) -> int:
    from payload.design import models_follow_design
    from payload.envelope.stowed_fit import stowed_fit_warning
    from payload.project import provenance
    from payload.trials.campaign import (
        default_workers,
        run_campaign,
        runner_trial_fn,
        trial_dir,
        write_summary,
    )
    from payload.trials.summary import campaign_title, trials_environment
    from payload.trials.terminal import summary_terminal, trial_line_printer

    if args.n < 1:
        raise TrialsCliError(f"--n must be >= 1, got {args.n}")
    if (problem := seed_problem(args.seed, args.n)) is not None:
        raise TrialsCliError(f"--seed {problem}")
    if args.workers is not None and args.workers < 0:
        raise TrialsCliError(f"--workers must be >= 0, got {args.workers}")
    check_seconds("--max-time", args.max_time, cap=True)
    from payload.trials.cluster import check_scheduler

    check_scheduler(args.scheduler, TrialsCliError)
    _check_physics_dt(args.physics_dt)
    _setup_defaults(args)
    _check_ctb(args.ctb)
    link_zones = _link_and_zones(args)
    project = command_project(args)
    models_follow_design(project.design_path, project.root, json=args.json)
    prov = provenance(project)
    # an --out that is not a folder, or another command's results: one line, before any
    # folder is made
    out_folder(args.out, holding=other_results("campaign"))
    seeds = list(range(args.seed, args.seed + args.n))
    # a scheduler not reached leaves no empty folder (the checks below never refuse one
    # made here: it is new, or empty)
    with results_folder(args.out, project, "campaign") as out:
        if not args.force:
            taken = [trial_dir(out, s) for s in seeds if any(trial_dir(out, s).glob("*"))]
            taken += [out / n for n in held(out, CAMPAIGN_FILES)]
            if taken:
                raise TrialsCliError(
                    f"{out}: already holds a campaign ({', '.join(p.name for p in taken[:4])}"
                    f"{', ...' if len(taken) > 4 else ''}); pass --force to replace it or "
                    "choose another --out"
                )
        workers = default_workers(args.n) if args.workers is None else args.workers
        t0, started = time.perf_counter(), time.time()
        try:
            results = run_campaign(
                runner_trial_fn(
                    "synthetic",
                    project.root,
                    max_time=args.max_time,
                    force=args.force,
                    **{name: getattr(args, name) for name in _SETUP},
                    **link_zones,
                ),
                seeds,
                out,
                workers=workers,
                scheduler=args.scheduler,
                progress=not args.json and sys.stderr.isatty() and sys.stdout.isatty(),
                on_trial=None
                if args.json or sys.stdout.isatty()
                else trial_line_printer(len(seeds)),
            )
            cap_before_teleoperation(args.max_time)  # after the trials: no bad input follows
            # after them too: a scheduler not reached is an error, which no warning precedes
            if (unfit := stowed_fit_warning(project.design_path, "the campaign ran")) is not None:
                warn(unfit)
            run = {
                "workers": None if args.scheduler else workers,
                "scheduler": args.scheduler,
                # a cap given says so (a default run's summary is as it was)
                **({"max_time_s": args.max_time} if args.max_time is not None else {}),
                "wall_s": time.perf_counter() - t0,
                "trial_wall_s": float(sum(r.get("wall_s") or 0.0 for r in results)),
            }
            title = campaign_title(args.n, {name: getattr(args, name) for name in RUN_SETTINGS})
            # what the trials ran on, as each trial's process reported it (a scheduler's
            # workers may be other machines than this one)
            prov = {**prov, "environment": trials_environment(results)}
            summary = write_summary(
                results, out, title=title, run=run, provenance=prov, force=args.force
            )
        except KeyboardInterrupt as exc:  # what is kept, and how to use it (the trials
            # finished, the summary not written: during the trials or after the last)
            scored = (trial_dir(out, s) / METRICS for s in seeds)
            # this run's trials only (a --force run's folder may hold others)
            done = [m for m in scored if m.is_file() and m.stat().st_mtime >= started]
            if done:
                exc.add_note(
                    f"{len(done)} finished trial(s) kept in {out}: `payload trials summarize "
                    f"{out}` summarises them"
                )
            raise
    if args.force:  # the replaced campaign's rescorings would describe it still
        from payload.trials.scoring import rescorings

        for stale in rescorings(out, (*CAMPAIGN_FILES, CAMPAIGN_FIGURE)):
            stale.unlink()
    ours = {trial_dir(out, s).name for s in seeds}
    earlier = sorted(p.name for p in out.glob("trial-*") if p.is_dir() and p.name not in ours)
    if earlier:  # kept (recordings), but not this campaign's: said, not silently summarized
        more = f" and {len(earlier) - 3} more" if len(earlier) > 3 else ""
        warn(
            f"{out} also holds {', '.join(earlier[:3])}{more} from an earlier run, left out of "
            "this summary (`trials summarize` would take them in: move them away)"
        )
    if args.json:
        emit_json(
            {**summary, "wall_s": run["wall_s"], "out_dir": str(out), "project": str(project.root)}
        )
    else:
        print(summary_terminal(summary, title))
        figure = out / CAMPAIGN_FIGURE
        also = f", {figure}" if figure.is_file() else ""
        print(f"wrote {out / SUMMARY_TEXT} (definitions, the paper-literal column, every "
              f"trial){also} and {out / SUMMARY}")  # fmt: skip
        import shlex

        ran = [r for r in results if not r.get("error")]
        folder = shlex.quote(str(out))
        said = [f"`payload trials compare {folder} OTHER` compares it with another run"]
        if ran:
            trial = shlex.quote(str(trial_dir(out, ran[0]["seed"])))
            said.insert(0, f"`payload review {trial}` replays a trial in the browser")
        if any(not r.get("ended_by") for r in ran):  # export leaves capped runs out
            said.append(f"`payload export lerobot {folder}` makes it a LeRobot dataset")
        print(f"next: {'; '.join(said)}")
    errors = [r for r in results if r.get("error")]
    if errors:
        first = errors[0]
        raise CheckFailed(
            f"{len(errors)} of {len(results)} trial(s) raised an error (seeds "
            f"{', '.join(str(r['seed']) for r in errors)}; first: {first['error']}; "
            f"tracebacks in {SUMMARY})"
        )
    return 0


def _cmd_trials_summarize(args: argparse.Namespace) -> int:
    from payload.trials.campaign import (
        contact_tag,
        load_trial_results,
        summary_markdown,
        write_summary,
    )
    from payload.trials.scoring import AS_RECORDED, MIXED_TAG, RESCORING, UNSCORED_TAG, WRITTEN
    from payload.trials.summary import campaign_summary, campaign_title

    for name in ("min_contact_s", "max_gap_s"):
        value = getattr(args, name)
        if value is not None and not (math.isfinite(value) and value >= 0):
            raise TrialsCliError(f"--{name.replace('_', '-')} must be a number >= 0, got {value}")
    relaxed = args.min_contact_s is not None or args.max_gap_s is not None
    rescore = args.recompute or relaxed
    results = load_trial_results(
        args.dir,
        recompute=rescore,
        min_interval_s=args.min_contact_s,
        max_gap_s=args.max_gap_s,
        force=args.force,
    )
    previous = _previous_summary(Path(args.dir) / SUMMARY)
    wall = {t.get("seed"): t.get("wall_s") for t in previous.get("trials", [])}
    budget = previous.get("retarget_budget")
    modelled = previous.get("retarget_collisions")
    for r in results:  # how long each trial took is known only from the campaign run
        if r.get("wall_s") is None and wall.get(r.get("seed")) is not None:
            r["wall_s"] = wall[r.get("seed")]
        # trials whose metrics.json lacks these: the campaign's summary says
        if isinstance(budget, str):
            r.setdefault("retarget_budget", budget)
        if isinstance(modelled, bool):
            r.setdefault("retarget_collisions", modelled)
        if isinstance(previous.get("controller"), str):
            r.setdefault("controller", previous["controller"])
        if isinstance(previous.get("controller_overrides"), list):
            r.setdefault("controller_overrides", previous["controller_overrides"])
    tag = None
    if rescore:  # a rescoring is written beside the originals, named by its definition
        defs = {
            (float(r.get("min_interval_s") or 0.0), float(r.get("max_gap_s") or 0.0))
            for r in results
            if not r.get("error")
        }
        tag = contact_tag(*defs.pop()) if len(defs) == 1 else MIXED_TAG if defs else UNSCORED_TAG
    prov = previous.get("provenance")
    if prov is None:  # no campaign summary before: what the trials themselves record
        from payload.trials.summary import trials_environment

        own = [r["provenance"] for r in results if isinstance(r.get("provenance"), dict)]
        prov = {**own[0], "environment": trials_environment(results)} if own else None
    scored = [r for r in results if not r.get("error")]
    title = previous.get("title")
    if title is None:  # no campaign summary before (an interrupted run): the trials say
        setup = {}
        for name in RUN_SETTINGS:
            values = {json.dumps(r.get(name)) for r in scored}
            setup[name] = scored[0].get(name) if len(values) == 1 else None
        title = campaign_title(len(results), setup) if scored else None
    out = Path(args.dir)
    again = [r for r in scored if r.get(RESCORING) == AS_RECORDED]
    # a trial scored before that no longer scores (its recording gone or unreadable) is news
    lost = [r for r in results if r.get("error") and (Path(r["out_dir"]) / METRICS).is_file()]
    if rescore and scored and len(again) == len(scored) and not lost:
        # every trial's own scoring again: a tagged copy of each would say nothing new
        summary = campaign_summary(results, title, previous.get("run"), prov)
        said = {"out_dir": str(args.dir), "rescored_as_recorded": [r["seed"] for r in again]}
        if args.json:
            emit_json({**summary, **said})
        else:
            print(summary_markdown(summary, title))
            print(f"rescored {len(again)} trial(s) from their {RECORDING} with the contact "
                  f"definition each was recorded with: every figure as its {METRICS} says; "
                  "nothing written (--min-contact-s or --max-gap-s rescores with another "
                  "definition)")  # fmt: skip
        return 0
    named = [out / tagged(name, tag) for name in (SUMMARY_TEXT, CAMPAIGN_FIGURE, SUMMARY)]
    before = {p: p.read_bytes() if p.is_file() else None for p in named}
    summary = write_summary(
        results,
        args.dir,
        title=title,
        run=previous.get("run"),
        provenance=prov,
        tag=tag,
        force=args.force,
    )
    if args.json:
        same = {"rescored_as_recorded": [r["seed"] for r in again]} if rescore else {}
        emit_json({**summary, "out_dir": str(args.dir), **same})
    else:
        print(summary_markdown(summary, title))
        present = [p for p in named if p.is_file()]
        written = [p for p in present if p.read_bytes() != before[p]]
        kept = [p for p in present if p not in written]
        changed = [Path(r["out_dir"]).name for r in scored if r.get(RESCORING) == WRITTEN]
        if written:
            print(f"wrote {', '.join(str(p) for p in written)}")
        if changed:
            print(f"wrote the rescored metrics and figures of {_trial_names(changed)}, "
                  "beside theirs")  # fmt: skip
        if again:  # some trials' scoring came out as recorded: theirs are not written
            print(f"{len(again)} trial(s) scored as their {METRICS} says: no rescoring "
                  "written for them")  # fmt: skip
        if rescore and len(scored) > len(again) + len(changed):
            print("unchanged (already what the recordings give): the rescorings of "
                  f"{len(scored) - len(again) - len(changed)} trial(s)")  # fmt: skip
        if kept:
            print(f"unchanged (already what the trials give): {', '.join(str(p) for p in kept)}")
    return 0


def _trial_names(names: list[str]) -> str:
    """``trial-0001`` or ``3 trials (trial-0001 to trial-0003)``."""
    return names[0] if len(names) == 1 else f"{len(names)} trials ({names[0]} to {names[-1]})"


def _previous_summary(path: Path) -> dict[str, Any]:
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError):
        return {}
    return data if isinstance(data, dict) else {}
