"""``--mesh-repair``: make an open, non-manifold or self-intersecting mesh one closed body.

Without the flag such a mesh is refused (:func:`server.objects.mesh.repair_mesh`, the message
suggests ``--mesh-repair``); with it, :func:`repair_mesh_topology` runs before those checks and
says what it changed (:class:`RepairReport`: holes filled, faces removed, vertices merged,
bodies joined or dropped), which the server logs and puts in ``/status``'s object info.

The library was chosen by measurement (``tools/mesh_repair_compare.py``, docs/real-objects.md):

- **manifold3d** (Apache-2.0) unions closed bodies exactly, so parts that overlap or intersect
  (a CAD assembly exported as one file, the ant of pyvista's examples: 15 intersecting bodies)
  become one closed body with the volume of their union. It accepts only closed, oriented
  2-manifold input, so it cannot close a hole or split a non-manifold edge;
- **pymeshfix** (MeshFix, Attene 2010) fills holes, removes self-intersections and non-manifold
  elements, but keeps only the largest connected piece: run alone on the ant it drops 14 of 15
  bodies. It is **AGPL**, so, as TetGen (docs/fem.md), it is not a dependency of the package
  and the server never imports it: :func:`meshfix` runs it in a child process
  (:mod:`server.objects.meshfix_step`), only for an open piece, and says how to install it when
  it is missing (``pip install pymeshfix``);
- **trimesh**'s repair only fills simple holes (one missing triangle or a planar loop) and fixes
  winding; it splits no non-manifold edge.

So the repair takes the pieces the surface falls into when it is cut at its non-manifold edges
(edges of more than two faces: a fin, an inner wall, parts touching along an edge), closes the
open ones with pymeshfix, and unions every closed piece with manifold3d. Parts that touch only
along an edge or at a point stay separate bodies after an exact union (a 2-manifold cannot join
them there); then the largest body is kept and the report says how many were dropped.

References
----------
- Attene, M. (2010). A lightweight approach to repairing digitized polygon meshes. *The Visual
  Computer* 26(11), 1393-1406 (MeshFix).
- Lague, E., et al. Manifold: a geometry library for topological robustness
  (manifold3d, https://github.com/elalish/manifold).

Nothing here uses threads, sockets or clocks.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from haptic_collab.shared.types import IntArray


class RepairError(ValueError):
    """A mesh that ``--mesh-repair`` could not make one closed body; the message says why."""


@dataclass(frozen=True, slots=True)
class RepairReport:
    """What :func:`repair_mesh_topology` changed, for the log line and ``/status``.

    Parameters
    ----------
    vertices_merged : int
        Vertices merged into others (same position: seams, an STL's unshared corners).
    faces_removed : int
        Degenerate, duplicate or non-manifold faces removed (before any hole was filled).
    holes_filled : int
        Boundary loops closed.
    bodies_joined : int
        Closed pieces united into one body (1: nothing to unite).
    bodies_dropped : int
        Bodies left out because they touch the kept one only along an edge or at a point, or
        not at all.
    vertices_in, vertices_out : int
        Vertex counts before and after.
    volume_change : float
        Relative change of the enclosed volume of the kept body against the input's pieces
        that were closed before (0 when none was).
    """

    vertices_merged: int
    faces_removed: int
    holes_filled: int
    bodies_joined: int
    bodies_dropped: int
    vertices_in: int
    vertices_out: int
    volume_change: float

    @property
    def changed(self) -> bool:
        """Whether the repair changed the topology (not only merged seam vertices)."""
        return bool(
            self.faces_removed or self.holes_filled or self.bodies_joined > 1 or self.bodies_dropped
        )

    def summary(self) -> str:
        """One line for the server's log: what the repair did."""
        return (
            f"mesh repair: {self.vertices_merged} vertices merged, {self.faces_removed} faces "
            f"removed, {self.holes_filled} holes filled, {self.bodies_joined} bodies united into "
            f"one, {self.bodies_dropped} bodies dropped; {self.vertices_in} -> "
            f"{self.vertices_out} vertices, volume {100.0 * self.volume_change:+.2g} %"
        )

    def as_dict(self) -> dict[str, int | float]:
        """The report as JSON-ready numbers (``/status``'s object info)."""
        return {
            "vertices_merged": self.vertices_merged,
            "faces_removed": self.faces_removed,
            "holes_filled": self.holes_filled,
            "bodies_joined": self.bodies_joined,
            "bodies_dropped": self.bodies_dropped,
            "vertices_in": self.vertices_in,
            "vertices_out": self.vertices_out,
            "volume_change": round(self.volume_change, 6),
        }


def _clean(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, int, int]:
    """A copy with vertices merged by position and degenerate and duplicate faces dropped.

    Returns ``(mesh, vertices merged, faces removed)``.
    """
    m = trimesh.Trimesh(
        vertices=np.asarray(mesh.vertices, dtype=np.float64),
        faces=np.asarray(mesh.faces, dtype=np.int64),
        process=False,
        validate=False,
    )
    n_v, n_f = len(m.vertices), len(m.faces)
    m.merge_vertices(merge_tex=True, merge_norm=True)
    m.remove_unreferenced_vertices()
    merged = n_v - len(m.vertices)
    m.update_faces(np.asarray(m.nondegenerate_faces(), dtype=bool))
    # a face and its reverse (a zero-thickness wall) are duplicates too: unique by sorted corners
    m.update_faces(m.unique_faces())
    m.remove_unreferenced_vertices()
    return m, merged, n_f - len(m.faces)


def _edge_face_counts(faces: IntArray) -> tuple[IntArray, IntArray]:
    """For each face's three edges (m, 3): the undirected edge id and how many faces hold it."""
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, inverse, counts = np.unique(e, axis=0, return_inverse=True, return_counts=True)
    inverse = np.asarray(inverse).reshape(-1)
    return inverse.reshape(-1, 3), counts[inverse].reshape(-1, 3)


def _radial_pairs(
    v: np.ndarray, f: IntArray, edge: IntArray, owners: IntArray
) -> list[tuple[int, int]]:
    """Pair the faces ``owners`` around one non-manifold edge ``edge`` (2,) as solids do.

    Around the edge the faces are sorted by angle; each face is paired with its neighbour on
    the side its material lies (opposite its normal) when that neighbour runs along the edge the
    other way: the pairing that closes two solids touching along the edge (or a solid and its
    overlapping copy) into two closed pieces. Faces that find no such partner stay unpaired.
    """
    a, b = v[edge[0]], v[edge[1]]
    axis = (b - a) / max(float(np.linalg.norm(b - a)), 1e-300)
    ref = np.cross(axis, [1.0, 0.0, 0.0])
    if float(np.linalg.norm(ref)) < 1e-6:
        ref = np.cross(axis, [0.0, 1.0, 0.0])
    ref /= np.linalg.norm(ref)
    other = np.cross(axis, ref)
    angles, forward, into = [], [], []
    for k in owners:
        tri = f[k]
        third = v[tri[(tri != edge[0]) & (tri != edge[1])][0]]
        w = third - a
        w = w - float(w @ axis) * axis
        theta = float(np.arctan2(w @ other, w @ ref))
        i = int(np.flatnonzero(tri == edge[0])[0])
        fwd = tri[(i + 1) % 3] == edge[1]  # the face runs a -> b
        normal = np.cross(v[tri[1]] - v[tri[0]], v[tri[2]] - v[tri[0]])
        t = np.cross(axis, w)  # the direction of increasing angle at this face
        angles.append(theta)
        forward.append(bool(fwd))
        into.append(float(-normal @ t) > 0.0)  # its material lies toward increasing angle
    order = np.argsort(angles)
    n = len(order)
    pos = {int(order[j]): j for j in range(n)}
    pairs: list[tuple[int, int]] = []
    for j_face in range(n):
        if not forward[j_face]:
            continue
        step = 1 if into[j_face] else -1
        partner = int(order[(pos[j_face] + step) % n])
        if not forward[partner]:
            pairs.append((int(owners[j_face]), int(owners[partner])))
    return pairs


def pieces(mesh: trimesh.Trimesh) -> list[trimesh.Trimesh]:
    """The pieces of surface a mesh falls into when cut at its non-manifold edges.

    Faces are joined across an edge held by exactly two faces; at an edge of more faces
    (solids touching or overlapping along it) they are paired as :func:`_radial_pairs` says,
    so two solids touching along an edge come out as two closed pieces. A piece keeps its own
    copy of the vertices it shares with another. Largest (most faces) first.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Vertices merged by position, no degenerate faces.

    Returns
    -------
    list of trimesh.Trimesh
        Each with its vertices renumbered, unprocessed.
    """
    f = np.asarray(mesh.faces, dtype=np.int64)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    edge_id, counts = _edge_face_counts(f)
    face_of = np.repeat(np.arange(len(f)), 3).reshape(-1, 3)
    manifold = counts == 2
    ids, owners = edge_id[manifold], face_of[manifold]
    order = np.argsort(ids, kind="stable")
    ids, owners = ids[order], owners[order]
    a, b = list(owners[0::2]), list(owners[1::2])  # each manifold edge appears exactly twice
    crowded = counts > 2
    if crowded.any():
        edges = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 3, 2), axis=2)
        cid, cown, cedge = edge_id[crowded], face_of[crowded], edges[crowded]
        for e in np.unique(cid):
            sel = cid == e
            for p, q in _radial_pairs(v, f, cedge[sel][0], cown[sel]):
                a.append(p)
                b.append(q)
    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(len(f), len(f)))
    n, label = connected_components(graph, directed=False)
    out = []
    for k in np.argsort(-np.bincount(label, minlength=n), kind="stable"):
        sub = f[label == k]
        used, inv = np.unique(sub, return_inverse=True)
        out.append(trimesh.Trimesh(v[used], inv.reshape(-1, 3), process=False, validate=False))
    return out


