"""Trial replay: a recorded cargo-transport trial as a meshcat animation.

The recording sampled at a stated rate (``--rate``, default :data:`DEFAULT_RATE`): Astrobee's
pose, every payload link placed by Pinocchio forward kinematics of the recorded (measured)
joints and deployment, the CTB's pose, the fingertip pads orange-red while the recording's
opposing-contact indicator is set (at any step since the previous frame), the task phase
as text over the view, the ISS modules named, the keep-in boxes when the world has them.
The camera follows the vehicle (a chase view); the whole-station view is a click away.
The ISS module walls, Astrobee's body and the CTB come from the simulator world built for the design
project (its ``[vehicle]`` table and generated MJCF).

Scene tree (under :data:`TRIAL`): ``iss/<geom>``, ``astrobee`` (animated) with ``body``,
``payload/<link>`` (animated, pads ``<f>_tip/pad_contact|pad_free``), ``ctb`` (animated),
``modules/<module>`` (label anchors), ``keep_in/<i>``.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import meshcat.geometry as mg
import mujoco
import numpy as np
from meshcat.animation import Animation

from payload.design import FINGERS, MANIPULATION_JOINTS, load_design
from payload.envelope.drawing import FINGER_COLOURS, STRUCTURE_COLOUR
from payload.folders import RECORDING
from payload.review.design_view import (
    BODY_COLOUR,
    OFFENDING_COLOUR,
    colour_text,
    draw_links,
    link_colour,
    set_track,
    set_visibility,
)
from payload.review.model import PayloadModel
from payload.review.project import (
    DEFAULT_RATE,
    TRIAL_OPTION,
    ProjectFiles,
    design_hash,
    page_title,
)
from payload.review.scene import (
    ROOT,
    Overlay,
    ReviewError,
    Scene,
    box_pose,
    framing,
    translation,
)
from payload.rotations import quat_to_matrix
from payload.schema import CONTROL_DT

TRIAL = f"{ROOT}/trial"
"""Root node of the trial replay."""

CONTACT_COLOUR, FREE_COLOUR = 0xFF4500, 0x303030
"""Pad colour with the opposing-contact indicator set (orange-red: far from every finger's
colour, finger C's green among them, and from the station's), and without."""

KEEP_IN_COLOUR = 0x7F00FF
"""Colour of the keep-in boxes."""

KEEP_OUT_COLOUR = OFFENDING_COLOUR
"""Colour of the keep-out boxes (a trial's ``--zones``), places the vehicle must not be:
the failure red (:data:`~payload.envelope.drawing.FAIL_COLOUR`), the one red."""

STATION_DIRECTION = (0.6, -1.0, 0.8)
"""The whole-station view looks from starboard-aft and above."""
CHASE_DIRECTION = (0.8, -1.0, 0.55)
"""The chase camera looks at the vehicle from forward-right and above."""
CHASE_RADIUS = 0.55
"""Radius about the vehicle's centre the chase view frames [m]: the body (a 0.32 m cube,
half-diagonal 0.28 m) with the deployed payload and a grasped CTB below it."""


@dataclass
class TrialReplay:
    """A built trial replay.

    Attributes:
        scene: The meshcat scene (its animation: one frame per recorded step).
        recording: The recording read.
        fps: Animation frame rate (the recorded rate) [Hz].
        centre: World point placed at the scene origin (the camera target) [m].
        mount: Payload frame in Astrobee's body frame, shape (4, 4).
    """

    scene: Scene
    recording: object
    fps: float
    centre: np.ndarray
    mount: np.ndarray


def read_trial(folder: str | Path, files: ProjectFiles, option: str | None = TRIAL_OPTION):
    """The recording of a trial folder, checked to be of this design project.

    Args:
        folder: The trial folder.
        files: The design project's files.
        option: The option that named the folder, which the errors begin with (``--trial
            DIR: ...``); None when it was named alone (``payload review TRIAL``): the
            errors begin with the folder.

    Raises:
        ReviewError: No folder, no readable recording, no steps, or another design's.
    """
    from payload.trials.recorder import RecordingError, read_recording

    folder = Path(folder)
    named = f"{folder}" if option is None else f"{option} {folder}"
    if not folder.is_dir():
        raise ReviewError(f"{named}: not a folder")
    try:
        rec = read_recording(folder / RECORDING)
    except RecordingError as exc:
        raise ReviewError(f"{named}: no readable recording ({exc})") from None
    if len(rec) == 0:
        raise ReviewError(f"{named}: the recording holds no control steps")
    recorded = rec.meta.get("design_hash")
    mine = design_hash(files.design)
    if recorded is None:
        raise ReviewError(f"{named}: the recording names no design (no design_hash)")
    if recorded != mine:
        raise ReviewError(
            f"{named}: recording of another design (design hash {recorded}, "
            f"{files.design} has {mine})"
        )
    return rec


def pose(pos: np.ndarray, quat_wxyz: np.ndarray) -> np.ndarray:
    """Homogeneous transform from a position and a w x y z quaternion, shape (4, 4)."""
    t = np.eye(4)
    t[:3, :3] = quat_to_matrix(np.asarray(quat_wxyz, dtype=float))
    t[:3, 3] = pos
    return t


def _body_geoms(world, body: int, data) -> list[tuple[str, list[float], np.ndarray, np.ndarray]]:
    """Box geoms of a body: name, size, pose in the body frame, rgba."""
    import mujoco

    m = world.model
    out = []
    for g in range(m.ngeom):
        if m.geom_bodyid[g] != body or m.geom_type[g] != mujoco.mjtGeom.mjGEOM_BOX:
            continue
        if m.geom_group[g] == 3:  # collision-only copy
            continue
        out.append(
            (
                world.name(mujoco.mjtObj.mjOBJ_GEOM, g),
                (2 * m.geom_size[g]).tolist(),
                pose(m.geom_pos[g], m.geom_quat[g]),
                m.geom_rgba[g],
            )
        )
    return out


def _rgba_material(rgba: np.ndarray) -> mg.MeshLambertMaterial:
    r, g, b, a = (float(v) for v in rgba)
    colour = (round(r * 255) << 16) | (round(g * 255) << 8) | round(b * 255)
    return mg.MeshLambertMaterial(color=colour, opacity=a, depthWrite=a >= 1.0)


def draw_world(scene: Scene, world, root: str) -> None:
    """The ISS interior (rack faces and handrails), Astrobee's body and the CTB."""
    import mujoco

    m = world.model
    data = mujoco.MjData(m)
    mujoco.mj_kinematics(m, data)
    for g in world.iss_geoms:
        name = world.name(mujoco.mjtObj.mjOBJ_GEOM, g)
        path = f"{root}/iss/{name}"
        rgba = m.geom_rgba[g].copy()
        rgba[3] = min(rgba[3], 0.12) if "wall" in name else rgba[3]
        scene.object(path, mg.Box((2 * m.geom_size[g]).tolist()), _rgba_material(rgba))
        t = np.eye(4)
        t[:3, :3] = data.geom_xmat[g].reshape(3, 3)
        t[:3, 3] = data.geom_xpos[g]
        scene.transform(path, t)
    size = [float(v) for v in world.vehicle.body_size]
    scene.object(
        f"{root}/astrobee/body",
        mg.Box(size),
        mg.MeshLambertMaterial(color=BODY_COLOUR, opacity=0.35),
    )
    if world.ctb >= 0:
        com = pose(m.body_ipos[world.ctb], m.body_iquat[world.ctb])
        for name, size, t, rgba in _body_geoms(world, world.ctb, data):
            path = f"{root}/ctb/{name}"
            scene.object(path, mg.Box(size), _rgba_material(rgba))
            scene.transform(path, np.linalg.inv(com) @ t)


