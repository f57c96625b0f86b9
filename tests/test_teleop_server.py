"""The live Quest server through a real WebSocket client: validation, security, safe stop."""

from __future__ import annotations

import contextlib
import json
import math
import re
import socket
import ssl
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from conftest import band_ticks, replace_once
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

import firmware_interface
from firmware_interface.control_table import BY_NAME, decode
from firmware_interface.options import EMULATOR_LATENCY_MS
from payload.teleop.calibration import Step
from payload.teleop.handmodel import HandModel
from payload.teleop.hands import WEBXR_TO_WORKBENCH, XR_JOINTS
from payload.teleop.live import LiveHub
from payload.teleop.messages import MAX_MESSAGE_BYTES, MessageError, parse_message
from payload.teleop.server import TOKEN_HINT, TeleopServer, page_files
from payload.teleop.tls import CA_NAME, ensure_certificate, server_context

STATUS_FIELDS = {"state", "driver", "operator", "clients", "max_clients", "frames", "dropped",
                 "frame_age_ms", "loop_overruns"}  # fmt: skip
DROPPED_FIELDS = {"malformed", "oversized", "non_finite", "out_of_order", "unauthorized",
                  "rate_limited", "not_holder", "connection_cap"}  # fmt: skip
NEUTRAL_WB = {"left": np.array([0.35, 0.15, 1.1]), "right": np.array([0.35, -0.15, 1.1])}


def xr_hand(side: str, wrist_wb: np.ndarray, aperture: float) -> list[list[float]]:
    """A hand's 25 joints in WebXR local-floor coordinates (independent of the server)."""
    joints_wb = HandModel(side).joints(wrist_wb, np.eye(3), aperture)
    # WebXR from workbench: x_xr = -y_wb, y_xr = z_wb, z_xr = -x_wb
    xr = np.column_stack([-joints_wb[:, 1], joints_wb[:, 2], -joints_wb[:, 0]])
    assert np.allclose(xr @ WEBXR_TO_WORKBENCH.T, joints_wb)
    return xr.tolist()


def frame_msg(
    seq: int, t: float, aperture: float = 0.5, left=None, right=None, untracked=()
) -> str:
    """A frame as the page sends it; the hands in ``untracked`` as the headset's lost ones."""
    left = NEUTRAL_WB["left"] if left is None else left
    right = NEUTRAL_WB["right"] if right is None else right
    hands = {
        "left": {"tracked": True, "joints": xr_hand("left", left, aperture)},
        "right": {"tracked": True, "joints": xr_hand("right", right, aperture)},
    }
    for side in untracked:
        hands[side] = {"tracked": False, "joints": None}
    return json.dumps({"type": "frame", "seq": seq, "t": t, "hands": hands})


def get_status(url: str, context: ssl.SSLContext | None = None) -> dict:
    with urllib.request.urlopen(url, context=context, timeout=10) as r:
        return json.loads(r.read())