def _closed(m: trimesh.Trimesh) -> bool:
    """Every edge of ``m`` held by exactly two faces."""
    f = np.asarray(m.faces, dtype=np.int64)
    return len(f) > 0 and bool(np.all(_edge_face_counts(f)[1] == 2))


def _boundary_loops(m: trimesh.Trimesh) -> int:
    """Number of boundary loops (holes) of ``m``: connected groups of single-face edges."""
    f = np.asarray(m.faces, dtype=np.int64)
    edges = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    open_edges = uniq[counts == 1]
    if len(open_edges) == 0:
        return 0
    verts, inv = np.unique(open_edges, return_inverse=True)
    inv = inv.reshape(-1, 2)
    graph = coo_matrix(
        (np.ones(len(inv), dtype=np.int8), (inv[:, 0], inv[:, 1])), shape=(len(verts),) * 2
    )
    return int(connected_components(graph, directed=False)[0])


def _to_manifold(m: trimesh.Trimesh):  # type: ignore[no-untyped-def]
    """A manifold3d Manifold of a closed piece, outward, or None when manifold3d refuses it."""
    import manifold3d

    piece = m.copy()
    trimesh.repair.fix_winding(piece)
    with np.errstate(all="ignore"):
        if float(piece.volume) < 0.0:
            piece.invert()
    mesh = manifold3d.Mesh64(
        vert_properties=np.ascontiguousarray(piece.vertices, dtype=np.float64),
        tri_verts=np.ascontiguousarray(piece.faces, dtype=np.uint64),
    )
    out = manifold3d.Manifold(mesh)
    if out.status() != manifold3d.Error.NoError or out.is_empty():
        return None
    return out


