"""The on-disk cache of a pair's self-collision geometry (:class:`~payload.retarget.collision.
PairCollision`): its capsules, structure boxes, pad links and clearance terms, pruned.

Deriving them reads every collision mesh of the URDF with trimesh, fits a capsule to each
finger link with SciPy's Nelder-Mead and evaluates every candidate term at
:data:`~payload.retarget.collision.PRUNE_SAMPLES` postures: about 1.5 s and 0.9 s of
imports at every start with the model (a ``safe`` trial, ``teleop serve``, ``hw run``),
for an answer that changes only with its inputs. It is kept beside the compiled solvers
(:func:`payload.cache.cache_dir`), named by a hash of everything it is derived from: the
URDF and every mesh file it names (their bytes), the design file, the pair's and hand's
descriptions, the margin, what :func:`payload.native.result_environment` names (the
workbench's code, the versions of numpy, SciPy, CasADi and Pinocchio, Python's build, the
machine, the processor and numpy's BLAS kernels), trimesh's version, and the C compiler
and its flags that evaluate the pruning's distances. A stale entry is never read; an
unreadable or torn one is derived again and rewritten.
:class:`~payload.retarget.collision.PairCollision` stores only what it derived from the
same bytes it keyed (the key is taken again after the derivation) and with the compiled
distances when there is a compiler. Postures derived
from the geometry (the retargeting's seed table, :func:`payload.retarget.budget.
seed_table`) are kept under keys made from its key (:func:`postures_key`).

The same model key names a pair's compiled retargeting solver (:func:`solver_key`, with
the solve's settings): which cached library it is, so a retargeter whose solver was built
before loads it without building its CasADi graph again (about 0.15 s a pair;
:class:`~payload.retarget.casadi_solver.PairRetargeter`). The newest :data:`KEEP` entries
of each kind are kept.
"""

from __future__ import annotations

import hashlib
import xml.etree.ElementTree as ET
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from payload.cache import cache_dir, dist_version
from payload.native import find_compiler, flags, result_environment
from payload.retarget.collision_geometry import Box, Capsule, mesh_path
from payload.retarget.features import PairKinematics
from payload.safeio import replacing

_CACHE_VERSION = "pair-collision-1"
_SOLVER_VERSION = "pair-solver-1"

MESH_LIBRARY = "trimesh"
"""The distribution that reads the meshes, whose version is in the key beside those of
:data:`payload.native.RESULT_PACKAGES` (numpy, SciPy, CasADi, Pinocchio: in
:func:`payload.native.result_environment`)."""

KEEP = 16
"""Pair shapes kept in the cache (the newest; two a design, one a pair)."""


@dataclass(frozen=True)
class CollisionShape:
    """What :class:`~payload.retarget.collision.PairCollision` derives from the model.

    Attributes:
        capsules: The finger links' capsules.
        finger_of: Per capsule, 0 or 1.
        boxes: The structure's boxes in the pair's base frame.
        pads: Per finger, its pad link or ``None``.
        all_terms: Every candidate term, ``(capsule, other, box)``.
        kept: Per candidate term, whether the pruning kept it.
    """

    capsules: tuple[Capsule, ...]
    finger_of: tuple[int, ...]
    boxes: tuple[Box, ...]
    pads: tuple[str | None, ...]
    all_terms: tuple[tuple[int, int, bool], ...]
    kept: tuple[bool, ...]


def shape_key(pk: PairKinematics, margin: float) -> str | None:
    """The cache key of a pair's shape, or None when a file it is derived from cannot be
    read (a temporary URDF gone, a mesh missing: derived, and its error raised, there)."""
    return model_key(pk, _CACHE_VERSION, repr(float(margin)))


