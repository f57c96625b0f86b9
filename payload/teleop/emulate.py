"""An emulated Quest 3 with hands: headless Chromium + Meta's ``iwer``, for tests and the bench.

The product page is loaded unchanged from the server; before it runs, scripts are
injected into the browser: iwer's browser build from the project's ``node_modules``
(installed by ``npm ci`` from ``package-lock.json``), then :func:`emulated_pose` and
``web/desktop/hands.js`` (:data:`HANDS_JS`, which ``payload teleop serve --desktop`` also
serves), which create ``new XRDevice(metaQuest3)``, install it as ``navigator.xr``
(``forceInstall``) and switch it to hand input, and a few lines that hand its controls to
this module. Hands then move toward targets at a human speed (a jump would be rejected by
the tracking supervisor as a glitch), in WebXR's local-floor space (metres, Y up, -Z
forward).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from payload.errors import PayloadError

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_FLAGS = (
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

# operator poses in local-floor [m]: wrists at chest height, about 35 cm in front
NEUTRAL = {"left": (-0.15, 1.1, -0.35), "right": (0.15, 1.1, -0.35)}
HEAD_PITCH_DEG = -25.0
"""The emulated head looks this far down [deg], at the vehicle (it floats at hand height a
metre ahead), as an operator does and as the desktop mode's does (both read it from
:func:`emulated_pose`, put before ``web/desktop/hands.js``): the view shows the scene and
the panel above it. The hands do not depend on it."""
GESTURES: dict[str, dict[str, Any]] = {
    "neutral": {"offset": (0.0, 0.0, 0.0), "spread": 0.0, "pinch": 0.5},
    "pinch": {"offset": (0.0, 0.0, 0.0), "spread": 0.0, "pinch": 1.0},
    "open": {"offset": (0.0, 0.0, 0.0), "spread": 0.0, "pinch": 0.0},
    "together": {"offset": (0.0, 0.0, 0.0), "spread": -0.1, "pinch": 0.5},
    "apart": {"offset": (0.0, 0.0, 0.0), "spread": 0.12, "pinch": 0.5},
    "release": {"offset": (0.0, 0.0, 0.0), "spread": 0.0, "pinch": 0.5},
}

HAND_SPEED = 0.4
"""How fast the emulated hands move toward their targets [m/s] (a human's; a jump would be
a tracking glitch to the server)."""

HANDS_JS = Path(__file__).resolve().parent / "web" / "desktop" / "hands.js"
"""The emulated Quest 3 and its hands (``window.emulatedQuest``), the desktop mode's and the
tests' headset's: after iwer's browser build and :func:`emulated_pose`."""

_QUEST_JS = """
(() => {
  const quest = window.emulatedQuest;
  window.__quest = {
    device: quest.device,
    target: quest.target,
    connect: quest.connect,
    wrist: quest.wrist,
    gesture(name, forward) { quest.pose(quest.gestures[name], { left: [0, 0, -forward] }); },
  };
})();
"""


def emulated_pose(speed: float = HAND_SPEED) -> str:
    """The JavaScript line ``hands.js`` reads (``EMULATED_POSE``): the wrists' neutral
    places, the head's pitch, the calibration gestures and the hands' speed [m/s]."""
    pose = {"neutral": NEUTRAL, "headPitchDeg": HEAD_PITCH_DEG, "gestures": GESTURES}
    return f"const EMULATED_POSE = {_js({**pose, 'speed': speed})};\n"


class EmulationError(PayloadError):
    """The emulated headset cannot run (no Chromium, no iwer, the page did not start)."""


WORKBENCH_ROOT = Path(__file__).resolve().parents[2]
"""The workbench's own checkout (its ``package.json`` pins iwer), where ``npm ci`` installs
it: a design project made with ``payload new`` has no ``package.json`` of its own."""


def find_iwer(start: Path | None = None) -> Path:
    """iwer's browser build in the nearest ``node_modules`` from ``start`` (cwd) upward,
    else in the workbench's own checkout (:data:`WORKBENCH_ROOT`).

    Raises:
        EmulationError: Not installed (run ``npm ci`` in the workbench's checkout).
    """
    here = (start or Path.cwd()).resolve()
    for d in (here, *here.parents, WORKBENCH_ROOT):
        p = d / "node_modules" / "iwer" / "build" / "iwer.js"
        if p.is_file():
            return p
    where = (
        f"in the workbench's checkout, {WORKBENCH_ROOT}"
        if (WORKBENCH_ROOT / "package.json").is_file()
        else "where a package.json pins it (the workbench's checkout)"
    )
    raise EmulationError(f"iwer is not installed: run `npm ci` {where}")


def chromium_path() -> str:
    """Debian's Chromium.

    Raises:
        EmulationError: It is not installed.
    """
    path = CHROMIUM if os.access(CHROMIUM, os.X_OK) else shutil.which("chromium")
    if not path:
        raise EmulationError(f"Chromium is not installed ({CHROMIUM}): apt-get install chromium")
    return path


def wait_on_page(page: Any, condition: str, timeout: float, what: str) -> None:
    """Poll a page until the JavaScript function ``condition`` (``"() => ..."``) is truthy.

    Polled from Python: Playwright's own ``wait_for_function`` re-evaluates a condition
    given as text with an ``eval`` that the live page's Content-Security-Policy refuses.

    Raises:
        EmulationError: The condition did not hold within ``timeout`` [s] (``what`` says
            what was awaited).
    """
    end = time.monotonic() + timeout
    while not page.evaluate(condition):
        if time.monotonic() > end:
            raise EmulationError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.05)


