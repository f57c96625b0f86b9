"""A Meshcat scene as data: the ordered commands a review sends, and where they go.

A :class:`Scene` holds meshcat command objects (``SetObject``, ``SetTransform``,
``SetProperty``, one ``SetAnimation``) in the order they are sent. Building a scene needs
no server, so tests can inspect it; :meth:`Scene.send` plays it into a live viewer and
:func:`payload.review.page.static_html` into a standalone HTML page (meshcat's JavaScript
inlined).

Paths are absolute meshcat paths (``/meshcat/review/payload/base``); the viewer's own
nodes (``/Background``, ``/Grid``, ``/Cameras/default``) are set the same way.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import meshcat.geometry as mg
import numpy as np
from meshcat.animation import Animation
from meshcat.commands import SetAnimation, SetObject, SetProperty, SetTransform
from meshcat.path import Path as MeshcatPath

from payload.review.errors import ReviewError

ROOT = "/meshcat"
"""Root of everything the review draws (meshcat's own default root)."""

BACKGROUND = (1.0, 1.0, 1.0)
"""Viewer background (both gradient ends), RGB in [0, 1]: plain white."""

CAMERA_FOV_DEG = 75.0
"""Vertical field of view of meshcat's default camera [deg]."""


def mpath(path: str) -> MeshcatPath:
    """A meshcat path from an absolute path string."""
    if not path.startswith("/"):
        raise ValueError(f"meshcat paths are absolute: {path!r}")
    return MeshcatPath(tuple(p for p in path.split("/") if p))


def hex_colour(colour: str | int) -> int:
    """``#rrggbb`` (or an int) as the integer meshcat materials take."""
    return colour if isinstance(colour, int) else int(colour.lstrip("#"), 16)


class StlGeometry(mg.MeshGeometry):
    """A binary STL file as meshcat geometry (``_meshfile_geometry``, its current name)."""

    def __init__(self, path: str) -> None:
        super().__init__(mg.StlMeshGeometry.from_file(path).contents, "stl")

    def lower(self, object_data: Any) -> dict[str, Any]:
        return {**super().lower(object_data), "type": "_meshfile_geometry"}


PASS, FAIL = "pass", "fail"
"""The outcomes of an overlay's verdict (:attr:`Overlay.outcome`); the page styles the
verdict by them (``payload-verdict-pass``, ``payload-verdict-fail``)."""


def tab_title(title: str) -> str:
    """The browser tab's text for a page titled ``title`` (the static page's ``<title>``,
    and the live page's script sets it from the overlay's ``tab``)."""
    return f"{title} - payload review" if title else "payload review"


@dataclass
class Overlay:
    """What the page draws over the 3D view (see :mod:`payload.review.page`).

    Attributes:
        title: First line of the title, ``<what> — <subject> (design <hash>)``
            (:func:`payload.review.project.page_title`); the browser tab shows it too.
        subtitle: Second line, ``<aspect>: <verdict>; ...`` (the stowed fit, the recording).
        outcome: What the subtitle judges, :data:`PASS` or :data:`FAIL` (the design review's
            verdict, drawn large, bold and in the outcome's colour); ``None``: a status,
            not a verdict (a trial replay's), drawn as plain text.
        legend: ``(#rrggbb, meaning)`` for every colour the scene uses.
        labels: ``(anchor node path, text)``: a label pointing at the node's origin, shown
            while the node is (so a label belongs to the state its node is shown in).
        phases: ``(phase, start [s], end [s])`` of a trial, shown at the animation time.
        views: Camera positions by name (``default``, ``station``), world frame [m].
        follow: ``(root path, vehicle path, station centre)``: the chase camera keeps the
            vehicle node at the origin by moving the root; ``None``: no chase camera.
        clear: Nodes the labels keep off: each frame, the screen box of each shown node
            (its meshes' bounds, projected) is a box no label may cover, as the title is.
        subject: World points [m] (the corners of the design review's bays and stowed
            payload) the page keeps clear of the title and the legend, as the ``default``
            view frames them: it draws the view where they fit beside those boxes; empty:
            the view only keeps below the title.
    """

    title: str = ""
    subtitle: str = ""
    outcome: str | None = None
    legend: list[tuple[str, str]] = field(default_factory=list)
    labels: list[tuple[str, str]] = field(default_factory=list)
    phases: list[tuple[str, float, float]] = field(default_factory=list)
    views: dict[str, list[float]] = field(default_factory=dict)
    follow: tuple[str, str, list[float]] | None = None
    clear: list[str] = field(default_factory=list)
    subject: list[list[float]] = field(default_factory=list)

    def as_json(self) -> dict[str, Any]:
        """The overlay as the page's script reads it."""
        return {
            "title": self.title,
            "subtitle": self.subtitle,
            "outcome": self.outcome,
            "legend": [list(e) for e in self.legend],
            "labels": [list(e) for e in self.labels],
            "phases": [list(e) for e in self.phases],
            "views": self.views,
            "follow": None if self.follow is None else list(self.follow),
            "clear": list(self.clear),
            "subject": [list(map(float, p)) for p in self.subject],
            "tab": tab_title(self.title),
        }


@dataclass
class Scene:
    """Meshcat commands in the order they are sent, plus at most one animation.

    Attributes:
        commands: ``SetObject``/``SetTransform``/``SetProperty`` commands.
        animation: The animation (``None``: none).
        camera: ``(position, target)`` of the camera in the world [m].
        notes: One line per thing worth printing (findings, phases).
        overlay: Title, legend, labels and camera views drawn over the 3D view.
        autoplay: Play the animation when the page opens.
    """

    commands: list[Any] = field(default_factory=list)
    animation: Animation | None = None
    camera: tuple[np.ndarray, np.ndarray] | None = None
    notes: list[str] = field(default_factory=list)
    overlay: Overlay = field(default_factory=Overlay)
    autoplay: bool = True

    def object(self, path: str, geometry: Any, material: Any = None) -> None:
        """Draw ``geometry`` (or a meshcat object) at ``path``."""
        self.commands.append(SetObject(geometry, material, mpath(path)))

    def transform(self, path: str, matrix: np.ndarray) -> None:
        """Place the node ``path`` (homogeneous matrix, shape (4, 4))."""
        self.commands.append(SetTransform(np.asarray(matrix, dtype=float), mpath(path)))

    def prop(self, path: str, key: str, value: Any) -> None:
        """Set a property (``visible``, ``position``, ...) of the node ``path``."""
        self.commands.append(SetProperty(key, value, mpath(path)))

    def objects(self) -> dict[str, Any]:
        """Path -> the meshcat object drawn there (the last one drawn)."""
        return {c.path.lower(): c.object for c in self.commands if isinstance(c, SetObject)}

    def transforms(self) -> dict[str, np.ndarray]:
        """Path -> the last transform set there."""
        return {c.path.lower(): c.matrix for c in self.commands if isinstance(c, SetTransform)}

    def properties(self, key: str) -> dict[str, Any]:
        """Path -> the last value of property ``key`` set there."""
        return {
            c.path.lower(): c.value
            for c in self.commands
            if isinstance(c, SetProperty) and c.key == key
        }

    def all_commands(self) -> list[Any]:
        """Every command to send: the scene, the viewer settings, then the animation."""
        out = list(self.commands)
        out += viewer_settings(self.camera)
        if self.animation is not None:
            out.append(SetAnimation(self.animation, play=self.autoplay, repetitions=1))
        return out

    def send(self, window: Any) -> None:
        """Send the scene to a meshcat ``ViewerWindow`` (``Visualizer().window``)."""
        for command in self.all_commands():
            window.send(command)


def camera_local(position: Sequence[float]) -> list[float]:
    """A world position ``(x, y, z)`` in meshcat's rotated camera node: ``(x, z, -y)``."""
    return [float(position[0]), float(position[2]), float(-position[1])]


def viewer_settings(camera: tuple[np.ndarray, np.ndarray] | None) -> list[Any]:
    """Plain background, no grid or axes, and the camera at ``camera`` looking at its target.

    meshcat's orbit controls turn about the world origin, so scenes are built with their
    target there; the camera's own node is rotated (three.js is y-up), so a world position
    ``(x, y, z)`` is ``(x, z, -y)`` in that node.
    """
    out: list[Any] = [
        SetProperty("top_color", list(BACKGROUND), mpath("/Background")),
        SetProperty("bottom_color", list(BACKGROUND), mpath("/Background")),
        SetProperty("visible", False, mpath("/Grid")),
        SetProperty("visible", False, mpath("/Axes")),
    ]
    if camera is not None:
        pos, target = (np.asarray(v, dtype=float) for v in camera)
        if np.linalg.norm(target) > 1e-9:
            raise ValueError("build the scene around the camera target: it must be the origin")
        out.append(
            SetProperty("position", camera_local(pos), mpath("/Cameras/default/rotated/<object>"))
        )
    return out


def framing(points: np.ndarray, direction: Sequence[float], margin: float = 1.15) -> np.ndarray:
    """Camera position, seen from ``direction``, that frames ``points`` centred on the origin.

    The distance puts the points' bounding sphere (about the origin) inside the vertical
    field of view :data:`CAMERA_FOV_DEG` with ``margin``.
    """
    d = np.asarray(direction, dtype=float)
    d /= np.linalg.norm(d)
    radius = float(np.max(np.linalg.norm(points, axis=1)))
    dist = margin * radius / math.sin(math.radians(CAMERA_FOV_DEG) / 2)
    return d * dist


def translation(p: Sequence[float]) -> np.ndarray:
    """Homogeneous translation, shape (4, 4)."""
    t = np.eye(4)
    t[:3, 3] = np.asarray(p, dtype=float)
    return t


def box_pose(lower: Sequence[float], upper: Sequence[float]) -> tuple[list[float], np.ndarray]:
    """Size and centre transform of the axis-aligned box ``lower``..``upper`` [m]."""
    lo, hi = np.asarray(lower, dtype=float), np.asarray(upper, dtype=float)
    return (hi - lo).tolist(), translation((lo + hi) / 2)


def segment(a: Sequence[float], b: Sequence[float]) -> mg.LineSegments:
    """A line segment from ``a`` to ``b`` [m], drawn in black."""
    pts = np.array([a, b], dtype=np.float32).T
    return mg.LineSegments(
        mg.PointsGeometry(pts), mg.LineBasicMaterial(color=0x000000, linewidth=2.0)
    )


def frame_values(animation: Animation, path: str, prop: str) -> tuple[list[float], list[Any]]:
    """Key times [frames] and values of one animated property (for tests and reports)."""
    clip = animation.clips.get(mpath(path))
    if clip is None or prop not in clip.tracks:
        raise KeyError(f"no {prop} track at {path}")
    track = clip.tracks[prop]
    return list(track.frames), list(track.values)


__all__ = [
    "BACKGROUND",
    "CAMERA_FOV_DEG",
    "FAIL",
    "PASS",
    "ROOT",
    "Overlay",
    "ReviewError",
    "Scene",
    "StlGeometry",
    "box_pose",
    "camera_local",
    "frame_values",
    "framing",
    "hex_colour",
    "mpath",
    "segment",
    "tab_title",
    "translation",
    "viewer_settings",
]
