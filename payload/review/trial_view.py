"""Trial replay: a recorded cargo-transport trial as a meshcat animation.

One animation frame per recorded control step, at the recorded rate: Astrobee's pose,
every payload link placed by Pinocchio forward kinematics of the recorded (measured)
joints and deployment, the CTB's pose, the fingertip pads green while the recording's
opposing-contact indicator is set, and a label naming the task phase. The ISS module
walls, Astrobee's body and the CTB come from the simulator world built for the design
project (its ``[vehicle]`` table and generated MJCF).

Scene tree (under :data:`TRIAL`): ``iss/<geom>``, ``astrobee`` (animated) with ``body``,
``payload/<link>`` (animated) and ``phase/<phase>`` (labels, visibility animated),
``ctb`` (animated).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import meshcat.geometry as mg
import numpy as np
from meshcat.animation import Animation, AnimationClip, AnimationTrack

from payload.design import FINGERS, MANIPULATION_JOINTS, load_design
from payload.review.design_view import draw_links, link_colour, set_track
from payload.review.model import PayloadModel
from payload.review.project import ProjectFiles, design_hash
from payload.review.scene import (
    ROOT,
    ReviewError,
    Scene,
    framing,
    label_object,
    mpath,
    translation,
)
from payload.rotations import quat_to_matrix
from payload.schema import CONTROL_DT

TRIAL = f"{ROOT}/trial"
"""Root node of the trial replay."""

CONTACT_COLOUR, FREE_COLOUR = 0x00C000, 0x303030
"""Pad colour with the opposing-contact indicator set, and without."""

RECORDING = "log.mcap"
VIEW_DIRECTION = (0.6, -1.0, 0.8)


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


def read_trial(folder: str | Path, files: ProjectFiles):
    """The recording of a trial folder, checked to be of this design project.

    Raises:
        ReviewError: No folder, no readable recording, no steps, or another design's.
    """
    from payload.trials.recorder import RecordingError, read_recording

    folder = Path(folder)
    if not folder.is_dir():
        raise ReviewError(f"--trial {folder}: not a folder")
    try:
        rec = read_recording(folder / RECORDING)
    except RecordingError as exc:
        raise ReviewError(f"--trial {folder}: no readable recording ({exc})") from None
    if len(rec) == 0:
        raise ReviewError(f"--trial {folder}: the recording holds no control steps")
    recorded = rec.meta.get("design_hash")
    mine = design_hash(files.design)
    if recorded is None:
        raise ReviewError(f"--trial {folder}: the recording names no design (no design_hash)")
    if recorded != mine:
        raise ReviewError(
            f"--trial {folder}: recording of another design (design hash {recorded}, "
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
        f"{root}/astrobee/body", mg.Box(size), mg.MeshLambertMaterial(color=0xB8BCC8, opacity=0.35)
    )
    if world.ctb >= 0:
        com = pose(m.body_ipos[world.ctb], m.body_iquat[world.ctb])
        for name, size, t, rgba in _body_geoms(world, world.ctb, data):
            path = f"{root}/ctb/{name}"
            scene.object(path, mg.Box(size), _rgba_material(rgba))
            scene.transform(path, np.linalg.inv(com) @ t)


def _visibility(animation: Animation, path: str, frames: list[float], on: np.ndarray) -> None:
    """Keys of a node's visibility at every frame where it changes (and the first)."""
    keep = [0, *[i for i in range(1, len(on)) if on[i] != on[i - 1]]]
    clip = animation.clips.setdefault(mpath(path), AnimationClip(fps=animation.default_framerate))
    values = [bool(on[i]) for i in keep]
    clip.tracks["visible"] = AnimationTrack("visible", "boolean", [frames[i] for i in keep], values)


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


def build_trial_replay(folder: str | Path, files: ProjectFiles, root: str = TRIAL) -> TrialReplay:
    """The replay scene of the trial recorded in ``folder`` (see the module docstring)."""
    from payload.sim.world import WorldConfig, build_world

    files.check()
    rec = read_trial(folder, files)
    design = load_design(files.design)
    if not files.mjcf.is_file():
        raise ReviewError(f"generated MJCF not found: {files.mjcf}; run `payload build`")
    world = build_world(WorldConfig(payload_mjcf=files.mjcf, design=files.design), design)
    model = PayloadModel(files.urdf)
    rate = rec.rate_hz
    fps = float(rate) if np.isfinite(rate) and rate > 0 else 1.0 / CONTROL_DT
    frames = [float(v) for v in (rec.t - rec.t[0]) * fps]

    centre = (rec.astrobee_pos.min(axis=0) + rec.astrobee_pos.max(axis=0)) / 2
    scene = Scene()
    scene.transform(root, translation(-centre))
    draw_world(scene, world, root)
    mount = translation(world.mount)
    scene.transform(f"{root}/astrobee/payload", mount)
    configs = []
    for q, deploy in zip(rec.q_meas, rec.deploy_meas):
        values = dict(zip(MANIPULATION_JOINTS, (float(v) for v in q)))
        values["stage"] = float(deploy)
        configs.append(model.configuration(values))
    placements = [model.placements(q) for q in configs]
    colours = {n: link_colour(n) for n in model.links}
    draw_links(scene, model, f"{root}/astrobee/payload", placements[0], colours)

    anim = Animation(default_framerate=fps)
    set_track(
        anim,
        f"{root}/astrobee",
        frames,
        [pose(p, q) for p, q in zip(rec.astrobee_pos, rec.astrobee_quat)],
    )
    set_track(anim, f"{root}/ctb", frames, [pose(p, q) for p, q in zip(rec.ctb_pos, rec.ctb_quat)])
    for link in model.links:
        set_track(anim, f"{root}/astrobee/payload/{link}", frames, [p[link] for p in placements])
    radius = 1.08 * design.finger.pad.radius
    contact = np.asarray(rec.contact, dtype=bool)
    for f in FINGERS:
        for state, colour, on in (
            ("contact", CONTACT_COLOUR, contact),
            ("free", FREE_COLOUR, ~contact),
        ):
            path = f"{root}/astrobee/payload/{f}_tip/pad_{state}"
            scene.object(path, mg.Sphere(radius), mg.MeshPhongMaterial(color=colour))
            _visibility(anim, path, frames, on)
    spans = phase_spans(rec)
    top = float(world.vehicle.body_size[2]) / 2 + 0.12
    for ph in dict.fromkeys(s[0] for s in spans):
        path = f"{root}/astrobee/phase/{ph}"
        scene.object(path, label_object(ph))
        scene.transform(path, translation([0, 0, top]) @ np.diag([0.35, 0.35, 0.35, 1.0]))
        _visibility(anim, path, frames, np.asarray(rec.phase == ph))
    scene.animation = anim

    extent = np.vstack([rec.astrobee_pos, rec.ctb_pos]) - centre
    scene.camera = (framing(np.vstack([extent, [[0.8, 0.8, 0.8]]]), VIEW_DIRECTION), np.zeros(3))
    scene.notes.append(f"trial: {Path(folder)} ({len(rec)} steps at {fps:.1f} Hz)")
    scene.notes += [f"  {ph}: {a:.2f} .. {b:.2f} s" for ph, a, b in spans]
    return TrialReplay(scene, rec, fps, centre, mount)


__all__ = [
    "CONTACT_COLOUR",
    "FREE_COLOUR",
    "TRIAL",
    "TrialReplay",
    "build_trial_replay",
    "phase_spans",
    "pose",
    "read_trial",
]