def model_key(pk: PairKinematics, kind: str, *settings: str) -> str | None:
    """A cache key of something derived from a pair's model: ``kind`` (what it is, with
    its format's version), what :func:`payload.native.result_environment` names (the
    workbench's code among it), trimesh's version, the C compiler and its flags, the URDF
    and every mesh file it names (their bytes), the design file, the pair's and hand's
    descriptions, and ``settings``. None when a file cannot be read."""
    urdf = Path(pk.kin.urdf)
    h = hashlib.sha256()

    def part(data: bytes | str) -> None:
        data = data.encode() if isinstance(data, str) else data
        h.update(len(data).to_bytes(8, "little") + data)

    try:
        text = urdf.read_bytes()
        part(kind)
        part(result_environment())  # the workbench's sources among them
        part(f"{MESH_LIBRARY}={dist_version(MESH_LIBRARY)}")
        compiler = find_compiler()
        part(str(compiler))
        part(" ".join(flags(compiler)) if compiler is not None else "")
        part(text)
        for mesh in ET.fromstring(text).iter("mesh"):  # collision and visual: both named
            path = mesh_path(mesh.get("filename", ""), urdf.parent)
            part(str(path))
            part(path.read_bytes())
        design = pk.hand.design
        part(Path(design).read_bytes() if design is not None else b"")
    except (OSError, ET.ParseError):
        return None
    part(repr(pk.desc))
    part(repr(pk.hand))
    for setting in settings:
        part(setting)
    return h.hexdigest()[:24]


def load_shape(key: str) -> CollisionShape | None:
    """The shape stored under ``key``, or None (none, or unreadable)."""
    try:
        with np.load(cache_dir() / f"pair_collision_{key}.npz") as z:
            links = [str(s) for s in z["capsule_links"]]
            ends, radii = z["capsule_ends"], z["capsule_radii"]
            capsules = tuple(
                Capsule(n, ends[i, 0].copy(), ends[i, 1].copy(), float(radii[i]))
                for i, n in enumerate(links)
            )
            boxes = tuple(
                Box(str(n), c.copy(), r.copy(), s.copy())
                for n, c, r, s in zip(
                    z["box_links"], z["box_centres"], z["box_rotations"], z["box_halves"]
                )
            )
            pads = tuple(str(p) or None for p in z["pads"])
            terms = tuple((int(a), int(b), bool(c)) for a, b, c in z["terms"].reshape(-1, 3))
            shape = CollisionShape(
                capsules,
                tuple(int(i) for i in z["finger_of"]),
                boxes,
                pads,
                terms,
                tuple(bool(k) for k in z["kept"]),
            )
    except (OSError, KeyError, ValueError, IndexError, EOFError, zipfile.BadZipFile):
        return None  # missing or unreadable (a torn write): derived again and rewritten
    return shape if _whole(shape) else None


def _whole(shape: CollisionShape) -> bool:
    """Whether a loaded shape's parts fit each other (a file that does not is derived
    again): a finger per capsule, a verdict per term, every term's indices in range."""
    n_caps, n_boxes = len(shape.capsules), len(shape.boxes)
    return (
        len(shape.finger_of) == n_caps
        and len(shape.kept) == len(shape.all_terms)
        and all(
            0 <= a < n_caps and 0 <= b < (n_boxes if box else n_caps)
            for a, b, box in shape.all_terms
        )
    )


def store_shape(key: str, shape: CollisionShape) -> None:
    """Keep ``shape`` under ``key`` (a read-only cache only costs the next derivation)."""
    caps, boxes = shape.capsules, shape.boxes
    _store(
        f"pair_collision_{key}.npz",
        capsule_links=np.array([c.link for c in caps], dtype=str),
        capsule_ends=np.array([[c.a, c.b] for c in caps], dtype=float).reshape(-1, 2, 3),
        capsule_radii=np.array([c.radius for c in caps], dtype=float),
        finger_of=np.array(shape.finger_of, dtype=np.int64),
        box_links=np.array([b.link for b in boxes], dtype=str),
        box_centres=np.array([b.centre for b in boxes], dtype=float).reshape(-1, 3),
        box_rotations=np.array([b.rotation for b in boxes], dtype=float).reshape(-1, 3, 3),
        box_halves=np.array([b.half for b in boxes], dtype=float).reshape(-1, 3),
        pads=np.array([p or "" for p in shape.pads], dtype=str),
        terms=np.array(shape.all_terms, dtype=np.int64).reshape(-1, 3),
        kept=np.array(shape.kept, dtype=bool),
    )