def phase_spans(rec) -> list[tuple[str, float, float]]:
    """``(phase, start, end)`` [s] of each run of one phase, in order."""
    out: list[tuple[str, float, float]] = []
    for i, ph in enumerate(rec.phase):
        t = float(rec.t[i])
        if out and out[-1][0] == ph:
            out[-1] = (ph, out[-1][1], t)
        else:
            out.append((str(ph), t, t))
    return out


Boxes = list[tuple[np.ndarray, np.ndarray]]


def zone_boxes(world, meta: dict | None = None) -> tuple[Boxes, Boxes]:
    """The keep-in and keep-out boxes the trial's base filter ran, world frame ``(lower,
    upper)`` corners [m]: its recorded zones (``meta["zones"]``, a trial run with
    ``--zones``), else the station's (:func:`payload.sim.zones.station_zones` of the
    world's ISS layout; no keep-out)."""
    from payload.sim.zones import StationZones, station_zones

    # a trial run with --zones records them (as data); null or none: the station's
    zones = StationZones.recorded(meta or {}) or station_zones(world.layout)
    return _boxes(zones.keepin), _boxes(zones.keepout)


def _boxes(boxes: Any) -> Boxes:
    return [(np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)) for lo, hi in boxes]


def draw_keep_in(scene: Scene, boxes: Boxes, root: str, kind: str = "keep_in") -> None:
    """Keep-in (``kind`` ``keep_in``) or keep-out (``keep_out``) boxes as translucent boxes
    under ``root/<kind>/<i>``."""
    colour = KEEP_IN_COLOUR if kind == "keep_in" else KEEP_OUT_COLOUR
    for i, (lo, hi) in enumerate(boxes):
        size, centre = box_pose(lo, hi)
        path = f"{root}/{kind}/{i}"
        scene.object(path, mg.Box(size), mg.MeshLambertMaterial(color=colour, opacity=0.08))
        scene.transform(path, centre)


