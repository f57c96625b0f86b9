"""The synthetic operator's tracked hand as compiled C, with numpy's bits.

Every control step the synthetic operator draws both hands: its tremor moves the wrist
(``amp sin(arg + phases)``), the parametric hand (:mod:`payload.teleop.handmodel`) gives
the 25 joints there, and the tracker's noise is added; the hand's aperture moves every
step, so the model's joints are worked out again each time: about twenty numpy calls on
small arrays a hand. Here they are one C call with the same operations in the same order
(the chains' cumulated angles and points as ``cumsum`` adds them, C's ``sin`` and ``cos``
where numpy's are called), checked against the numpy code on random hands when it is
built: where the C library's ``sin`` or ``cos`` rounds otherwise than numpy's, the check
fails and the numpy code runs.

The operator's hands are never rotated: the numpy code multiplies the model's joints by
the identity and adds the wrist; the C adds the wrist alone. That is the same number in
every bit wherever the wrist's coordinate is not zero (the product's nonzero entries are
exact, a zero entry of either sign plus a nonzero coordinate is that coordinate); a hand
whose wrist has a zero coordinate goes to the numpy code. Without a compiler or with
``PAYLOAD_NATIVE=0`` the numpy code runs.
"""

from __future__ import annotations

import ctypes
import logging
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from payload import native
from payload.teleop.hands import JOINTS_SHAPE

log = logging.getLogger(__name__)

CHAINS, PHALANGES, METACARPALS = 5, 3, 4
"""The hand model's planar chains (four fingers, then the thumb), the phalanges of each,
and the fingers' metacarpals: the shapes of :data:`TABLES` the C is written for."""

ZERO_WRIST_EVERY = 25
"""Every so many probes of the self-check (:func:`_probes`) has a wrist coordinate that
the tremor brings to zero exactly (a hand the C leaves to numpy)."""

TABLES: tuple[tuple[str, str], ...] = (
    ("origins", "float64"),
    ("lengths", "float64"),
    ("u", "float64"),
    ("v", "float64"),
    ("chain_rows", "int64"),
    ("metacarpals", "float64"),
    ("metacarpal_rows", "int64"),
    ("index_angles", "float64"),
    ("thumb_angles", "float64"),
    ("curl_shares", "float64"),
)
"""The hand model's tables the kernel reads (``struct tables`` of :data:`SOURCE`, in this
order): the chains' origins, phalanx lengths and flexion planes (chains, 3), the joint
rows their points fill (chains, phalanges + 1), the metacarpals (metacarpals, 3) and their
rows, the index's and the thumb's angle coefficients (phalanges, 2) and the curl's shares
(phalanges,)."""

_SIZES = {
    "N_JOINTS": JOINTS_SHAPE[0],
    "CHAINS": CHAINS,
    "PHALANGES": PHALANGES,
    "METACARPALS": METACARPALS,
}
"""The sizes the C is compiled with (its ``#define`` lines)."""

PRELUDE = "".join(f"#define {name} {value}\n" for name, value in _SIZES.items())
"""The sizes as the C's ``#define`` lines (what :data:`SOURCE` is compiled after)."""

DEFAULT_CURL = 0.6
"""How far the three fingers besides the index curl when nothing says otherwise (the hand
model's default ``curl``, the synthetic operator's held hands')."""

_SHAPES: dict[str, tuple[int, ...]] = {
    "origins": (CHAINS, 3),
    "lengths": (CHAINS, PHALANGES),
    "u": (CHAINS, 3),
    "v": (CHAINS, 3),
    "chain_rows": (CHAINS, PHALANGES + 1),
    "metacarpals": (METACARPALS, 3),
    "metacarpal_rows": (METACARPALS,),
    "index_angles": (PHALANGES, 2),
    "thumb_angles": (PHALANGES, 2),
    "curl_shares": (PHALANGES,),
}

