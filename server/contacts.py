"""Per-user contact geometry on the current surface (DESIGN section 6).

Pure functions, run once per simulation tick for every user:

- :func:`closest_point`: the point of the *current* deformed surface nearest to a probe, the
  outward normal there and the signed penetration (paper section 6, Step 1: "the local model is
  calculated ... using the current surface configuration of the deformable object, as if it was
  static"): where a probe that is not yet in contact meets the surface.
- :func:`track_proxy`: a proxy in contact that *follows* the surface (god-object: Zilles and
  Salisbury 1995; Ruspini, Kolarov and Khatib 1997): from where it was, carried by the surface's
  deformation, it slides along the current surface down the distance to the probe and stops at
  the first local minimum; it never jumps to a nearer point on another part of the object (the
  far side of a thin part, the other wall of a crease). The paper's closing section names this
  step; :func:`segment_entry` is where a probe that moved from outside to inside crossed the
  surface, where such a proxy starts.
- :func:`fit_plane`, :func:`fit_sphere`: the local model's geometric primitive (Adachi et al.
  1995, Balaniuk 1999) as :mod:`shared.primitives` objects.

Multipoint stability (the coupled slow loop of several contacts and the ``K_o_eff`` the server
reports per contact) is :mod:`server.contact_stiffness`.

Closest-point search without rebuilding a spatial index each tick: vertices move by at most
``W = max |current - rest|``, so a ball query on a KD-tree of the *rest* face centroids, built
once, bounds the candidate faces exactly; the exact point-triangle distance is then taken over
the few faces whose bounds can still hold the minimum.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from haptic_collab.shared.primitives import (
    MAX_RADIUS_M,
    MIN_RADIUS_M,
    Plane,
    Sphere,
    make_plane,
    make_sphere,
)
from haptic_collab.shared.types import FloatArray, IntArray

#: A fitted sphere larger than this [m] is rendered as a plane (nearly flat surface).
FLAT_RADIUS_M = 2.0


@dataclass(frozen=True, slots=True)
class SurfaceIndex:
    """Topology and rest-state search structures of a triangle mesh, built once.

    Attributes
    ----------
    rest_vertices : (n, 3) float64 [m]
    faces : (m, 3) int64
    tree : scipy.spatial.cKDTree over ``rest_vertices``
    face_tree : scipy.spatial.cKDTree over the rest face centroids
    vf_indptr, vf_faces : CSR vertex-to-incident-faces map, (n + 1,) and (3m,) int64
    max_rest_edge_m : float, longest rest edge [m]
    max_rest_face_radius_m : float, largest rest centroid-to-vertex distance [m]
    """

    rest_vertices: FloatArray
    faces: IntArray
    tree: cKDTree
    face_tree: cKDTree
    vf_indptr: IntArray
    vf_faces: IntArray
    max_rest_edge_m: float
    max_rest_face_radius_m: float

    @classmethod
    def build(cls, rest_vertices: npt.ArrayLike, faces: npt.ArrayLike) -> SurfaceIndex:
        """Index a mesh: ``rest_vertices`` (n, 3) [m], ``faces`` (m, 3) int.

        Raises
        ------
        ValueError
            Wrong shapes, no faces, non-finite vertices or face indices out of range.
        """
        v = np.ascontiguousarray(rest_vertices, dtype=np.float64)
        f = np.ascontiguousarray(faces, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise ValueError("rest_vertices must be (n, 3) and faces (m, 3) with m > 0")
        if not np.all(np.isfinite(v)):
            raise ValueError("rest_vertices must be finite")
        if f.min() < 0 or f.max() >= len(v):
            raise ValueError("face indices out of range")
        flat = f.ravel()
        order = np.argsort(flat, kind="stable")
        vf_faces = (order // 3).astype(np.int64)
        counts = np.bincount(flat, minlength=len(v))
        vf_indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        edges = np.concatenate(
            [v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 1]], v[f[:, 0]] - v[f[:, 2]]]
        )
        max_edge = float(np.sqrt(np.max(_rowdot(edges, edges))))
        tri = v[f]
        centroids = tri.mean(axis=1)
        spread = tri - centroids[:, None, :]
        face_radius = float(np.sqrt(np.max(np.einsum("kij,kij->ki", spread, spread))))
        return cls(v, f, cKDTree(v), cKDTree(centroids), vf_indptr, vf_faces, max_edge, face_radius)


@dataclass(frozen=True, slots=True)
class SurfacePoint:
    """The current surface near a probe.

    Attributes
    ----------
    point : (3,) float64 [m]
        Closest surface point (the proxy x_o).
    normal : (3,) float64
        Outward unit normal there (interpolated vertex normals of the current surface).
    penetration_m : float
        Signed depth of the probe past the surface [m]: positive inside, negative outside.
    face : int
        Index of the face holding ``point``.
    bary : (3,) float64 or None
        Barycentric coordinates of ``point`` in ``face``: the material point of the surface that
        the proxy sits on, which the next tick's deformation carries along (:func:`track_proxy`).
    """

    point: FloatArray
    normal: FloatArray
    penetration_m: float
    face: int
    bary: FloatArray | None = None


#: sin^2 of the smallest angle a triangle may have to be projected on (else: its edges).
_FLAT_SIN2 = 1e-12


def _closest_on_triangles(
    p: FloatArray, a: FloatArray, b: FloatArray, c: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Closest points on triangles (a, b, c), each (k, 3), to the point p (3,).

    The projection onto the triangle's plane when it falls inside, else the closest of the three
    edge points (clamped segment projections).

    Returns
    -------
    points : (k, 3) float64
    bary : (k, 3) float64 barycentric coordinates of the points w.r.t. (a, b, c)
    """
    k = len(a)
    ab, ac, ap = b - a, c - a, p - a
    d00 = _rowdot(ab, ab)
    d01 = _rowdot(ab, ac)
    d11 = _rowdot(ac, ac)
    d1 = _rowdot(ab, ap)
    d2 = _rowdot(ac, ap)
    den = d00 * d11 - d01 * d01
    # den = |ab|^2 |ac|^2 sin^2(angle at a): a triangle flatter than a microradian (a face squashed
    # flat by the deformation: its vertices in a line) has no interior to project on; rounding
    # left den slightly positive there and the "projection" could land centimetres away. Its
    # closest point is on an edge.
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        v = (d11 * d1 - d01 * d2) / den
        w = (d00 * d2 - d01 * d1) / den
        inside = (v >= 0.0) & (w >= 0.0) & (v + w <= 1.0) & (den > _FLAT_SIN2 * d00 * d11)
    # edges a->b, b->c, c->a as one (3k, 3) batch of segments
    start = np.concatenate([a, b, c])
    edge = np.concatenate([ab, c - b, a - c])
    e2 = _rowdot(edge, edge)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = _rowdot(p - start, edge) / e2
    t = np.clip(np.where(e2 > 0.0, t, 0.0), 0.0, 1.0)
    on_edge = start + t[:, None] * edge
    gap = on_edge - p
    best = np.argmin(_rowdot(gap, gap).reshape(3, k), axis=0)
    rows = best * k + np.arange(k)
    points = on_edge[rows]
    t_best = t[rows]
    bary = np.zeros((k, 3))
    cols = np.arange(k)
    # edge j runs from vertex j to vertex (j + 1) % 3
    bary[cols, best] = 1.0 - t_best
    bary[cols, (best + 1) % 3] = t_best
    if inside.any():
        vi, wi = v[inside], w[inside]
        points[inside] = a[inside] + vi[:, None] * ab[inside] + wi[:, None] * ac[inside]
        bary[inside] = np.stack([1.0 - vi - wi, vi, wi], axis=1)
    return points, bary