class EmulatedQuest:
    """The product page in headless Chromium with an emulated Quest 3 and hands.

    Args:
        url: The page's address (with its token).
        iwer_js: iwer's browser build (default: :func:`find_iwer`).
        speed: How fast the hands move toward their targets [m/s] (default
            :data:`HAND_SPEED`).
        ignore_https_errors: Accept the server's self-signed certificate.
    """

    def __init__(
        self,
        url: str,
        iwer_js: Path | None = None,
        speed: float = HAND_SPEED,
        ignore_https_errors: bool = False,
    ) -> None:
        self.url = url
        self.iwer_js = iwer_js or find_iwer()
        self.speed = speed
        self.ignore_https_errors = ignore_https_errors
        self.console: list[str] = []
        self._pw: Any = None
        self._browser: Any = None
        self._profile: str | None = None
        self.page: Any = None

    def __enter__(self) -> EmulatedQuest:
        from playwright.sync_api import sync_playwright

        exe = chromium_path()
        self._profile = tempfile.mkdtemp(prefix="payload-chromium-")
        self._pw = sync_playwright().start()
        try:
            ctx = self._pw.chromium.launch_persistent_context(
                self._profile,
                executable_path=exe,
                headless=True,
                args=list(CHROMIUM_FLAGS),
                ignore_https_errors=self.ignore_https_errors,
                viewport={"width": 320, "height": 240},  # software GL: keep the pixels few
            )
            self._browser = ctx
            ctx.add_init_script(path=str(self.iwer_js))
            hands = HANDS_JS.read_text(encoding="utf-8")
            ctx.add_init_script(script=emulated_pose(self.speed) + hands + _QUEST_JS)
            self.page = ctx.pages[0] if ctx.pages else ctx.new_page()
            self.page.on("console", lambda m: self.console.append(f"{m.type}: {m.text}"))
            self.page.on("pageerror", lambda e: self.console.append(f"pageerror: {e}"))
            self.page.goto(self.url)
            enabled = "() => !document.getElementById('enter').disabled"
            wait_on_page(self.page, enabled, 30.0, "Enter VR to be offered")
            self.page.click("#enter")
            in_vr = "() => Boolean(window.__teleop && window.__teleop.xr)"
            wait_on_page(self.page, in_vr, 30.0, "the page to enter VR")
        except Exception:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        if self._browser is not None:
            self._browser.close()
        if self._pw is not None:
            self._pw.stop()
        if self._profile is not None:
            shutil.rmtree(self._profile, ignore_errors=True)
        self._browser = self._pw = self._profile = None

    # -- hands -------------------------------------------------------------------------------
    def target(self, side: str, pos: tuple[float, float, float], pinch: float) -> None:
        """Move a hand toward ``pos`` (local-floor [m]) and a pinch value (0 open, 1 pinch)."""
        self.page.evaluate(
            "([s, p, v]) => window.__quest.target(s, p, v)", [side, list(pos), pinch]
        )

    def connect(self, side: str, on: bool) -> None:
        """Start or stop tracking a hand."""
        self.page.evaluate("([s, on]) => window.__quest.connect(s, on)", [side, on])

    def wrist(self, side: str) -> list[float]:
        """The emulated hand's position (local-floor [m])."""
        return self.page.evaluate("(s) => window.__quest.wrist(s)", side)

    def gesture(self, name: str, forward: float = 0.0) -> None:
        """Both hands to a calibration gesture (:data:`GESTURES`), left wrist ``forward`` [m]."""
        if name not in GESTURES:
            raise EmulationError(f"no gesture {name!r}; one of {', '.join(GESTURES)}")
        self.page.evaluate("([g, f]) => window.__quest.gesture(g, f)", [name, forward])

    def debug(self) -> dict[str, Any]:
        """The page's ``window.__teleop`` (frames sent, last state, link)."""
        return self.page.evaluate(
            "() => { const d = window.__teleop; return {sent: d.sent, received: d.received, "
            "connects: d.connects, open: d.open, xr: d.xr, state: d.state}; }"
        )

    def follow_calibration(
        self, timeout: float = 60.0, state: Callable[[], dict[str, Any]] | None = None
    ) -> dict[str, Any]:
        """Make each gesture the page prompts until the server reports teleoperation.

        Args:
            timeout: Give up after this long [s].
            state: Where to read the prompt (default: the page's last state message).

        Returns:
            The last state.

        Raises:
            EmulationError: Not calibrated within ``timeout`` [s].
        """
        end = time.monotonic() + timeout
        done = ""
        while time.monotonic() < end:
            st = (state() if state is not None else self.debug()["state"]) or {}
            if st.get("state") in ("teleop", "safe_stop"):
                self.gesture("neutral")
                return st
            step = st.get("step") or ""
            if step and step != done and step in GESTURES:
                self.gesture(step)
                done = step
            time.sleep(0.05)
        raise EmulationError(f"not calibrated within {timeout:.0f} s; page log: {self.console}")


def _js(obj: Any) -> str:
    import json

    return json.dumps(obj)