SOURCE = r"""
#include <math.h>
#include <stdint.h>

struct tables {
    const double *origins, *lengths, *u, *v; const int64_t *chain_rows;
    const double *metacarpals; const int64_t *metacarpal_rows;
    const double *index_angles, *thumb_angles, *curl_shares;
};

/* handmodel.held_hand: joints (25, 3) = the model's joints at the wrist
   w + amp sin(arg + phases), unrotated, plus the noise (25, 3), written over the noise.
   1, nothing written, if a wrist coordinate is zero or not finite, or the size, aperture
   or curl not finite (the numpy code). */
/* the trembling wrist w + amp sin(arg + phases) into wrist, and whether payload_held_hand
   draws the hand there: 0 if a wrist coordinate is zero or not finite, or the size,
   aperture or curl not finite (the numpy code draws it) */
int payload_held_wrist(double size, double aperture, double curl, const double *w,
                       double amp, double arg, const double *phases, double *wrist)
{
    if (!isfinite(size) || !isfinite(aperture) || !isfinite(curl)) return 0;
    for (int k = 0; k < 3; k++) {
        wrist[k] = w[k] + amp * sin(arg + phases[k]);
        if (!(wrist[k] != 0.0) || !isfinite(wrist[k])) return 0;
    }
    return 1;
}

int payload_held_hand(const struct tables *h, double size, int left, double aperture,
                      double curl, const double *w, double amp, double arg,
                      const double *phases, double *noise)
{
    double wrist[3];
    if (!payload_held_wrist(size, aperture, curl, w, amp, arg, phases, wrist)) return 1;
    double m = (0.0 > aperture) ? 0.0 : aperture; /* Python max(aperture, 0.0) */
    double s = (1.0 < m) ? 1.0 : m;               /* Python min(m, 1.0) */
    double c = 1.0 - s;
    double angles[CHAINS][PHALANGES]; /* the index, three fingers' curl, the thumb */
    for (int j = 0; j < PHALANGES; j++) {
        angles[0][j] = h->index_angles[2 * j] - h->index_angles[2 * j + 1] * s;
        for (int r = 1; r < CHAINS - 1; r++) angles[r][j] = curl * h->curl_shares[j];
        angles[CHAINS - 1][j] = h->thumb_angles[2 * j] + h->thumb_angles[2 * j + 1] * c;
    }
    double out[N_JOINTS][3];
    for (int i = 0; i < N_JOINTS; i++) out[i][0] = out[i][1] = out[i][2] = 0.0;
    for (int r = 0; r < METACARPALS; r++)
        for (int k = 0; k < 3; k++) out[h->metacarpal_rows[r]][k] = h->metacarpals[3 * r + k];
    for (int r = 0; r < CHAINS; r++) {
        const int64_t *rows = h->chain_rows + (PHALANGES + 1) * r;
        double cum = 0.0, p[3];
        for (int k = 0; k < 3; k++) p[k] = h->origins[3 * r + k];
        for (int k = 0; k < 3; k++) out[rows[0]][k] = p[k];
        for (int j = 0; j < PHALANGES; j++) {
            cum = (j == 0) ? angles[r][0] : cum + angles[r][j]; /* cumsum */
            double cs = cos(cum), sn = sin(cum), len = h->lengths[PHALANGES * r + j];
            for (int k = 0; k < 3; k++) {
                p[k] = p[k] + len * (cs * h->u[3 * r + k] + sn * h->v[3 * r + k]);
                out[rows[j + 1]][k] = p[k];
            }
        }
    }
    for (int i = 0; i < N_JOINTS; i++) {
        for (int k = 0; k < 3; k++) out[i][k] *= size;
        if (left) out[i][1] *= -1.0;
        for (int k = 0; k < 3; k++) noise[3 * i + k] = (out[i][k] + wrist[k]) + noise[3 * i + k];
    }
    return 0;
}
"""
"""The kernel's C (:func:`payload.native.build_library` compiles it)."""

_P, _D = ctypes.c_void_p, ctypes.c_double


class _Tables(ctypes.Structure):
    _fields_ = [(name, _P) for name, _ in TABLES]


class CompiledHeldHand:
    """``held_hand`` of :mod:`payload.teleop.handmodel`, compiled.

    Args:
        lib: The kernel's library (:data:`SOURCE`).
        tables: The hand model's tables by name (:data:`TABLES`).
    """

    def __init__(self, lib: ctypes.CDLL, tables: Mapping[str, np.ndarray]) -> None:
        self._keep = [np.ascontiguousarray(tables[name], dtype=kind) for name, kind in TABLES]
        for (name, _), a in zip(TABLES, self._keep):
            if a.shape != _SHAPES[name]:
                raise ValueError(f"the hand model's {name} are {a.shape}, not {_SHAPES[name]}")
        rows = np.concatenate([self._keep[4].ravel(), self._keep[6]])
        if rows.min() < 0 or rows.max() >= JOINTS_SHAPE[0]:
            raise ValueError("the hand model's rows are not joints")
        self._tables = _Tables(*(a.ctypes.data for a in self._keep))
        fn = lib.payload_held_hand
        fn.restype = ctypes.c_int
        fn.argtypes = [_P, _D, ctypes.c_int, _D, _D, _P, _D, _D, _P, _P]
        self._fn = fn
        self._addr = ctypes.addressof(self._tables)

    @property
    def tables_address(self) -> int:
        """The address of the tables' ``struct tables`` (kept while this object lives)."""
        return self._addr

    def __call__(
        self,
        left: bool,
        size: float,
        aperture: float,
        curl: float,
        wrist: np.ndarray,
        amp: float,
        arg: float,
        phases: np.ndarray,
        noise: np.ndarray,
    ) -> np.ndarray | None:
        """The hand's joints, written over ``noise`` (a float64 (25, 3) array of this
        call's own) and returned, or None (nothing written: the numpy code is to run)."""
        if not (takes_vector(wrist) and takes_vector(phases)):
            return None
        if not (noise.dtype == np.float64 and noise.shape == JOINTS_SHAPE):
            return None
        if not noise.flags.c_contiguous or not noise.flags.writeable:
            return None
        if self._fn(
            self._addr, size, left, aperture, curl, wrist.ctypes.data, amp, arg,
            phases.ctypes.data, noise.ctypes.data,
        ):  # fmt: skip
            return None
        return noise


