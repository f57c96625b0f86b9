"""Parametric payload design: parameters, validation, solids, kinematic tree, exporters.

The exporters (``generate``, ``stale_files``, ``write``) load on first use: they need
trimesh, about 0.6 s of imports that the simulator, the teleoperation loop and the
trials do not need.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

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

if TYPE_CHECKING:
    from payload.design.build import generate, stale_files, write
    from payload.design.follow import models_follow_design

_BUILD_NAMES = ("generate", "models_follow_design", "stale_files", "write")


def __getattr__(name: str) -> Any:
    if name == "models_follow_design":  # no trimesh while the models are fresh
        from payload.design.follow import models_follow_design

        return models_follow_design
    if name in _BUILD_NAMES:
        from payload.design import build

        return getattr(build, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_BUILD_NAMES})


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
    "models_follow_design",
    "stale_files",
    "write",
]
