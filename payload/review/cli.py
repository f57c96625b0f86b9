"""``payload review``: the Meshcat design review (and trial replay) in the browser."""

from __future__ import annotations

import argparse
import sys
import time
import webbrowser
from pathlib import Path
from typing import TYPE_CHECKING

from payload.review.errors import ReviewError

if TYPE_CHECKING:
    from payload.review.scene import Scene

DEFAULT_REACH_SAMPLES = 5000


def build_review(
    design: str | None, trial: str | None, reach_samples: int = DEFAULT_REACH_SAMPLES
) -> Scene:
    """The review scene: the design review, and the trial replay when ``trial`` is given.

    With a trial, the replay is what shows (the design review stays in the scene tree,
    hidden) and its animation is the trial's.
    """
    from payload.review.design_view import REVIEW, build_design_review
    from payload.review.project import project_files

    files = project_files(design)
    if trial is not None:
        from payload.review.trial_view import read_trial

        files.check()
        read_trial(trial, files)  # bad input fails before the slow work
    review = build_design_review(files, reach_samples=reach_samples).scene
    if trial is None:
        return review
    from payload.review.trial_view import build_trial_replay

    replay = build_trial_replay(trial, files).scene
    replay.commands += review.commands
    replay.prop(REVIEW, "visible", False)
    replay.notes = review.notes + replay.notes
    return replay


def _cmd_review(args: argparse.Namespace) -> int:
    from payload.review.serve import check_server, close_viewer, open_viewer, static_html

    if args.zmq_url is not None:
        check_server(args.zmq_url)
    if args.reach_samples < 0:
        raise ReviewError(f"--reach-samples must be >= 0 (got {args.reach_samples})")
    if args.static is not None and Path(args.static).is_dir():
        raise ReviewError(f"--static {args.static}: is a folder, expected a file name")
    from payload.cli import command_project

    project = command_project(args, args.design)  # named first; library defaults use it
    from payload.design import models_follow_design

    models_follow_design(project.design_path, project.root)  # the one rule for stale models
    scene = build_review(args.design, args.trial, args.reach_samples)
    for line in scene.notes:
        print(line)
    if args.static is not None:
        out = Path(args.static)
        html = static_html(scene, args.zmq_url)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(html, encoding="utf-8")
        print(f"wrote {out} ({len(html) / 1e6:.1f} MB)")
        if args.open:
            webbrowser.open(out.resolve().as_uri(), new=2)
        return 0
    vis = open_viewer(args.zmq_url)
    scene.send(vis.window)
    print(f"meshcat: {vis.url()}")
    if args.open:
        vis.open()
    if args.zmq_url is not None:
        return 0
    print("serving the review; Ctrl-C to stop", file=sys.stderr)
    try:
        while True:
            time.sleep(3600)
    finally:
        close_viewer(vis)


def register(
    sub: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction]
) -> None:
    p = sub.add_parser("review", help="Meshcat design review (and trial replay) in the browser")
    p.add_argument("--design", help="design TOML (default: the project's cad/design.toml)")
    p.add_argument("--trial", metavar="DIR", help="replay the trial recorded in DIR")
    p.add_argument("--static", metavar="FILE", help="write a standalone HTML file and exit")
    p.add_argument("--zmq-url", metavar="URL", help="use the meshcat server at URL")
    p.add_argument("--open", action="store_true", help="open the review in a browser")
    p.add_argument(
        "--reach-samples",
        type=int,
        default=DEFAULT_REACH_SAMPLES,
        metavar="N",
        help=f"configurations sampled for the reach clouds (default {DEFAULT_REACH_SAMPLES})",
    )
    p.set_defaults(func=_cmd_review)
