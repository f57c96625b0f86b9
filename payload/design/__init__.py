"""Parametric payload design: parameters, validation, solids, kinematic tree, exporters."""

from payload.design.build import generate, stale_files, write
from payload.design.params import (
    FINGER_JOINTS,
    FINGERS,
    SIDE_OF,
    Design,
    design_from_dict,
    design_to_dict,
    load_design,
)
from payload.design.tree import (
    ALL_JOINTS,
    MANIPULATION_JOINTS,
    Frame,
    Joint,
    KinematicTree,
    Link,
    build_tree,
)

__all__ = [
    "ALL_JOINTS",
    "FINGERS",
    "FINGER_JOINTS",
    "MANIPULATION_JOINTS",
    "SIDE_OF",
    "Design",
    "Frame",
    "Joint",
    "KinematicTree",
    "Link",
    "build_tree",
    "design_from_dict",
    "design_to_dict",
    "generate",
    "load_design",
    "stale_files",
    "write",
]
