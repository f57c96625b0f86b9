"""Which convex pieces overlap, compiled: the reach check's narrow phase.

The reach report asks one question of every sampled configuration: which pairs of bodies
touch. MuJoCo answers a wider one (every touching pair of pieces, with its penetration
depth and contact frame: MPR or EPA after the overlap is found), which is most of the
check's time. This module answers only the question asked, with the same poses (MuJoCo's
``mj_kinematics``) and the same convex sets (the hull of each piece's vertices, as MuJoCo
collides a mesh; a box's eight corners; a sphere's centre and radius):

1. each piece's world box (its local bounding box, rotated: ``|R| h``) rules out most
   pairs, the oriented boxes' 15 separating axes about half of the rest;
2. the remaining pairs go through GJK (Gilbert, Johnson, Keerthi 1988; the simplex's
   closest point by Voronoi regions, Ericson 2005, sec. 5.1, a face's through its
   normal): it stops as soon as a plane separates the two pieces (``v . w > 0``: apart),
   the simplex holds the origin or comes within :data:`TOUCH_TOLERANCE` of it (they
   touch), or stops getting closer (rounding, at a grazing contact: decided by
   :data:`STALL_TOLERANCE`);
3. a body pair is done at its first overlapping pair of pieces.

Compiled by Numba (IEEE arithmetic, no fast-math), cached on disk beside this module.
"""

from __future__ import annotations

import numba
import numpy as np

GJK_ITERATIONS = 64
"""Iterations before GJK gives up on a pair (it needs about 4 to 12 here); a pair still
undecided then is decided as a stalled one (:data:`STALL_TOLERANCE`)."""
TOUCH_TOLERANCE = 1e-9
"""The pieces touch when the simplex's point closest to the origin is this close [m]."""
STALL_TOLERANCE = 1e-7
"""When GJK stops getting closer (rounding, at a grazing contact: |v| does not shrink) no
plane along v has separated the pieces, and |v| bounds their distance from above; they
count as touching when it is under this [m]. MuJoCo's MPR stops at 1e-6 of its own
portal measure; the check's agreement with MuJoCo is tested (tests/test_reach.py)."""
_FLAT = 1e-24
"""A triangle is flat when |ab x ac|^2 is under this fraction of |ab|^2 |ac|^2 (the sine
of its angle at a under 1e-12)."""


@numba.njit(cache=True, error_model="numpy", inline="always")
def _support(
    verts: np.ndarray,
    a: int,
    n: int,
    rad: float,
    r: np.ndarray,
    p: np.ndarray,
    dx: float,
    dy: float,
    dz: float,
) -> tuple[float, float, float]:
    """The piece's world point furthest along (dx, dy, dz): the hull of vertices
    ``verts[a:a+n]`` (in the piece's frame; ``r`` its rotation, row-major 9, ``p`` its
    origin) grown by a ball of radius ``rad`` (a sphere is one vertex and its radius).
    Every vertex is tried: with 8 to 175 of them, twice as fast here as climbing the
    hull's vertex graph (measured)."""
    lx = r[0] * dx + r[3] * dy + r[6] * dz
    ly = r[1] * dx + r[4] * dy + r[7] * dz
    lz = r[2] * dx + r[5] * dy + r[8] * dz
    best = -np.inf
    k = a
    for i in range(a, a + n):
        sv = verts[i, 0] * lx + verts[i, 1] * ly + verts[i, 2] * lz
        if sv > best:
            best = sv
            k = i
    x, y, z = verts[k, 0], verts[k, 1], verts[k, 2]
    if rad > 0.0:
        f = rad / np.sqrt(lx * lx + ly * ly + lz * lz)
        x, y, z = x + f * lx, y + f * ly, z + f * lz
    return (
        p[0] + r[0] * x + r[1] * y + r[2] * z,
        p[1] + r[3] * x + r[4] * y + r[5] * z,
        p[2] + r[6] * x + r[7] * y + r[8] * z,
    )


