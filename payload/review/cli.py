"""``payload review``: the Meshcat design review (and trial replay) in the browser."""

from __future__ import annotations

import argparse
import math
import webbrowser
from pathlib import Path
from typing import TYPE_CHECKING

from payload.cliutil import command_project, warn
from payload.folders import RECORDING
from payload.project import DESIGN_FILE, is_project_design
from payload.review.errors import ReviewError
from payload.review.project import DEFAULT_RATE, TRIAL_OPTION
from payload.safeio import cannot_write_in

if TYPE_CHECKING:
    from payload.review.live import LiveReview
    from payload.review.scene import Scene

DEFAULT_REACH_SAMPLES = 5000
DEFAULT_PORT = 7070
"""TCP port of the ``--watch`` page."""


def build_review(
    design: str | None,
    trial: str | None,
    reach_samples: int = DEFAULT_REACH_SAMPLES,
    check_models: bool = True,
    rate: float = DEFAULT_RATE,
    trial_option: str | None = TRIAL_OPTION,
) -> Scene:
    """The review scene: the design review, and the trial replay when ``trial`` is given.

    With a trial, the replay is what shows (the design review stays in the scene tree,
    hidden) and its animation is the trial's. ``check_models`` False skips the check that
    the generated models match the design (for a caller that has just written them).
    ``trial_option`` is the option that named the trial, which its errors begin with
    (None: it was named alone, as ``payload review TRIAL``).
    """
    from payload.review.design_view import REVIEW, build_design_review
    from payload.review.project import project_files

    files = project_files(design)
    rec = None
    if trial is not None:
        from payload.review.trial_view import read_trial

        files.check()
        rec = read_trial(trial, files, trial_option)  # bad input fails before the slow work
    review = build_design_review(files, reach_samples, check_models=check_models).scene
    if trial is None:
        return review
    from payload.review.trial_view import build_trial_replay

    replay = build_trial_replay(trial, files, rate=rate, recording=rec).scene
    replay.commands += review.commands
    replay.prop(REVIEW, "visible", False)
    replay.notes = review.notes + replay.notes
    return replay


def live_review(design: str | None, reach_samples: int) -> LiveReview:
    """A live review of the design project of ``design``: each build regenerates the
    project's models from the design file, then builds the review scene."""
    from payload.design import load_design
    from payload.design.build import write
    from payload.review.live import LiveReview
    from payload.review.project import project_files

    files = project_files(design)

    def build() -> Scene:
        write(load_design(files.design), files.urdf.parent.parent)
        return build_review(str(files.design), None, reach_samples, check_models=False)

    return LiveReview(files.design, build)


def _watch_alone(args: argparse.Namespace) -> None:
    """``--watch`` serves its own page of the design: it takes no page file, trial or
    Meshcat server (one line, before anything else is checked)."""
    if not args.watch:
        return
    for option in ("static", "trial", "zmq_url"):
        if getattr(args, option) is not None:
            flag = "--" + option.replace("_", "-")
            raise ReviewError(f"--watch serves its own page; it does not take {flag}")
    if args.trial_folder is not None:
        raise ReviewError(
            f"--watch serves its own page; it does not take a trial (TRIAL {args.trial_folder})"
        )


def _cmd_watch(args: argparse.Namespace) -> int:
    from payload.review.live import run

    live = live_review(args.design, args.reach_samples)
    error = live.rebuild()
    if error is not None:
        raise ReviewError(error)
    for line in live.notes():
        print(line)
    return run(live, args.port, _open_in_browser if args.open else None)


def _open_in_browser(url: str) -> None:
    """``--open``: the page in a new tab of the user's browser, or one warning line when
    there is none to open it in (a server, a container: the page is still served)."""
    if not webbrowser.open(url, new=2):
        warn(f"--open: no browser to open here; open {url} in one")


HTML_SUFFIXES = (".html", ".htm")
"""What a ``--static`` page's file name may end in."""


