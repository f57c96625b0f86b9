"""MJCF exporter in MuJoCo Menagerie's conventions: ``urdf/payload.xml`` and ``urdf/scene.xml``.

Visual geoms use the STL meshes (group 2, no contacts); collision geoms are
primitives (group 3): boxes for links and brackets, cylinders for the guide
columns, spheres for the fingertip pads. Structure geoms (base, stage, carriage)
do not collide with each other, only with fingers and the world.
"""

from __future__ import annotations

from xml.sax.saxutils import quoteattr

from payload.design.fmt import num, quat_from_matrix, vec
from payload.design.servo import JOINT_KINDS
from payload.design.tree import KinematicTree, rpy_matrix
from payload.schema import PHYSICS_DT

MESH_DIR = "../cad/meshes"

MATERIALS = {
    "structure": "0.55 0.57 0.6 1",
    "finger": "0.15 0.15 0.17 1",
    "pad": "0.85 0.35 0.1 1",
}


def _servo_classes(tree: KinematicTree) -> list[str]:
    """One default class per servo joint kind (the values of :mod:`payload.design.servo`)."""
    out = []
    for kind in JOINT_KINDS:
        j = next(j for j in tree.joints if j.group == kind)
        hinge = "hinge" if j.kind == "revolute" else "slide"
        out += [
            f'      <default class="{kind}">',
            f'        <joint type="{hinge}" damping="{num(j.damping)}" '
            f'frictionloss="{num(j.frictionloss)}" armature="{num(j.armature)}"/>',
            f'        <position kp="{num(j.kp)}" kv="{num(j.kv)}" '
            f'forcerange="{num(-j.effort)} {num(j.effort)}"/>',
            "      </default>",
        ]
    return out


def _defaults(tree: KinematicTree) -> list[str]:
    d = tree.design
    mu = d.finger.pad.friction
    return [
        "  <default>",
        '    <default class="payload">',
        '      <default class="visual">',
        '        <geom type="mesh" contype="0" conaffinity="0" group="2" density="0"/>',
        "      </default>",
        '      <default class="collision">',
        '        <geom group="3" contype="1" conaffinity="1" density="0"/>',
        '        <default class="structure">',
        '          <geom contype="2" conaffinity="1"/>',
        "        </default>",
        '        <default class="pad">',
        f'          <geom type="sphere" condim="4" priority="1" '
        f'friction="{num(mu)} 0.005 0.0001"/>',
        "        </default>",
        "      </default>",
        *_servo_classes(tree),
        "    </default>",
        "  </default>",
    ]


def _assets(tree: KinematicTree) -> list[str]:
    out = ["  <asset>"]
    for name, rgba in MATERIALS.items():
        out.append(f'    <material name="{name}" rgba="{rgba}"/>')
    meshes = sorted({link.body.mesh for link in tree.links if link.body is not None})
    for mesh in meshes:
        out.append(f'    <mesh name="{mesh}" file="{mesh}.stl"/>')
    out.append("  </asset>")
    return out


def _body_geoms(tree: KinematicTree, link_name: str, indent: str) -> list[str]:
    link = tree.link_map[link_name]
    out = []
    m = link.mass
    if m.mass > 0:
        i = m.inertia
        full = [i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2]]
        out.append(
            f'{indent}<inertial pos="{vec(m.com)}" mass="{num(m.mass)}" fullinertia="{vec(full)}"/>'
        )
    body = link.body
    if body is None:
        return out
    material = "finger" if body.mesh.startswith("finger") else "structure"
    coll = "collision" if body.mesh.startswith("finger") else "structure"
    out.append(f'{indent}<geom class="visual" mesh="{body.mesh}" material="{material}"/>')
    for center, half in body.boxes:
        out.append(
            f'{indent}<geom class="{coll}" type="box" pos="{vec(center)}" size="{vec(half)}"/>'
        )
    for center, axis, radius, half_len in body.cylinders:
        if axis != "z":  # pragma: no cover - only vertical guide columns exist
            raise ValueError("only z cylinders are exported")
        out.append(
            f'{indent}<geom class="{coll}" type="cylinder" pos="{vec(center)}" '
            f'size="{num(radius)} {num(half_len)}"/>'
        )
    for center, radius in body.spheres:
        out.append(
            f'{indent}<geom class="pad" name="{link_name}_pad" pos="{vec(center)}" '
            f'size="{num(radius)}" material="pad"/>'
        )
    return out