@numba.njit(cache=True, error_model="numpy")
def _closest_triangle(s: np.ndarray, ia: int, ib: int, ic: int) -> tuple[float, float, float, int]:
    """The point of triangle (s[ia], s[ib], s[ic]) closest to the origin, and the vertices
    it needs (bit 1: a, 2: b, 4: c); Ericson (2005), ``ClosestPtPointTriangle``."""
    abx, aby, abz = s[ib, 0] - s[ia, 0], s[ib, 1] - s[ia, 1], s[ib, 2] - s[ia, 2]
    acx, acy, acz = s[ic, 0] - s[ia, 0], s[ic, 1] - s[ia, 1], s[ic, 2] - s[ia, 2]
    ax, ay, az = s[ia, 0], s[ia, 1], s[ia, 2]
    bx, by, bz = s[ib, 0], s[ib, 1], s[ib, 2]
    cx, cy, cz = s[ic, 0], s[ic, 1], s[ic, 2]
    d1 = -(abx * ax + aby * ay + abz * az)
    d2 = -(acx * ax + acy * ay + acz * az)
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az, 1
    d3 = -(abx * bx + aby * by + abz * bz)
    d4 = -(acx * bx + acy * by + acz * bz)
    if d3 >= 0.0 and d4 <= d3:
        return bx, by, bz, 2
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        t = d1 / (d1 - d3)
        return ax + t * abx, ay + t * aby, az + t * abz, 3
    d5 = -(abx * cx + aby * cy + abz * cz)
    d6 = -(acx * cx + acy * cy + acz * cz)
    if d6 >= 0.0 and d5 <= d6:
        return cx, cy, cz, 4
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        t = d2 / (d2 - d6)
        return ax + t * acx, ay + t * acy, az + t * acz, 5
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return bx + t * (cx - bx), by + t * (cy - by), bz + t * (cz - bz), 6
    # inside the face: the origin's projection on the triangle's plane (through the
    # normal, which keeps its precision on a sliver where the barycentric weights lose it)
    nx = aby * acz - abz * acy
    ny = abz * acx - abx * acz
    nz = abx * acy - aby * acx
    nn = nx * nx + ny * ny + nz * nz
    if nn <= _FLAT * (abx * abx + aby * aby + abz * abz) * (acx * acx + acy * acy + acz * acz):
        return _closest_flat(s, ia, ib, ic)  # a degenerate (flat) triangle: its best edge
    f = (nx * ax + ny * ay + nz * az) / nn
    return f * nx, f * ny, f * nz, 7


@numba.njit(cache=True, error_model="numpy")
def _closest_segment(s: np.ndarray, ia: int, ib: int) -> tuple[float, float, float, int]:
    """The point of segment (s[ia], s[ib]) closest to the origin, and the vertices it
    needs (bit 1: a, 2: b)."""
    ex, ey, ez = s[ib, 0] - s[ia, 0], s[ib, 1] - s[ia, 1], s[ib, 2] - s[ia, 2]
    ee = ex * ex + ey * ey + ez * ez
    t = -(s[ia, 0] * ex + s[ia, 1] * ey + s[ia, 2] * ez)
    if t <= 0.0 or ee == 0.0:
        return s[ia, 0], s[ia, 1], s[ia, 2], 1
    if t >= ee:
        return s[ib, 0], s[ib, 1], s[ib, 2], 2
    t = t / ee
    return s[ia, 0] + t * ex, s[ia, 1] + t * ey, s[ia, 2] + t * ez, 3


@numba.njit(cache=True, error_model="numpy")
def _closest_flat(s: np.ndarray, ia: int, ib: int, ic: int) -> tuple[float, float, float, int]:
    """The best of a flat triangle's three edges."""
    best = np.inf
    rx = ry = rz = 0.0
    rm = 0
    edges = ((ia, ib, 1, 2), (ia, ic, 1, 4), (ib, ic, 2, 4))
    for i, j, bi, bj in edges:
        x, y, z, m = _closest_segment(s, i, j)
        dd = x * x + y * y + z * z
        if dd < best:
            best = dd
            rx, ry, rz = x, y, z
            rm = (bi if m & 1 else 0) | (bj if m & 2 else 0)
    return rx, ry, rz, rm


