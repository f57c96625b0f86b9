"""The per-step reading of MuJoCo's contact list as compiled C.

Two readers go through the contacts after every control step while the payload holds the
CTB: :meth:`ContactMonitor.touching <payload.sim.contact.ContactMonitor.touching>` (which
fingertips touch the CTB) and :meth:`StationMonitor.read
<payload.sim.station.StationMonitor.read>` (whether the vehicle or the payload touches the
station). In numpy each is about ten calls on the contact list's fields (new views every
step: the list lives in MuJoCo's arena). Here each is one C call that reads the list
through MuJoCo's own ``mjData`` struct (compiled against the headers MuJoCo's Python
package ships, keyed by its version):

* the same fields (``geom`` for the fingertips, ``geom1``/``geom2`` for the station) and
  the same test (``dist <= 0``, false for NaN);
* a negative geom id (a flex contact) wraps to the last geom, as numpy's indexing does.

:func:`compiled_contacts` checks the kernel against the numpy readers on the data's own
contact list rewritten with random geom pairs and distances (and restored) when it is
built, which is at the first step with contacts; without MuJoCo's headers or a C compiler,
with ``PAYLOAD_NATIVE=0``, or on a single different answer, the numpy code runs.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from payload import native

log = logging.getLogger(__name__)

SOURCE = r"""
#include <mujoco/mujoco.h>

static int64_t wrap(int64_t g, int64_t n) { return g < 0 ? g + n : g; }

/* bit k set when a contact with dist <= 0 pairs geoms whose pair_finger (n x n) is k */
int64_t payload_touching(const mjData *d, const int64_t *pair_finger, int64_t n)
{
    int64_t bits = 0;
    for (int i = 0; i < d->ncon; i++) {
        const mjContact *c = d->contact + i;
        if (!(c->dist <= 0.0)) continue;
        int64_t k = pair_finger[wrap(c->geom[0], n) * n + wrap(c->geom[1], n)];
        if (k >= 0) bits |= (int64_t)1 << k;
    }
    return bits;
}

/* 1 when a contact with dist <= 0 pairs a station geom with a moving one */
int payload_station_contact(const mjData *d, const unsigned char *station,
                            const unsigned char *moving, int64_t n)
{
    for (int i = 0; i < d->ncon; i++) {
        const mjContact *c = d->contact + i;
        int64_t a = wrap(c->geom1, n), b = wrap(c->geom2, n);
        if (((station[a] & moving[b]) | (station[b] & moving[a])) && c->dist <= 0.0) return 1;
    }
    return 0;
}
"""


def _load() -> ctypes.CDLL | None:
    headers = native.mujoco_headers()
    if headers is None:
        return None
    return native.load_kernel(
        "contacts", SOURCE, "the contacts kernel", log, key_parts=(headers[1],),
        include_dirs=(headers[0],),
    )  # fmt: skip


class CompiledTouching:
    """Which fingertips touch the CTB, for one model's pair table (any data of it).

    Args:
        lib: The kernel's library.
        pair_finger: (ngeom, ngeom) int64: the finger (index) a geom pair's contact counts
            for, -1 for none.
    """

    def __init__(self, lib: ctypes.CDLL, pair_finger: np.ndarray) -> None:
        n = len(pair_finger)
        if pair_finger.shape != (n, n):
            raise ValueError("the pair table is not square")
        self._table = np.ascontiguousarray(pair_finger, dtype=np.int64)
        fn = lib.payload_touching
        fn.restype, fn.argtypes = ctypes.c_int64, [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64]
        table = self._table.ctypes.data
        self._fn = lambda address: fn(address, table, n)

    def __call__(self, data: Any) -> int:
        """The touching fingers' bits (bit k: finger k)."""
        return self._fn(data._address)


class CompiledStationContact:
    """Whether a station geom and a moving one touch, for one model's tables.

    Args:
        lib: The kernel's library.
        is_station, is_moving: (ngeom,) bool: the station's geoms and the moving ones.
    """

    def __init__(self, lib: ctypes.CDLL, is_station: np.ndarray, is_moving: np.ndarray) -> None:
        n = len(is_station)
        if is_moving.shape != (n,):
            raise ValueError("the station and moving tables differ in size")
        self._tables = (
            np.ascontiguousarray(is_station, dtype=np.bool_),
            np.ascontiguousarray(is_moving, dtype=np.bool_),
        )
        fn = lib.payload_station_contact
        ptr = ctypes.c_void_p
        fn.restype, fn.argtypes = ctypes.c_int, [ptr, ptr, ptr, ctypes.c_int64]
        st, mv = (a.ctypes.data for a in self._tables)
        self._fn = lambda address: fn(address, st, mv, n)

    def __call__(self, data: Any) -> bool:
        return bool(self._fn(data._address))


