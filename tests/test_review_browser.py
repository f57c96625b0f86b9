"""Browser test of the static review: headless Chromium draws the payload where it must be.

The page is the one ``payload review --static`` writes. With the vehicle, findings and
reach clouds hidden and the deployment animation held at its start (stowed), the payload
must cover the region where its meshes project through the camera the review sets (a
pinhole projection computed here, independently of three.js), in the fingers' colours,
and the background must be untouched everywhere else.

Without Chromium the test skips, except under CI (``CI`` set), where it fails.
"""

from __future__ import annotations

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
    screenshot(html, png, time_s=0.0, hide=hide)
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
