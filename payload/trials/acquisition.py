"""The trial's starting scene for a real acquisition: a seeded CTB pose offset.

The CTB starts displaced from where the calibrated pinch would close on its handle: an
offset of a few centimetres in the vehicle's body frame and a yaw about the vehicle's
vertical, drawn from the trial's seed (ranges below, ASSUMPTION: what a person leaving a
bag floating in front of the robot would leave it within). A draw whose bag would start
touching anything (fingers, vehicle, walls) is redrawn from the same generator, so the
scene starts without contact and the offset is still a function of the seed alone.
"""

from __future__ import annotations

import math
from typing import Any

import mujoco
import numpy as np

from payload.retarget.calibration import PairRange
from payload.retarget.casadi_solver import PairRetargeter
from payload.rotations import quat_to_matrix, yaw_quat

OFFSET_RANGE_M = (0.04, 0.025, 0.02)
"""Half-ranges of the uniform CTB offset along the body x, y, z [m]."""

YAW_RANGE_DEG = 10.0
"""Half-range of the uniform CTB yaw about the body z axis [deg]."""

_SALT = 0x15C7B  # keeps this stream apart from the operator's own generator


def sample_offset(seed: int, k: int = 0) -> tuple[np.ndarray, float]:
    """The ``k``-th draw of (body-frame offset (3,) [m], yaw [deg]) for this seed."""
    rng = np.random.default_rng([int(seed), _SALT, int(k)])
    offset = rng.uniform(-1.0, 1.0, size=3) * np.asarray(OFFSET_RANGE_M)
    yaw = float(rng.uniform(-YAW_RANGE_DEG, YAW_RANGE_DEG))
    return offset, yaw


def _ctb_touched(model: mujoco.MjModel, data: mujoco.MjData, ctb: int) -> bool:
    for i in range(data.ncon):
        g = data.contact.geom[i]
        if data.contact.dist[i] <= 0.0 and ctb in (
            model.geom_bodyid[g[0]],
            model.geom_bodyid[g[1]],
        ):
            return True
    return False


def place_offset(
    driver: Any, seed: int, offset: np.ndarray | None = None, yaw_deg: float | None = None
) -> tuple[np.ndarray, float]:
    """Displace the CTB (already placed under the pinch) by the seed's offset and yaw.

    Args:
        driver: The :class:`~payload.sim.driver.SimDriver` (its ``data`` is changed).
        seed: The trial's seed.
        offset: Use this body-frame offset [m] instead of drawing one (replays).
        yaw_deg: Use this yaw [deg] instead of drawing one.

    Returns:
        The offset (3,) [m] and yaw [deg] applied.
    """
    w, m, d = driver.world, driver.model, driver.data
    a, c = w.astrobee_qpos, w.ctb_qpos
    rot = quat_to_matrix(d.qpos[a + 3 : a + 7])
    pos0 = d.qpos[c : c + 3].copy()
    quat0 = d.qpos[c + 3 : c + 7].copy()

    def put(off: np.ndarray, yaw: float) -> None:
        d.qpos[c : c + 3] = pos0 + rot @ off
        q = np.zeros(4)
        mujoco.mju_mulQuat(q, quat0, yaw_quat(math.radians(yaw)))
        d.qpos[c + 3 : c + 7] = q
        mujoco.mj_forward(m, d)

    if offset is not None and yaw_deg is not None:
        put(np.asarray(offset, dtype=float), float(yaw_deg))
        return np.asarray(offset, dtype=float), float(yaw_deg)
    for k in range(100):
        off, yaw = sample_offset(seed, k)
        put(off, yaw)
        if not _ctb_touched(m, d, w.ctb):
            return off, yaw
    raise RuntimeError(f"seed {seed}: no CTB offset without initial contact in 100 draws")


def handle_site(driver: Any) -> int:
    """The index of the CTB handle's site in the driver's model.

    Raises:
        KeyError: The model has no CTB handle.
    """
    site = mujoco.mj_name2id(driver.model, mujoco.mjtObj.mjOBJ_SITE, "ctb_handle")
    if site < 0:
        raise KeyError("ctb_handle")  # what d.site("ctb_handle") raises
    return site


def handle_in_body(
    driver: Any, site: int | None = None, rotation: np.ndarray | None = None
) -> np.ndarray:
    """The CTB handle's centre in Astrobee's body frame, shape (3,) [m]; ``site``: the
    handle's site (:func:`handle_site`), ``rotation``: Astrobee's body -> world rotation
    now (of the data's quaternion), when the caller has them."""
    w, d = driver.world, driver.data
    a = w.astrobee_qpos
    rot = quat_to_matrix(d.qpos[a + 3 : a + 7]) if rotation is None else rotation
    if site is None:
        site = handle_site(driver)
    return rot.T @ (d.site_xpos[site] - d.qpos[a : a + 3])


def place_ctb_for_teleop(
    driver: Any, retargeters: dict[str, PairRetargeter], ranges: dict[str, PairRange]
) -> np.ndarray:
    """Move the CTB so its handle sits where the teleoperated pinch closes on it.

    The pinch the operator commands follows the posture reference of the calibrated pair
    ranges. For each pair, the span at which the reference posture's pads first reach the
    handle's side faces is found by bisection; the handle bar is centred on the mean of
    the four fingertips there. Only the CTB's initial pose changes.

    Returns:
        That grasp point (the handle centre) in Astrobee's body frame, shape (3,) [m].
    """
    import mujoco

    from payload.design.tree import MANIPULATION_JOINTS
    from payload.sim.world import PAYLOAD_PREFIX

    w, m = driver.world, driver.model
    data = mujoco.MjData(m)
    data.qpos[:] = driver.data.qpos
    handle = w.config.handle
    a = w.astrobee_qpos
    rot = quat_to_matrix(driver.data.qpos[a + 3 : a + 7])
    pad = float(m.geom_size[next(iter(w.pad_geoms.values()))][0])

    def tips_at(pair: str, span: float) -> np.ndarray:
        r = retargeters[pair]
        for name, v in zip(r.joints, ranges[pair].posture(span)):
            data.qpos[w.qpos[MANIPULATION_JOINTS.index(name)]] = v
        mujoco.mj_kinematics(m, data)
        sites = r.kinematics.hand.pair(pair).tips
        return np.array([data.site(f"{PAYLOAD_PREFIX}{s}").xpos for s in sites])

    tips = []
    for pair in retargeters:
        lo, hi = ranges[pair].span_min, ranges[pair].span_max
        for _ in range(40):  # across-array gap between the pads = handle width
            mid = 0.5 * (lo + hi)
            t = tips_at(pair, mid)
            gap = abs(float(rot[:, 1] @ (t[0] - t[1]))) - 2 * pad
            lo, hi = (mid, hi) if gap < handle.width else (lo, mid)
        tips.append(tips_at(pair, 0.5 * (lo + hi)))
    centre = np.vstack(tips).mean(axis=0)
    # the bag hangs below its handle bar: bar centre -> bag centre along the body -z axis
    size = w.config.ctb_size
    drop = handle.height / 2.0 + handle.standoff + size.height / 2.0
    c = w.ctb_qpos
    driver.data.qpos[c : c + 3] = centre - rot[:, 2] * drop
    mujoco.mj_forward(m, driver.data)
    return rot.T @ (centre - driver.data.qpos[a : a + 3])


__all__ = [
    "OFFSET_RANGE_M",
    "YAW_RANGE_DEG",
    "handle_in_body",
    "handle_site",
    "place_ctb_for_teleop",
    "place_offset",
    "sample_offset",
]