def wait_for(predicate, timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(0.01)
    raise AssertionError("condition not met in time")


# -- messages alone ----------------------------------------------------------------------


def test_valid_frame_parses_to_webxr_joints():
    msg = parse_message(frame_msg(3, 12.5))
    assert msg.seq == 3 and msg.t == 12.5
    expected = np.array(xr_hand("left", NEUTRAL_WB["left"], 0.5))
    np.testing.assert_array_equal(msg.left.joints, expected)
    assert msg.left.tracked and msg.right.tracked
    assert len(XR_JOINTS) == 25


NULL = '"hands": {"left": null, "right": null}'


@pytest.mark.parametrize(
    ("text", "kind"),
    [
        ("{not json", "malformed"),
        ("[1, 2]", "malformed"),
        ('{"type": "frame", "seq": "1", "t": 0, ' + NULL + "}", "malformed"),
        ('{"type": "frame", "seq": true, "t": 0, ' + NULL + "}", "malformed"),
        ('{"type": "frame", "seq": 1, "t": NaN, ' + NULL + "}", "non_finite"),
        ('{"type": "frame", "seq": 1, "t": 1e999, ' + NULL + "}", "non_finite"),
        ('{"type": "frame", "seq": 1, "t": 0, "extra": 1, ' + NULL + "}", "malformed"),
        ('{"type": "frame", "seq": 1, "t": 0, "hands": {"left": 3, "right": null}}', "malformed"),
        ('{"type": "hello"}', "malformed"),
        ('{"type": "xr_end", "reason": "exit"}', "malformed"),
        ("x" * (MAX_MESSAGE_BYTES + 1), "oversized"),
    ],
)
def test_bad_messages_are_refused_with_their_kind(text, kind):
    with pytest.raises(MessageError) as err:
        parse_message(text)
    assert err.value.kind == kind


def test_short_or_non_finite_joints_are_refused():
    good = json.loads(frame_msg(1, 0.0))
    short = json.loads(json.dumps(good))
    short["hands"]["left"]["joints"] = short["hands"]["left"]["joints"][:24]
    with pytest.raises(MessageError, match="25 points"):
        parse_message(json.dumps(short))
    nan = json.dumps(good).replace(str(good["hands"]["right"]["joints"][7][1]), "NaN", 1)
    with pytest.raises(MessageError) as err:
        parse_message(nan)
    assert err.value.kind == "non_finite"


# -- the server with a hub (no simulator) -------------------------------------------------


@pytest.fixture
def local_server():
    hub = LiveHub()
    server = TeleopServer(hub, port=0).start()
    yield hub, server
    server.stop()


def test_status_has_exactly_the_documented_fields(local_server):
    _, server = local_server
    st = get_status(f"http://127.0.0.1:{server.port}/status")
    assert set(st) == STATUS_FIELDS
    assert set(st["dropped"]) == DROPPED_FIELDS
    assert set(st["frame_age_ms"]) == {"median", "p99"}
    assert st["clients"] == 0 and st["frames"] == 0


def test_only_the_page_files_are_served(local_server):
    _, server = local_server
    base = f"http://127.0.0.1:{server.port}"
    with urllib.request.urlopen(base + "/", timeout=10) as r:
        assert b"app.js" in r.read()
    assert set(page_files()) >= {"/", "/app.js", "/render.js"}
    for path in ("/server.py", "/../server.py", "/web/app.js", "/%2e%2e/live.py", "/etc/passwd"):
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(base + path, timeout=10)
        err.value.close()  # else its connection stays open and the server's stop waits on it
        assert err.value.code == 404, path


def test_every_bad_message_is_dropped_and_counted_and_the_server_keeps_serving(local_server):
    hub, server = local_server
    origin = f"http://127.0.0.1:{server.port}"
    with connect(f"ws://127.0.0.1:{server.port}/ws", origin=origin) as ws:
        assert json.loads(ws.recv())["type"] == "hello"
        ws.send(frame_msg(5, 100.0))
        wait_for(lambda: hub.frames == 1)
        bad = [
            "{oops",  # malformed JSON
            '{"type": "frame", "seq": 6, "t": "soon", "hands": {"left": null, "right": null}}',
            frame_msg(6, 101.0).replace('"t": 101.0', '"t": NaN'),
            "[" * 70000,  # oversized (and nested)
            frame_msg(5, 100.0),  # replayed
            frame_msg(4, 102.0),  # out of order (older seq)
            frame_msg(7, 99.0),  # out of order (time going backwards)
        ]
        for m in bad:
            ws.send(m)
        ws.send(frame_msg(8, 103.0))  # still served: a valid frame is taken
        wait_for(lambda: hub.frames == 2)
        st = get_status(f"{origin}/status")
        assert st["dropped"] == {
            "malformed": 2,
            "oversized": 1,
            "non_finite": 1,
            "out_of_order": 3,
            "unauthorized": 0,
            "rate_limited": 0,
            "not_holder": 0,
            "connection_cap": 0,
        }
        assert st["clients"] == 1 and st["frames"] == 2
        # refused frames never reach the hand source: the newest frame is the valid one
        assert hub.latest.message.seq == 8


def test_a_huge_message_closes_only_its_connection(local_server):
    hub, server = local_server
    origin = f"http://127.0.0.1:{server.port}"
    with connect(f"ws://127.0.0.1:{server.port}/ws", origin=origin) as ws:
        ws.recv()
        ws.send("x" * (2 * 1024 * 1024))  # past the wire limit: the link is closed
        wait_for(lambda: hub.status()["clients"] == 0)
    assert hub.status()["dropped"]["oversized"] == 1
    with connect(f"ws://127.0.0.1:{server.port}/ws", origin=origin) as ws:
        ws.recv()
        ws.send(frame_msg(0, 1.0))
        wait_for(lambda: hub.frames == 1)


def test_clock_sync_gives_frame_ages(local_server):
    hub, server = local_server
    origin = f"http://127.0.0.1:{server.port}"
    t0 = time.perf_counter()
    with connect(f"ws://127.0.0.1:{server.port}/ws", origin=origin) as ws:
        page_clock = lambda: (time.perf_counter() - t0) * 1e3 + 5e6  # noqa: E731
        ws.recv()
        pongs = 0
        while pongs < 3:
            msg = json.loads(ws.recv())
            if msg["type"] == "ping":
                ws.send(json.dumps({"type": "pong", "id": msg["id"], "t": page_clock()}))
                pongs += 1
        for k in range(20):
            # frames stamped 30 ms in the past on the page's clock
            ws.send(frame_msg(k, page_clock() - 30.0))
            time.sleep(0.005)
        wait_for(lambda: hub.frames == 20)
    age = get_status(f"{origin}/status")["frame_age_ms"]
    assert 29.0 < age["median"] < 60.0, age
    assert age["p99"] >= age["median"]


def test_foreign_origin_and_rebinding_host_are_refused_on_a_local_bind(local_server):
    hub, server = local_server
    url = f"ws://127.0.0.1:{server.port}/ws"
    with pytest.raises(InvalidStatus):
        connect(url, origin="https://evil.example")
    with pytest.raises(InvalidStatus):
        connect(url)  # no Origin at all
    with pytest.raises(InvalidStatus):  # DNS rebinding: a foreign name for our address
        sock = socket.create_connection(("127.0.0.1", server.port))
        connect("ws://evil.example:1/ws", sock=sock, origin="http://evil.example:1")
    with pytest.raises(InvalidStatus):  # two Host headers
        connect(url, origin=f"http://127.0.0.1:{server.port}", additional_headers={"Host": "x"})
    assert hub.status()["dropped"]["unauthorized"] == 4
    with connect(url, origin=f"http://127.0.0.1:{server.port}") as ws:
        assert json.loads(ws.recv())["type"] == "hello"


def test_non_local_bind_needs_tls():
    from payload.teleop.server import ServerError

    with pytest.raises(ServerError, match="TLS"):
        TeleopServer(LiveHub(), host="127.0.0.2", port=0)


def test_non_local_bind_checks_token_and_origin_over_tls(tmp_path):
    host = "127.0.0.2"  # not a loopback *name*: treated as a network bind
    cert, key, made = ensure_certificate(host, tmp_path)
    assert made and oct(key.stat().st_mode & 0o777) == "0o600"
    assert ensure_certificate(host, tmp_path)[2] is False  # kept for the next run
    hub = LiveHub()
    server = TeleopServer(hub, host=host, port=0, ssl_context=server_context(cert, key)).start()
    try:
        client = ssl.create_default_context(
            cafile=str(cert.parent / CA_NAME)
        )  # trusts the CA, as a headset
        base = f"{host}:{server.port}"
        origin = f"https://{base}"
        token = server.token
        assert token and len(token) >= 20
        for url, kwargs in [
            (f"wss://{base}/ws", {"origin": origin}),  # missing token
            (f"wss://{base}/ws?token=wrong", {"origin": origin}),  # wrong token
            (f"wss://{base}/ws?token={token}", {"origin": "https://evil.example"}),
        ]:
            with pytest.raises(InvalidStatus) as err:
                connect(url, ssl=client, **kwargs)
            assert err.value.response.status_code == 403
        with pytest.raises(urllib.error.HTTPError):
            get_status(f"https://{base}/status", client)
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(f"https://{base}/", context=client, timeout=10)
        # a person who typed the address without its token is told what opens the page
        assert TOKEN_HINT in refused.value.read().decode()
        st = get_status(f"https://{base}/status?token={token}", client)
        assert st["dropped"]["unauthorized"] == 5
        with connect(f"wss://{base}/ws?token={token}", ssl=client, origin=origin) as ws:
            assert json.loads(ws.recv())["type"] == "hello"
            ws.send(frame_msg(0, 1.0))
            wait_for(lambda: hub.frames == 1)
        assert server.url().startswith("https://") and f"token={token}" in server.url()
    finally:
        server.stop()


# -- the whole live session with the simulator --------------------------------------------

QUICK_STEPS = (
    Step("neutral", 0.8, 0.4, "neutral"),
    Step("pinch", 0.6, 0.3, "pinch"),
    Step("open", 0.6, 0.3, "open"),
    Step("together", 0.6, 0.3, "together"),
    Step("apart", 0.6, 0.3, "apart"),
    Step("release", 0.4, 0.2, "release"),
)
GESTURE = {  # step -> (aperture, half inter-wrist distance change [m])
    "neutral": (0.5, 0.0),
    "pinch": (0.0, 0.0),
    "open": (1.0, 0.0),
    "together": (0.5, -0.1),
    "apart": (0.5, 0.1),
    "release": (0.5, 0.0),
}


class Page(threading.Thread):
    """A scripted page: follows the prompts, then flies the left wrist forward.

    ``hide_left``: the headset has lost the left hand until the page is told why the
    calibration restarted (``calibration_failure``); ``quiet``: set, the page sends no
    frames (it left VR); ``outbox``: messages it sends once; ``states``: the ``state``
    messages it was sent.
    """

    def __init__(self, hub, port, forward: float = 0.0, hide_left: bool = False):
        super().__init__(daemon=True)
        self.hub, self.port = hub, port
        self.forward = forward
        self.hide_left = hide_left
        self.seq = 0
        self.halt = threading.Event()
        self.quiet = threading.Event()
        self.outbox: list[str] = []
        self.states: list[dict] = []
        self.left = NEUTRAL_WB["left"].copy()
        self.right = NEUTRAL_WB["right"].copy()
        self.aperture = 0.5

    def run(self):
        with connect(
            f"ws://127.0.0.1:{self.port}/ws", origin=f"http://127.0.0.1:{self.port}"
        ) as ws:
            while not self.halt.is_set():
                with self.hub.lock:
                    snap = dict(self.hub.snapshot)
                    state = self.hub.state
                step = snap.get("step") or "neutral"
                if state == "calibrating":
                    self.aperture, half = GESTURE.get(step, (0.5, 0.0))
                    target_l = NEUTRAL_WB["left"] + [0, half, 0]
                    target_r = NEUTRAL_WB["right"] - [0, half, 0]
                elif state in ("teleop", "safe_stop"):
                    self.aperture = 0.5
                    target_l = NEUTRAL_WB["left"] + [self.forward, 0, 0]
                    target_r = NEUTRAL_WB["right"]
                else:
                    target_l, target_r = NEUTRAL_WB["left"], NEUTRAL_WB["right"]
                # hands move at most 0.5 m/s (a jump would be a tracking glitch)
                for cur, tgt in ((self.left, target_l), (self.right, target_r)):
                    d = tgt - cur
                    n = float(np.linalg.norm(d))
                    if n > 0:
                        cur += d * min(1.0, 0.5 * 0.0125 / n)
                while self.outbox:
                    ws.send(self.outbox.pop(0))
                hidden = ("left",) if self.hide_left else ()
                if not self.quiet.is_set():
                    ws.send(frame_msg(self.seq, self.seq * 12.5, self.aperture, self.left,
                                      self.right, untracked=hidden))  # fmt: skip
                self.seq += 1
                try:
                    while True:
                        msg = json.loads(ws.recv(timeout=0))
                        if msg["type"] == "state":
                            self.states.append(msg)
                            if msg.get("calibration_failure"):
                                self.hide_left = False  # told why: the hand is back
                except TimeoutError:
                    pass
                time.sleep(0.0125)


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    out = tmp_path_factory.mktemp("live") / "session"
    hub, session, server, worker = _serving(out=out)
    yield hub, server, session, out
    hub.stop.set()
    worker.join(30)
    server.stop()
    session.close()


def test_dropped_connection_brakes_and_holds_then_resumes_blended(live):
    from payload.teleop.replay import read_hand_recording
    from payload.trials.recorder import read_recording

    hub, server, session, out = live
    # the vehicle flies under the left wrist; with no cargo in opposing contact the phase
    # tracker calls that flight "acquisition" (lining up), with contact "translation"
    flying = ("acquisition", "translation", "turn")

    def driven() -> bool:
        snap = hub.snapshot
        return snap.get("phase") in flying and (snap.get("vehicle") or {}).get("speed", 0) > 1e-3

    # the page reads state and snapshot together: sample both under the hub's lock all along
    pairs: list[tuple[str, object]] = []
    sampling = threading.Event()

    def sample() -> None:
        deadline = time.monotonic() + 180.0  # ends by itself if the test fails early
        while not sampling.is_set() and time.monotonic() < deadline:
            with hub.lock:
                pairs.append((hub.state, (hub.snapshot or {}).get("safe_stop")))
            time.sleep(0.0005)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    page = Page(hub, server.port, forward=0.12)
    page.start()
    wait_for(lambda: hub.state in ("teleop", "safe_stop"), timeout=60)
    wait_for(driven, timeout=30)
    # calibrated: the operator's instruction, addressed to the page that holds control
    assert (hub.snapshot["notice"], hub.snapshot["notice_to"]) == (
        "calibrated: fly with your left wrist",
        "holder",
    )
    time.sleep(1.0)
    page.halt.set()  # the page goes away mid-flight
    page.join(10)
    wait_for(lambda: hub.state == "safe_stop", timeout=5)
    assert "disconnected" in hub.snapshot["safe_stop"]
    time.sleep(1.0)
    page2 = Page(hub, server.port, forward=0.12)  # it comes back
    page2.seq = 0
    page2.left, page2.right = page.left.copy(), page.right.copy()
    page2.start()
    wait_for(lambda: hub.state == "teleop", timeout=10)
    wait_for(driven, timeout=30)
    time.sleep(0.8)
    page2.halt.set()
    page2.join(10)
    steps = session.steps
    sampling.set()
    sampler.join(5)
    # every published state agrees with its snapshot: safe stop exactly when a reason is shown
    live_states = ("teleop", "safe_stop")
    seen = {(state, reason is not None) for state, reason in pairs if state in live_states}
    assert seen == {("teleop", False), ("safe_stop", True)}, seen
    hub.stop.set()
    wait_for(lambda: hub.state == "stopped", timeout=30)
    session.close()
    rec = read_recording(out / "log.mcap")
    phases = [str(p) for p in rec.phase]
    tracked = np.asarray(rec.left_tracked, bool)
    q = np.asarray(rec.q_cmd)
    twist = np.asarray(rec.twist_cmd)
    teleop = next(k for k, p in enumerate(phases) if p in flying and np.any(twist[k] != 0))
    lost = teleop + int(np.argmax(~tracked[teleop:]))
    assert not tracked[lost] and tracked[lost - 1]
    # from the very step the link dropped: braking (no speed request), fingers and rail held
    speed = np.linalg.norm(twist[:, :3], axis=1)  # the commanded body velocity [m/s]
    np.testing.assert_array_equal(q[lost], q[lost - 1])
    back = lost + int(np.argmax(tracked[lost:]))
    np.testing.assert_array_equal(q[lost:back], np.repeat(q[lost - 1 : lost], back - lost, 0))
    # no speed requested from then on: the jerk-bounded limiter can only ramp its
    # acceleration down, so the speed rises by at most a^2 / (2 j) (closed form), then falls
    from payload.teleop.channels import BaseConfig

    base = BaseConfig()
    rise = base.max_accel**2 / (2 * base.max_jerk)
    assert speed[lost:back].max() - speed[lost] <= rise + 1e-4
    peak = lost + int(np.argmax(speed[lost:back]))
    assert peak < back - 1 and np.all(np.diff(speed[peak:back]) <= 1e-12)
    assert all(p != "calibration" for p in phases[lost:back])
    # reconnect: no recalibration, control resumes, the commands blend in without a jump
    assert "calibration" not in phases[teleop:]
    assert any(p in flying and np.any(twist[k] != 0) for k, p in enumerate(phases) if k >= back)
    jumps = np.abs(np.diff(q[back - 1 : back + 40], axis=0)).max()
    assert jumps < 0.05, jumps
    assert len(rec) >= steps - 1 and rec.complete
    header, frames = read_hand_recording(out / "hands.jsonl")  # replayable, frame by frame
    assert header["frame"] == "webxr" and len(frames) == len(rec)
    np.testing.assert_array_equal(frames[lost - 1].left.joints, rec.left_joints[lost - 1])
    assert math.isfinite(hub.status()["frame_age_ms"]["median"] or 0.0)


def _end_session(page: Page, hub: LiveHub, worker: threading.Thread, server) -> None:
    """The page gone, the session's loop stopped and the server down (a test's cleanup)."""
    page.halt.set()
    page.join(10)
    hub.stop.set()
    worker.join(30)
    server.stop()


def _serving(steps=QUICK_STEPS, out=None):
    """A live session (recording into ``out``, or none), its server and its loop's
    thread, running."""
    from payload.trials.live import LiveSession

    hub = LiveHub()
    session = LiveSession(hub, out, steps=steps)
    server = TeleopServer(hub, port=0, scene=session.scene).start()
    worker = threading.Thread(target=session.run, daemon=True)
    worker.start()
    return hub, session, server, worker


def test_a_refused_calibration_says_why_on_every_page_while_the_next_one_runs(caplog):
    """The headset loses the left hand all through a calibration: the captures are
    unusable and the calibration starts again. Every page (the operator's, a watcher's) is
    told why in the state messages' ``calibration_failure`` from the next attempt's first
    prompt to its end, in the terminal's words; once that attempt calibrates, no more."""
    import logging

    hub, session, server, worker = _serving()
    watcher = Page(hub, server.port)
    watcher.quiet.set()  # connected, sending nothing: it watches
    watcher.start()
    page = Page(hub, server.port, hide_left=True)
    try:
        with caplog.at_level(logging.WARNING, logger="payload.trials.live"):
            wait_for(lambda: hub.status()["clients"] == 1, timeout=10)
            page.start()
            wait_for(lambda: hub.state == "teleop", timeout=60)
            wait_for(lambda: any(m["state"] == "teleop" for m in watcher.states), timeout=5)
    finally:
        watcher.halt.set()
        watcher.join(10)
        _end_session(page, hub, worker, server)
        session.close()
    said = [r.getMessage() for r in caplog.records if r.name == "payload.trials.live"]
    assert len(said) == 1 and said[0].startswith("teleop: calibration restarted: "), said
    reason = said[0].removeprefix("teleop: calibration restarted: ")
    assert "no left hand" in reason and "'neutral'" in reason, reason
    for who, states in (("operator", page.states), ("watcher", watcher.states)):
        calibrating = [m for m in states if m["state"] == "calibrating"]
        told = [k for k, m in enumerate(calibrating) if m["calibration_failure"]]
        assert told, (who, calibrating[-1])
        # not during the first attempt; from the second's first prompt to its end
        first = calibrating[told[0]]
        assert told[0] > 0 and told == list(range(told[0], len(calibrating))), who
        assert (first["step"], first["prompt"]) == ("neutral", QUICK_STEPS[0].prompt), first
        assert {m["calibration_failure"] for m in calibrating[told[0] :]} == {reason}, who
        # calibrated: nothing is said any more
        assert all(m["calibration_failure"] == "" for m in states if m["state"] == "teleop")


def test_leaving_vr_brakes_saying_so_not_that_the_page_disconnected(caplog):
    """Exit VR ends the page's XR session; the page stays connected and sends ``xr_end``:
    the safe stop's reason is "operator left VR" on the page and in the terminal (the
    safety supervisor's lines), not "page disconnected", which stays the reason of a
    closed socket; a hand-over (``release``) is said as such too."""
    import logging

    hub, session, server, worker = _serving()
    page = Page(hub, server.port, forward=0.12)
    page.start()

    def driving() -> bool:  # both hands tracked by the supervisor (a loss is then said)
        with hub.lock:
            pipeline = session.source.pipeline if session.source else None
        return pipeline is not None and not any(
            st.lost for st in pipeline.supervisor.status.values()
        )

    def stop_for(message: str) -> str:
        """The page leaves the controls by ``message``: the safe stop's reason."""
        wait_for(driving, timeout=10)
        page.quiet.set()  # no more frames from it: it is out of VR
        page.outbox.append(json.dumps({"type": message}))
        wait_for(lambda: hub.state == "safe_stop", timeout=5)
        reason = hub.snapshot["safe_stop"]
        told = len(page.states)
        wait_for(lambda: any(m["state"] == "safe_stop" for m in page.states[told:]))
        assert {m["safe_stop"] for m in page.states[told:] if m["state"] == "safe_stop"} == {reason}
        page.quiet.clear()  # back in VR: its frames take control again
        wait_for(lambda: hub.state == "teleop", timeout=10)
        return reason

    try:
        with caplog.at_level(logging.WARNING, logger="payload.teleop.safety"):
            wait_for(lambda: hub.state == "teleop", timeout=60)
            left_vr = stop_for("xr_end")
            handed_over = stop_for("release")
            wait_for(driving, timeout=10)
            page.halt.set()  # the socket closes
            page.join(10)
            wait_for(lambda: hub.state == "safe_stop", timeout=5)
            closed = hub.snapshot["safe_stop"]
    finally:
        _end_session(page, hub, worker, server)
        session.close()
    assert (left_vr, handed_over, closed) == (
        "operator left VR",
        "operator handed control over",
        "page disconnected",
    )
    said = [r.getMessage() for r in caplog.records if r.name == "payload.teleop.safety"]
    for reason in (left_vr, handed_over, closed):
        for side in ("left", "right"):
            assert sum(m.endswith(f"{side} hand lost: {reason}") for m in said) == 1, said


def test_a_page_that_leaves_before_its_calibration_leaves_the_watchdog_disarmed():
    """``teleop serve --driver hardware``: a page that goes away mid-calibration ends the
    attempt, and nothing is sent until another page comes; the payload's Bus Watchdog,
    armed 25 steps into the attempt, is disarmed when it ends (the servos hold their goal
    either way) instead of tripping 100 ms later and logging a trip per page that left."""
    from payload.sim.driver import SimDriver
    from payload.teleop.loop import ARM_AFTER_STEPS
    from payload.trials.live import LiveSession

    armed_at = ARM_AFTER_STEPS - 1  # sends before the rig arms it (with its 25th send)

    class Bench:  # the payload on the bench, as the rig sees it: a simulated one
        def __init__(self):
            self.sim, self.sends, self.armed = SimDriver(), 0, []

        def read(self):
            return self.sim.read()

        def send(self, command):
            self.sends += 1
            self.sim.send(command)

        def set_watchdog(self, on):
            self.armed.append((self.sends, on))

        def close(self):
            self.sim.close()

    bench = Bench()
    hub = LiveHub()
    session = LiveSession(hub, None, steps=QUICK_STEPS, payload=bench)
    server = TeleopServer(hub, port=0, scene=session.scene).start()
    worker = threading.Thread(target=session.run, daemon=True)
    worker.start()
    page = Page(hub, server.port)
    page.start()
    try:
        wait_for(lambda: bench.armed[-1:] == [(armed_at, True)], timeout=60)
        page.halt.set()  # gone mid-calibration (the prompts take 3.6 s)
        page.join(10)
        wait_for(lambda: hub.state == "waiting", timeout=10)
        assert not session.calibrated
        sent = bench.sends
        time.sleep(0.3)  # nothing goes out while no page is there
        assert bench.sends == sent and bench.armed[-1] == (sent, False)
    finally:
        _end_session(page, hub, worker, server)
        session.close()


def test_a_payload_lost_while_no_page_drives_it_stops_the_server_saying_so():
    """``teleop serve --driver hardware`` with no page: the payload's health is read about
    once a second (``IDLE_CHECK_S``), so a bus that stops answering ends the server with
    one line naming it (exit 1: :class:`RunAborted`) instead of a status that goes on
    saying the hardware waits, as it did until the server was stopped."""
    from payload.errors import PayloadError, RunAborted
    from payload.sim.driver import SimDriver
    from payload.trials.live import IDLE_CHECK_S, LiveSession

    class BusGone(PayloadError):
        pass

    class Bench:  # the payload on the bench: answers twice, then its bus is gone
        def __init__(self):
            self.sim, self.checks = SimDriver(), []

        def read(self):
            return self.sim.read()

        def send(self, command):
            self.sim.send(command)

        def check_health(self):
            self.checks.append(time.monotonic())
            if len(self.checks) > 2:
                raise BusGone("/dev/ttyUSB0: the serial device failed (unplugged?)")

        def close(self):
            self.sim.close()

    bench = Bench()
    hub = LiveHub()
    session = LiveSession(hub, None, steps=QUICK_STEPS, payload=bench)
    guard = threading.Timer(20.0, hub.stop.set)  # the test's own bound, never reached
    guard.start()
    try:
        t0 = time.monotonic()
        with pytest.raises(RunAborted, match="while no page drove it: /dev/ttyUSB0: the serial"):
            session.run()
    finally:
        guard.cancel()
        session.close()
    assert len(bench.checks) == 3 and hub.state == "stopped"
    # read no more often than IDLE_CHECK_S (how soon after is the machine's load)
    gaps = np.diff([t0, *bench.checks])
    assert np.all(gaps >= IDLE_CHECK_S - 0.01), gaps


@pytest.mark.parametrize("theirs", ["log.mcap", "hands.jsonl"])
def test_a_second_server_on_one_record_folder_refuses_and_keeps_the_firsts(tmp_path, theirs):
    """Two ``teleop serve --record`` on one folder both pass the start-up check; the one
    whose operator calibrates second finds the other's recording (or, an instant earlier,
    only its hands' file) there: its session stops with an error, and every byte of the
    other's files stays, with nothing of its own left beside them."""
    from payload.errors import PayloadError
    from payload.trials.live import LiveSession

    out = tmp_path / "session"
    hub = LiveHub()
    session = LiveSession(hub, out, steps=QUICK_STEPS)
    (out / theirs).parent.mkdir(parents=True, exist_ok=True)
    (out / theirs).write_bytes(b"the other server's recording\n")  # made after the check
    server = TeleopServer(hub, port=0, scene=session.scene).start()
    failed: list[BaseException] = []

    def run() -> None:
        try:
            session.run()
        except BaseException as exc:  # what stopped it is what the test reads
            failed.append(exc)

    worker = threading.Thread(target=run, daemon=True)
    worker.start()
    page = Page(hub, server.port)
    page.start()
    try:
        wait_for(lambda: bool(failed) or hub.state == "teleop", timeout=60)
        wait_for(lambda: bool(failed), timeout=10)
    finally:
        _end_session(page, hub, worker, server)
    assert session.close() is None
    assert isinstance(failed[0], PayloadError) and "already exists" in str(failed[0])
    assert "overwrite=True" not in str(failed[0])  # a command's line, not the API's advice
    assert [f.name for f in out.iterdir()] == [theirs]
    assert (out / theirs).read_bytes() == b"the other server's recording\n"


def test_live_session_records_the_safety_channel_and_station_metrics(tmp_path, monkeypatch):
    """A live session with the base filter (``teleop serve``'s default) records what a
    trial does: one ``/safety/filter`` record per recorded step, taken at that step, and
    ``metrics.json``'s station figures, which agree with the records, the steps after the
    recorder's last flush included (the station monitor here reads 0.1 mm nearer at every
    step and a touch every other one, so any step left out changes a figure)."""
    from mcap.reader import make_reader

    from payload.sim.station import CLEARANCE_CAP, StationMonitor, StationReading
    from payload.trials.live import LiveSession
    from payload.trials.recorder import read_recording
    from payload.trials.safety import FILTER_TOPIC, KEEPIN_TOPIC

    seen = [0]

    def read(self, data):
        seen[0] += 1
        return StationReading(seen[0] % 2 == 0, CLEARANCE_CAP - 1e-4 * seen[0])

    monkeypatch.setattr(StationMonitor, "read", read)

    out = tmp_path / "session"
    hub = LiveHub()
    session = LiveSession(hub, out, steps=QUICK_STEPS, base_filter=True)
    server = TeleopServer(hub, port=0, scene=session.scene).start()
    worker = threading.Thread(target=session.run, daemon=True)
    worker.start()
    page = Page(hub, server.port, forward=0.12)
    page.start()
    try:
        wait_for(lambda: hub.state == "teleop", timeout=60)
        wait_for(lambda: (hub.snapshot.get("vehicle") or {}).get("speed", 0) > 1e-3, timeout=30)
        time.sleep(1.5)
    finally:
        _end_session(page, hub, worker, server)
    result = session.close()
    rec = read_recording(out / "log.mcap")
    # scored as a trial is (confirmed contact: held 0.5 s, dropouts of 0.1 s bridged,
    # docs/trials.md), with what it ran on
    assert rec.meta["contact_definition"] == {"min_interval_s": 0.5, "max_gap_s": 0.1}
    assert (result["min_interval_s"], result["max_gap_s"]) == (0.5, 0.1)
    metrics = json.loads((out / "metrics.json").read_text())
    assert "environment" in metrics["provenance"] and "design_sha256" in metrics["provenance"]
    # the hands each step took, in log.mcap as a trial keeps them (so it replays): the
    # hands.jsonl's WebXR frames in the workbench convention
    from payload.teleop.replay import read_hand_recording
    from payload.trials.recorder import read_hand_frames

    _, in_log = read_hand_frames(out / "log.mcap")
    _, in_jsonl = read_hand_recording(out / "hands.jsonl")
    assert len(in_log) == len(rec) == len(in_jsonl)
    assert all(
        np.array_equal(a.right.joints, b.to_workbench().right.joints, equal_nan=True)
        for a, b in zip(in_log, in_jsonl)
    )
    with open(out / "log.mcap", "rb") as f:
        msgs = list(make_reader(f).iter_messages(topics=[FILTER_TOPIC, KEEPIN_TOPIC]))
    records = [json.loads(m.data) for _, c, m in msgs if c.topic == FILTER_TOPIC]
    assert len(records) == len(rec) > 50
    np.testing.assert_allclose([r["t"] for r in records], rec.t, atol=1e-6)
    assert any(c.topic == KEEPIN_TOPIC for _, c, _ in msgs)
    clearance = np.array([r["station_clearance_m"] for r in records])
    assert np.all((clearance >= 0.0) & (clearance <= CLEARANCE_CAP))
    # the filter's clearance of each step, taken at that step: it changes as the stack flies
    assert len({r["filter_clearance_m"] for r in records}) > 10
    for r in records:
        assert isinstance(r["active"], bool) and r["constraints"] >= 0
        assert r["change_mps"] >= 0.0 and math.isfinite(r["yaw_change_radps"])
        assert r["shape"] in ("", "astrobee", "payload", "ctb")
        if r["constraints"]:  # the QP ran: the filter acted, near a named face
            assert r["active"] and r["shape"] and r["face"]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics == result and metrics["base_filter"] is True
    assert metrics["station_contacts"] == sum(r["station_contact"] for r in records)
    assert metrics["min_station_clearance_mm"] == round(clearance.min() * 1e3, 1)
    active = sum(r["active"] for r in records)
    assert metrics["filter_active_s"] == round(active * 0.02, 2)


def test_calibration_captures_webxr_frames_in_the_workbench_frame():
    from payload.teleop.calibration import CalibrationProcedure
    from payload.teleop.hands import Hand, HandFrame

    steps = (Step("neutral", 0.2, 0.1, "n"), Step("pinch", 0.2, 0.1, "p"))
    cal = CalibrationProcedure(steps)
    for k in range(30):
        left = Hand(xr_hand("left", NEUTRAL_WB["left"], 0.5))
        right = Hand(xr_hand("right", NEUTRAL_WB["right"], 0.5))
        cal.step(HandFrame(k * 0.02, left, right, "webxr"))
    wrist = cal.captures.get("neutral", "left").wrist
    np.testing.assert_allclose(wrist, NEUTRAL_WB["left"], atol=1e-12)


def test_status_line_reads_before_any_frame():
    from payload.teleop.cli import status_line

    hub = LiveHub()
    line = status_line(hub.status(), hub.latency())
    assert line.startswith("waiting") and "age=-/- ms" in line and "dropped: none" in line
    hub.drop("oversized")
    assert "oversized=1" in status_line(hub.status(), hub.latency())


def test_payload_rig_commands_both_drivers_and_reads_the_payload():
    from payload.schema import PayloadCommand
    from payload.sim.driver import SimDriver
    from payload.trials.live import PayloadRig

    with SimDriver() as sim, SimDriver() as bench:
        rig = PayloadRig(sim, bench)
        q = sim.read().q.copy()
        q[-1] = 0.02  # rail
        rig.send(PayloadCommand(q, sim.read().deploy, 0.0))
        for _ in range(25):
            sim.step(1)
            bench.step(1)
        assert rig.read().q[-1] == bench.read().q[-1]
        assert abs(bench.read().q[-1] - 0.02) < 0.005 and abs(sim.read().q[-1] - 0.02) < 0.005
        assert rig.world is sim.world  # the vehicle and the world stay the simulator's


def test_payload_rig_disarms_the_watchdog_over_the_pipelines_first_steps():
    """``teleop serve --driver hardware``: the Bus Watchdog is armed 25 sends into the
    loop, then disarmed when the calibration builds the pipeline (its first step builds
    what it uses once: 99 ms measured on the emulator rig at load 2, beside the
    watchdog's 100 ms) and armed again 25 sends later; disarmed too when an attempt ends
    and nothing is sent (the page gone before its calibration), until the next attempt's
    loop has run 25 steps."""
    from payload.schema import PayloadCommand
    from payload.sim.driver import SimDriver
    from payload.teleop.loop import ARM_AFTER_STEPS
    from payload.trials.live import PayloadRig

    class Bench:
        def __init__(self):
            self.sends, self.armed = 0, []

        def send(self, command):
            self.sends += 1

        def set_watchdog(self, on):
            self.armed.append((self.sends, on))

    with SimDriver() as sim:
        bench = Bench()
        rig = PayloadRig(sim, bench)
        hold = PayloadCommand(sim.read().q, sim.read().deploy, 0.0)
        for _ in range(100):
            rig.send(hold)
        rig.pipeline_built()
        for _ in range(100):
            rig.send(hold)
        rig.idle()  # the attempt ended (a page gone before its calibration): none sent
        for _ in range(100):
            rig.send(hold)
    first = ARM_AFTER_STEPS - 1  # armed just before its 25th send goes out
    assert bench.armed == [
        (first, True), (100, False), (100 + first, True), (200, False), (200 + first, True)
    ]  # fmt: skip


@pytest.mark.parametrize(
    ("flag", "modelled", "recorded"),
    [
        ([], True, ("safe", [])),
        (["--controller", "paper"], False, ("paper", [])),
        (["--no-retarget-collisions"], False, ("safe", ["retarget_collisions"])),
        (
            ["--controller", "paper", "--retarget-collisions"],
            True,
            ("paper", ["retarget_collisions"]),
        ),
    ],
)
def test_serve_models_self_collision_unless_told_not_to(
    monkeypatch, capsys, flag, modelled, recorded
):
    """``payload teleop serve`` runs the ``safe`` controller profile by default (a person
    and possibly real servos in the loop): its session models self-collision unless the
    ``paper`` profile or ``--no-retarget-collisions`` is given, and records which."""
    from payload.cli import main
    from payload.trials import live

    seen = []

    class Stop(Exception):
        pass

    def session(hub, record, payload=None, collisions=False, budget="paper", controller=None,
                **safety):  # fmt: skip
        seen.append((collisions, budget, controller))
        raise Stop

    monkeypatch.setattr(live, "LiveSession", session)
    with pytest.raises(Stop):
        main(["teleop", "serve", "--port", "0", *flag])
    assert seen == [(modelled, "paper", recorded)]


@pytest.mark.parametrize(
    ("flags", "expected"),
    [([], (True, None)), (["--no-base-filter", "--link-delay", "0.5:0.1"], (False, (0.5, 0.1)))],
)
def test_serve_runs_the_base_filter_by_default(monkeypatch, flags, expected):
    """``payload teleop serve``: the base safety filter on unless ``--no-base-filter``
    (the ``safe`` profile), and ``--link-delay`` parsed for the session."""
    from payload.cli import main
    from payload.trials import live

    seen = []

    class Stop(Exception):
        pass

    def session(hub, record, payload=None, base_filter=None, link_delay=None, **settings):
        seen.append((base_filter, link_delay))
        raise Stop

    monkeypatch.setattr(live, "LiveSession", session)
    with pytest.raises(Stop):
        main(["teleop", "serve", "--port", "0", *flags])
    assert seen == [expected]


def test_serve_says_install_the_ca_again_only_when_one_was_there_before(
    monkeypatch, capsys, tmp_path
):
    """``payload teleop serve --tls``: the first certificate is to be installed on the
    headset (not "again"); a kept one asks nothing; a remade one is installed again."""
    from payload.cli import main
    from payload.teleop.tls import CERT_NAME, config_dir
    from payload.trials import live

    class Stop(Exception):
        pass

    def session(*args, **kwargs):
        raise Stop

    monkeypatch.setattr(live, "LiveSession", session)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))

    def ca_line() -> str:
        with pytest.raises(Stop):
            main(["teleop", "serve", "--port", "0", "--tls"])
        out = capsys.readouterr().out
        return next(line for line in out.splitlines() if "through the CA" in line)

    assert ca_line().endswith("(new: install it on the headset)")
    assert "new" not in ca_line()  # kept for the next run
    (config_dir() / CERT_NAME).unlink()  # remade, with a new CA
    assert ca_line().endswith("(new: install it on the headset again)")