def _check_static(out: Path) -> None:
    """``--static FILE``: a new file, or an earlier page (HTML) to replace; never a folder,
    nor any other file (a recording, a summary)."""
    if out.is_dir():
        raise ReviewError(f"--static {out}: is a folder, expected a file name")
    if not out.parent.is_dir():  # a typo's folder is not made (it was, at the root even)
        raise ReviewError(f"--static {out}: no folder {out.parent} (make it first)")
    problem = cannot_write_in(out.parent)
    if problem is not None:  # before the page is built (a replay's takes seconds)
        raise ReviewError(f"--static {out}: cannot write in {out.parent} ({problem})")
    if out.exists():
        with out.open("rb") as fh:
            head = fh.read(256).lstrip().lower()
        if not head.startswith(b"<!doctype html"):
            raise ReviewError(
                f"--static {out}: exists and is not an HTML page; a review replaces only an "
                "earlier page (choose another file name)"
            )
    if out.suffix.lower() not in HTML_SUFFIXES:  # review.png: a page, not a picture
        raise ReviewError(
            f"--static {out}: writes an HTML page, so the name ends in .html (its picture: "
            "python -m payload.review.browser PAGE PNG)"
        )


def _check_project_design(design: Path) -> None:
    """``--design F``: the review shows F's generated models, which live in F's project
    (``<project>/urdf``, ``<project>/cad/meshes``), so F must be a project's
    ``cad/design.toml`` (as for ``payload build --design F``)."""
    if not design.is_file():
        raise ReviewError(f"--design {design}: {'a folder' if design.is_dir() else 'no such file'}")
    if not is_project_design(design):
        raise ReviewError(
            f"--design {design}: not a design project's cad/design.toml, so it has no "
            "models to review; nothing written (make a project with `payload new DIR` and save "
            "the design as DIR/cad/design.toml)"
        )


def _trial_folder(args: argparse.Namespace) -> None:
    """The trial to replay, named alone (``payload review TRIAL``) or by ``--trial DIR``:
    a trial folder or its ``log.mcap`` (set as ``args.trial``, the folder). A design
    project, a folder of runs (a campaign's, a project's ``runs/``) or a folder without a
    recording is refused naming what to give instead (the line begins with the option
    when the trial was named by it)."""
    if args.trial_folder is not None and args.trial is not None:
        raise ReviewError(
            f"{args.trial_folder}: give the trial once, as TRIAL or as {TRIAL_OPTION} DIR"
        )
    given = args.trial_folder if args.trial_folder is not None else args.trial
    if given is None:
        return
    path = Path(given)
    named = f"{path}" if args.trial_folder is not None else f"{TRIAL_OPTION} {path}"
    if path.name == RECORDING and path.is_file():  # the recording itself: its trial folder
        path = path.parent
    if not path.is_dir():
        raise ReviewError(f"{named}: not a folder (a trial folder, holding {RECORDING})")
    if not (path / RECORDING).is_file():
        if (path / DESIGN_FILE).is_file():
            raise ReviewError(
                f"{named}: is a design project, not a trial; review it with --project {path}"
            )
        runs = sorted(p.parent for p in path.glob(f"*/{RECORDING}"))
        runs = runs or sorted(p.parent for p in path.glob(f"*/*/{RECORDING}"))
        if runs:  # a campaign's folder, or a project's runs/ (of campaigns, perhaps)
            raise ReviewError(
                f"{named}: holds {len(runs)} recorded run(s), each in its own folder; name "
                f"one, e.g. {runs[0]}"
            )
        raise ReviewError(f"{named}: not a trial folder (no {RECORDING} in it)")
    args.trial = str(path)


def _rate_and_port(args: argparse.Namespace) -> None:
    """``--rate`` and ``--port`` in range, and only where they act: the rate is a trial
    replay's, the port the served page's (not a ``--static`` file's nor another Meshcat
    server's). Their defaults are set here."""
    if args.rate is not None and not (math.isfinite(args.rate) and args.rate > 0):
        raise ReviewError(f"--rate must be > 0 Hz, got {args.rate}")
    if args.port is not None and not 0 <= args.port <= 65535:
        raise ReviewError(f"--port must be 0..65535, got {args.port}")
    if args.rate is not None and args.watch:
        raise ReviewError("--watch serves the design review, no replay; it takes no --rate")
    if args.rate is not None and args.trial is None:
        raise ReviewError(
            "--rate is a trial replay's frame rate; give the trial (TRIAL or --trial DIR) "
            "or leave --rate out"
        )
    if args.port is not None and not args.watch:
        elsewhere = "--static writes a file" if args.static is not None else None
        if args.zmq_url is not None:
            elsewhere = "--zmq-url uses that Meshcat server's page"
        if elsewhere is not None:
            raise ReviewError(f"--port is the served page's port, but {elsewhere}; leave it out")
    args.rate = DEFAULT_RATE if args.rate is None else args.rate
    args.port = DEFAULT_PORT if args.port is None else args.port


