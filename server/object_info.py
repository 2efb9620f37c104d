"""The object as the users are told of it: its rest-state bounds, top and side anchors, and the
side anchors ordered by how much of a push on the top each carries (the ``welcome``'s
:class:`shared.protocol.ObjectInfo`).

Pure functions of the rest mesh and the object's contact compliance (DESIGN section 6); no I/O.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from haptic_collab.shared.protocol import ObjectInfo, SurfacePoint

__all__ = ["object_info", "order_sides_by_coupling", "side_coupling"]


def object_info(vertices: np.ndarray, faces: np.ndarray) -> ObjectInfo:
    """Rest-state description of the object: bounds, bounding radius, a top and side anchors.

    The top is the vertex with the largest z, the side the one with the largest x, and ``sides``
    the vertices furthest along +x, +y, -x and -y (so users resting on a side spread apart);
    their normals are area-weighted vertex normals. Among the vertices within 1 % of the
    object's size of that extreme, the one nearest the bounding box's axis through it is taken:
    the middle of a flat top or side (a box's face, not its corner), the extreme itself on a
    rounded object. Shapes: vertices (n, 3) [m], faces (m, 3).
    """
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-18)
    lo, hi = v.min(axis=0), v.max(axis=0)
    center = 0.5 * (lo + hi)
    tol = 0.01 * float(np.max(hi - lo))

    def extreme(axis: int, sign: float) -> int:
        along = sign * v[:, axis]
        near = np.flatnonzero(along >= along.max() - tol)
        others = np.array([k for k in range(3) if k != axis], dtype=np.int64)
        off = v[np.ix_(near, others)] - center[others]
        return int(near[np.argmin(np.einsum("ij,ij->i", off, off))])

    top, side = extreme(2, 1.0), extreme(0, 1.0)

    def t3(a: np.ndarray) -> tuple[float, float, float]:
        return (float(a[0]), float(a[1]), float(a[2]))

    return ObjectInfo(
        n_vertices=int(v.shape[0]),
        n_faces=int(f.shape[0]),
        center_m=t3(center),
        radius_m=float(np.max(np.linalg.norm(v - center, axis=1))),
        bounds_min_m=t3(lo),
        bounds_max_m=t3(hi),
        top_m=t3(v[top]),
        top_normal=t3(vn[top]),
        side_m=t3(v[side]),
        side_normal=t3(vn[side]),
        sides=[
            SurfacePoint(point_m=t3(v[i]), normal=t3(vn[i]))
            for i in (side, extreme(1, 1.0), extreme(0, -1.0), extreme(1, -1.0))
        ],
    )


def side_coupling(info: ObjectInfo, obj: Any) -> np.ndarray:
    """How much of a push on the top a user resting on each side anchor feels, (len(sides),).

    ``C_top,side / C_side,side`` of the object's load patches there (``obj.contact_compliance``,
    DESIGN section 6): a user held firmly on the side feels its force change by this share of
    the top's push (``K_o,side`` times the side's displacement ``C_top,side F``); negative when
    the side bulges out (the force rises), positive when it is drawn in. ``obj`` is the world's
    object (balloon or FEM solid); empty when ``info.sides`` is.
    """
    points = [(info.top_m, info.top_normal)] + [(s.point_m, s.normal) for s in info.sides]
    if len(points) == 1:
        return np.zeros(0)
    keys = [int(obj.patch_key(np.asarray(p), None, np.asarray(n))) for p, n in points]
    c = np.asarray(obj.contact_compliance(keys), dtype=np.float64)
    own = np.maximum(np.diag(c)[1:], 1e-300)
    return np.asarray(c[0, 1:] / own, dtype=np.float64)


def order_sides_by_coupling(info: ObjectInfo, obj: Any) -> ObjectInfo:
    """``info`` with its side anchors ordered by how much a push on the top is felt there.

    A user resting on a side feels a user pressing the top only as far as the object carries
    the push there: on a balloon every side bulges out (13 % of the push felt), but a thin
    plate's +y rim hardly moves (0.3 %) and a box's far face 1 % (:func:`side_coupling`). The
    share felt, not the displacement, sets the order: the most displaced side of a scanned bunny
    is its soft ear (K_o 40-50 N/m), where a light touch is hard to hold still. The clients
    place users on the sides in this order (``--anchor side:N``; ``side`` by join order), so the
    first users to rest go where the object carries a press to them; ``side_m`` stays the
    geometric +x side. An object without contact compliance keeps the geometric order.
    """
    if not info.sides or not hasattr(obj, "contact_compliance"):
        return info
    felt = np.abs(side_coupling(info, obj))
    order = sorted(range(len(info.sides)), key=lambda i: -float(felt[i]))  # stable on ties
    return info.model_copy(update={"sides": [info.sides[i] for i in order]})
