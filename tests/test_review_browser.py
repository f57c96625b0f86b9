"""Browser test of the static review: headless Chromium draws the payload where it must be.

The page is the one ``payload review --static`` writes. With the vehicle, findings and
reach clouds hidden and the deployment animation held at its start (stowed), the payload
must cover the region where its meshes project through the camera the review sets (a
pinhole projection computed here, independently of three.js), in the fingers' colours,
and the background must be untouched everywhere else.

The same page, as it opens: every finger, the stage, the carriage and Astrobee's body lie
inside the viewport, projected through the page's own three.js camera; no two label boxes
(their screen rectangles) intersect; the legend lists every colour the scene draws. On a
failing design, the title (its verdict wrapped) and the legend cover none of those.

Without Chromium the tests skip, except under CI (``CI`` set), where they fail.
"""

from __future__ import annotations

import itertools
import math
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from payload.design import build_tree, load_design
from payload.envelope.geometry import PayloadGeometry
from payload.review.browser import CONTROLS_BAR, VIEWPORT, chromium_path
from payload.review.design_view import build_design_review
from payload.review.project import project_files
from payload.review.scene import BACKGROUND, CAMERA_FOV_DEG
from payload.sim.iss import IssModule


def _require_browser() -> None:
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:  # pragma: no cover
        if os.environ.get("CI"):
            pytest.fail("CI: playwright is not installed")
        pytest.skip("playwright is not installed")
    if chromium_path() is None:
        if os.environ.get("CI"):
            pytest.fail("CI: Chromium is missing (/usr/bin/chromium)")
        pytest.skip("Chromium is not installed")


def test_a_missing_browser_fails_under_ci_and_skips_elsewhere(monkeypatch) -> None:
    monkeypatch.setattr(sys.modules[__name__], "chromium_path", lambda: None)
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="Chromium is missing"):
        _require_browser()
    monkeypatch.delenv("CI")
    with pytest.raises(pytest.skip.Exception):
        _require_browser()