def _store(name: str, **arrays: np.ndarray) -> None:
    """Write ``arrays`` as the cache's file ``name`` (through a temporary file and an
    atomic rename: :func:`payload.safeio.replacing`), then keep the newest :data:`KEEP`
    files of its kind (the name up to the key; each change to the workbench's code keys
    new ones). A read-only or full cache writes nothing: derived again next time."""
    path = cache_dir() / name
    try:
        with replacing(path) as tmp:
            np.savez(tmp, **arrays)
        kind = name.rsplit("_", 1)[0]
        found = sorted(path.parent.glob(f"{kind}_*.npz"), key=lambda p: p.stat().st_mtime_ns)
        for old in found[:-KEEP]:
            old.unlink(missing_ok=True)
    except OSError:  # nothing written, or another process pruned them first
        pass


def postures_key(key: str, what: str, count: int) -> str:
    """The cache key of postures derived from a pair's shape (``key``: its
    :func:`shape_key`), e.g. the retargeting's seed table (``what``) of ``count``."""
    return hashlib.sha256(f"{key}\n{what}\n{count}".encode()).hexdigest()[:24]


def load_postures(key: str) -> np.ndarray | None:
    """The postures stored under ``key`` (:func:`postures_key`), or None."""
    try:
        with np.load(cache_dir() / f"pair_postures_{key}.npz") as z:
            qs = z["postures"]
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
        return None
    return qs if qs.ndim == 2 and qs.dtype == np.float64 else None


def store_postures(key: str, postures: np.ndarray) -> None:
    """Keep ``postures`` under ``key`` (best effort, as :func:`store_shape`)."""
    _store(f"pair_postures_{key}.npz", postures=np.asarray(postures, dtype=np.float64))


def solver_key(pk: PairKinematics, *settings: str) -> str | None:
    """The cache key of a pair's compiled retargeting solver (:func:`load_solver`): the
    pair's model (:func:`model_key`: its files, the workbench's sources, the packages'
    versions, the compiler) and ``settings`` (the compiler and flags the solver is built
    with, the solve's configuration, its symbol)."""
    return model_key(pk, _SOLVER_VERSION, *settings)


def load_solver(key: str) -> tuple[Path, list[int], list[int]] | None:
    """The compiled solver stored under ``key`` (:func:`store_solver`): its library and
    its inputs' and outputs' sizes, or None (none, unreadable, or its library gone)."""
    try:
        with np.load(cache_dir() / f"pair_solver_{key}.npz") as z:
            library = cache_dir() / str(z["library"])
            inputs = [int(k) for k in z["inputs"]]
            outputs = [int(k) for k in z["outputs"]]
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile):
        return None
    return (library, inputs, outputs) if library.is_file() else None


def store_solver(key: str, library: Path, inputs: list[int], outputs: list[int]) -> None:
    """Keep which library (in the cache's folder) is the solver keyed ``key``, and its
    inputs' and outputs' sizes (best effort, as :func:`store_shape`)."""
    if library.parent != cache_dir():
        return
    _store(
        f"pair_solver_{key}.npz",
        library=np.array(library.name),
        inputs=np.array(inputs, dtype=np.int64),
        outputs=np.array(outputs, dtype=np.int64),
    )


__all__ = [
    "KEEP",
    "MESH_LIBRARY",
    "CollisionShape",
    "load_postures",
    "load_shape",
    "load_solver",
    "model_key",
    "postures_key",
    "shape_key",
    "solver_key",
    "store_postures",
    "store_shape",
    "store_solver",
]