def _closest_on_triangle(
    p: Sequence[float], a: Sequence[float], b: Sequence[float], c: Sequence[float]
) -> tuple[tuple[float, float, float], tuple[float, float, float], float]:
    """:func:`_closest_on_triangles` for one triangle, in plain floats.

    A proxy that follows the surface tests one face, then the few around an edge or a vertex, a
    few times per user per tick: on so few faces numpy's per-call overhead is most of the cost.
    The same arithmetic in the same order (and the same first minimum among the edges), so the
    same numbers.

    Parameters
    ----------
    p, a, b, c : sequences of 3 floats [m]
        The point and the triangle's corners.

    Returns
    -------
    point : tuple of 3 floats [m]
    bary : tuple of 3 floats, barycentric coordinates of ``point`` w.r.t. (a, b, c)
    dist2 : float, squared distance [m^2] from ``p`` to ``point``
    """
    px, py, pz = p
    ax, ay, az = a
    bx, by, bz = b
    cx, cy, cz = c
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d00 = abx * abx + aby * aby + abz * abz
    d01 = abx * acx + aby * acy + abz * acz
    d11 = acx * acx + acy * acy + acz * acz
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    den = d00 * d11 - d01 * d01
    if den > _FLAT_SIN2 * d00 * d11:  # den > 0: a triangle with an interior to project on
        v = (d11 * d1 - d01 * d2) / den
        w = (d00 * d2 - d01 * d1) / den
        if v >= 0.0 and w >= 0.0 and v + w <= 1.0:
            qx = ax + v * abx + w * acx
            qy = ay + v * aby + w * acy
            qz = az + v * abz + w * acz
            gx, gy, gz = qx - px, qy - py, qz - pz
            return (qx, qy, qz), (1.0 - v - w, v, w), gx * gx + gy * gy + gz * gz
    # the edges a->b, b->c, c->a: the first of the nearest clamped projections
    best, best_g2, best_t, best_q = -1, math.inf, 0.0, (ax, ay, az)
    for j, (sx, sy, sz, ex, ey, ez) in enumerate(
        (
            (ax, ay, az, abx, aby, abz),
            (bx, by, bz, cx - bx, cy - by, cz - bz),
            (cx, cy, cz, ax - cx, ay - cy, az - cz),
        )
    ):
        e2 = ex * ex + ey * ey + ez * ez
        t = ((px - sx) * ex + (py - sy) * ey + (pz - sz) * ez) / e2 if e2 > 0.0 else 0.0
        t = 0.0 if t < 0.0 else 1.0 if t > 1.0 else t
        qx, qy, qz = sx + t * ex, sy + t * ey, sz + t * ez
        gx, gy, gz = qx - px, qy - py, qz - pz
        g2 = gx * gx + gy * gy + gz * gz
        if best < 0 or g2 < best_g2:
            best, best_g2, best_t, best_q = j, g2, t, (qx, qy, qz)
    wts = [0.0, 0.0, 0.0]
    wts[best] = 1.0 - best_t
    wts[(best + 1) % 3] = best_t
    return best_q, (wts[0], wts[1], wts[2]), best_g2