def sample_steps(t: np.ndarray, rate: float) -> np.ndarray:
    """Indices of the recorded steps shown at ``rate`` [Hz]: the first step at or after
    each multiple of ``1 / rate`` from the start, and the last step, shape (k,)."""
    t = np.asarray(t, dtype=float) - float(t[0])
    ticks = np.arange(0.0, t[-1] + 1e-9, 1.0 / rate)
    idx = np.unique(np.searchsorted(t, ticks - 1e-9))
    idx = idx[idx < len(t)]
    return np.unique(np.r_[idx, len(t) - 1])


def any_since_last(flags: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Per shown step: whether ``flags`` was set at any step since the previous shown one
    (so a contact shorter than a frame still shows), shape (k,)."""
    flags = np.asarray(flags, dtype=bool)
    starts = np.r_[0, idx[:-1] + 1]
    return np.array([flags[a : b + 1].any() for a, b in zip(starts, idx)])


def _to_polyline(points: np.ndarray, line: np.ndarray) -> np.ndarray:
    """Distance of each point (n, 3) to the polyline ``line`` (k, 3), shape (n,) [m]."""
    out = np.full(len(points), np.inf)
    for a, b in itertools.pairwise(line):
        ab = b - a
        s = np.clip((points - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        out = np.minimum(out, np.linalg.norm(points - (a + s[:, None] * ab), axis=1))
    return out


def module_anchor(zone, route: np.ndarray) -> np.ndarray:
    """Where a module's label points: at ceiling height, the middle of the module's wall
    (side or end) farthest from the cargo route ``route`` (k, 3) [m]: Kibo's far end,
    Node 2's aft end, a side of the vestibule. Both views look from above, so a point on the
    ceiling stays clear of the vehicle flying the route below it. Shape (3,) [m]."""
    half = zone.size / 2
    tops = []
    for axis in (0, 1):  # the walls: x and y faces
        for side in (-1.0, 1.0):
            p = zone.centre.copy()
            p[axis] += side * half[axis]
            p[2] = zone.hi[2]
            tops.append(p)
    tops = np.array(tops)
    return tops[int(np.argmax(_to_polyline(tops, np.asarray(route, dtype=float))))]


def draw_modules(scene: Scene, world, root: str) -> None:
    """A label anchor in each module along the route (:func:`module_anchor`)."""
    route = world.layout.route()
    for zone in world.layout.zones():
        path = f"{root}/modules/{zone.module.value}"
        scene.transform(path, translation(module_anchor(zone, route)))
        scene.overlay.labels.append((path, zone.module.title))


def draw_pads(scene: Scene, anim: Animation, root: str, radius: float, frames, contact) -> None:
    """Each fingertip pad twice, coloured by the opposing-contact indicator, one shown."""
    for f in FINGERS:
        for state, colour, on in (
            ("contact", CONTACT_COLOUR, contact),
            ("free", FREE_COLOUR, ~contact),
        ):
            path = f"{root}/{f}_tip/pad_{state}"
            scene.object(path, mg.Sphere(radius), mg.MeshPhongMaterial(color=colour))
            set_visibility(anim, path, frames, list(on))


def trial_legend(world, keep_in: bool, keep_out: bool = False) -> list[tuple[str, str]]:
    """The replay's colours: fingers, structure, pads, the vehicle, the CTB, the station
    (and the keep-in boxes when drawn)."""
    out = [(FINGER_COLOURS[f], f"finger {f}") for f in FINGERS]
    out += [
        (STRUCTURE_COLOUR, "structure: base, stage, carriage"),
        (colour_text(CONTACT_COLOUR), "pads in opposing contact"),
        (colour_text(FREE_COLOUR), "pads not in opposing contact"),
        (colour_text(BODY_COLOUR), "Astrobee's body"),
    ]
    if keep_in:
        out.append((colour_text(KEEP_IN_COLOUR), "keep-in boxes"))
    if keep_out:
        out.append((colour_text(KEEP_OUT_COLOUR), "keep-out boxes (the trial's zones)"))
    seen = {c for c, _ in out}
    m = world.model
    for kind, geoms in (("CTB", _ctb_geoms(world)), ("ISS", world.iss_geoms)):
        parts: dict[str, list[str]] = {}  # colour -> the geoms drawn in it, by name
        for g in geoms:
            c = colour_text(_rgb(m.geom_rgba[g]))
            parts.setdefault(c, []).append(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or "")
        for c, names in parts.items():
            if c not in seen:
                seen.add(c)
                out.append((c, _part_label(kind, names)))
    return out


def _part_label(kind: str, names: list[str]) -> str:
    """A legend row's words for the CTB's or the station's geoms of one colour (named as
    the world names them): each colour its own row, so no name twice."""
    if kind == "CTB":
        return "CTB handle" if any("handle" in n for n in names) else "CTB bag"
    return "ISS handrails" if all("handrail" in n for n in names) else "ISS walls"


def _ctb_geoms(world) -> list[int]:
    m = world.model
    return [
        g
        for g in range(m.ngeom)
        if world.ctb >= 0 and m.geom_bodyid[g] == world.ctb and m.geom_group[g] != 3
    ]


def _rgb(rgba: np.ndarray) -> int:
    r, g, b = (round(float(v) * 255) for v in rgba[:3])
    return (r << 16) | (g << 8) | b


def trial_title(
    folder: str | Path, files: ProjectFiles, rec, why: str | None, cut: str | None = None
) -> tuple[str, str]:
    """The title (:func:`~payload.review.project.page_title`: the trial folder, named with
    its parent as the design review names its project, and the design's hash) and the
    recording's status line (``recording: finished; 144.6 s in 7233 steps``), the design
    review's verdict line's counterpart. ``why``: why the run is not finished, or None;
    ``cut``: why a finished recording's session stopped before its task's end (the
    ``--max-time`` cap, a replay of an unfinished run: ``reading.cut_reason``), or None."""
    folder = Path(folder).resolve()
    if why is not None:
        state = f"not finished: {why}"
    else:
        state = "finished" if cut is None else f"finished, the session stopped early: {cut}"
    span = float(rec.t[-1] - rec.t[0])
    status = f"recording: {state}; {span:.1f} s in {len(rec)} steps"
    return page_title("trial replay", f"{folder.parent.name}/{folder.name}", files.design), status


def build_trial_replay(
    folder: str | Path,
    files: ProjectFiles,
    root: str = TRIAL,
    rate: float = DEFAULT_RATE,
    recording: object | None = None,
) -> TrialReplay:
    """The replay scene of the trial recorded in ``folder`` (see the module docstring).

    Args:
        folder: The trial folder (its ``log.mcap``).
        files: The design project's files.
        root: Scene node to build under.
        rate: Animation frames per second of trial time [Hz]; the recording is sampled
            at this rate (a 150 s trial at 10 Hz: 1,500 frames).
        recording: The folder's recording when the caller has read it already
            (:func:`read_trial`); reading a long recording is most of a replay's time.

    Raises:
        ReviewError: Bad folder or recording (see :func:`read_trial`), or a rate <= 0.
    """
    from payload.sim.world import WorldConfig, build_world

    if not (np.isfinite(rate) and rate > 0):
        raise ReviewError(f"--rate must be > 0 Hz, got {rate}")
    files.check()
    rec = read_trial(folder, files) if recording is None else recording
    design = load_design(files.design)
    if not files.mjcf.is_file():
        raise ReviewError(f"generated MJCF not found: {files.mjcf}; run `payload build`")
    world = build_world(WorldConfig(payload_mjcf=files.mjcf, design=files.design), design)
    model = PayloadModel(files.urdf)
    recorded = rec.rate_hz if np.isfinite(rec.rate_hz) and rec.rate_hz > 0 else 1 / CONTROL_DT
    fps = float(min(rate, recorded))
    idx = sample_steps(rec.t, fps)
    frames = [float(v) for v in (rec.t[idx] - rec.t[0]) * fps]

    centre = (rec.astrobee_pos.min(axis=0) + rec.astrobee_pos.max(axis=0)) / 2
    scene = Scene()
    scene.transform(root, translation(-centre))
    draw_world(scene, world, root)
    draw_modules(scene, world, root)
    keep_in, keep_out = zone_boxes(world, rec.meta)
    draw_keep_in(scene, keep_in, root)
    draw_keep_in(scene, keep_out, root, "keep_out")
    mount = translation(world.mount)
    scene.transform(f"{root}/astrobee/payload", mount)
    placements = []
    for k in idx:
        values = dict(zip(MANIPULATION_JOINTS, (float(v) for v in rec.q_meas[k])))
        values["stage"] = float(rec.deploy_meas[k])
        placements.append(model.placements(model.configuration(values)))
    colours = {n: link_colour(n) for n in model.links}
    draw_links(scene, model, f"{root}/astrobee/payload", placements[0], colours)

    anim = Animation(default_framerate=fps)
    vehicle = [pose(rec.astrobee_pos[k], rec.astrobee_quat[k]) for k in idx]
    set_track(anim, f"{root}/astrobee", frames, vehicle)
    set_track(anim, f"{root}/ctb", frames, [pose(rec.ctb_pos[k], rec.ctb_quat[k]) for k in idx])
    for link in model.links:
        set_track(anim, f"{root}/astrobee/payload/{link}", frames, [p[link] for p in placements])
    contact = any_since_last(rec.contact, idx)
    radius = 1.08 * design.finger.pad.radius
    draw_pads(scene, anim, f"{root}/astrobee/payload", radius, frames, contact)
    scene.animation = anim

    spans = phase_spans(rec)
    t0 = float(rec.t[0])
    extent = np.vstack([rec.astrobee_pos, rec.ctb_pos]) - centre
    station = framing(np.vstack([extent, [[0.8, 0.8, 0.8]]]), STATION_DIRECTION)
    chase = framing(np.array([[CHASE_RADIUS, 0.0, 0.0]]), CHASE_DIRECTION)
    scene.camera = (chase, np.zeros(3))
    from payload.trials.reading import cut_reason, unfinished_reason

    why = unfinished_reason(rec.meta, rec.complete)
    head, status = trial_title(folder, files, rec, why, cut_reason(rec.meta, rec.complete))
    scene.overlay = Overlay(
        title=head,
        subtitle=f"{status}; shown at {fps:g} Hz, chase view (Open Controls: whole station view)",
        legend=trial_legend(world, bool(keep_in), bool(keep_out)),
        labels=scene.overlay.labels,
        phases=[(ph, a - t0, b - t0) for ph, a, b in spans],
        views={"default": chase.tolist(), "station": station.tolist()},
        follow=(root, f"{root}/astrobee", centre.tolist()),
        clear=[f"{root}/astrobee", f"{root}/ctb"],
    )
    scene.notes.append(f"trial: {Path(folder)} ({len(rec)} steps, shown at {fps:g} Hz)")
    if why is not None:  # a replay of what it holds, said as such
        scene.notes.append(f"  not a finished run: {why}; the replay ends where it does")
    scene.notes += [f"  {ph}: {a:.2f} .. {b:.2f} s" for ph, a, b in spans]
    return TrialReplay(scene, rec, fps, centre, mount)


__all__ = [
    "CONTACT_COLOUR",
    "DEFAULT_RATE",
    "FREE_COLOUR",
    "TRIAL",
    "TrialReplay",
    "build_trial_replay",
    "phase_spans",
    "pose",
    "read_trial",
    "sample_steps",
]