@pytest.mark.parametrize(
    ("flags", "says"),
    [
        (["--link-delay", "soon"], "--link-delay"),
        (["--device", "/dev/ttyUSB0"], "--device /dev/ttyUSB0: only with --driver hardware"),
        (["--driver", "hardware"], "--driver hardware needs --device DEV"),
        (["--servos", "mine.toml"], "--servos mine.toml: only with --driver hardware"),
        (["--latency-ms", "1"], "--latency-ms 1.0: only with --driver hardware"),
        (["--emulator"], "--emulator: only with --driver hardware"),
        (["--stay-deployed"], "--stay-deployed: only with --driver hardware"),
        (["--driver", "hardware", "--emulator", "--device", "/dev/x"], "give one bus"),
        (["--driver", "hardware", "--emulator", "--latency-ms", "nan"], "got nan"),
        (["--cert", "c.pem"], "--cert and --key go together"),
        (["--port", "{busy}"], "cannot listen on 127.0.0.1:{busy}"),
        (["--port", "{busy}"], "choose another --port, or --port 0"),
        (["--link-delay", "nan"], "--link-delay nan: not a number"),
        (["--host", "0.0.0.0", "--cert", "{missing}", "--key", "{missing}"], "no such file"),
    ],
)
def test_serve_refuses_a_bad_command_line_before_loading_anything(monkeypatch, capsys, flags, says):
    """``payload teleop serve`` checks its whole command line (and that its port is free)
    before the models and the simulator load, which takes seconds: one line, exit 2."""
    import socket

    import payload.design
    from payload.cli import main

    def started(*args, **kwargs):
        raise AssertionError("the set-up started")

    monkeypatch.setattr(payload.design, "models_follow_design", started)
    with socket.socket() as busy:  # a port in use (listening, as another server's is)
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = str(busy.getsockname()[1])
        missing = "/nonexistent/cert.pem"
        argv = [f.format(busy=port, missing=missing) for f in flags]
        assert main(["teleop", "serve", *argv]) == 2
    err = capsys.readouterr()
    lines = err.err.strip().splitlines()
    assert len(lines) == 1 and says.format(busy=port) in lines[0], err.err
    assert "Errno" not in lines[0], lines[0]
    assert "loading" not in err.out


