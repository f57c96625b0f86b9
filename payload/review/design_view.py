"""The design review: the payload on Astrobee, stowed and deployed, envelope and reach.

Everything comes from the design project: Astrobee's body and the bay envelope from the
design's ``[vehicle]`` table, the payload's generated meshes placed by Pinocchio forward
kinematics of the generated URDF, the findings from the envelope report's checks
(:func:`payload.envelope.fit.check_stowed`) and the reach clouds from the reach report's
sampling and collision model.

Scene tree (under :data:`REVIEW`):
``vehicle/body/<i>``, ``vehicle/bays``, ``payload/<link>`` (every URDF link; meshes at
``payload/<link>/visual<k>``), ``findings/clearance/<wall>`` and
``findings/protrusion/<wall>/<part>`` (segments and label anchors; shown with the stowed
payload only), ``reach/<finger>`` (point clouds, hidden until ticked). The page's overlay
(:class:`~payload.review.scene.Overlay`) carries the title, the legend of every colour, the
labels and the box the default view frames (the bays and the stowed payload).
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import meshcat.geometry as mg
import numpy as np
from meshcat.animation import Animation, AnimationClip, AnimationTrack

from payload.design import FINGERS, build_tree, load_design
from payload.envelope.deployment import unfolding_postures
from payload.envelope.drawing import (
    COLLISION_COLOUR,
    FAIL_COLOUR,
    FINGER_COLOURS,
    STRUCTURE_COLOUR,
    TIGHT_COLOUR,
)
from payload.envelope.fit import StowedCheck, check_stowed, wall_gaps
from payload.envelope.fit_results import (
    COLLIDES_MEANING,
    OUTSIDE_MEANING,
    clearance_text,
    tight_meaning,
)
from payload.envelope.geometry import PayloadGeometry
from payload.envelope.vehicle import Vehicle, vehicle_from_dict
from payload.errors import first_of
from payload.review.model import PayloadModel
from payload.review.project import ProjectFiles, page_title
from payload.review.scene import (
    FAIL,
    PASS,
    ROOT,
    Overlay,
    ReviewError,
    Scene,
    StlGeometry,
    box_pose,
    framing,
    hex_colour,
    mpath,
    segment,
    translation,
)

REVIEW = f"{ROOT}/review"
"""Root node of the design review."""

OFFENDING_COLOUR = hex_colour(FAIL_COLOUR)
"""Colour of a part that protrudes from the bays or hits the vehicle as the stage deploys."""
COLLIDING = hex_colour(COLLISION_COLOUR)
"""Colour of a part that collides with another link, stowed or as the fingers unfold
(:attr:`StowedCheck.unfolding`), and is not outside the bays (nor hit by the vehicle as the
payload deploys: those are :data:`OFFENDING_COLOUR`); the envelope figure edges a stowed
one in it."""
TIGHT = hex_colour(TIGHT_COLOUR)
"""Colour of a link that does not fail but is under
:data:`~payload.envelope.fit_results.TIGHT_CLEARANCE` to a bay wall or to another link (the
envelope verdict's "tight")."""

BODY_COLOUR, BAY_COLOUR, SEGMENT_COLOUR = 0xB8BCC8, 0x17BECF, 0x000000
DEPLOY_FPS = 30
STAGE_SECONDS, FINGER_SECONDS = 2.0, 1.5
VIEW_DIRECTION = (1.0, -1.25, -0.45)
"""The camera looks at the payload from forward, right and a little below the vehicle."""
FRAME_MARGIN = 1.3
"""Margin of the default view around the bays and the stowed payload (:func:`subject_box`;
see :func:`payload.review.scene.framing`): Astrobee's body shows around them, and the
deployed payload reaches below the view (zoom out to follow it)."""


def colour_text(colour: int) -> str:
    """An integer colour as ``#rrggbb``."""
    return f"#{colour:06x}"


def link_colour(name: str) -> int:
    """A finger link in its finger's colour, structure in grey."""
    if name[1:2] == "_" and name[0] in FINGER_COLOURS:
        return hex_colour(FINGER_COLOURS[name[0]])
    return hex_colour(STRUCTURE_COLOUR)


@dataclass
class DesignReview:
    """A built design review.

    Attributes:
        scene: The meshcat scene.
        check: The envelope checks of the stowed configuration.
        offending: Links that fail (protruding, colliding stowed or deploying, or hit in
            the deployment): drawn red, or magenta when they only collide with another link.
        centre: Payload-frame point placed at the world origin (the camera target) [m].
        stowed: Link placements in the stowed configuration (payload frame).
        deployed: Link placements in the home (deployed) configuration.
    """

    scene: Scene
    check: StowedCheck
    offending: frozenset[str]
    centre: np.ndarray
    stowed: dict[str, np.ndarray]
    deployed: dict[str, np.ndarray]


def offending_parts(check: StowedCheck) -> frozenset[str]:
    """Links that fail: protrude from the bays, hit the vehicle as the stage deploys, or
    collide with another link (:meth:`StowedCheck.link_role` other than tight or none)."""
    return frozenset(p.name for p in check.parts if check.link_role(p.name) not in (None, "tight"))


def draw_vehicle(scene: Scene, vehicle: Vehicle, root: str) -> None:
    """Astrobee's body (around the open bays) and the bay envelope, translucent."""
    for i, (lo, hi) in enumerate(vehicle.body_boxes()):
        size, pose = box_pose(lo, hi)
        path = f"{root}/body/{i}"
        scene.object(path, mg.Box(size), mg.MeshLambertMaterial(color=BODY_COLOUR, opacity=0.3))
        scene.transform(path, pose)
    size, pose = box_pose(vehicle.bay_lower, vehicle.bay_upper)
    scene.object(
        f"{root}/bays",
        mg.Box(size),
        mg.MeshLambertMaterial(color=BAY_COLOUR, opacity=0.15, depthWrite=False),
    )
    scene.transform(f"{root}/bays", pose)


def draw_links(
    scene: Scene,
    model: PayloadModel,
    root: str,
    poses: Mapping[str, np.ndarray],
    colours: Mapping[str, int],
) -> None:
    """Every URDF link as a node at its pose, its meshes as children."""
    for link in model.links:
        path = f"{root}/{link}"
        for k, v in enumerate(model.visuals[link]):
            origin = v.origin @ np.diag([*v.scale, 1.0])
            mat = mg.MeshPhongMaterial(color=colours[link], shininess=30)
            scene.object(f"{path}/visual{k}", StlGeometry(str(v.mesh)), mat)
            scene.transform(f"{path}/visual{k}", origin)
        scene.transform(path, poses[link])


def _label(scene: Scene, path: str, text: str, at: np.ndarray) -> None:
    """A label anchor: an empty node at ``at``; the overlay draws ``text`` pointing there."""
    scene.transform(path, translation(at))
    scene.overlay.labels.append((path, text))


def wall_name(wall: str) -> str:
    """A bay wall as a label names it: ``'-z (bottom face)'`` -> ``'bay bottom face'``."""
    return "bay " + wall.partition("(")[2].rstrip(")") if "(" in wall else f"bay {wall}"


def wall_key(wall: str) -> str:
    """A bay wall as a scene path names it: ``'-z (bottom face)'`` -> ``'minus_z'``."""
    return wall.split()[0].replace("+", "plus_").replace("-", "minus_")


def draw_findings(
    scene: Scene, geom: PayloadGeometry, check: StowedCheck, vehicle: Vehicle, root: str
) -> list[tuple[str, float, np.ndarray, np.ndarray]]:
    """One label per bay wall, as envelope.png marks each wall: the tightest clearance to
    it as a labelled segment (over every part, inside the bays or not, as the envelope
    report's per-part clearances), or, on a wall parts cross, the part sticking out
    farthest beyond it and how many more cross it (every one of them is drawn red; a
    label per part crowded a failing design's view).

    Labels name the part, the wall and the distance (``stage - bay bottom face 6.0 mm``,
    ``A_knuckle - 9.9 mm beyond bay bottom face (and 12 more)``).

    Returns:
        ``(wall, clearance [m], part point, wall point)`` per drawn clearance segment.
    """
    lo, hi = vehicle.bay_lower, vehicle.bay_upper
    poses = geom.poses(check.q)
    drawn = []
    for w, wall in enumerate(vehicle.walls):
        near = check.nearest_to_wall(w)  # over every part, inside or not
        if near is None or check.beyond_wall(w):
            continue  # a wall a part crosses (0 to it): its protrusion is labelled below
        d, name = near.wall_clearance[w], near.name
        pts = geom.hull_vertices(name, poses[name])
        k = int(np.argmin(wall_gaps(pts, lo, hi)[:, w]))
        a = pts[k]
        b = a.copy()
        b[w // 2] = lo[w // 2] if w % 2 == 0 else hi[w // 2]
        key = wall_key(wall)
        scene.object(f"{root}/clearance/{key}/segment", segment(a, b))
        text = f"{name} - {wall_name(wall)} {clearance_text(d)}"
        _label(scene, f"{root}/clearance/{key}/label", text, (a + b) / 2)
        drawn.append((wall, float(d), a, b))
    for w, wall in enumerate(vehicle.walls):
        crossing = check.beyond_wall(w)  # every part crossing it, not only most
        if not crossing:
            continue
        out, more = crossing[0], len(crossing) - 1
        pts = geom.hull_vertices(out.name, poses[out.name])
        far = pts[int(np.argmin(wall_gaps(pts, lo, hi)[:, w]))]  # farthest beyond the wall
        text = f"{out.name} - {out.wall_protrusion[w] * 1e3:.1f} mm beyond {wall_name(wall)}"
        if more:
            text += f" (and {more} more)"
        _label(scene, f"{root}/protrusion/{wall_key(wall)}/{out.name}", text, far)
    return drawn


def reach_clouds(
    geom: PayloadGeometry, vehicle: Vehicle, samples: int, seed: int
) -> dict[str, np.ndarray]:
    """Each finger's collision-free fingertip cloud, as the reach report samples it [m]."""
    # from the defining modules: payload.envelope.reach loads the grasp check (SciPy's optimize)
    from payload.envelope.batch_fk import fingertips_batch
    from payload.envelope.collisions import CollisionModel
    from payload.envelope.pairs import finger_link_names
    from payload.envelope.sampling import sample_configurations

    tree = geom.tree
    q = sample_configurations(tree, samples, np.random.default_rng(seed))
    tips = fingertips_batch(tree, q)
    contacts = CollisionModel(geom, vehicle).check(q, workers=1)
    links = {f: finger_link_names(tree, f) for f in FINGERS}
    out = {}
    for i, f in enumerate(FINGERS):
        others = [n for g in FINGERS if g != f for n in links[g]]
        out[f] = tips[~contacts.involving(links[f], ignore=others), i]
    return out


def draw_reach(scene: Scene, clouds: Mapping[str, np.ndarray], root: str) -> None:
    """Reach clouds in the fingers' colours, hidden until ticked in the scene tree."""
    for f, pts in clouds.items():
        colour = np.array([int(FINGER_COLOURS[f][i : i + 2], 16) / 255 for i in (1, 3, 5)])
        cols = np.tile(colour, (len(pts), 1)).T.astype(np.float32)
        geometry = mg.PointsGeometry(pts.T.astype(np.float32), cols)
        scene.object(f"{root}/{f}", geometry, mg.PointsMaterial(size=0.002))
        scene.prop(f"{root}/{f}", "visible", False)


def set_track(
    animation: Animation, path: str, frames: list[float], poses: list[np.ndarray]
) -> None:
    """Keyframes of a node's pose: one per frame (``frames`` in animation frames)."""
    from scipy.spatial.transform import Rotation

    mats = np.asarray(poses, dtype=float).reshape(-1, 4, 4)
    pos = mats[:, :3, 3].tolist()
    quat = Rotation.from_matrix(mats[:, :3, :3]).as_quat().tolist()  # x y z w, as three.js
    clip = animation.clips.setdefault(mpath(path), AnimationClip(fps=animation.default_framerate))
    clip.tracks["position"] = AnimationTrack("position", "vector3", list(frames), pos)
    clip.tracks["quaternion"] = AnimationTrack("quaternion", "quaternion", list(frames), quat)


def deployment_postures(
    stowed: Mapping[str, float], home: Mapping[str, float]
) -> tuple[list[dict[str, float]], list[dict[str, float]]]:
    """The deployment's frames (:data:`DEPLOY_FPS`) as joint values, in two phases: the stage
    down with the fingers stowed, then the fingers and the rail from stowed to home."""
    n_stage, n_finger = round(STAGE_SECONDS * DEPLOY_FPS), round(FINGER_SECONDS * DEPLOY_FPS)
    stage = []
    for s in np.linspace(0.0, 1.0, n_stage + 1):
        values = dict(stowed)
        values["stage"] = (1 - s) * stowed["stage"] + s * home["stage"]
        stage.append(values)
    return stage, unfolding_postures(stowed, home, n_finger)


def deployment_configurations(
    model: PayloadModel, stowed: Mapping[str, float], home: Mapping[str, float]
) -> list[np.ndarray]:
    """Stage down with the fingers stowed, then fingers and rail from stowed to home."""
    stage, unfold = deployment_postures(stowed, home)
    return [model.configuration(values) for values in stage + unfold]


ROLE_COLOURS = {
    "outside": OFFENDING_COLOUR,
    "hit": OFFENDING_COLOUR,
    "colliding": COLLIDING,
    "tight": TIGHT,
}
"""A link's colour by its :meth:`~payload.envelope.fit_results.StowedCheck.link_role`."""


def part_colours(model: PayloadModel, check: StowedCheck) -> dict[str, int]:
    """Each link's colour by its role (:meth:`StowedCheck.link_role`, failing first, as
    envelope.png): red outside the bays or hit deploying, magenta colliding with another
    link (stowed, or as the fingers unfold), amber tight; else its finger's colour or
    grey."""
    roles = {n: check.link_role(n) for n in model.links}
    return {n: ROLE_COLOURS.get(roles[n] or "", link_colour(n)) for n in model.links}


def legend(colours: Mapping[str, int], reach: bool) -> list[tuple[str, str]]:
    """The legend: every colour the design review draws, with what it means; the verdict's
    two colours always, marked "none here" when no part is drawn in them (a reviewer
    reads that nothing fails or is tight, not a colour missing)."""
    used = set(colours.values())

    def verdict(colour: int, meaning: str) -> tuple[str, str]:
        return colour_text(colour), meaning + ("" if colour in used else " (none here)")

    out = [
        (FINGER_COLOURS[f], f"finger {f}" + (" and its reach" if reach else "")) for f in FINGERS
    ]
    out += [
        (STRUCTURE_COLOUR, "structure: base, stage, carriage"),
        verdict(OFFENDING_COLOUR, f"fails: {OUTSIDE_MEANING} or hits the vehicle"),
        verdict(COLLIDING, f"fails: {COLLIDES_MEANING}, stowed or deploying"),
        verdict(TIGHT, tight_meaning(walls=True, links=True)),
        (colour_text(BODY_COLOUR), "Astrobee's body"),
        (colour_text(BAY_COLOUR), "payload bays (the stowed envelope)"),
        (colour_text(SEGMENT_COLOUR), "clearance measured (stowed)"),
    ]
    listed = {hex_colour(c) for c, _ in out}
    missing = used - listed
    if missing:  # a colour drawn but not explained is a bug here, not in the design
        raise AssertionError(f"legend misses {sorted(map(colour_text, missing))}")
    return out


def box_corners(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """The 8 corners of the axis-aligned box ``lower``..``upper``, shape (8, 3) [m]."""
    pick = np.array(list(itertools.product((0, 1), repeat=3)))
    return np.where(pick, upper, lower)


def subject_box(vehicle: Vehicle, stowed: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """What the default view frames: the two lower bays and the stowed payload's meshes in
    them (a part sticking out of the bays included), as one axis-aligned box, payload frame
    (lower, upper corners) [m]."""
    pts = np.vstack([vehicle.bay_lower, vehicle.bay_upper, *stowed])
    return pts.min(axis=0), pts.max(axis=0)


def title(files: ProjectFiles, check: StowedCheck) -> tuple[str, str]:
    """The title (:func:`~payload.review.project.page_title`: the project, design file and
    hash) and the verdict line (``stowed fit: pass; ...``, the envelope report's verdict:
    the deployment's failures among its reasons)."""
    design = Path(files.design)
    name = f"{design.resolve().parents[1].name}/{design.parent.name}/{design.name}"
    verdict = "stowed fit: pass" if check.passed else "stowed fit: FAIL"
    reasons = [] if check.passed else check.failures()
    if reasons:  # what failed, as `payload report envelope` says it
        verdict += f": {first_of(reasons, 1, 'payload report envelope')}"
    if check.parts and check.tightest.clearance >= 0:  # (one sticking out leads the reasons)
        t = check.tightest
        verdict += f"; tightest {t.name} {clearance_text(t.clearance)}"
    return page_title("design review", name, design), verdict


def build_design_review(
    files: ProjectFiles,
    reach_samples: int = 5000,
    seed: int = 0,
    root: str = REVIEW,
    check_models: bool = True,
) -> DesignReview:
    """The design review scene of a design project (stowed, with the deployment animation).

    The page opens on the stowed payload with its clearance labels; the deployment plays
    from the controls (the labels hide once the stage moves).

    Args:
        files: The design project's files.
        reach_samples: Configurations sampled for the reach clouds (0: no clouds).
        seed: Seed of the reach sampling.
        root: Scene node to build under.
        check_models: Check that the generated models match the design (skip it only
            right after writing them).
    """
    files.check()
    design = load_design(files.design)
    stale = []
    if check_models:
        from payload.design import stale_files  # generates every model: trimesh

        stale = stale_files(design, files.urdf.parent.parent)
    if stale:
        raise ReviewError(
            f"the generated models do not match {files.design} ({', '.join(stale)}); "
            "run `payload build`"
        )
    vehicle = vehicle_from_dict(design.vehicle or {}, source=str(files.design))
    tree = build_tree(design)
    geom = PayloadGeometry(tree)
    model = PayloadModel(files.urdf)
    stowed_q, home_q = tree.posture("stowed"), tree.posture("home")
    check = check_stowed(geom, vehicle, stowed_q)
    bad = offending_parts(check)
    stowed = model.placements(model.configuration(check.q))
    deployed = model.placements(model.configuration(home_q))
    clouds = reach_clouds(geom, vehicle, reach_samples, seed) if reach_samples else {}

    placed = [
        geom.mesh_vertices[n] @ stowed[n][:3, :3].T + stowed[n][:3, 3]
        for n in model.links
        if n in geom.solids
    ]
    lo, hi = subject_box(vehicle, placed)
    centre = (lo + hi) / 2  # the camera's target: the view turns about the payload
    subject = box_corners(lo, hi) - centre

    scene = Scene(autoplay=False)
    scene.transform(root, translation(-centre))
    draw_vehicle(scene, vehicle, f"{root}/vehicle")
    colours = part_colours(model, check)
    draw_links(scene, model, f"{root}/payload", stowed, colours)
    draw_findings(scene, geom, check, vehicle, f"{root}/findings")
    if clouds:
        draw_reach(scene, clouds, f"{root}/reach")
    scene.camera = (framing(subject, VIEW_DIRECTION, FRAME_MARGIN), np.zeros(3))
    head, verdict = title(files, check)
    scene.overlay = Overlay(
        title=head,
        subtitle=verdict,
        outcome=PASS if check.passed else FAIL,
        legend=legend(colours, bool(clouds)),
        labels=scene.overlay.labels,
        views={"default": [float(v) for v in scene.camera[0]]},
        # the labels go beside the payload, not over its parts (a failing one's red parts)
        clear=[f"{root}/payload"],
        subject=subject.tolist(),
    )

    anim = Animation(default_framerate=DEPLOY_FPS)
    configs = deployment_configurations(model, check.q, home_q)
    frames = list(range(len(configs)))
    placements = [model.placements(q) for q in configs]
    for link in model.links:
        set_track(anim, f"{root}/payload/{link}", frames, [p[link] for p in placements])
    set_visibility(anim, f"{root}/findings", frames, [i == 0 for i in frames])
    scene.animation = anim
    scene.notes += [f"design: {Path(files.design)}", verdict]
    scene.notes += [f"  {line}" for line in check.failures()]
    return DesignReview(scene, check, bad, centre, stowed, deployed)


def set_visibility(animation: Animation, path: str, frames: list[float], on: list[bool]) -> None:
    """Keys of a node's visibility at the first frame and every frame where it changes."""
    keep = [0, *[i for i in range(1, len(on)) if on[i] != on[i - 1]]]
    clip = animation.clips.setdefault(mpath(path), AnimationClip(fps=animation.default_framerate))
    values = [bool(on[i]) for i in keep]
    clip.tracks["visible"] = AnimationTrack("visible", "boolean", [frames[i] for i in keep], values)


__all__ = [
    "COLLIDING",
    "OFFENDING_COLOUR",
    "REVIEW",
    "DesignReview",
    "build_design_review",
    "deployment_configurations",
    "deployment_postures",
    "draw_findings",
    "draw_links",
    "draw_vehicle",
    "link_colour",
    "offending_parts",
    "reach_clouds",
    "set_track",
    "set_visibility",
]