def _body(tree: KinematicTree, joint_name: str, depth: int, qpos_order: list[str]) -> list[str]:
    j = tree.joint_map[joint_name]
    ind = "  " * depth
    quat = quat_from_matrix(rpy_matrix(j.rpy))
    attrs = f'name={quoteattr(j.child)} pos="{vec(j.xyz)}"'
    if any(abs(v) > 0 for v in j.rpy):
        attrs += f' quat="{vec(quat)}"'
    out = [f"{ind}<body {attrs}>"]
    out += _body_geoms(tree, j.child, ind + "  ")
    if j.kind != "fixed":
        out.append(
            f'{ind}  <joint name={quoteattr(j.name)} class="{j.group}" axis="{vec(j.axis)}" '
            f'range="{num(j.lower)} {num(j.upper)}"/>'
        )
        qpos_order.append(j.name)
    for fr in tree.frames:
        if fr.parent == j.child:
            out.append(f'{ind}  <site name={quoteattr(fr.name)} pos="{vec(fr.xyz)}" size="0.003"/>')
    for child in tree.children(j.child):
        out += _body(tree, child.name, depth + 1, qpos_order)
    out.append(f"{ind}</body>")
    return out


def to_mjcf(tree: KinematicTree) -> tuple[str, list[str]]:
    """The MJCF text of the payload and the joint order of its ``qpos``.

    Returns:
        (xml, qpos_joint_names).
    """
    qpos_order: list[str] = []
    out = [
        "<!-- Generated by `payload build` from cad/design.toml. Do not edit by hand. -->",
        '<mujoco model="payload">',
        f'  <compiler angle="radian" meshdir="{MESH_DIR}" autolimits="true"/>',
        f'  <option timestep="{num(PHYSICS_DT)}" integrator="implicitfast" gravity="0 0 0"/>',
    ]
    out += _defaults(tree)
    out += _assets(tree)
    out.append("  <worldbody>")
    out.append(f'    <body name="{tree.root}" childclass="payload">')
    out += _body_geoms(tree, tree.root, "      ")
    for child in tree.children(tree.root):
        out += _body(tree, child.name, 3, qpos_order)
    out.append("    </body>")
    out.append("  </worldbody>")
    out.append("  <actuator>")
    for j in tree.actuated:
        out.append(
            f'    <position name={quoteattr(j.name)} joint={quoteattr(j.name)} class="{j.group}" '
            f'ctrlrange="{num(j.lower)} {num(j.upper)}"/>'
        )
    out.append("  </actuator>")
    home = tree.posture("home")
    qpos = [home[n] for n in qpos_order]
    ctrl = [home[j.name] for j in tree.actuated]
    out.append("  <keyframe>")
    out.append(f'    <key name="home" qpos="{vec(qpos)}" ctrl="{vec(ctrl)}"/>')
    stowed = tree.posture("stowed")
    out.append(
        f'    <key name="stowed" qpos="{vec(stowed[n] for n in qpos_order)}" '
        f'ctrl="{vec(stowed[j.name] for j in tree.actuated)}"/>'
    )
    out.append("  </keyframe>")
    out.append("</mujoco>")
    return "\n".join(out) + "\n", qpos_order


def scene_xml() -> str:
    """A zero-gravity viewing scene that includes ``payload.xml``."""
    return "\n".join(
        [
            "<!-- Generated by `payload build`. Do not edit by hand. -->",
            '<mujoco model="payload scene">',
            '  <include file="payload.xml"/>',
            '  <statistic center="0 0 -0.12" extent="0.35"/>',
            "  <visual>",
            '    <headlight diffuse="0.6 0.6 0.6" ambient="0.3 0.3 0.3" specular="0 0 0"/>',
            '    <global azimuth="140" elevation="-20"/>',
            "  </visual>",
            "  <worldbody>",
            '    <light pos="0 0 1" dir="0 0 -1" directional="true"/>',
            "  </worldbody>",
            "</mujoco>",
            "",
        ]
    )