def _from_manifold(man) -> trimesh.Trimesh:  # type: ignore[no-untyped-def]
    mesh = man.to_mesh64()
    return trimesh.Trimesh(
        np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3],
        np.asarray(mesh.tri_verts, dtype=np.int64),
        process=False,
    )


#: Seconds the MeshFix child process may take (the 50000-vertex Stanford bunny scan: about 5 s).
MESHFIX_TIMEOUT_S = 120.0


def meshfix(m: trimesh.Trimesh) -> trimesh.Trimesh:
    """pymeshfix's repair of one piece, in a child process (AGPL: module docstring).

    Holes filled, self-intersections and non-manifold elements removed, only the largest
    connected part kept (:mod:`server.objects.meshfix_step`).

    Parameters
    ----------
    m : trimesh.Trimesh
        One piece, vertices (n, 3) float64, faces (m, 3).

    Returns
    -------
    trimesh.Trimesh
        The repaired piece, unprocessed.

    Raises
    ------
    RepairError
        pymeshfix is not installed, fails, or takes longer than :data:`MESHFIX_TIMEOUT_S`.
    """
    with tempfile.TemporaryDirectory(prefix="haptic-meshfix-") as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, vertices=np.asarray(m.vertices, np.float64), faces=np.asarray(m.faces))
        cmd = [sys.executable, str(Path(__file__).with_name("meshfix_step.py")), str(src), str(dst)]
        try:
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=MESHFIX_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            raise RepairError(f"MeshFix took longer than {MESHFIX_TIMEOUT_S:g} s") from None
        if done.returncode != 0 or not dst.is_file():
            why = (done.stderr.strip().splitlines() or [f"exit status {done.returncode}"])[-1]
            raise RepairError(f"closing an open piece needs MeshFix: {why}")
        with np.load(dst) as data:
            return trimesh.Trimesh(
                np.asarray(data["vertices"]), np.asarray(data["faces"]), process=False
            )


