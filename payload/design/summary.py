"""A design's summary: DoF, joint ranges, masses, stowed and deployed bounding boxes."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from payload.design.params import Design
from payload.design.servo import JOINT_KINDS, joint_servo
from payload.design.solids import to_trimesh
from payload.design.tree import MANIPULATION_JOINTS, KinematicTree, build_tree, load_inertia


def bounding_box(tree: KinematicTree, q: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds of every link solid posed at ``q`` (payload frame) [m].

    Returns:
        (lower corner, upper corner), shape (3,) each.
    """
    poses = tree.link_poses(q)
    cache: dict[str, np.ndarray] = {}
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for link in tree.links:
        if link.body is None:
            continue
        if link.body.mesh not in cache:
            cache[link.body.mesh] = np.asarray(to_trimesh(link.body.solid()).vertices)
        v = cache[link.body.mesh] @ poses[link.name][:3, :3].T + poses[link.name][:3, 3]
        lo, hi = np.minimum(lo, v.min(axis=0)), np.maximum(hi, v.max(axis=0))
    return lo, hi


def summarize(design: Design, tree: KinematicTree | None = None) -> dict[str, Any]:
    """Plain-data summary (SI units, plus mm where named so)."""
    tree = tree or build_tree(design)
    joints = []
    for j in tree.actuated:
        joints.append(
            {
                "name": j.name,
                "type": j.kind,
                "lower": j.lower,
                "upper": j.upper,
                "effort": j.effort,
                "velocity": j.velocity,
            }
        )
    masses = {link.name: link.mass.mass for link in tree.links if link.mass.mass > 0}
    groups: dict[str, float] = {}
    for name, m in masses.items():
        key = f"finger_{name[0]}" if name[:2] in ("A_", "B_", "C_", "D_") else name
        groups[key] = groups.get(key, 0.0) + m
    boxes = {}
    for posture in ("stowed", "home"):
        lo, hi = bounding_box(tree, tree.posture(posture))
        boxes[posture] = {
            "min_mm": [round(float(v) * 1e3, 2) for v in lo],
            "max_mm": [round(float(v) * 1e3, 2) for v in hi],
            "size_mm": [round(float(v) * 1e3, 2) for v in hi - lo],
        }
    return {
        "design": design.source,
        "dof": {
            "manipulation": len(MANIPULATION_JOINTS),
            "deployment": 1,
            "total": len(tree.actuated),
        },
        "joints": joints,
        "mass_kg": {"total": tree.total_mass(), "groups": groups, "links": masses},
        "bounding_box": {"stowed": boxes["stowed"], "deployed": boxes["home"]},
        "servo": servo_summary(tree),
    }


def servo_summary(tree: KinematicTree) -> dict[str, dict[str, Any]]:
    """Per joint kind: the MuJoCo parameters and the free response they give.

    ``natural_hz = sqrt(kp / M) / 2 pi`` and ``damping_ratio = (kv + damping) / (2 sqrt(kp
    M))`` with ``M`` = armature + :func:`load_inertia` (linear, Coulomb friction aside).
    """
    out = {}
    for kind in JOINT_KINDS:
        js = joint_servo(tree.design, kind)
        m = js.armature + load_inertia(tree, kind)
        out[kind] = {
            "kp": js.kp,
            "kv": js.kv,
            "damping": js.damping,
            "armature": js.armature,
            "frictionloss": js.frictionloss,
            "torque_cap": js.torque_cap,
            "natural_hz": math.sqrt(js.kp / m) / (2.0 * math.pi),
            "damping_ratio": (js.kv + js.damping) / (2.0 * math.sqrt(js.kp * m)),
        }
    return out


def print_summary(summary: dict[str, Any]) -> None:
    """Print the summary as rich tables."""
    from rich.markup import escape
    from rich.table import Table

    from payload.console import console as make_console

    console = make_console()
    dof = summary["dof"]
    console.print(
        f"[bold]Payload design[/bold] {summary['design']}: {dof['manipulation']} manipulation DoF "
        f"+ {dof['deployment']} deployment DoF"
    )
    t = Table(title="Joints")
    for col in ("joint", "type", "lower", "upper", "effort", "max speed"):
        t.add_column(col, justify="right" if col != "joint" else "left")
    for j in summary["joints"]:
        if j["type"] == "revolute":
            lo, hi = f"{np.degrees(j['lower']):.1f} deg", f"{np.degrees(j['upper']):.1f} deg"
            eff, vel = f"{j['effort']:.3f} N m", f"{j['velocity']:.2f} rad/s"
        else:
            lo, hi = f"{j['lower'] * 1e3:.1f} mm", f"{j['upper'] * 1e3:.1f} mm"
            eff, vel = f"{j['effort']:.1f} N", f"{j['velocity'] * 1e3:.1f} mm/s"
        t.add_row(j["name"], j["type"], lo, hi, eff, vel)
    console.print(t)
    t = Table(title="Masses")
    t.add_column("part")
    t.add_column("mass", justify="right")
    for name, m in summary["mass_kg"]["groups"].items():
        t.add_row(name, f"{m * 1e3:.1f} g")
    t.add_row("[bold]total[/bold]", f"[bold]{summary['mass_kg']['total'] * 1e3:.1f} g[/bold]")
    console.print(t)
    t = Table(title="Bounding boxes (payload frame)")
    for col in ("posture", "x [mm]", "y [mm]", "z [mm]", "size [mm]"):
        t.add_column(escape(col))
    for name, b in summary["bounding_box"].items():
        rng = [f"{lo:.1f} .. {hi:.1f}" for lo, hi in zip(b["min_mm"], b["max_mm"])]
        t.add_row(name, *rng, " x ".join(f"{s:.1f}" for s in b["size_mm"]))
    console.print(t)