def test_publish_sets_the_snapshot_and_the_state_together():
    """One lock for both, so a reader never sees a state beside another step's snapshot."""
    hub = LiveHub()
    hub.publish({"t": 1.0, "safe_stop": None}, state="teleop")
    assert (hub.state, hub.snapshot_seq) == ("teleop", 1)
    hub.publish({"t": 1.02, "safe_stop": "left hand lost"}, state="safe_stop")
    assert (hub.state, hub.snapshot["safe_stop"], hub.snapshot_seq) == (
        "safe_stop",
        "left hand lost",
        2,
    )
    hub.publish({"t": 1.04})  # no state given: the state is kept
    assert hub.state == "safe_stop" and hub.snapshot == {"t": 1.04}


# -- one operator at a time, rate and connection limits, tokens, certificates ----------------
def _roles(ws, until: str, timeout: float = 5.0) -> str:
    """Read messages until a ``control`` message with role ``until`` (returned) arrives."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            msg = json.loads(ws.recv(timeout=0.2))
        except TimeoutError:
            continue
        if msg["type"] == "control" and msg["role"] == until:
            return until
    raise AssertionError(f"never told {until!r}")


def test_a_second_client_is_refused_control_and_both_are_told(local_server):
    hub, server = local_server
    url, origin = f"ws://127.0.0.1:{server.port}/ws", f"http://127.0.0.1:{server.port}"
    with connect(url, origin=origin) as a, connect(url, origin=origin) as b:
        _roles(a, "free")
        a.send(frame_msg(0, 0.0, aperture=0.1))
        _roles(a, "holder")
        _roles(b, "watching")  # b is told someone else holds control
        b.send(frame_msg(0, 0.0, aperture=0.9))
        wait_for(lambda: hub.status()["dropped"]["not_holder"] == 1)
        assert hub.status()["frames"] == 1  # only a's frame drives
        a.send(json.dumps({"type": "release"}))  # a hands over: both told
        _roles(a, "free")
        _roles(b, "free")
        b.send(frame_msg(1, 20.0, aperture=0.9))
        _roles(b, "holder")
        _roles(a, "watching")
    wait_for(lambda: hub.status()["clients"] == 0)
    assert hub.status()["operator"] == "none"


def test_connections_beyond_the_cap_are_refused(local_server):
    from payload.teleop.server import MAX_CLIENTS

    hub, server = local_server
    url, origin = f"ws://127.0.0.1:{server.port}/ws", f"http://127.0.0.1:{server.port}"
    with contextlib.ExitStack() as stack:
        for _ in range(MAX_CLIENTS):
            stack.enter_context(connect(url, origin=origin))
        wait_for(lambda: hub.status()["clients"] == MAX_CLIENTS)
        with pytest.raises(InvalidStatus):
            connect(url, origin=origin)
        assert hub.status()["dropped"]["connection_cap"] == 1


FLOOD = """
import sys, time, json
from websockets.sync.client import connect
port, seconds, msg = int(sys.argv[1]), float(sys.argv[2]), sys.stdin.read()
with connect(f"ws://127.0.0.1:{port}/ws", origin=f"http://127.0.0.1:{port}") as ws:
    n, t0 = 0, time.monotonic()
    while time.monotonic() - t0 < seconds:
        due = int((time.monotonic() - t0) * 2000.0)  # 2 kHz on average, sent as due
        while n < due:
            ws.send(msg.replace('"seq": 0', f'"seq": {n}'))
            n += 1
        time.sleep(0.002)
    print(json.dumps({"sent": n, "seconds": time.monotonic() - t0}))