def takes_vector(a: Any) -> bool:
    """Whether the compiled held hand reads ``a`` (a wrist or the tremor's phases) as it is:
    a C-ordered float64 numpy array of 3 (anything else goes to the numpy code)."""
    return (
        type(a) is np.ndarray and a.dtype == np.float64 and a.shape == (3,) and a.flags.c_contiguous
    )


def tremulous_wrist(wrist: np.ndarray, amp: float, arg: float, phases: np.ndarray) -> np.ndarray:
    """The operator's wrist with its tremor: ``wrist + amp sin(arg + phases)`` (numpy)."""
    return wrist + amp * np.sin(arg + phases)


CHECK_HANDS = 400
"""Random hands of the kernel's full self-check (:func:`compiled_held_hand`)."""


def _probes(n: int) -> list[tuple[Any, ...]]:
    """``n`` random argument lists of ``held_hand`` (sides, sizes, apertures inside and
    beyond [0, 1], curls, wrists, tremors, noise); every :data:`ZERO_WRIST_EVERY`-th with
    a wrist coordinate that the tremor brings to zero (the numpy code's)."""
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        phases = rng.uniform(0.0, 2 * np.pi, size=3)
        amp, arg = float(rng.uniform(0.0, 0.004)), float(rng.uniform(0.0, 3000.0))
        wrist = rng.normal(scale=0.5, size=3)
        if i % ZERO_WRIST_EVERY == ZERO_WRIST_EVERY - 1:
            wrist[i % 3] = 0.0
            wrist[i % 3] = -tremulous_wrist(wrist, amp, arg, phases)[i % 3]
        aperture = float(rng.uniform(-0.2, 1.2)) if i % 7 else float(i % 2)
        curl = DEFAULT_CURL if i % 3 else float(rng.uniform(0.0, 1.2))
        noise = rng.normal(0.0, 0.002, size=JOINTS_SHAPE)
        left, size = bool(i % 2), float(rng.uniform(0.7, 1.3))
        out.append((left, size, aperture, curl, wrist, amp, arg, phases, noise))
    return out


@native.reported("held hand")
def compiled_held_hand(
    tables: Mapping[str, np.ndarray], reference: Callable[..., np.ndarray]
) -> CompiledHeldHand | None:
    """The compiled ``held_hand`` of the hand model whose ``tables`` are given, or None to
    run ``reference`` (the numpy code, called with the kernel's arguments): no compiler,
    ``PAYLOAD_NATIVE=0``, a failed build, or a self-check on :data:`CHECK_HANDS` random
    hands (their first tenth once a full check passed, here or in an earlier process:
    :func:`payload.native.probes`) whose joints differ from ``reference``'s in a single bit,
    or that it leaves to the numpy code though the wrist has no zero coordinate."""
    lib = native.load_kernel(
        "held_hand", SOURCE, "the held hand kernel", log,
        prelude=PRELUDE,
    )  # fmt: skip
    if lib is None:
        return None
    try:
        kernel = CompiledHeldHand(lib, tables)
    except ValueError as exc:
        log.warning("held hand: numpy (%s)", exc)
        return None

    def same(args: tuple[Any, ...]) -> bool:  # refused only with a wrist coordinate zero
        got = kernel(*args[:-1], args[-1].copy())
        if got is None:
            return not bool(np.all(tremulous_wrist(*args[4:8]) != 0.0))
        return got.tobytes() == reference(*args[:-1], args[-1].copy()).tobytes()

    def check(n: int) -> bool:
        return all(same(args) for args in _probes(n))

    if not native.self_checked(lib, "held hand", CHECK_HANDS, check):
        log.warning("held hand: numpy (the compiled hand differs)")
        return None
    return kernel


__all__ = [
    "CHAINS",
    "CHECK_HANDS",
    "DEFAULT_CURL",
    "METACARPALS",
    "PHALANGES",
    "PRELUDE",
    "SOURCE",
    "TABLES",
    "ZERO_WRIST_EVERY",
    "CompiledHeldHand",
    "compiled_held_hand",
    "takes_vector",
    "tremulous_wrist",
]