def _rewritten_contacts(
    data: Any, rng: np.random.Generator, geoms: np.ndarray, probes: int
) -> Iterator[None]:
    """Yield ``probes`` times with the data's contact list rewritten (random pairs among
    ``geoms``, now and then any geom or -1, random distances of both signs, some zero or
    NaN, in every fourth all apart but at most one); restore it afterwards."""
    con = data.contact
    saved = (con.geom.copy(), con.geom1.copy(), con.geom2.copy(), con.dist.copy())
    n, ngeom = len(saved[3]), int(geoms.max()) + 1
    try:
        for k in range(probes):
            pairs = rng.choice(geoms, size=(n, 2))
            if k % 5 == 1:
                pairs[rng.integers(n), rng.integers(2)] = rng.integers(-1, ngeom)
            dist = rng.normal(scale=1e-3, size=n)
            dist[rng.random(n) < 0.1] = (0.0, -0.0, np.nan)[k % 3]
            if k % 4 == 3:  # all apart but at most one: a long list need not answer yes
                dist = np.abs(dist) + 1e-9
                dist[rng.integers(n)] *= (1.0, -1.0)[k % 8 == 3]
            con.geom[:] = pairs
            con.geom1[:], con.geom2[:] = (pairs[:, ::-1] if k % 2 else pairs).T
            con.dist[:] = dist
            yield
    finally:
        con.geom[:], con.geom1[:], con.geom2[:], con.dist[:] = saved


def _made(make: Callable[[ctypes.CDLL], Any], what: str) -> Any:
    """``make(library)``, or None: no library, or tables it refuses (said on the log)."""
    lib = _load()
    if lib is None:
        return None
    try:
        return make(lib)
    except ValueError as exc:
        log.warning("%s: numpy (%s)", what, exc)
        return None


def _checked(kernel: Any, data: Any, reference: Callable[[Any], Any], geoms: np.ndarray,
             what: str) -> Any:  # fmt: skip
    """``kernel`` if it answers as ``reference`` on the data's rewritten contact list (and
    gives more than one answer), else None."""
    answers = set()
    # closed on leaving, an exception included: the data's own contact list comes back
    with contextlib.closing(
        _rewritten_contacts(data, np.random.default_rng(0), geoms, 300)
    ) as probes:
        for _ in probes:
            mine = kernel(data)
            if mine != reference(data):
                log.warning("%s: numpy (the compiled reader differs)", what)
                return None
            answers.add(mine)
    if len(answers) < 2:  # pragma: no cover - the probes give both answers
        log.warning("%s: numpy (the self-check saw one answer only)", what)
        return None
    return kernel


@native.reported("fingertip contacts")
def compiled_touching(
    data: Any, pair_finger: np.ndarray, reference: Callable[[Any], int]
) -> CompiledTouching | None:
    """The compiled fingertip reader, or None for ``reference(data)`` (the numpy bits of
    :meth:`~payload.sim.contact.ContactMonitor.touching`): no MuJoCo headers, no
    compiler, ``PAYLOAD_NATIVE=0``, a failed build, or a self-check on ``data``'s contact
    list (the callers build it at the first step with contacts), rewritten, that answers
    otherwise."""
    kernel = _made(lambda lib: CompiledTouching(lib, pair_finger), "fingertip contacts")
    if kernel is None:
        return None
    tips = np.flatnonzero((pair_finger >= 0).any(axis=1))
    rest = np.random.default_rng(1).integers(0, len(pair_finger), size=4)
    return _checked(kernel, data, reference, np.concatenate([tips, rest]), "fingertip contacts")


@native.reported("station contacts")
def compiled_station_contact(
    data: Any, is_station: np.ndarray, is_moving: np.ndarray, reference: Callable[[Any], bool]
) -> CompiledStationContact | None:
    """The compiled station-contact reader, or None for ``reference(data)`` (the numpy
    test of :meth:`~payload.sim.station.StationMonitor.read`): as
    :func:`compiled_touching`."""
    kernel = _made(
        lambda lib: CompiledStationContact(lib, is_station, is_moving), "station contacts"
    )
    if kernel is None:
        return None
    rng = np.random.default_rng(1)
    geoms = np.concatenate([
        rng.choice(np.flatnonzero(is_station), size=8), np.flatnonzero(is_moving),
        rng.integers(0, len(is_station), size=4),
    ])  # fmt: skip
    return _checked(kernel, data, reference, geoms, "station contacts")


__all__ = [
    "SOURCE",
    "CompiledStationContact",
    "CompiledTouching",
    "compiled_station_contact",
    "compiled_touching",
]