def _rowdot(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise dot product (k,) of (k, 3) arrays (cheaper than einsum for small k)."""
    return np.asarray((a * b).sum(axis=1), dtype=np.float64)


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    """Row-wise cross product of (k, 3) arrays (cheaper than np.cross for small k)."""
    out = np.empty_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _vertex_normals(index: SurfaceIndex, vertices: FloatArray, ids: IntArray) -> FloatArray:
    """Area-weighted outward unit normals (k, 3) of the current surface at vertices ``ids``."""
    starts = index.vf_indptr[ids]
    counts = index.vf_indptr[ids + 1] - starts
    group_start = np.concatenate([[0], counts.cumsum()[:-1]])
    total = int(counts.sum())
    gather = (starts - group_start).repeat(counts) + np.arange(total)
    fs = index.faces[index.vf_faces[gather]]
    p0 = vertices[fs[:, 0]]
    fn = _cross(vertices[fs[:, 1]] - p0, vertices[fs[:, 2]] - p0)
    sums = np.add.reduceat(fn, group_start, axis=0)
    lengths = np.sqrt(_rowdot(sums, sums))
    safe = lengths > 0.0
    sums[safe] /= lengths[safe, None]
    sums[~safe] = (0.0, 0.0, 1.0)
    return sums


def closest_point(
    index: SurfaceIndex,
    vertices: npt.ArrayLike,
    probe: npt.ArrayLike,
    displacement_bound_m: float,
) -> SurfacePoint:
    """Closest point of the current surface to ``probe``, outward normal, signed penetration.

    Exact over the mesh: every face that could hold the minimum is tested. Cost: one KD-tree
    query and one ball query on the rest face centroids, vectorized bounds on the faces within
    about ``d + 3 * displacement_bound_m`` of the probe, and an exact point-triangle test on the
    few faces whose bounds can still hold the minimum.

    Parameters
    ----------
    index : SurfaceIndex
        Built once from the rest mesh.
    vertices : (n, 3) float [m]
        Current vertex positions (same topology as the index).
    probe : (3,) float [m]
        Haptic interface point x_h.
    displacement_bound_m : float
        An upper bound [m] on ``|vertices - index.rest_vertices|`` (e.g. max |w|).

    Returns
    -------
    SurfacePoint
        ``penetration_m`` > 0 when the probe is inside the object (sign from the interpolated
        vertex normal at the closest point, a pseudo-normal that is exact on smooth regions).

    Raises
    ------
    ValueError
        ``probe`` not 3 finite numbers, or a negative/non-finite ``displacement_bound_m``.
    """
    p = np.asarray(probe, dtype=np.float64)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise ValueError(f"probe must be 3 finite numbers [m], got {probe!r}")
    bound = float(displacement_bound_m)
    if not (math.isfinite(bound) and bound >= 0.0):
        raise ValueError(
            f"displacement_bound_m must be finite and >= 0, got {displacement_bound_m!r}"
        )
    cur = np.asarray(vertices, dtype=np.float64)

    # Each face contains its centroid g and lies within its radius rc of it, so
    # |p - g| - rc <= dist(p, face) <= |p - g|. Centroids move by at most W and radii grow by at
    # most 2W from rest, so every face that can hold the minimum has its rest centroid within
    # ub + rc_max + 3W of p, ub being any face's |p - g| (here: the nearest rest centroid's).
    _, f0 = index.face_tree.query(p)
    g0 = cur[index.faces[int(f0)]].mean(axis=0) - p
    ub0 = math.sqrt(float(g0 @ g0))
    radius = ub0 + index.max_rest_face_radius_m + 3.0 * bound + 1e-12
    fids = np.asarray(
        index.face_tree.query_ball_point(p, radius, return_sorted=False), dtype=np.int64
    )
    if len(fids) == 0:
        fids = np.asarray([int(f0)], dtype=np.int64)
    tri = cur[index.faces[fids]]  # (k, 3, 3)
    g = tri.mean(axis=1)
    spread = tri - g[:, None, :]
    rc = np.sqrt(np.max(np.einsum("kij,kij->ki", spread, spread), axis=1))
    dg = g - p
    dist_g = np.sqrt(_rowdot(dg, dg))
    sel = (dist_g - rc) <= dist_g.min()
    fids, tri = fids[sel], tri[sel]
    q, bary_all = _closest_on_triangles(p, tri[:, 0], tri[:, 1], tri[:, 2])
    dq = q - p
    dist2 = _rowdot(dq, dq)
    j = int(np.argmin(dist2))
    return _surface_point(index, cur, p, int(fids[j]), q[j], bary_all[j], float(dist2[j]))


def surface_normal(
    index: SurfaceIndex, vertices: FloatArray, face: int, bary: FloatArray
) -> FloatArray:
    """Outward unit normal (3,) float64 of the surface ``vertices`` (n, 3) [m] at barycentric
    ``bary`` (3,) in ``face``: the interpolated vertex normals (a pseudo-normal exact on smooth
    regions), the face's own where they cancel, +z for a degenerate face."""
    tri = index.faces[face]
    normal = bary @ _vertex_normals(index, vertices, tri)
    length = math.sqrt(float(normal @ normal))
    if length < 1e-12:
        a, b, c = vertices[tri]
        normal = _cross((b - a)[None, :], (c - a)[None, :])[0]
        length = math.sqrt(float(normal @ normal))
    return normal / length if length > 0.0 else np.array([0.0, 0.0, 1.0])


def _surface_point(
    index: SurfaceIndex,
    cur: FloatArray,
    p: FloatArray,
    face: int,
    point: FloatArray,
    bary: FloatArray,
    dist2: float,
) -> SurfacePoint:
    """The :class:`SurfacePoint` at ``point`` (barycentric ``bary`` in ``face``) for probe ``p``.

    The normal interpolates the current vertex normals (a pseudo-normal exact on smooth regions;
    the face's own normal where they cancel); the penetration's sign says on which side of it the
    probe is.
    """
    normal = surface_normal(index, cur, face, bary)
    dist = math.sqrt(dist2)
    penetration = -dist if float((p - point) @ normal) >= 0.0 else dist
    return SurfacePoint(
        point=point, normal=normal, penetration_m=penetration, face=face, bary=bary.copy()
    )


#: A barycentric coordinate below this puts a proxy on the face's edge or vertex (it may slide on).
_ON_BOUNDARY = 1e-9

#: At most this many faces a proxy crosses in one :func:`track_proxy` call.
MAX_SLIDE_FACES = 512


def _faces_around(index: SurfaceIndex, vertices: Sequence[int]) -> IntArray:
    """Faces holding every one of ``vertices`` (1 or 2 vertex ids): a vertex's ring, an edge's pair."""
    v0 = int(vertices[0])
    ring = index.vf_faces[index.vf_indptr[v0] : index.vf_indptr[v0 + 1]]
    for v in vertices[1:]:
        ring = ring[(index.faces[ring] == int(v)).any(axis=1)]
    return ring


def track_proxy(
    index: SurfaceIndex,
    vertices: npt.ArrayLike,
    probe: npt.ArrayLike,
    face: int,
    bary: npt.ArrayLike,
    max_faces: int = MAX_SLIDE_FACES,
) -> SurfacePoint:
    """Slide a proxy along the current surface from where it was toward the probe (god-object).

    The proxy starts at its material point (``bary`` in ``face``) of the *current* surface, so the
    deformation since the last tick carries it along, and descends the distance to the probe
    along a continuous path on the surface: the closest point of its face; when that lies on an
    edge or a vertex, the best of the faces sharing it, while the distance strictly decreases. It
    stops at the first local minimum of the distance on the surface (Zilles and Salisbury 1995;
    Ruspini, Kolarov and Khatib 1997; paper section 8), so a probe pushed through a thin part or
    into a crease keeps its proxy on the side it entered: the global closest point
    (:func:`closest_point`) would jump to the far side. Where the surface is smooth and the probe
    near it, the result is the closest point.

    Parameters
    ----------
    index : SurfaceIndex
    vertices : (n, 3) float [m]
        Current vertex positions.
    probe : (3,) float [m]
        Haptic interface point x_h.
    face : int
        Face holding the proxy last tick.
    bary : (3,) float
        Its barycentric coordinates there (:attr:`SurfacePoint.bary`), >= 0, summing to 1.
    max_faces : int
        At most this many faces are crossed (a bound on the cost; a proxy that needs more stops
        where it got to and goes on next tick).

    Returns
    -------
    SurfacePoint
        The proxy, its outward normal and the signed penetration of the probe along it.

    Raises
    ------
    ValueError
        ``probe`` not 3 finite numbers, ``face`` out of range, ``bary`` not 3 finite weights.
    """
    p = np.asarray(probe, dtype=np.float64)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise ValueError(f"probe must be 3 finite numbers [m], got {probe!r}")
    f = int(face)
    if not 0 <= f < len(index.faces):
        raise ValueError(f"face must be in [0, {len(index.faces)}), got {face!r}")
    w = np.asarray(bary, dtype=np.float64)
    if w.shape != (3,) or not np.isfinite(w).all():
        raise ValueError(f"bary must be 3 finite weights, got {bary!r}")
    cur = np.asarray(vertices, dtype=np.float64)
    # one face, then the few around an edge or a vertex: plain floats (_closest_on_triangle)
    pt = p.tolist()
    a, b, c = cur[index.faces[f]].tolist()
    point, wts, _ = _closest_on_triangle(pt, a, b, c)
    gap = np.array(point) - p
    best = float(gap @ gap)
    for _ in range(max(1, int(max_faces))):
        corners = index.faces[f].tolist()
        support = [v for v, wt in zip(corners, wts, strict=True) if wt > _ON_BOUNDARY]
        if len(support) == 3:
            break  # the minimum is inside the face: a local minimum of the surface
        around = _faces_around(index, support)
        around = around[around != f]
        if len(around) == 0:
            break
        j, d2 = -1, math.inf
        for i, (a, b, c) in enumerate(cur[index.faces[around]].tolist()):
            qi, bi, di = _closest_on_triangle(pt, a, b, c)
            if j < 0 or di < d2:
                j, d2, q, bq = i, di, qi, bi
        if not d2 < best * (1.0 - 1e-12):
            break  # no neighbour across the edge or vertex is nearer: a local minimum
        f, point, wts, best = int(around[j]), q, bq, d2
    return _surface_point(index, cur, p, f, np.array(point), np.array(wts), best)


def segment_entry(
    index: SurfaceIndex,
    vertices: npt.ArrayLike,
    start: npt.ArrayLike,
    end: npt.ArrayLike,
    displacement_bound_m: float,
) -> SurfacePoint | None:
    """Where the segment ``start -> end`` first enters the current surface, or None.

    A probe that was outside last tick and is inside now crossed the surface on the way: the
    god-object's proxy stops there (Zilles and Salisbury 1995) and slides on from it
    (:func:`track_proxy`). The entry is the crossing nearest ``start`` through a face whose
    outward normal faces the motion (Moller-Trumbore over the faces near the segment).

    Parameters
    ----------
    index : SurfaceIndex
    vertices : (n, 3) float [m], current positions
    start, end : (3,) float [m], the probe last tick and now
    displacement_bound_m : float, bound [m] on the vertices' distance from rest

    Returns
    -------
    SurfacePoint or None
        At the entry, with the penetration of ``end`` along its normal; None when the segment
        enters no face.
    """
    a = np.asarray(start, dtype=np.float64)
    e = np.asarray(end, dtype=np.float64)
    d = e - a
    half = 0.5 * math.sqrt(float(d @ d))
    if half <= 0.0:
        return None
    cur = np.asarray(vertices, dtype=np.float64)
    radius = half + index.max_rest_face_radius_m + 3.0 * max(0.0, float(displacement_bound_m))
    fids = np.asarray(
        index.face_tree.query_ball_point(0.5 * (a + e), radius, return_sorted=False),
        dtype=np.int64,
    )
    if len(fids) == 0:
        return None
    tri = cur[index.faces[fids]]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    dd = np.broadcast_to(d, e1.shape)
    h = _cross(dd, e2)
    det = _rowdot(e1, h)
    facing = _rowdot(_cross(e1, e2), dd) < 0.0  # the motion goes against the outward normal
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = a - tri[:, 0]
        u = _rowdot(s, h) * inv
        qv = _cross(s, e1)
        v = _rowdot(dd, qv) * inv
        t = _rowdot(e2, qv) * inv
    hit = facing & (np.abs(det) > 1e-30) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)
    if not hit.any():
        return None
    k = int(np.flatnonzero(hit)[np.argmin(t[hit])])
    wts = np.array([1.0 - u[k] - v[k], u[k], v[k]])
    point = a + t[k] * d
    gap = point - e
    return _surface_point(index, cur, e, int(fids[k]), point, wts, float(gap @ gap))