def _cmd_review(args: argparse.Namespace) -> int:
    from payload.review.page import static_html
    from payload.review.serve import check_server, open_viewer

    _watch_alone(args)
    _trial_folder(args)
    _rate_and_port(args)
    if args.zmq_url is not None and not args.watch:  # --watch refuses it, below
        check_server(args.zmq_url)
    if args.reach_samples < 0:
        raise ReviewError(f"--reach-samples must be >= 0, got {args.reach_samples}")
    if args.static is not None:
        _check_static(Path(args.static))

    project = command_project(args, args.design)  # named first; library defaults use it
    if args.design is not None:
        _check_project_design(Path(args.design))
    if args.watch:
        return _cmd_watch(args)
    from payload.design import models_follow_design

    models_follow_design(project.design_path, project.root)  # the one rule for stale models
    scene = build_review(  # the models have just been made to follow the design
        args.design, args.trial, args.reach_samples, check_models=False, rate=args.rate,
        trial_option=None if args.trial_folder is not None else TRIAL_OPTION,
    )  # fmt: skip
    for line in scene.notes:
        print(line)
    if args.static is not None:
        out = Path(args.static)
        html = static_html(scene)
        try:
            out.write_text(html, encoding="utf-8")
        except OSError as exc:  # a read-only folder, a file on the way
            raise ReviewError(f"--static {out}: cannot write it ({exc.strerror or exc})") from None
        print(f"wrote {out} ({len(html) / 1e6:.1f} MB)")
        if args.open:
            _open_in_browser(out.resolve().as_uri())
        return 0
    opener = _open_in_browser if args.open else None
    if args.zmq_url is None:  # the review's own page: title, legend, labels, chase camera
        from payload.review.live import LiveReview, run

        live = LiveReview(Path(args.design or "."), lambda: scene)
        live.rebuild()
        return run(live, args.port, opener, watch=False)
    vis = open_viewer(args.zmq_url)  # meshcat's own page: the scene without the overlay
    scene.send(vis.window)
    print(f"meshcat: {vis.url()}")
    if args.open:
        vis.open()
    return 0


def register(
    sub: argparse._SubParsersAction, groups: dict[str, argparse._SubParsersAction]
) -> None:
    p = sub.add_parser("review", help="Meshcat design review (and trial replay) in the browser")
    p.add_argument(
        "trial_folder",
        nargs="?",
        metavar="TRIAL",
        help="a trial folder to replay (the same as --trial TRIAL)",
    )
    p.add_argument("--design", help="design TOML (default: the project's cad/design.toml)")
    p.add_argument(TRIAL_OPTION, metavar="DIR", help="replay the trial recorded in DIR")
    p.add_argument("--static", metavar="FILE", help="write a standalone HTML file and exit")
    p.add_argument("--zmq-url", metavar="URL", help="use the meshcat server at URL")
    p.add_argument("--open", action="store_true", help="open the review in a browser")
    p.add_argument(
        "--rate",
        type=float,
        metavar="HZ",
        help=f"frames per second of trial time in a --trial replay (default {DEFAULT_RATE:g})",
    )
    p.add_argument(
        "--watch",
        action="store_true",
        help="serve the review and follow the design file: every save rebuilds the models, "
        "the envelope check and the open page (Ctrl-C stops)",
    )
    p.add_argument(
        "--port",
        type=int,
        help=f"TCP port of the served page (default {DEFAULT_PORT}; 0: any free port)",
    )
    p.add_argument(
        "--reach-samples",
        type=int,
        default=DEFAULT_REACH_SAMPLES,
        metavar="N",
        help=f"configurations sampled for the reach clouds (default {DEFAULT_REACH_SAMPLES})",
    )
    p.set_defaults(func=_cmd_review)