"""


def test_a_2khz_client_is_rate_limited_while_a_50hz_loop_keeps_its_rate(local_server):
    import subprocess
    import sys

    from payload.teleop.server import RATE_BURST, RATE_LIMIT_HZ

    hub, server = local_server
    periods: list[float] = []
    halt = threading.Event()

    def loop():  # a 50 Hz consumer of the hub, on absolute deadlines like the live loop
        t_next = time.monotonic()
        while not halt.is_set():
            with hub.lock:
                _ = hub.latest
            t_next += 0.02
            time.sleep(max(0.0, t_next - time.monotonic()))
            periods.append(time.monotonic())

    worker = threading.Thread(target=loop, daemon=True)
    worker.start()
    seconds = 2.0
    proc = subprocess.run([sys.executable, "-c", FLOOD, str(server.port), str(seconds)],
                          input=frame_msg(0, 0.0), capture_output=True, text=True,
                          timeout=60)  # fmt: skip
    halt.set()
    worker.join(5)
    sent = json.loads(proc.stdout)
    # it really flooded (2 kHz asked; a loaded machine may send a little less)
    assert sent["sent"] / sent["seconds"] > 1500, sent
    st = hub.status()
    taken = st["frames"] + st["dropped"]["out_of_order"]
    limited = st["dropped"]["rate_limited"]
    wait_for(lambda: hub.status()["frames"] + hub.status()["dropped"]["rate_limited"] > 0)
    assert limited > sent["sent"] / 2, (sent, st)  # most of it dropped, and counted
    assert taken <= RATE_BURST + RATE_LIMIT_HZ * sent["seconds"] * 1.1 + 5, (sent, st)
    # the loop kept 50 Hz: as many steps as the wall time allows
    span = periods[-1] - periods[0]
    assert (len(periods) - 1) / span == pytest.approx(50.0, rel=0.05), (len(periods), span)


def test_an_empty_or_short_token_is_refused():
    from payload.teleop.server import ServerError

    for token in ("", "short"):
        with pytest.raises(ServerError, match="session token"):
            TeleopServer(LiveHub(), port=0, token=token)


def test_the_size_limit_counts_bytes_not_characters():
    pad = "\u20ac" * (MAX_MESSAGE_BYTES // 2)  # 3 bytes each in UTF-8
    text = json.dumps({"type": "frame", "pad": pad}, ensure_ascii=False)
    assert len(text) < MAX_MESSAGE_BYTES < len(text.encode())
    with pytest.raises(MessageError) as info:
        parse_message(text)
    assert info.value.kind == "oversized"


def test_the_leaf_certificate_is_not_a_ca_and_names_the_bind_address(tmp_path):
    import datetime
    import ipaddress

    from cryptography import x509

    from payload.teleop.tls import CA_NAME

    cert_path, key_path, made = ensure_certificate("192.0.2.10", tmp_path)
    assert made
    leaf = x509.load_pem_x509_certificate(cert_path.read_bytes())
    ca = x509.load_pem_x509_certificate((tmp_path / CA_NAME).read_bytes())
    assert leaf.extensions.get_extension_for_class(x509.BasicConstraints).value.ca is False
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca is True
    assert not leaf.extensions.get_extension_for_class(x509.KeyUsage).value.key_cert_sign
    leaf.verify_directly_issued_by(ca)  # signed by the CA the headset trusts
    san = leaf.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert ipaddress.ip_address("192.0.2.10") in san.get_values_for_type(x509.IPAddress)
    life = leaf.not_valid_after_utc - leaf.not_valid_before_utc
    assert datetime.timedelta(days=360) < life < datetime.timedelta(days=370)
    assert key_path.stat().st_mode & 0o077 == 0  # the key: the user's only
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [cert_path.name, key_path.name, CA_NAME]
    )  # the CA's key is nowhere
    assert ensure_certificate("192.0.2.10", tmp_path)[2] is False  # kept for the next run


def test_a_design_project_of_its_own_finds_the_workbenchs_iwer(tmp_path):
    """``--desktop`` from a project made with ``payload new`` (no ``package.json``, no
    ``node_modules``): the emulated headset comes from the workbench checkout's
    ``npm ci`` (``make test`` runs it), not a demand the project cannot meet."""
    from conftest import ROOT

    from payload.teleop.emulate import find_iwer

    # the checkout as the test suite finds it (conftest), not as the module computes it
    assert (ROOT / "package.json").is_file()
    assert find_iwer(tmp_path) == ROOT.resolve() / "node_modules" / "iwer" / "build" / "iwer.js"


def test_latency_figures_of_no_frames_are_json_nulls():
    """No frames yet: the percentiles are None, which JSON can carry (a NaN would print
    as bare ``NaN``, which is not JSON)."""
    from payload.teleop.live import percentiles

    assert percentiles([]) == {"median": None, "p99": None}
    assert json.loads(json.dumps(percentiles([]), allow_nan=False)) == {"median": None, "p99": None}
    assert percentiles([1.0, 3.0]) == {"median": 2.0, "p99": pytest.approx(2.98)}


def test_one_ctrl_c_while_a_session_is_scored_does_not_stop_the_scoring(tmp_path, capsys):
    """`teleop serve` closes and scores a recorded session after the Ctrl-C that stops it
    (a second or so); a second Ctrl-C in that time used to stop it without metrics.json
    and figures, saying only "interrupted". Now it says what one more press would cost,
    and only that one stops, naming what was not written."""
    import os
    import signal

    from payload.teleop.cli import _press_twice_to_abandon

    done = []
    with _press_twice_to_abandon(tmp_path):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)  # the handler runs between bytecodes of this thread
        done.append("scored")
    assert done == ["scored"]
    assert "Ctrl-C again stops without its metrics.json" in capsys.readouterr().err
    with pytest.raises(KeyboardInterrupt), _press_twice_to_abandon(tmp_path):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
        done.append("not reached")
    assert done == ["scored"]
    assert f"metrics.json and the figures of {tmp_path} were not written" in (
        capsys.readouterr().err
    )
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_a_stop_while_the_session_closes_still_closes_its_driver():
    """A Ctrl-C or SIGTERM raised while a live session closes (its last command, the
    recording, the scoring) used to skip the driver's close: with the hardware driver
    the servos stayed torqued. The driver is closed however far the close got."""
    from payload.trials.live import LiveSession

    session = LiveSession(LiveHub(), None, steps=QUICK_STEPS)
    real, closed = session.driver, []

    class Interrupted:
        def command_twist(self, twist):
            raise KeyboardInterrupt

        def close(self):
            closed.append(True)
            real.close()

    session.driver = Interrupted()
    with pytest.raises(KeyboardInterrupt):
        session.close()
    assert closed == [True]


def test_serve_stopped_while_loading_leaves_the_servos_torque_off(tmp_path, monkeypatch, capsys):
    """`teleop serve --driver hardware`: the servos are powered and homed before the
    simulator and the retargeters load (seconds), each stage said first on stderr, as `hw
    run` says them (the servos moved without a word before). A Ctrl-C (or SIGTERM) then
    used to leave all 18 torqued, their watchdog off; the driver is closed now."""
    from firmware_interface.emulator import EmulatorProcess
    from payload.cli import _parse
    from payload.teleop.cli import serve

    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))

    def loading(*args, **kwargs):
        raise KeyboardInterrupt

    with EmulatorProcess() as emu:
        argv = ["teleop", "serve", "--driver", "hardware", "--device", emu.port, "--port", "0"]
        with pytest.raises(KeyboardInterrupt):
            serve(_parse(argv), loading)
        assert not any(s["torque"] for s in emu.servos().values())
    said = capsys.readouterr().err.splitlines()
    assert said[:2] == [
        f"bringing up the servos on {emu.port} and homing the rail and the stage ...",
        "moving to the design's home posture ...",
    ], said


@pytest.mark.parametrize("stay", [False, True])
def test_serve_stows_the_payload_when_it_stops_unless_told_to_stay(
    tmp_path, monkeypatch, capsys, stay
):
    """`teleop serve --driver hardware` closed the payload deployed, its torque off, and the
    next bring-up drove the stage up into the bays with the fingers out. A server that
    stops (here: its session ends at once, as when ``--seconds`` elapse) stows it first,
    saying so: the servos rest stowed, the stage at its stop. ``--stay-deployed`` leaves
    it out, the stage down."""
    from firmware_interface.emulator import EmulatorProcess
    from firmware_interface.servo_map import load_servo_map, posture_ticks
    from payload.cli import _parse
    from payload.design.params import load_design
    from payload.teleop.cli import serve

    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))

    class Ended:  # the session the server runs (the simulator's, here ending at once)
        scene = None

        def run(self) -> None:
            return None

        def close(self) -> None:
            return None

    argv = ["teleop", "serve", "--driver", "hardware", "--port", "0"]
    with EmulatorProcess() as emu:
        extra = ["--stay-deployed"] if stay else []
        assert serve(_parse([*argv, "--device", emu.port, *extra]), lambda *a, **k: Ended()) == 0
        where = {i: s["pos"] for i, s in emu.servos().items()}
    smap = load_servo_map()
    target = posture_ticks(smap, load_design(), "home" if stay else "stowed")
    off = {s.joint: abs(where[s.id] - target[s.id]) for s in smap.servos}
    assert all(off[j] <= band_ticks(j) for j in off), off
    said = capsys.readouterr().err
    assert ("stowing the payload (the deployment's reverse) ..." in said) is not stay, said


def test_serve_drives_the_hardware_with_its_servo_map_and_latency(tmp_path, monkeypatch, capsys):
    """`teleop serve --driver hardware` opened the bus with the packaged servo map and a
    16 ms latency allowance whatever the user's rig (hardware.md's steps 1 and 2 set both
    for `hw run`): a mirrored joint of the user's map would have run the wrong way. Now
    `--servos` and `--latency-ms` are the hw commands': the home posture is reached in
    the given map's ticks, and a reply timeout the bus cannot meet fails the bring-up."""
    from firmware_interface.emulator import EmulatorProcess
    from firmware_interface.servo_map import home_ticks, load_servo_map
    from payload.cli import _parse
    from payload.errors import RunAborted
    from payload.teleop.cli import serve

    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    packaged = Path(firmware_interface.__file__).with_name("servos.toml")
    mine = tmp_path / "mine.toml"  # servo 1's horn fitted 100 ticks round from the packaged
    servo1 = 'id = 1\njoint = "A_mcp_flex"\ndirection = 1\nzero = 2048\n'
    mine.write_text(replace_once(packaged.read_text(), servo1, servo1.replace("2048", "2148")))

    def loading(*args, **kwargs):
        raise KeyboardInterrupt

    expected = home_ticks(load_servo_map(str(mine)))[1]
    assert expected != home_ticks(load_servo_map())[1]
    base = ["teleop", "serve", "--driver", "hardware", "--port", "0", "--servos", str(mine)]
    with EmulatorProcess(str(mine)) as emu:
        with pytest.raises(KeyboardInterrupt):
            serve(_parse([*base, "--device", emu.port]), loading)
        table = emu.table(1)
    r = BY_NAME["goal_position"]
    assert decode(r, table[r.address : r.address + r.size]) == expected
    capsys.readouterr()
    # replies 10 ms late: inside 16 ms's allowance, past 0 ms's
    with EmulatorProcess(str(mine), faults=["latency:10ms"]) as emu:
        with pytest.raises(RunAborted):
            serve(_parse([*base, "--device", emu.port, "--latency-ms", "0"]), loading)