@numba.njit(cache=True, error_model="numpy", inline="always")
def _outside(s: np.ndarray, ia: int, ib: int, ic: int, idd: int) -> int:
    """Whether the origin lies on the other side of plane (a, b, c) from d: 1 outside,
    0 inside, -1 the tetrahedron is flat."""
    abx, aby, abz = s[ib, 0] - s[ia, 0], s[ib, 1] - s[ia, 1], s[ib, 2] - s[ia, 2]
    acx, acy, acz = s[ic, 0] - s[ia, 0], s[ic, 1] - s[ia, 1], s[ic, 2] - s[ia, 2]
    nx = aby * acz - abz * acy
    ny = abz * acx - abx * acz
    nz = abx * acy - aby * acx
    sp = -(s[ia, 0] * nx + s[ia, 1] * ny + s[ia, 2] * nz)
    sd = (s[idd, 0] - s[ia, 0]) * nx + (s[idd, 1] - s[ia, 1]) * ny + (s[idd, 2] - s[ia, 2]) * nz
    if sd == 0.0:
        return -1
    return 1 if sp * sd < 0.0 else 0


@numba.njit(cache=True, error_model="numpy")
def _closest_tetrahedron(s: np.ndarray) -> tuple[float, float, float, int]:
    """The point of tetrahedron s[0:4] closest to the origin and the vertices it needs
    (bits 1, 2, 4, 8); mask 15 with the origin inside. Ericson (2005),
    ``ClosestPtPointTetrahedron``; a flat tetrahedron is tested through all four faces."""
    faces = ((0, 1, 2, 3), (0, 2, 3, 1), (0, 3, 1, 2), (1, 3, 2, 0))
    best = np.inf
    rx = ry = rz = 0.0
    rm = 15
    for ia, ib, ic, idd in faces:
        side = _outside(s, ia, ib, ic, idd)
        if side == 0:
            continue
        x, y, z, m = _closest_triangle(s, ia, ib, ic)
        dd = x * x + y * y + z * z
        if dd < best:
            best = dd
            rx, ry, rz = x, y, z
            rm = (1 << ia if m & 1 else 0) | (1 << ib if m & 2 else 0) | (1 << ic if m & 4 else 0)
    return rx, ry, rz, rm


@numba.njit(cache=True, error_model="numpy")
def overlap(
    verts: np.ndarray,
    a1: int,
    n1: int,
    rad1: float,
    r1: np.ndarray,
    p1: np.ndarray,
    a2: int,
    n2: int,
    rad2: float,
    r2: np.ndarray,
    p2: np.ndarray,
    vx: float,
    vy: float,
    vz: float,
    s: np.ndarray,
) -> bool:
    """Whether two convex pieces overlap (GJK on their Minkowski difference).

    Args:
        verts: Every piece's vertices in its own frame, shape (V, 3).
        a1, n1, rad1, r1, p1: First piece: the hull of its vertices ``verts[a1:a1+n1]``
            grown by ``rad1`` (0 for a polytope), its world rotation (row-major 9) and origin.
        a2, n2, rad2, r2, p2: Second piece.
        vx, vy, vz: A first guess of the direction from the second piece to the first.
        s: Scratch, shape (4, 3).

    Returns:
        True when they overlap: the simplex holds the origin or comes within
        :data:`TOUCH_TOLERANCE` of it, or GJK stops getting closer (or runs out of
        iterations) within :data:`STALL_TOLERANCE` with no separating plane found.
    """
    if vx == 0.0 and vy == 0.0 and vz == 0.0:
        vx = 1.0
    n = 0
    last = np.inf  # |v|^2 of the simplex before
    for _ in range(GJK_ITERATIONS):
        # w: the point of A - B furthest along -v
        ax, ay, az = _support(verts, a1, n1, rad1, r1, p1, -vx, -vy, -vz)
        bx, by, bz = _support(verts, a2, n2, rad2, r2, p2, vx, vy, vz)
        wx, wy, wz = ax - bx, ay - by, az - bz
        if vx * wx + vy * wy + vz * wz > 0.0:  # the plane through w normal to v
            return False  # separates A - B from the origin
        s[n, 0], s[n, 1], s[n, 2] = wx, wy, wz
        n += 1
        if n == 1:
            vx, vy, vz, mask = wx, wy, wz, 1
        elif n == 2:
            vx, vy, vz, mask = _closest_segment(s, 0, 1)
        elif n == 3:
            vx, vy, vz, mask = _closest_triangle(s, 0, 1, 2)
        else:
            vx, vy, vz, mask = _closest_tetrahedron(s)
            if mask == 15:
                return True
        vv = vx * vx + vy * vy + vz * vz
        if vv <= TOUCH_TOLERANCE * TOUCH_TOLERANCE:
            return True
        if vv >= last:  # no progress (rounding, at a grazing contact): no plane separates
            return vv <= STALL_TOLERANCE * STALL_TOLERANCE  # them along v; how close?
        last = vv
        k = 0  # keep the vertices the closest point needs, in order
        for i in range(n):
            if mask & (1 << i):
                if k != i:
                    s[k, 0], s[k, 1], s[k, 2] = s[i, 0], s[i, 1], s[i, 2]
                k += 1
        n = k
    return vx * vx + vy * vy + vz * vz <= STALL_TOLERANCE * STALL_TOLERANCE