def fit_plane(surface: SurfacePoint) -> Plane:
    """Plane primitive tangent to the current surface at the closest point (section 6, Step 1).

    Parameters
    ----------
    surface : SurfacePoint

    Returns
    -------
    shared.primitives.Plane
        Through ``surface.point`` [m] with outward ``surface.normal``.
    """
    return make_plane(surface.point.tolist(), surface.normal.tolist())


def fit_sphere(
    surface: SurfacePoint,
    index: SurfaceIndex,
    vertices: npt.ArrayLike,
    radius_m: float,
    displacement_bound_m: float,
) -> Plane | Sphere:
    """Sphere primitive fitted to the local curvature of the current surface (section 6, Step 1).

    The sphere is tangent at ``surface.point`` with outward normal ``surface.normal``; its
    curvature ``c = 1/R`` is the least-squares fit of the height function ``h = h0 - c r^2 / 2`` of
    the current vertices within ``radius_m`` (``h`` along the normal, ``r`` tangential distance;
    ``h0`` absorbs the offset of a proxy inside a flat facet), over the vertices whose normals
    face the same way as the proxy's (the far side of a thin part is not fitted).
    A concave or nearly flat fit (``R`` > :data:`FLAT_RADIUS_M`), or fewer than 3 neighbours,
    gives a :class:`~shared.primitives.Plane` instead.

    Parameters
    ----------
    surface : SurfacePoint
    index : SurfaceIndex
    vertices : (n, 3) float [m], current positions
    radius_m : float, neighbourhood radius [m] (e.g. the finger-pad patch radius)
    displacement_bound_m : float, bound [m] on the vertices' distance from rest

    Returns
    -------
    shared.primitives.Sphere or shared.primitives.Plane

    Raises
    ------
    ValueError
        ``radius_m`` not finite and positive.
    """
    r_fit = float(radius_m)
    if not (math.isfinite(r_fit) and r_fit > 0.0):
        raise ValueError(f"radius_m must be finite and > 0, got {radius_m!r}")
    cur = np.asarray(vertices, dtype=np.float64)
    p, n = surface.point, surface.normal
    cand = np.asarray(
        index.tree.query_ball_point(p, r_fit + max(0.0, float(displacement_bound_m))),
        dtype=np.int64,
    )
    if len(cand) < 3:
        return fit_plane(surface)
    d = cur[cand] - p
    h = d @ n
    r2 = _rowdot(d, d) - h * h
    # the sheet the proxy is on: not the far side of a part thinner than the fit radius
    facing = _vertex_normals(index, cur, cand) @ n > 0.0
    keep = (r2 + h * h <= r_fit * r_fit) & (r2 > 1e-12) & facing
    if int(keep.sum()) < 3:
        return fit_plane(surface)
    h, r2 = h[keep], r2[keep]
    # least squares h = h0 - (c / 2) r^2: the offset h0 absorbs the facet's sag at the proxy
    r2_mean, h_mean = float(r2.mean()), float(h.mean())
    spread = float((r2 - r2_mean) @ (r2 - r2_mean))
    if spread <= 0.0:
        return fit_plane(surface)
    curvature = -2.0 * float((r2 - r2_mean) @ (h - h_mean)) / spread
    if not math.isfinite(curvature) or curvature <= 1.0 / min(FLAT_RADIUS_M, MAX_RADIUS_M):
        return fit_plane(surface)
    radius = max(1.0 / curvature, MIN_RADIUS_M)
    return make_sphere((p - radius * n).tolist(), radius)
