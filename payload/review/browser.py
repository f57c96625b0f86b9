"""Headless Chromium screenshots of a static review page (Playwright, the ``test`` extra).

The browser test and the README's screenshot use this one code path::

    python -m payload.review.browser review.html docs/review.png

Only a system Chromium is driven (``executable_path``); no browser is ever downloaded.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from payload.cliutil import OneLineParser

CHROMIUM = "/usr/bin/chromium"
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--use-angle=swiftshader",
)
VIEWPORT = (960, 640)
"""Screenshot size in pixels (width, height)."""

CONTROLS_BAR = (250, 24)
"""Size of meshcat's "Open Controls" bar in the top-right corner [px]."""


# the static page sends its commands as fetch() calls of data: URLs; count the pending ones
_COUNT_FETCHES = """
window.__pending = 0;
const __fetch = window.fetch.bind(window);
window.fetch = (...args) => {
    window.__pending++;
    return __fetch(...args).finally(() => setTimeout(() => window.__pending--, 0));
};
"""


def chromium_path() -> str | None:
    """The system Chromium, or ``None`` when it is not installed."""
    for candidate in (os.environ.get("PAYLOAD_CHROMIUM"), CHROMIUM, shutil.which("chromium")):
        if candidate and Path(candidate).is_file():
            return candidate
    return None


@contextlib.contextmanager
def open_page(url: str | Path, viewport: tuple[int, int] = VIEWPORT) -> Iterator[Any]:
    """A review page open in headless Chromium, once its scene is loaded.

    Args:
        url: A static review file, or the address of a live review.
        viewport: Page size [px].

    Yields:
        The Playwright page (``viewer`` and ``payloadReview`` are its globals).

    Raises:
        RuntimeError: No Chromium.
    """
    from playwright.sync_api import sync_playwright

    exe = chromium_path()
    if exe is None:
        raise RuntimeError(f"Chromium not found at {CHROMIUM}")
    w, h = viewport
    with tempfile.TemporaryDirectory(prefix="payload-chromium-") as profile, sync_playwright() as p:
        ctx = p.chromium.launch_persistent_context(
            profile,
            executable_path=exe,
            args=list(FLAGS),
            headless=True,
            viewport={"width": w, "height": h},
        )
        try:
            page = ctx.new_page()
            page.add_init_script(_COUNT_FETCHES)
            page.goto(url.resolve().as_uri() if isinstance(url, Path) else url)
            page.wait_for_function(
                "() => window.__pending === 0 && window.payloadReady === true",
                timeout=120_000,
            )
            settle(page)
            yield page
        finally:
            ctx.close()


def settle(page: Any) -> None:
    """Let the viewer render a few frames (it renders in its requestAnimationFrame loop)."""
    page.evaluate("() => viewer.set_dirty()")
    for _ in range(3):
        page.evaluate("() => new Promise(r => requestAnimationFrame(() => r()))")
    page.wait_for_timeout(300)


def pose_page(
    page: Any,
    time_s: float | None = 0.0,
    hide: Sequence[Sequence[str]] = (),
    show: Sequence[Sequence[str]] = (),
    overlay: bool = True,
) -> None:
    """Hide and show scene-tree paths (lists of names), hold the animation at ``time_s``;
    ``overlay`` False hides the title, legend and labels (the view then takes the whole
    page: the review's camera as it is, no room kept for the title)."""
    script = """([hide, show, t, overlay]) => {
        document.getElementById("payload-overlay").style.display = overlay ? "" : "none";
        for (const p of hide) viewer.scene_tree.find(p).set_property("visible", false);
        for (const p of show) viewer.scene_tree.find(p).set_property("visible", true);
        if (t !== null) { viewer.animator.pause(); viewer.animator.seek(t); }
        viewer.set_dirty();
    }"""
    page.evaluate(script, [list(map(list, hide)), list(map(list, show)), time_s, overlay])
    settle(page)


def screenshot(
    html: Path,
    png: Path,
    *,
    time_s: float | None = 0.0,
    hide: Sequence[Sequence[str]] = (),
    show: Sequence[Sequence[str]] = (),
    viewport: tuple[int, int] = VIEWPORT,
    overlay: bool = True,
) -> bytes:
    """Open a static review page, pose it, wait for it to render, and screenshot it.

    Args:
        html: The static HTML file.
        png: Where to write the PNG.
        time_s: Animation time to show (the animation is paused there); ``None`` lets it play.
        hide: Scene-tree paths (lists of names) to hide first.
        show: Scene-tree paths to show.
        viewport: Page size [px].
        overlay: Draw the title, legend and labels.

    Returns:
        The PNG bytes.

    Raises:
        RuntimeError: No Chromium, or the page did not render a meshcat viewer.
    """
    with open_page(html, viewport) as page:
        pose_page(page, time_s, hide, show, overlay)
        page.wait_for_timeout(200)
        return page.screenshot(path=str(png))


def main(argv: Sequence[str] | None = None) -> int:
    parser = OneLineParser(
        prog="python -m payload.review.browser",
        description="Screenshot a static review page",
        allow_abbrev=False,
    )
    parser.add_argument("html", type=Path)
    parser.add_argument("png", type=Path)
    parser.add_argument("--time", type=float, default=None, help="animation time [s]")
    parser.add_argument("--show", action="append", default=[], help="scene path to show")
    args = parser.parse_args(argv)
    if not args.html.is_file():
        parser.error(f"{args.html}: no such file (a page `payload review --static` wrote)")
    show = [[p for p in s.split("/") if p] for s in args.show]
    screenshot(args.html, args.png, time_s=args.time, show=show)
    print(f"wrote {args.png}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