@pytest.mark.parametrize(
    "given, allowance", [([], EMULATOR_LATENCY_MS), (["--latency-ms", "20"], 20.0)]
)
def test_serve_on_its_own_emulator_gets_a_50_ms_reply_allowance(
    given, allowance, tmp_path, monkeypatch
):
    """`teleop serve --driver hardware --emulator` gave the driver the USB adapter's 16 ms
    latency allowance, which the emulator on a loaded host does not meet; it now gives
    50 ms unless --latency-ms says otherwise."""
    from payload.cli import _parse
    from payload.errors import RunAborted
    from payload.teleop.cli import serve

    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    seen = []

    def spy(device, smap, **kwargs):
        seen.append(kwargs["latency_timer_ms"])
        raise RunAborted("the spy stops here")

    def loading(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(firmware_interface, "DynamixelDriver", spy)
    argv = ["teleop", "serve", "--driver", "hardware", "--emulator", "--port", "0", *given]
    with pytest.raises(RunAborted, match="the spy stops here"):
        serve(_parse(argv), loading)
    assert seen == [allowance]


def test_a_bad_servo_map_is_refused_before_any_certificate_is_made(tmp_path, monkeypatch, capsys):
    """`--servos` names a map that cannot be read: one line, exit 2, before the TLS
    certificate a LAN bind makes (the map was read only when the bus was opened)."""
    from payload.cli import main

    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))
    missing = tmp_path / "nowhere.toml"
    argv = ["teleop", "serve", "--driver", "hardware", "--emulator", "--host", "0.0.0.0",
            "--port", "0", "--servos", str(missing)]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(missing) in err[0], err
    assert not (tmp_path / "config").exists() or not any((tmp_path / "config").rglob("*.pem"))


