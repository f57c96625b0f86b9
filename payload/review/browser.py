"""Headless Chromium screenshots of a static review page (Playwright, the ``test`` extra).

The browser test and the README's screenshot use this one code path::

    python -m payload.review.browser review.html docs/review.png

Only a system Chromium is driven (``executable_path``); no browser is ever downloaded.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path

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


def screenshot(
    html: Path,
    png: Path,
    *,
    time_s: float | None = 0.0,
    hide: Sequence[Sequence[str]] = (),
    show: Sequence[Sequence[str]] = (),
    viewport: tuple[int, int] = VIEWPORT,
) -> bytes:
    """Open a static review page, pose it, wait for it to render, and screenshot it.

    Args:
        html: The static HTML file.
        png: Where to write the PNG.
        time_s: Animation time to show (the animation is paused there); ``None`` lets it play.
        hide: Scene-tree paths (lists of names) to hide first.
        show: Scene-tree paths to show.
        viewport: Page size [px].

    Returns:
        The PNG bytes.

    Raises:
        RuntimeError: No Chromium, or the page did not render a meshcat viewer.
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
            page.goto(Path(html).resolve().as_uri())
            page.wait_for_function(
                "() => window.__pending === 0 && typeof viewer !== 'undefined'"
                " && viewer.animator.actions.length > 0",
                timeout=120_000,
            )
            script = """([hide, show, t]) => {
                for (const p of hide) viewer.scene_tree.find(p).set_property("visible", false);
                for (const p of show) viewer.scene_tree.find(p).set_property("visible", true);
                if (t !== null) { viewer.animator.pause(); viewer.animator.seek(t); }
                viewer.set_dirty();
            }"""
            page.evaluate(script, [list(map(list, hide)), list(map(list, show)), time_s])
            for _ in range(3):  # the viewer renders in its requestAnimationFrame loop
                page.evaluate("() => new Promise(r => requestAnimationFrame(() => r()))")
            page.wait_for_timeout(500)
            data = page.screenshot(path=str(png))
        finally:
            ctx.close()
    return data


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Screenshot a static review page")
    parser.add_argument("html", type=Path)
    parser.add_argument("png", type=Path)
    parser.add_argument("--time", type=float, default=None, help="animation time [s]")
    parser.add_argument("--show", action="append", default=[], help="scene path to show")
    args = parser.parse_args(argv)
    show = [[p for p in s.split("/") if p] for s in args.show]
    screenshot(args.html, args.png, time_s=args.time, show=show)
    print(f"wrote {args.png}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