@numba.njit(cache=True, error_model="numpy")
def _boxes_apart(
    r1: np.ndarray, p1: np.ndarray, c1: np.ndarray, h1: np.ndarray,
    r2: np.ndarray, p2: np.ndarray, c2: np.ndarray, h2: np.ndarray, scratch: np.ndarray,
) -> bool:  # fmt: skip
    """Whether two oriented boxes are apart: a separating axis among the 15 of two boxes
    (their faces' normals and the cross products of their edges; Gottschalk, Lin,
    Manocha 1996). Box k has centre ``c_k`` and half-sizes ``h_k`` in the frame of
    rotation ``r_k`` (row-major 9) and origin ``p_k``."""
    # the centres in the world, and the second box's axes and centre in the first's frame
    w1, w2, t = scratch[0, 0], scratch[0, 1], scratch[0, 2]
    rr, ar = scratch[1], scratch[2]
    for i in range(3):
        w1[i] = p1[i] + r1[3 * i] * c1[0] + r1[3 * i + 1] * c1[1] + r1[3 * i + 2] * c1[2]
        w2[i] = p2[i] + r2[3 * i] * c2[0] + r2[3 * i + 1] * c2[1] + r2[3 * i + 2] * c2[2]
    for i in range(3):
        t[i] = r1[i] * (w2[0] - w1[0]) + r1[3 + i] * (w2[1] - w1[1]) + r1[6 + i] * (w2[2] - w1[2])
        for j in range(3):
            rr[i, j] = r1[i] * r2[j] + r1[3 + i] * r2[3 + j] + r1[6 + i] * r2[6 + j]
            ar[i, j] = abs(rr[i, j]) + 1e-12
    for i in range(3):  # the first box's faces
        if abs(t[i]) > h1[i] + h2[0] * ar[i, 0] + h2[1] * ar[i, 1] + h2[2] * ar[i, 2]:
            return True
    for j in range(3):  # the second box's faces
        proj = t[0] * rr[0, j] + t[1] * rr[1, j] + t[2] * rr[2, j]
        if abs(proj) > h1[0] * ar[0, j] + h1[1] * ar[1, j] + h1[2] * ar[2, j] + h2[j]:
            return True
    for i in range(3):  # edge by edge
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for j in range(3):
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            lhs = abs(t[i2] * rr[i1, j] - t[i1] * rr[i2, j])
            rhs = h1[i1] * ar[i2, j] + h1[i2] * ar[i1, j] + h2[j1] * ar[i, j2] + h2[j2] * ar[i, j1]
            if lhs > rhs:
                return True
    return False