def test_serve_with_the_emulator_starts_and_stops_its_own_bus(tmp_path, monkeypatch, capsys):
    """`teleop serve --driver hardware --emulator` (as `hw run --emulator`): a bus
    emulated for the session, brought up and homed, and gone when the command ends."""
    from payload.cli import _parse
    from payload.teleop.cli import serve

    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))

    def loading(*args, **kwargs):
        raise KeyboardInterrupt

    argv = ["teleop", "serve", "--driver", "hardware", "--emulator", "--port", "0"]
    with pytest.raises(KeyboardInterrupt):
        serve(_parse(argv), loading)
    said = capsys.readouterr().err.splitlines()
    first = re.fullmatch(
        r"bringing up the servos on (/dev/pts/\d+) and homing the rail and the stage \.\.\.",
        said[0],
    )
    assert first is not None and said[1] == "moving to the design's home posture ...", said
    assert not Path(first.group(1)).exists()  # the emulator's pty closed with it


def test_a_sigterm_while_a_session_is_scored_counts_as_a_press(tmp_path, capsys):
    """The command stops on SIGTERM as on Ctrl-C (payload.cli's handler): while the session
    is scored, one SIGTERM says what the next would cost and the second stops, raising the
    command's own stop (Terminated); the handler is the command's again after."""
    import os
    import signal

    from payload.cli import _terminate as terminate
    from payload.errors import Terminated
    from payload.teleop.cli import _press_twice_to_abandon

    before = signal.signal(signal.SIGTERM, terminate)
    try:
        with pytest.raises(Terminated), _press_twice_to_abandon(tmp_path):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
            assert "Ctrl-C again stops" in capsys.readouterr().err
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
        assert signal.getsignal(signal.SIGTERM) is terminate
    finally:
        signal.signal(signal.SIGTERM, before)