def _components(mesh: trimesh.Trimesh) -> tuple[list[trimesh.Trimesh], int]:
    """The input's bodies as its file wrote them: faces joined through shared vertex indices.

    A file that shares no indices (an STL: every triangle its own corners) is merged by position
    first, so its bodies are found by position instead. Returns the bodies, unprocessed, and
    the number of vertices that merge removed (0 for an indexed file).

    Limitation: in a triangle soup, two bodies whose faces coincide exactly (overlapping boxes
    on one grid) lose those faces as duplicates; an indexed file keeps its bodies apart.
    """
    n_merged = 0
    f = np.asarray(mesh.faces, dtype=np.int64)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    if len(np.unique(f)) >= 2.5 * len(f):  # a triangle soup: no index is shared
        merged = trimesh.Trimesh(v, f, process=False, validate=False)
        merged.merge_vertices()
        n_merged = len(v) - len(merged.vertices)
        f, v = np.asarray(merged.faces, dtype=np.int64), np.asarray(merged.vertices)
    e = f[:, [0, 1, 1, 2]].reshape(-1, 2)
    graph = coo_matrix((np.ones(len(e), dtype=np.int8), (e[:, 0], e[:, 1])), shape=(len(v),) * 2)
    _, label = connected_components(graph, directed=False)
    face_label = label[f[:, 0]]
    out = []
    for k in np.unique(face_label):
        sub = f[face_label == k]
        used, inv = np.unique(sub, return_inverse=True)
        out.append(trimesh.Trimesh(v[used], inv.reshape(-1, 3), process=False, validate=False))
    return out, n_merged


def _flip_slivers(m: trimesh.Trimesh, rounds: int = 20) -> trimesh.Trimesh:
    """Remove zero-area slivers of a closed mesh by flipping their longest edge.

    An exact boolean leaves a few collinear triangles (a vertex on the middle of an edge);
    dropping them would open the surface. Flipping the sliver's longest edge with the face
    across it replaces the two by two faces through the middle vertex: closed, same shape.
    """
    v = np.asarray(m.vertices, dtype=np.float64)
    f = np.asarray(m.faces, dtype=np.int64).copy()
    for _ in range(rounds):
        bad = np.flatnonzero(~trimesh.Trimesh(v, f, process=False).nondegenerate_faces())
        if len(bad) == 0:
            break
        edges = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 3, 2)
        where: dict[tuple[int, int], int] = {}
        for k, tri_edges in enumerate(edges):
            for p, q in tri_edges:
                where[(int(p), int(q))] = k
        done: set[int] = set()
        for kk in bad:
            k = int(kk)
            if k in done:
                continue
            tri = f[k]
            lengths = np.linalg.norm(v[tri[[1, 2, 0]]] - v[tri], axis=1)
            i = int(np.argmax(lengths))
            a, b, c = int(tri[i]), int(tri[(i + 1) % 3]), int(tri[(i + 2) % 3])
            other = where.get((b, a))
            if other is None or other in done:
                continue
            o = f[other]
            d = int(o[(o != a) & (o != b)][0])
            f[k] = (c, a, d)  # c lies on a-b: split the neighbour (b, a, d) at c instead
            f[other] = (b, c, d)
            done.update((k, int(other)))
    return trimesh.Trimesh(v, f, process=False)


def _largest_closed_piece(m: trimesh.Trimesh) -> tuple[trimesh.Trimesh, int]:
    """The largest-volume closed piece of ``m`` cut at its non-manifold edges (after merging
    by position and flipping away zero-area slivers), and how many other pieces there were:
    bodies an exact union leaves touching along an edge."""
    c = trimesh.Trimesh(np.asarray(m.vertices), np.asarray(m.faces), process=False)
    c.merge_vertices()
    c = _flip_slivers(c)
    parts = [p for p in pieces(c) if _closed(p)]
    if not parts:
        return c, 0
    with np.errstate(all="ignore"):
        volumes = [abs(float(p.volume)) for p in parts]
    return parts[int(np.argmax(volumes))], len(parts) - 1