@numba.njit(cache=True, error_model="numpy")
def touching(
    xpos: np.ndarray,
    xmat: np.ndarray,
    verts: np.ndarray,
    vadr: np.ndarray,
    vnum: np.ndarray,
    radius: np.ndarray,
    box_c: np.ndarray,
    box_h: np.ndarray,
    pair_g1: np.ndarray,
    pair_g2: np.ndarray,
    group_start: np.ndarray,
) -> np.ndarray:
    """Which body pairs touch in each configuration.

    Args:
        xpos: Every piece's world origin per configuration, shape (n, G, 3).
        xmat: Its world rotation, row-major, shape (n, G, 9).
        verts, vadr, vnum: Every piece's vertices in its frame, shape (V, 3), and where its
            own start and how many.
        radius: Every piece's ball radius (a sphere's; 0 for a polytope), shape (G,).
        box_c, box_h: Every piece's bounding box in its frame: centre and half-sizes, (G, 3)
            (the ball included).
        pair_g1, pair_g2: The pieces that may touch, pair by pair, grouped by body pair.
        group_start: Where each body pair's pieces start in ``pair_g1``/``pair_g2``
            (length: body pairs + 1).

    Returns:
        Flags, shape (n, body pairs).
    """
    n, ng = xpos.shape[0], xpos.shape[1]
    ngroup = len(group_start) - 1
    out = np.zeros((n, ngroup), dtype=np.bool_)
    lo = np.empty((ng, 3))
    hi = np.empty((ng, 3))
    s = np.empty((4, 3))
    scratch = np.empty((3, 3, 3))
    for k in range(n):
        for g in range(ng):
            r = xmat[k, g]
            for i in range(3):
                c = xpos[k, g, i]
                h = 0.0
                for j in range(3):
                    c += r[3 * i + j] * box_c[g, j]
                    h += abs(r[3 * i + j]) * box_h[g, j]
                lo[g, i] = c - h
                hi[g, i] = c + h
        for grp in range(ngroup):
            for t in range(group_start[grp], group_start[grp + 1]):
                g1, g2 = pair_g1[t], pair_g2[t]
                if (
                    lo[g1, 0] > hi[g2, 0]
                    or lo[g2, 0] > hi[g1, 0]
                    or lo[g1, 1] > hi[g2, 1]
                    or lo[g2, 1] > hi[g1, 1]
                    or lo[g1, 2] > hi[g2, 2]
                    or lo[g2, 2] > hi[g1, 2]
                ):
                    continue
                if _boxes_apart(
                    xmat[k, g1], xpos[k, g1], box_c[g1], box_h[g1],
                    xmat[k, g2], xpos[k, g2], box_c[g2], box_h[g2], scratch,
                ):  # fmt: skip
                    continue
                vx = (lo[g1, 0] + hi[g1, 0] - lo[g2, 0] - hi[g2, 0]) * 0.5
                vy = (lo[g1, 1] + hi[g1, 1] - lo[g2, 1] - hi[g2, 1]) * 0.5
                vz = (lo[g1, 2] + hi[g1, 2] - lo[g2, 2] - hi[g2, 2]) * 0.5
                if overlap(
                    verts, vadr[g1], vnum[g1], radius[g1], xmat[k, g1], xpos[k, g1],
                    vadr[g2], vnum[g2], radius[g2], xmat[k, g2], xpos[k, g2],
                    vx, vy, vz, s,
                ):  # fmt: skip
                    out[k, grp] = True
                    break
    return out


def compile_check() -> None:
    """Compile :func:`touching` now, or load it from Numba's cache (setup runs this once,
    so that the first ``report reach`` does not spend 4 to 5 s compiling; the argument
    types are those :class:`payload.envelope.collisions.CollisionModel` passes)."""
    i = np.zeros(1, dtype=np.int64)
    f3 = np.zeros((1, 3))
    touching(
        np.zeros((0, 1, 3)), np.zeros((0, 1, 9)), f3, i, i + 1, np.zeros(1), f3, f3, i[:0].copy(),
        i[:0].copy(), i,
    )  # fmt: skip