def test_a_warning_under_the_status_line_starts_a_line_of_its_own(caplog):
    """On a terminal the status line is redrawn in place (``\\r`` ... ``\\033[K``, no
    newline); a warning logged then ran on from it ("...dropped: noneWARNING ..."). The
    handler clears the line first on a terminal (read back through a pseudo-terminal),
    and writes the record alone elsewhere; a safety event names its hand, kind and reason
    ("left hand lost: page disconnected")."""
    import io
    import logging
    import os

    from payload.teleop.cli import _BesideStatusLine
    from payload.teleop.safety import SafetyConfig, TrackingSupervisor

    master, slave = os.openpty()
    try:
        with os.fdopen(os.dup(slave), "w") as tty:
            handler = _BesideStatusLine(tty)
            tty.write("\rlive: 50 Hz, dropped: none\033[K")
            record = logging.LogRecord(
                "payload.teleop.x", logging.WARNING, __file__, 1, "a warning", (), None
            )
            handler.emit(record)
        seen = ""
        while "a warning" not in seen or not seen.endswith("\n"):
            seen += os.read(master, 4096).decode()  # the terminal's lines, as written
    finally:
        os.close(master)
        os.close(slave)
    status_end = seen.index("\x1b[K") + len("\x1b[K")
    assert seen[status_end:].startswith("\r\x1b[KWARNING a warning"), repr(seen)
    plain = io.StringIO()
    handler = _BesideStatusLine(plain)
    handler.emit(record)
    # off a terminal: the record alone; another library's record names its logger
    other = logging.LogRecord("websockets", logging.WARNING, __file__, 1, "closed", (), None)
    handler.emit(other)
    assert plain.getvalue() == "WARNING a warning\nWARNING websockets: closed\n"
    supervisor = TrackingSupervisor(SafetyConfig(), {"left": np.zeros(3), "right": np.zeros(3)})
    with caplog.at_level(logging.WARNING, logger="payload.teleop.safety"):
        supervisor._event(1.5, "left", "lost", "page disconnected")  # what force_lost logs
    said = [r.getMessage() for r in caplog.records]
    assert any(m.endswith("left hand lost: page disconnected") for m in said), said


def test_a_page_sees_the_vehicle_and_the_bag_before_anyone_drives():
    """Before any page sends hands the session publishes the world as it stands ("waiting"):
    a page drew the modules' walls alone until a calibration began. The vehicle, the bag
    and the fingertips are MuJoCo's own positions (read from its data, rounded as sent)."""
    from payload.trials.live import LiveSession

    hub = LiveHub()
    session = LiveSession(hub, None, steps=QUICK_STEPS)
    worker = threading.Thread(target=session.run, daemon=True)
    worker.start()
    try:
        end = time.monotonic() + 30
        while time.monotonic() < end and not hub.snapshot.get("vehicle"):
            time.sleep(0.02)
        snap, state = dict(hub.snapshot), hub.state
    finally:
        hub.stop.set()
        worker.join(30)
        session.close()
    assert state == "waiting" and snap["phase"] == "waiting" and snap["prompt"] == ""
    world, data = session.driver.world, session.driver.data
    np.testing.assert_allclose(snap["vehicle"]["pos"], data.xpos[world.astrobee], atol=1e-5)
    np.testing.assert_allclose(snap["ctb"]["pos"], data.xpos[world.ctb], atol=1e-5)
    tip = data.site("payload/A_tip").xpos
    np.testing.assert_allclose(snap["fingers"]["A"], tip, atol=1e-5)
    assert snap["calibrated"] is False and snap["safe_stop"] is None


def test_a_certificate_with_another_certificates_key_is_said_plainly(tmp_path):
    """Two certificates made as `teleop serve` makes them; the first with the second's key
    is refused naming the key ("KEY_VALUES_MISMATCH", OpenSSL's constant, was the whole
    reason); each with its own key loads."""
    from payload.teleop.tls import TlsError

    (c1, k1, _), (c2, k2, _) = (
        ensure_certificate("127.0.0.1", tmp_path / name) for name in ("one", "two")
    )
    server_context(c1, k1), server_context(c2, k2)
    with pytest.raises(TlsError) as err:
        server_context(c1, k2)
    assert str(err.value) == f"TLS certificate {c1}: the key {k2} is not this certificate's"


def test_a_file_that_is_not_pem_is_named(tmp_path):
    """A certificate or key file holding no PEM block (a DER file, a wrong file given):
    the file is named, with what it lacks (OpenSSL's "[SSL] PEM lib (_ssl.c:...)" was the
    whole reason)."""
    from payload.teleop.tls import TlsError

    cert, key, _ = ensure_certificate("127.0.0.1", tmp_path / "made")
    notes = tmp_path / "notes.txt"
    notes.write_text("not a certificate\n")
    for c, k, lacking in ((notes, key, "certificate"), (cert, notes, "private key")):
        with pytest.raises(TlsError) as err:
            server_context(c, k)
        assert str(err.value) == (
            f"TLS certificate {c}: {notes} holds no PEM {lacking} "
            f"(-----BEGIN ... {lacking.upper()}-----)"
        )


def test_a_recorded_live_session_says_what_its_scoring_found(tmp_path, monkeypatch, capsys):
    """``teleop serve --record`` said only "recorded DIR (N steps)" when it stopped: it now
    says what the scoring wrote and prints the trial's summary as ``payload trial`` does
    (the serve command hands its scored result to the trials' printer)."""
    from test_trials import fixture_synthetic_trial

    from payload.cli import main
    from payload.trials import live_cli

    result = fixture_synthetic_trial(2, tmp_path / "t")
    capsys.readouterr()

    class Scored:  # the session as the real one ends: run returns, close scores it
        def __init__(self, *args, **kwargs) -> None:
            self.scene: dict = {}

        def run(self) -> None:
            pass

        def close(self) -> dict:
            return result

    monkeypatch.setattr(live_cli, "_live_session", Scored)
    assert main(["teleop", "serve", "--port", "0", "--record", str(tmp_path / "s")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert "  scored: metrics.json, fig_ctb_body_frame.png, fig_route.png written" in out
    assert f"  success: {'yes' if result['success'] else 'no'}" in out
    assert any(line.startswith("  RMS deviation") for line in out), out


def test_the_status_line_to_a_log_is_written_on_change_not_every_second(monkeypatch, capsys):
    """Without a terminal, ``teleop serve`` wrote its status line once a second, filling a
    log with the same waiting line. It writes it when the session's state or operator
    changes, and else every STATUS_LOG_S."""
    from payload.teleop import cli

    hub = LiveHub()
    stop = threading.Event()
    printer = threading.Thread(target=cli._status_printer, args=(hub, stop, 0.01))
    printer.start()
    time.sleep(0.5)  # about 50 status reads, one state
    hub.state = "calibrating"
    time.sleep(0.5)
    stop.set()
    printer.join()
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2 and "waiting" in lines[0] and "calibrating" in lines[1], lines
    monkeypatch.setattr(cli, "STATUS_LOG_S", 0.1)  # the same state, again after this long
    stop.clear()
    printer = threading.Thread(target=cli._status_printer, args=(hub, stop, 0.01))
    printer.start()
    time.sleep(0.6)
    stop.set()
    printer.join()
    assert 2 <= len(capsys.readouterr().err.splitlines()) <= 7