def repair_mesh_topology(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, RepairReport]:
    """Make ``mesh`` one closed, manifold body; the input is not modified.

    Steps (module docstring): take the file's bodies (faces joined through shared vertex
    indices; an STL's by position); in each, merge vertices by position and drop degenerate and
    duplicate faces (trimesh), cut the surface at its non-manifold edges into pieces
    (:func:`pieces`), close every open piece of at least 1 % of the faces with pymeshfix (smaller
    open scraps are dropped); unite every closed piece with manifold3d; keep the largest body
    (bodies that do not overlap, or touch only along an edge, cannot be one 2-manifold).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Any triangle mesh, vertices (n, 3) in any unit.

    Returns
    -------
    (trimesh.Trimesh, RepairReport)
        The repaired mesh (same units; :func:`server.objects.mesh.repair_mesh` still checks
        it) and what changed.

    Raises
    ------
    RepairError
        No face, no piece that could be closed (nothing left but scraps), manifold3d refused
        every piece, or an open piece and MeshFix missing or failing (:func:`meshfix`).
    """
    import manifold3d

    n_in = len(mesh.vertices)
    if len(mesh.faces) == 0:
        raise RepairError("the mesh has no faces")
    removed = holes = 0
    solids: list[trimesh.Trimesh] = []
    closed_volume = 0.0
    n_faces = len(mesh.faces)
    bodies_in, merged = _components(mesh)
    for body in bodies_in:
        m, n_merged, n_removed = _clean(body)
        merged += n_merged
        removed += n_removed
        for piece in pieces(m) if len(m.faces) else []:
            if _closed(piece):
                solids.append(piece)
                with np.errstate(all="ignore"):
                    closed_volume += abs(float(piece.volume))
            elif len(piece.faces) < 0.01 * n_faces:
                removed += len(piece.faces)
            else:
                holes += _boundary_loops(piece)
                fixed = meshfix(piece)
                if len(fixed.faces) and _closed(fixed):
                    solids.append(fixed)
    manifolds = [x for x in (_to_manifold(p) for p in solids) if x is not None]
    if not manifolds:
        raise RepairError(
            "no piece of the surface could be closed (pymeshfix) or taken as a closed solid "
            "(manifold3d); repair the mesh in a mesh editor"
        )
    union = manifold3d.Manifold.batch_boolean(manifolds, manifold3d.OpType.Add)
    bodies = sorted(union.decompose(), key=lambda b: -b.volume())
    kept, touching = _largest_closed_piece(_from_manifold(bodies[0]))
    with np.errstate(all="ignore"):
        volume = abs(float(kept.volume))
    change = volume / closed_volume - 1.0 if closed_volume > 0.0 else 0.0
    report = RepairReport(
        vertices_merged=int(merged),
        faces_removed=int(removed),
        holes_filled=int(holes),
        bodies_joined=len(manifolds),
        bodies_dropped=len(bodies) - 1 + touching,
        vertices_in=int(n_in),
        vertices_out=len(kept.vertices),
        volume_change=float(change),
    )
    return kept, report


# ---- the candidates measured against each other (tools/mesh_repair_compare.py) ----


def repair_pymeshfix(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """pymeshfix alone on the merged mesh (its default repair: largest component kept)."""
    m, _, _ = _clean(mesh)
    return meshfix(m)


def repair_manifold3d(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """manifold3d alone: the union of the file's bodies (:func:`_components`), each merged by
    position and taken as a closed solid (raises :class:`RepairError` when it refuses one)."""
    import manifold3d

    parts, _ = _components(mesh)
    mans = [_to_manifold(_clean(p)[0]) for p in parts]
    if not mans or any(x is None for x in mans):
        raise RepairError("manifold3d refuses a body that is not a closed oriented 2-manifold")
    return _from_manifold(manifold3d.Manifold.batch_boolean(mans, manifold3d.OpType.Add))


def repair_trimesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """trimesh's repair alone: holes filled, winding and normals fixed."""
    m, _, _ = _clean(mesh)
    trimesh.repair.fill_holes(m)
    trimesh.repair.fix_winding(m)
    with np.errstate(all="ignore"):
        trimesh.repair.fix_normals(m, multibody=True)
    return m