def project(points: np.ndarray, camera: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Pixel coordinates (u right, v down) of world points seen from ``camera``, looking at
    the origin with z up, vertical field of view CAMERA_FOV_DEG."""
    w, h = size
    f = -camera / np.linalg.norm(camera)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    up = np.cross(r, f)
    d = points - camera
    xc, yc, zc = d @ r, d @ up, d @ f
    t = math.tan(math.radians(CAMERA_FOV_DEG) / 2)
    ndc_x, ndc_y = xc / (zc * t * w / h), yc / (zc * t)
    return np.stack([(ndc_x + 1) / 2 * w, (1 - ndc_y) / 2 * h], axis=1)


def _hull_mask(uv: np.ndarray, size: tuple[int, int], grow: float) -> np.ndarray:
    from matplotlib.path import Path as MplPath
    from scipy.spatial import ConvexHull

    hull = uv[ConvexHull(uv).vertices]
    centre = hull.mean(axis=0)
    d = hull - centre
    hull = centre + d * (1 + grow / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9))
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w]
    pix = np.stack([xx.ravel() + 0.5, yy.ravel() + 0.5], axis=1)
    return MplPath(hull).contains_points(pix).reshape(h, w)


def _hue(rgb: np.ndarray) -> np.ndarray:
    import matplotlib.colors as mc

    return mc.rgb_to_hsv(np.clip(rgb, 0, 1))


def test_static_review_draws_the_payload_where_it_projects(tmp_path: Path) -> None:
    _require_browser()
    from matplotlib.image import imread

    from payload.cli import main
    from payload.envelope.report import FINGER_COLOURS
    from payload.review.browser import screenshot

    html = tmp_path / "review.html"
    assert main(["review", "--static", str(html), "--reach-samples", "1000"]) == 0
    text = html.read_text()
    assert "<script src=" not in text and "MeshCat.Viewer" in text  # standalone page

    png = tmp_path / "review.png"
    hide = [["meshcat", "review", n] for n in ("vehicle", "findings", "reach")]
    screenshot(html, png, time_s=0.0, hide=hide, overlay=False)
    img = imread(png)[..., :3].astype(float)
    h, w = img.shape[:2]
    assert (w, h) == VIEWPORT

    # where the stowed payload must appear: its meshes posed by the design's own tree
    review = build_design_review(project_files(), reach_samples=0)
    tree = build_tree(load_design(project_files().design))
    geom = PayloadGeometry(tree)
    poses = tree.link_poses(review.check.q)
    pts = np.vstack(
        [geom.mesh_vertices[n] @ poses[n][:3, :3].T + poses[n][:3, 3] for n in geom.links]
    )
    camera, _ = review.scene.camera
    uv = project(pts - review.centre, np.asarray(camera), (w, h))
    assert np.all((uv > 0) & (uv < [w, h])), "the camera does not frame the payload"
    inside = _hull_mask(uv, (w, h), grow=-2.0)
    near = _hull_mask(uv, (w, h), grow=6.0)

    bg = np.abs(img - np.asarray(BACKGROUND)).max(axis=2) < 3 / 255
    bar = np.zeros_like(bg)
    bar[: CONTROLS_BAR[1], w - CONTROLS_BAR[0] :] = True
    outside = ~near & ~bar
    assert bg[outside].mean() > 0.999, "something is drawn outside the payload's projection"
    drawn = ~bg & inside
    assert drawn.sum() > 0.25 * inside.sum(), "the payload's projection is mostly empty"
    ys, xs = np.nonzero(~bg & ~bar)
    got = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1])
    want = np.concatenate([uv.min(axis=0), uv.max(axis=0)])
    assert np.abs(got - want).max() < 3.0, f"drawn box {got} != projected box {want.round(1)}"

    hsv = _hue(img)
    for finger, colour in FINGER_COLOURS.items():
        want = _hue(np.array([int(colour[i : i + 2], 16) / 255 for i in (1, 3, 5)]))
        dh = np.abs(hsv[..., 0] - want[0])
        dh = np.minimum(dh, 1 - dh)
        match = (dh < 0.03) & (hsv[..., 1] > 0.4) & (hsv[..., 2] > 0.15)
        assert match[inside].sum() > 40, f"finger {finger} ({colour}) is not drawn"
        assert match[outside].sum() == 0, f"finger {finger}'s colour outside the payload"


# ------------------------------------------------------------- the default view


@pytest.fixture(scope="module")
def static_review(tmp_path_factory) -> Path:
    from payload.cli import main

    html = tmp_path_factory.mktemp("review") / "review.html"
    assert main(["review", "--static", str(html), "--reach-samples", "1000"]) == 0
    return html


_CAMERA = """(names) => {
    const c = viewer.camera;
    c.updateMatrixWorld();
    const root = viewer.scene_tree.find(names).object;
    root.updateMatrixWorld(true);
    return {P: c.projectionMatrix.elements, V: c.matrixWorldInverse.elements,
            R: root.matrixWorld.elements,
            w: viewer.renderer.domElement.clientWidth, h: viewer.renderer.domElement.clientHeight};
}"""


def page_projection(page, root: str = "review") -> tuple[np.ndarray, tuple[int, int]]:
    """The page's projection, view and scene-root (``/meshcat/<root>``) matrices as one
    (4, 4) matrix: from a point in the root's frame to clip coordinates."""
    cam = page.evaluate(_CAMERA, ["meshcat", root])
    m = [np.array(cam[k], dtype=float).reshape(4, 4).T for k in ("P", "V", "R")]  # column-major
    return m[0] @ m[1] @ m[2], (int(cam["w"]), int(cam["h"]))


def to_pixels(points: np.ndarray, m: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Pixel coordinates (u right, v down) of payload-frame points, shape (n, 2)."""
    clip = np.c_[points, np.ones(len(points))] @ m.T
    assert np.all(clip[:, 3] > 0), "a point is behind the camera"
    ndc = clip[:, :3] / clip[:, 3:]
    w, h = size
    return np.stack([(ndc[:, 0] + 1) / 2 * w, (1 - ndc[:, 1]) / 2 * h], axis=1)


def _posed(geom, poses: dict, links) -> dict[str, np.ndarray]:
    return {n: geom.mesh_vertices[n] @ poses[n][:3, :3].T + poses[n][:3, 3] for n in links}


def _framed_on_screen(page, design_file: Path) -> dict[str, np.ndarray]:
    """Pixel coordinates of what the default view frames, as the page opens (the payload
    stowed): the corners of the bays' box (from the design's ``[vehicle]`` table), every
    finger link, the stage and the carriage (posed by the design tree of ``design_file``),
    and the corners of Astrobee's body; projected through the page's own camera
    (:func:`page_projection`)."""
    from payload.envelope.vehicle import vehicle_from_dict

    design = load_design(design_file)
    tree = build_tree(design)
    geom = PayloadGeometry(tree)
    sx, sy, sz = design.vehicle["bay_size"]
    bays = np.array([-sx / 2, -sy / 2, -sz]), np.array([sx / 2, sy / 2, 0.0])
    vehicle = vehicle_from_dict(design.vehicle or {})
    body = vehicle.body_lower, vehicle.body_upper
    wanted = ["stage", "carriage"] + [n for n in geom.links if n[1:2] == "_"]
    assert {n[0] for n in wanted if n[1:2] == "_"} == set("ABCD")
    m, size = page_projection(page)
    parts = _posed(geom, tree.link_poses(tree.posture("stowed")), wanted)
    corners = list(itertools.product((0, 1), repeat=3))
    parts["bays"] = np.array([np.where(c, bays[1], bays[0]) for c in corners])
    parts["Astrobee"] = np.array([np.where(c, body[1], body[0]) for c in corners])
    return {name: to_pixels(pts, m, size) for name, pts in parts.items()}


def _screen_box(uv: np.ndarray) -> dict[str, float]:
    """The screen rectangle (x, y, w, h) [px] bounding pixel coordinates, shape (n, 2)."""
    (x0, y0), (x1, y1) = uv.min(axis=0), uv.max(axis=0)
    return {"x": x0, "y": y0, "w": x1 - x0, "h": y1 - y0}


_OVERLAY_BOXES = """() => ["payload-title", "payload-legend"].map((id) => {
    const r = document.getElementById(id).getBoundingClientRect();
    return {id, x: r.x, y: r.y, w: r.width, h: r.height};
})"""


def _payload_framed(page, design_file: Path, viewport: tuple[int, int]) -> None:
    """The default view as the page opens frames the payload: the bays' box and every
    stowed finger link, the stage and the carriage lie in the viewport, none under the
    title's box or the legend's (read from the page); the bays fill a good part of the
    view (their screen box at least 30 % of its width) and Astrobee's body shows around
    them (at least 5 % of the width beyond them on each side), so the reviewer sees where
    they are."""
    overlay = page.evaluate(_OVERLAY_BOXES)
    seen = _framed_on_screen(page, design_file)
    body = seen.pop("Astrobee")
    for name, uv in seen.items():
        assert np.all((uv >= 0) & (uv <= viewport)), (viewport, name)
        for box in overlay:
            assert _apart(box, _screen_box(uv)), (viewport, name, box)
    bays = _screen_box(seen["bays"])
    w = viewport[0]
    assert bays["w"] >= 0.3 * w, (viewport, bays)
    left, right = max(body[:, 0].min(), 0.0), min(body[:, 0].max(), w)
    assert bays["x"] - left >= 0.05 * w and right - (bays["x"] + bays["w"]) >= 0.05 * w


def test_the_default_view_frames_the_bays_and_the_stowed_payload(static_review) -> None:
    """The default view framed the whole vehicle with the payload deployed and the reach
    clouds: the stowed payload, the thing under review, was a small cluster (its bays
    about 14 % of the view's width) under labels that crowded it. It now frames the two
    lower bays and the stowed payload in them (:func:`_payload_framed`)."""
    _require_browser()
    from payload.review.browser import open_page

    with open_page(static_review) as page:
        assert page_projection(page)[1] == VIEWPORT
        _payload_framed(page, project_files().design, VIEWPORT)


def _failing_page(tmp_path: Path, design_dict: dict) -> tuple[Path, Path]:
    """A project whose bays are too small for the payload (its design file), and its
    design review's static page (no reach clouds)."""
    from test_review import _copy_project

    from payload.review.page import static_html

    failing = _copy_project(tmp_path, design_dict, [0.18, 0.10, 0.085])  # bays too small
    html = tmp_path / "failing.html"
    html.write_text(static_html(build_design_review(project_files(failing), reach_samples=0).scene))
    return failing, html


def test_a_failing_verdict_covers_neither_the_bays_nor_the_payload(tmp_path, design_dict) -> None:
    """A failing design's verdict (its first failure, and how many more) wraps onto a
    second line, and the title's box lay over the top of Astrobee's body in the default
    view. At the tests' size and at 1280 x 800 the view still frames the bays and the
    stowed payload clear of the title and the legend (:func:`_payload_framed`)."""
    _require_browser()
    from payload.review.browser import open_page
    from payload.review.page import VERDICT_FONT_PX

    failing, html = _failing_page(tmp_path, design_dict)
    for viewport in (VIEWPORT, (1280, 800)):
        with open_page(html, viewport) as page:
            verdict = page.evaluate(
                "() => document.querySelector('#payload-title .payload-subtitle')"
                ".getBoundingClientRect().height"
            )
            assert verdict >= 2 * VERDICT_FONT_PX, verdict  # two lines (the case at issue)
            _payload_framed(page, failing, viewport)


def test_no_two_labels_overlap_and_each_names_what_it_measures(static_review) -> None:
    _require_browser()
    _labels_shown_apart(static_review, project_files().design)


def test_a_failing_designs_labels_are_one_per_wall_and_all_shown(tmp_path, design_dict) -> None:
    """With the bays too small, 14 parts stick out: a label each (and one per clear wall)
    crowded 20 labels over Astrobee's body. At most one label per bay wall, every one shown
    beside the payload, no two overlapping."""
    _require_browser()
    from payload.envelope.vehicle import vehicle_from_dict

    failing, html = _failing_page(tmp_path, design_dict)
    boxes = _labels_shown_apart(html, failing)
    walls = vehicle_from_dict(load_design(failing).vehicle or {}).walls
    assert len(boxes) <= len(walls), [b["text"] for b in boxes]
    assert any("(and " in b["text"] for b in boxes)  # the rest of a wall's crowd, counted


def _labels_shown_apart(html: Path, design_file: Path) -> list[dict]:
    """The label boxes of the review page ``html`` of ``design_file`` (read from the page),
    checked: every stowed label shown, in the viewport, none over the stowed payload's
    screen box, no two overlapping."""
    from payload.review.browser import open_page

    review = build_design_review(project_files(design_file), reach_samples=0)
    texts = sorted(t for _, t in review.scene.overlay.labels)
    with open_page(html) as page:
        boxes = page.evaluate("() => payloadReview.labelBoxes()")
        m, size = page_projection(page)
    assert sorted(b["text"] for b in boxes) == texts  # every stowed label shown
    # beside the stowed payload, not over its parts (a failing design's red ones were hidden
    # under its labels): the payload's screen box, its meshes projected here
    tree = build_tree(load_design(design_file))
    geom = PayloadGeometry(tree)
    posed = _posed(geom, tree.link_poses(review.check.q), geom.links)
    uv = to_pixels(np.vstack(list(posed.values())), m, size)
    (x0, y0), (x1, y1) = uv.min(axis=0), uv.max(axis=0)
    payload = {"x": x0, "y": y0, "w": x1 - x0, "h": y1 - y0}
    for b in boxes:
        assert _apart(b, payload), (b, payload)
    for a, b in itertools.combinations(boxes, 2):
        assert _apart(a, b), f"labels overlap: {a} {b}"
    for b in boxes:
        assert 0 <= b["x"] and b["x"] + b["w"] <= VIEWPORT[0]
        assert 0 <= b["y"] and b["y"] + b["h"] <= VIEWPORT[1]
    return boxes


_COLOURS = """() => {
    const out = new Set();
    viewer.scene_tree.find(["meshcat"]).object.traverseVisible(o => {
        const mats = o.material ? [].concat(o.material) : [];
        for (const m of mats) if (m.color && !m.vertexColors && m.type !== "SpriteMaterial")
            out.add("#" + m.color.getHexString());
    });
    return [...out];
}"""


def test_the_legend_lists_every_colour_drawn(static_review) -> None:
    _require_browser()
    from payload.review.browser import open_page, pose_page

    with open_page(static_review) as page:
        rows = page.evaluate(
            "() => [...document.querySelectorAll('.payload-legend-row')]"
            ".map(r => [r.dataset.colour, r.textContent])"
        )
        legend = {colour for colour, _ in rows}
        pose_page(page, 0.0, show=[["meshcat", "review", "reach"]])
        drawn = set(page.evaluate(_COLOURS))
    assert len(drawn) >= 6  # fingers, structure, body, bays, segments
    assert drawn <= legend, f"colours drawn but not in the legend: {drawn - legend}"
    # a colour listed as "(none here)" (the verdict's, on a passing design) is drawn nowhere
    absent = {colour for colour, text in rows if text.rstrip().endswith("(none here)")}
    assert absent and not absent & drawn, (absent, drawn)


_VERDICT = """() => {
    const style = (el) => getComputedStyle(el);
    const verdict = document.querySelector("#payload-title .payload-subtitle");
    const body = [document.getElementById("payload-overlay"),
                  ...document.querySelectorAll(".payload-legend-row, .payload-label")];
    return {text: verdict.textContent, colour: style(verdict).color,
            size: parseFloat(style(verdict).fontSize),
            weight: parseInt(style(verdict).fontWeight, 10),
            title: parseFloat(style(document.getElementById("payload-title")).fontSize),
            body: Math.max(...body.map((el) => parseFloat(style(el).fontSize)))};
}"""


def _rgb(colour: str) -> str:
    """``#rrggbb`` as a browser's computed colour, ``rgb(r, g, b)``."""
    return "rgb({}, {}, {})".format(*(int(colour[i : i + 2], 16) for i in (1, 3, 5)))


def test_the_verdict_is_drawn_large_bold_and_in_its_outcomes_colour(
    static_review, tmp_path, design_dict
) -> None:
    """The verdict, the first thing a reviewer reads, was a small grey line: as the browser
    draws it (its computed style), a failing design's is the fail colour and a passing
    one's the pass colour, both bold and larger than the title and the body text (the
    overlay's, the legend's and the labels'), and it says pass or FAIL in words too."""
    _require_browser()
    from payload.envelope.drawing import FAIL_COLOUR, PASS_COLOUR
    from payload.review.browser import open_page

    _, html = _failing_page(tmp_path, design_dict)
    seen = {}
    for outcome, page_file in (("pass", static_review), ("fail", html)):
        with open_page(page_file) as page:
            seen[outcome] = page.evaluate(_VERDICT)
    assert seen["pass"]["text"].startswith("stowed fit: pass"), seen["pass"]
    assert seen["fail"]["text"].startswith("stowed fit: FAIL: "), seen["fail"]
    assert seen["pass"]["colour"] == _rgb(PASS_COLOUR), seen["pass"]
    assert seen["fail"]["colour"] == _rgb(FAIL_COLOUR), seen["fail"]
    for outcome, got in seen.items():
        assert got["weight"] >= 700, (outcome, got)
        assert got["size"] > max(got["body"], got["title"]), (outcome, got)


_LOCAL = """(links) => links.map(n => viewer.scene_tree.find(["meshcat", "review", "payload", n])
    .object.position.toArray())"""


def test_the_deployment_shows_at_any_time_before_play_is_pressed(static_review) -> None:
    """The page opens paused on the stowed payload; holding the animation at its end (as
    ``payload.review.browser --time`` does) or dragging meshcat's time slider there shows
    the deployed payload (stage down, fingers at home), without pressing Play first."""
    _require_browser()
    from payload.review.browser import open_page, pose_page

    tree = build_tree(load_design(project_files().design))
    links = ["stage", "A_distal", "carriage"]
    want = {p: tree.link_poses(tree.posture(p)) for p in ("stowed", "home")}
    with open_page(static_review) as page:
        end = page.evaluate("() => Math.max(...viewer.animator.actions.map(a => a._clip.duration))")
        assert end > 0
        for t, posture in ((0.0, "stowed"), (end, "home"), (0.0, "stowed")):
            pose_page(page, t)
            got = page.evaluate(_LOCAL, links)
            for n, xyz in zip(links, got):
                np.testing.assert_allclose(xyz, want[posture][n][:3, 3], atol=1e-6, err_msg=n)
    with open_page(static_review) as page:  # a person drags the slider of the opened page
        page.evaluate(f"() => viewer.animator.time_scrubber.setValue({end})")
        got = page.evaluate(_LOCAL, links)
        for n, xyz in zip(links, got):
            np.testing.assert_allclose(xyz, want["home"][n][:3, 3], atol=1e-6, err_msg=n)


# ------------------------------------------------------------- the live review

_DISTAL = """() => {
    const n = viewer.scene_tree.find(["meshcat", "review", "payload", "A_distal", "visual0",
                                      "<object>"]).object;
    const g = n.geometry;
    if (!g) return null;
    g.computeBoundingBox();
    return [g.attributes.position.count, g.boundingBox.min.toArray(), g.boundingBox.max.toArray()];
}"""


def _wait_for(page, check, seconds: float) -> float:
    """Seconds until ``check(page)`` holds (fails after ``seconds``)."""
    import time

    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        if check(page):
            return time.perf_counter() - t0
        page.wait_for_timeout(50)
    raise AssertionError(f"the page did not change within {seconds} s")


def _watched_project(tmp_path, design_dict):
    """A project of the committed models and ``design_dict`` as its design file."""
    from test_review import _copy_project

    return _copy_project(tmp_path, design_dict, design_dict["vehicle"]["bay_size"])


def _with_distal(design_dict: dict, distal: float) -> dict:
    """``design_dict`` with the distal link ``distal`` long [m]."""
    lengths = {**design_dict["finger"]["lengths"], "distal": distal}
    return {**design_dict, "finger": {**design_dict["finger"], "lengths": lengths}}


def test_watch_follows_the_saved_design_and_shows_an_invalid_one(tmp_path, design_dict) -> None:
    _require_browser()
    import threading

    import tomli_w

    from payload.review.browser import open_page
    from payload.review.cli import live_review
    from payload.review.live import serve

    design = _watched_project(tmp_path, design_dict)
    live = live_review(str(design), 0)
    assert live.rebuild() is None
    server = serve(live, 0)
    stop = threading.Event()
    watcher = threading.Thread(target=live.watch, args=(stop, lambda line: None), daemon=True)
    watcher.start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}/"
        with open_page(url) as page:
            before = page.evaluate(_DISTAL)
            assert before is not None and before[0] > 0
            distal = design_dict["finger"]["lengths"]["distal"]
            design.write_bytes(tomli_w.dumps(_with_distal(design_dict, distal - 0.006)).encode())
            took = _wait_for(page, lambda p: p.evaluate(_DISTAL) != before, 3.0)
            after = page.evaluate(_DISTAL)
            # the distal mesh is shorter along the finger (its longest extent) by about 6 mm
            span = lambda b: max(np.subtract(b[2], b[1]))  # noqa: E731
            assert span(before) - span(after) == pytest.approx(0.006, abs=1e-3), took
            # only what changed was sent: the vehicle's boxes are not in the update
            update = live.update(live.builds[-2].version)
            assert 0 < len(update["commands"]) < len(live.builds[-1].commands) / 2

            design.write_bytes(tomli_w.dumps(_with_distal(design_dict, -0.01)).encode())
            _wait_for(page, lambda p: p.evaluate("() => payloadReview.error || ''") != "", 3.0)
            text = page.evaluate("() => document.getElementById('payload-error').textContent")
            assert "distal" in text and "\n" not in text
            assert page.evaluate(_DISTAL) == after  # the last good model stays
    finally:
        stop.set()
        server.shutdown()
        server.server_close()


def test_an_open_page_shows_the_design_of_a_review_restarted_on_its_port(
    tmp_path, design_dict
) -> None:
    """Stop a live review, change the design, start a review on the same port: the page
    left open shows the new design (it did keep the old one: both servers' first build is
    version 0, so the page asked for nothing and cleared its 'server stopped' banner)."""
    _require_browser()
    import hashlib

    import tomli_w

    from payload.review.browser import open_page
    from payload.review.cli import live_review
    from payload.review.live import serve

    design = _watched_project(tmp_path, design_dict)

    def start(port: int):
        live = live_review(str(design), 0)
        assert live.rebuild() is None
        return serve(live, port)

    def stop(server) -> None:
        server.shutdown()
        server.server_close()

    def shown(page, script: str):
        """``script``'s value, or None while the page is (re)loading."""
        from playwright.sync_api import Error

        try:
            return page.evaluate(script)
        except Error:  # the page navigated away under the call (a reload)
            return None

    def title(page) -> str:
        return shown(page, "() => document.getElementById('payload-title').textContent") or ""

    server = start(0)
    port = server.server_address[1]
    try:
        with open_page(f"http://127.0.0.1:{port}/") as page:
            before = page.evaluate(_DISTAL)
            old_hash = hashlib.sha256(design.read_bytes()).hexdigest()[:16]
            assert old_hash in title(page)
            assert old_hash in page.title() and page.title().endswith(" - payload review")
            stop(server)
            _wait_for(page, lambda p: "stopped" in p.evaluate("() => payloadReview.error"), 3)
            distal = design_dict["finger"]["lengths"]["distal"]
            design.write_bytes(tomli_w.dumps(_with_distal(design_dict, distal - 0.006)).encode())
            new_hash = hashlib.sha256(design.read_bytes()).hexdigest()[:16]
            server = start(port)
            _wait_for(page, lambda p: new_hash in title(p), 5.0)
            _wait_for(page, lambda p: new_hash in (shown(p, "() => document.title") or ""), 5.0)
            _wait_for(page, lambda p: shown(p, _DISTAL) not in (None, before), 5.0)
            assert shown(page, "() => payloadReview.error") == ""
    finally:
        stop(server)


# ------------------------------------------------------------- the trial replay


def test_a_trial_replay_follows_the_vehicle_from_first_to_last_frame(tmp_path) -> None:
    _require_browser()
    import itertools

    from test_review import _record_trial

    from payload.cli import main
    from payload.envelope.vehicle import vehicle_from_dict
    from payload.review.browser import open_page, pose_page
    from payload.review.trial_view import pose
    from payload.trials.recorder import read_recording

    folder = _record_trial(tmp_path / "trial")
    html = tmp_path / "replay.html"
    assert main(["review", "--trial", str(folder), "--static", str(html)]) == 0
    rec = read_recording(folder / "log.mcap")
    vehicle = vehicle_from_dict(load_design(project_files().design).vehicle or {})
    half = np.asarray(vehicle.body_size) / 2
    box = np.array([np.where(c, half, -half) for c in itertools.product((0, 1), repeat=3)])
    with open_page(html) as page:
        end = page.evaluate("() => Math.max(...viewer.animator.actions.map(a => a._clip.duration))")
        for k, t in ((0, 0.0), (len(rec) - 1, end)):
            pose_page(page, t)
            m, size = page_projection(page, "trial")  # ISS frame -> clip, as the page draws
            body = pose(rec.astrobee_pos[k], rec.astrobee_quat[k])
            pts = box @ body[:3, :3].T + body[:3, 3]
            uv = to_pixels(pts, m, size)
            assert np.all((uv >= 0) & (uv <= size)), f"the vehicle leaves the view at step {k}"
            assert np.ptp(uv[:, 1]) >= 0.2 * size[1], f"the vehicle is small at step {k}"
        text = page.evaluate("() => document.getElementById('payload-phase').textContent")
        assert "translation" in text  # the last frame's phase, as text
        names = {b["text"] for b in page.evaluate("() => payloadReview.labelBoxes()")}
        page.evaluate("() => payloadReview.toggleView()")  # the whole-station view
        pose_page(page, 0.0)
        names |= {b["text"] for b in page.evaluate("() => payloadReview.labelBoxes()")}
    assert names & {module.title for module in IssModule}


def _apart(a: dict, b: dict) -> bool:
    """Two screen rectangles (x, y, w, h) do not intersect."""
    return (
        a["x"] + a["w"] <= b["x"]
        or b["x"] + b["w"] <= a["x"]
        or a["y"] + a["h"] <= b["y"]
        or b["y"] + b["h"] <= a["y"]
    )


def _trial_at_the_route_start(tmp_path: Path):
    """A short trial starting where the route does, mid-Kibo (Kibo's centre then lies among
    the payload's fingers), its replay page, and its recording."""
    from test_review import _record_trial

    from payload.cli import main
    from payload.sim.iss import IssLayout
    from payload.trials.recorder import read_recording

    folder = _record_trial(tmp_path / "trial", start=tuple(IssLayout().route()[0]))
    html = tmp_path / "replay.html"
    assert main(["review", "--trial", str(folder), "--static", str(html)]) == 0
    return html, read_recording(folder / "log.mcap")


def _vehicle_screen_box(page, rec, k: int) -> dict:
    """Screen rectangle of Astrobee's body box and its payload's meshes at step ``k``: the
    recorded pose and joints, the meshes posed by the design tree, projected through the
    page's camera (x, y, w, h) [px]."""
    from payload.design import MANIPULATION_JOINTS
    from payload.envelope.vehicle import vehicle_from_dict
    from payload.review.trial_view import pose
    from payload.sim.astrobee import payload_mount

    design = load_design(project_files().design)
    tree = build_tree(design)
    geom = PayloadGeometry(tree)
    vehicle = vehicle_from_dict(design.vehicle or {})
    half = np.asarray(vehicle.body_size) / 2
    body_box = np.array([np.where(c, half, -half) for c in itertools.product((0, 1), repeat=3)])
    values = dict(zip(MANIPULATION_JOINTS, (float(v) for v in rec.q_meas[k])))
    values["stage"] = float(rec.deploy_meas[k])
    posed = _posed(geom, tree.link_poses(values), geom.links)
    payload = np.vstack(list(posed.values())) + payload_mount(vehicle)  # body frame
    body = pose(rec.astrobee_pos[k], rec.astrobee_quat[k])
    pts = np.vstack([body_box, payload]) @ body[:3, :3].T + body[:3, 3]  # ISS frame
    m, size = page_projection(page, "trial")
    uv = to_pixels(pts, m, size)
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    return {"x": lo[0], "y": lo[1], "w": hi[0] - lo[0], "h": hi[1] - lo[1]}


@pytest.mark.parametrize("viewport", [VIEWPORT, (1280, 800)])
def test_the_module_labels_keep_off_the_vehicle_and_its_payload(tmp_path, viewport) -> None:
    """At the first and last frames of a trial starting mid-Kibo, in the chase and the
    whole station view, no label's box meets the screen box of Astrobee's body and its
    payload; and the opening view still names Kibo."""
    _require_browser()
    from payload.review.browser import open_page, pose_page

    html, rec = _trial_at_the_route_start(tmp_path)
    seen = {}
    with open_page(html, viewport) as page:
        end = page.evaluate("() => Math.max(...viewer.animator.actions.map(a => a._clip.duration))")
        for view in ("chase", "station"):
            for k, t in ((0, 0.0), (len(rec) - 1, end)):
                pose_page(page, t)
                vehicle = _vehicle_screen_box(page, rec, k)
                boxes = page.evaluate("() => payloadReview.labelBoxes()")
                seen[view, k] = {b["text"] for b in boxes}
                for b in boxes:
                    assert _apart(b, vehicle), f"{view} view, step {k}: {b} on {vehicle}"
            page.evaluate("() => payloadReview.toggleView()")  # the whole-station view
    assert "Kibo (JEM)" in seen["chase", 0], seen


_RELABEL = """([clear]) => payloadReview.apply({overlay: {
    title: "t", labels: [["/meshcat/trial/astrobee/payload/A_tip", "A_tip"]], clear}})"""


def test_a_label_is_placed_off_the_nodes_its_overlay_keeps_clear(tmp_path) -> None:
    """A label pointing at the payload's fingertip sits beside the tip, on the vehicle's
    screen box; with the vehicle named in the overlay's ``clear`` list, the layout places
    it off that box (the box projected here, independently of the page's)."""
    _require_browser()
    from payload.review.browser import open_page, pose_page, settle

    html, rec = _trial_at_the_route_start(tmp_path)
    with open_page(html) as page:
        pose_page(page, 0.0)
        vehicle = _vehicle_screen_box(page, rec, 0)
        placed = {}
        for clear in ([], ["/meshcat/trial/astrobee"]):
            page.evaluate(_RELABEL, [clear])
            settle(page)
            (placed[bool(clear)],) = page.evaluate("() => payloadReview.labelBoxes()")
    assert not _apart(placed[False], vehicle), (placed[False], vehicle)
    assert _apart(placed[True], vehicle), (placed[True], vehicle)


def test_a_long_replay_subtitle_wraps_short_of_the_phase_box(tmp_path) -> None:
    """A replay's title and subtitle (e.g. a run not finished, with why) never run under
    the phase box at the top right, at the tests' 960 px width and at 1280 px; the design
    review, which has no phase box, keeps its one-line title."""
    _require_browser()
    from payload.review.browser import open_page, pose_page

    html, _ = _trial_at_the_route_start(tmp_path)
    long = "recording: not finished: aborted (KeyboardInterrupt); " * 3
    rect = "(id) => { const r = document.getElementById(id).getBoundingClientRect(); " \
        "return {x: r.x, y: r.y, w: r.width, h: r.height}; }"  # fmt: skip
    for viewport in (VIEWPORT, (1280, 800)):
        with open_page(html, viewport) as page:
            pose_page(page, 0.0)
            page.evaluate(
                """(sub) => { const d = JSON.parse(
                    document.getElementById('payload-data').textContent);
                    d.overlay.subtitle = sub; payloadReview.apply(d); }""",
                long,
            )
            pose_page(page, 0.0)
            title = page.evaluate(rect, "payload-title")
            phase = page.evaluate(rect, "payload-phase")
            assert phase["w"] > 0 and title["h"] > 0
            assert _apart(title, phase), (viewport, title, phase)
            # an error banner goes below the wrapped lines, not over them (it lay at a
            # fixed height, over a verdict's second line)
            page.evaluate("() => payloadReview.apply({error: 'the design does not load'})")
            banner = page.evaluate(rect, "payload-error")
            assert banner["h"] > 0 and banner["y"] >= title["y"] + title["h"], (title, banner)
            assert _apart(banner, phase), (viewport, banner, phase)
