"""Closed triangle meshes for deformable objects: the default balloon and validated mesh files.

Why one module: it is one pipeline (read, repair, validate, scale, refine, warn) whose steps
share the size limits, the unit hints and the topology checks, and this docstring is the one list
of what is repaired and what is refused, kept beside the code that does it.

DESIGN section 5: the default object is "any closed triangle mesh (icosphere from trimesh by
default, or a mesh file)". An admittance model needs a *closed* (watertight), consistently wound
surface enclosing a positive volume: the water term of the balloon is the enclosed volume, and the
outward normals define which way "pushing in" is. This module is the one place where mesh files
are read; everything past it receives a repaired, validated :class:`trimesh.Trimesh` in metres.
(:mod:`server.objects.shapes` builds a stress set of harder closed shapes by name.)

Repairs applied by :func:`load_mesh` (:func:`prepare_mesh` for a mesh in memory), in order:

1. a scene (several geometries, e.g. a GLB) is flattened into one mesh with its transforms;
2. vertices split at texture or normal seams are merged (``merge_tex``/``merge_norm``);
3. degenerate (zero-area) and duplicate faces, then unreferenced vertices, are dropped;
4. winding and normals are made consistent and outward (positive volume);
5. a uniform scale is applied (``scale``, or ``target_size_m`` for the largest extent);
6. on request (``max_edge_m``, ``--mesh-max-edge``) every edge longer than that is split at its
   midpoint (:func:`trimesh.remesh.subdivide_to_size`): the surface keeps its shape exactly,
   sharp edges included (no smoothing), and stays closed.

With ``repair=True`` (``--mesh-repair``, :mod:`server.objects.repair`) an open, non-manifold,
self-intersecting or several-body mesh is first made one closed body (pymeshfix closes open
pieces, manifold3d unites closed ones; the largest body is kept) and the checks below run on the
result; what the repair changed is logged and kept as ``mesh.metadata["mesh_repair"]``
(:func:`repair_report_of`). Without it such a mesh is refused and the message suggests the flag.

What is refused, with a :class:`MeshError` of one line that names the file and the failed check,
before the server starts:

- no faces, NaN/inf coordinates, or a file that cannot be read;
- an open surface (not watertight: edges that belong to one face only);
- a non-manifold surface: an edge shared by more than two faces (a fin, an inner wall, parts
  touching along an edge), or a vertex where sheets of surface meet only at that point (parts
  touching at a corner). The admittance model's Laplacian and outward normals are defined only
  on a 2-manifold;
- several bodies (more than one connected piece of surface, counted after merging seams): the
  water term couples the whole enclosed volume, and a second body would be a separate object
  that no contact can move. The message says how many and suggests keeping the largest;
- degenerate faces beyond repair. A few zero-area faces (collapsed edges, collinear slivers)
  are what exporters leave behind, and dropping them changes nothing a finger can feel, so they
  are dropped silently. More than :data:`MAX_DEGENERATE_FRACTION` (1 %) of the faces means a
  broken export (coordinates rounded to too few digits, say), whose geometry itself is
  suspect: refused. So is a mesh that is closed only *through* its degenerate faces (slivers
  filling T-junction cracks), because dropping them opens it;
- zero enclosed volume (a flat closed mesh);
- an absurd size after scaling: a largest extent below :data:`MIN_SIZE_ERROR_M` (1 mm) or above
  :data:`MAX_SIZE_ERROR_M` (20 m) is a unit mistake, not an object to touch (the message
  suggests ``--mesh-scale``/``--mesh-size``);
- a refinement (``max_edge_m``) that would make more than :data:`MAX_REFINED_FACES` faces.

A mesh that is valid but probably not what the user meant is accepted, and
:func:`mesh_warnings` says why (the server logs it): a size outside 1 cm - 2 m (a file in
centimetres read as metres, say), a model too coarse for a 15 mm finger-pad patch (it suggests
``--mesh-max-edge``), or a box of a few vertices that cannot dent.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import numpy.typing as npt
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from haptic_collab.server.objects.repair import RepairError, RepairReport, repair_mesh_topology
from haptic_collab.shared.checks import positive as _positive_finite
from haptic_collab.shared.types import FloatArray, IntArray

log = logging.getLogger("haptic.server.mesh")

#: ``mesh.metadata`` key of the :class:`~server.objects.repair.RepairReport` of a repaired mesh.
REPAIR_KEY = "mesh_repair"

#: The hint every refusal that ``--mesh-repair`` can mend ends with.
REPAIR_HINT = "; or try --mesh-repair (it makes the mesh one closed body and says what changed)"

#: File suffixes :func:`load_mesh` accepts (lower case, with the dot).
SUPPORTED_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".glb")

#: Enclosed volume below this fraction of the bounding-box volume counts as degenerate.
_MIN_VOLUME_FRACTION = 1e-9

#: Object sizes [m] (largest bounding-box extent) outside which :func:`mesh_warnings` warns.
MIN_SIZE_M = 0.01
MAX_SIZE_M = 2.0

#: Object sizes [m] after scaling outside which :func:`load_mesh` refuses the mesh: below 1 mm
#: or above 20 m it is a unit mistake (a file in micrometres, or in millimetres of a 20 m part),
#: not something a hand-held device could touch, and the patch and contact geometry would be
#: meaningless. Between these and the warning band the mesh loads with a warning.
MIN_SIZE_ERROR_M = 0.001
MAX_SIZE_ERROR_M = 20.0

#: Degenerate (zero-area) faces are dropped silently up to this fraction of all faces; more is
#: a broken export and is refused (module docstring).
MAX_DEGENERATE_FRACTION = 0.01

#: A refinement (``max_edge_m``) that would make more faces than this is refused: the object's
#: one-time factorization and the viewer stream grow with it (40962 vertices, about 82000
#: faces, take 1 s to build; ``haptic bench``).
MAX_REFINED_FACES = 500_000

#: Fewer vertices under one finger-pad patch than this (median over the surface) is too coarse:
#: a centre and its ring of six neighbours is the smallest stencil on which a dent has a shape.
MIN_PATCH_VERTICES = 7

#: A closed mesh with fewer vertices than this is a box or a low-poly model: it cannot dent.
MIN_VERTICES = 50

#: File units :func:`mesh_warnings` tries when the size is off: (factor to metres, unit name).
_UNIT_GUESSES = ((0.001, "millimetres"), (0.01, "centimetres"), (0.0254, "inches"))

#: At most this many vertices are sampled to count the vertices under a patch.
_PATCH_SAMPLES = 2000


class MeshError(ValueError):
    """A mesh file or mesh that cannot be used as a closed deformable surface.

    The message names the file (when there is one) and the failed check: missing file,
    unsupported format, unparsable content, no faces, non-finite coordinates, too many or
    crack-filling degenerate faces, not watertight (with the number of open edges), not
    manifold (edges or vertices), several bodies, zero enclosed volume, an absurd size, or a
    refinement too fine.
    """


def default_balloon(radius_m: float = 0.1, subdivisions: int = 4) -> trimesh.Trimesh:
    """The default water balloon surface: an icosphere of ``radius_m`` centred at the origin.

    DESIGN section 5. Vertex counts: ``subdivisions`` 0 -> 12, 3 -> 642, 4 -> 2562, 5 -> 10242,
    6 -> 40962 (10 * 4**s + 2).

    Parameters
    ----------
    radius_m : float
        Sphere radius [m]; 0.1 m is a hand-sized balloon.
    subdivisions : int
        Icosahedron subdivision level, 0 to 7.

    Returns
    -------
    trimesh.Trimesh
        ``vertices`` (n, 3) float64 [m], ``faces`` (m, 3) int64, outward winding.

    Raises
    ------
    ValueError
        A non-finite or non-positive radius, or ``subdivisions`` outside 0..7.
    """
    r = _positive_finite("radius_m", radius_m)
    if isinstance(subdivisions, bool) or not isinstance(subdivisions, int | np.integer):
        raise ValueError(f"subdivisions must be an integer, got {subdivisions!r}")
    if not 0 <= int(subdivisions) <= 7:
        raise ValueError(f"subdivisions must be in 0..7, got {subdivisions}")
    return trimesh.creation.icosphere(subdivisions=int(subdivisions), radius=r)


def mesh_size_m(vertices: npt.ArrayLike) -> float:
    """The object's size [m]: the largest extent of its axis-aligned bounding box.

    The size ``--mesh-size`` sets and :func:`mesh_warnings` checks (0.2 m for the default
    balloon of radius 0.1 m).

    Parameters
    ----------
    vertices : (n, 3) float [m]

    Raises
    ------
    ValueError
        ``vertices`` not a non-empty (n, 3) array.
    """
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise ValueError(f"vertices must be a non-empty (n, 3) array, got shape {v.shape}")
    return float(np.max(v.max(axis=0) - v.min(axis=0)))


def scale_mesh_to_size(vertices: npt.ArrayLike, size_m: float) -> FloatArray:
    """Vertices scaled uniformly about the origin so the object's size is ``size_m``.

    ``--mesh-size`` (:func:`load_mesh` ``target_size_m``): the largest bounding-box extent
    (:func:`mesh_size_m`) becomes ``size_m``; shape and proportions are kept.

    Parameters
    ----------
    vertices : (n, 3) float
        In any unit.
    size_m : float
        Wanted size [m], finite and > 0.

    Returns
    -------
    (n, 3) float64 [m]
        A new array.

    Raises
    ------
    ValueError
        ``size_m`` not finite and > 0, ``vertices`` not (n, 3), or an object of zero size.
    """
    target = _positive_finite("size_m", size_m)
    v = np.asarray(vertices, dtype=np.float64)
    size = mesh_size_m(v)
    if not (math.isfinite(size) and size > 0.0):
        raise ValueError(f"cannot scale an object of size {size!r} to {target:g} m")
    return v * (target / size)


def mesh_warnings(
    mesh: trimesh.Trimesh, patch_radius_m: float = 0.015, where: str = "mesh"
) -> list[str]:
    """What is probably wrong with a valid object mesh, as messages for the log.

    The checks (none raises; a valid mesh is always accepted):

    - size (:func:`mesh_size_m`) outside :data:`MIN_SIZE_M` - :data:`MAX_SIZE_M` (1 cm - 2 m):
      suggests ``--mesh-scale`` with the file unit that brings it in range (millimetres,
      centimetres, inches) or ``--mesh-size``; clients would otherwise get
      ``probe_out_of_range`` or a pebble;
    - fewer than :data:`MIN_VERTICES` vertices (an 8-vertex box): the surface cannot dent;
    - too coarse for the finger pad (only when the size is plausible): the median number of
      vertices within ``patch_radius_m`` of a vertex is below :data:`MIN_PATCH_VERTICES`
      (the median edge length is reported too); the contact would feel faceted and K_o jump
      from vertex to vertex. It suggests ``--mesh-max-edge`` of half the patch radius
      (:func:`load_mesh` ``max_edge_m``). The default icosphere (2562 vertices, r = 0.1 m) has 15 vertices
      under a 15 mm patch and 7.5 mm edges; 642 vertices has 5 and warns.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The object as the server will use it (after ``--mesh-scale``/``--mesh-size``), in m.
    patch_radius_m : float
        Finger-pad patch radius [m] (``BalloonParams.patch_radius_m``), > 0.
    where : str
        Name that starts each message (the mesh file).

    Returns
    -------
    list of str
        One message per problem, empty for a sensible object.

    Raises
    ------
    ValueError
        ``patch_radius_m`` not finite and > 0.
    """
    r = _positive_finite("patch_radius_m", patch_radius_m)
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    out: list[str] = []
    n = len(verts)
    size = mesh_size_m(verts) if n else 0.0
    size_ok = MIN_SIZE_M <= size <= MAX_SIZE_M
    if not size_ok:
        out.append(
            f"{where}: the object is {size:.3g} m across (largest bounding-box extent), "
            f"outside {MIN_SIZE_M * 100:g} cm - {MAX_SIZE_M:g} m; {_size_hint(size)}"
        )
    if n < MIN_VERTICES:
        out.append(
            f"{where}: only {n} vertices (a box or a low-poly model?): the surface cannot dent "
            f"under a finger; subdivide it to edges of at most {r / 2 * 1000:.3g} mm "
            f"(--mesh-max-edge {r / 2:.3g})"
        )
    elif size_ok:
        step = max(1, n // _PATCH_SAMPLES)
        counts = cKDTree(verts).query_ball_point(verts[::step], r, return_length=True)
        under = float(np.median(counts))
        edge = float(np.median(mesh.edges_unique_length))
        if under < MIN_PATCH_VERTICES:
            out.append(
                f"{where}: too coarse for a finger pad of radius {r * 1000:.3g} mm: a median of "
                f"{under:.0f} vertices under one patch (at least {MIN_PATCH_VERTICES} wanted), "
                f"median edge {edge * 1000:.3g} mm; contacts will feel faceted and K_o jump "
                f"between vertices. Refine it with --mesh-max-edge {r / 2:.3g} (edges of at most "
                f"{r / 2 * 1000:.3g} mm)"
            )
    return out


def _size_hint(size: float) -> str:
    """How to bring an object of ``size`` [m] to a plausible size: the file unit that would
    (millimetres, centimetres, inches) with its ``--mesh-scale``, else ``--mesh-size``."""
    fits = [(f, unit) for f, unit in _UNIT_GUESSES if MIN_SIZE_M <= size * f <= MAX_SIZE_M]
    if size > MAX_SIZE_M and fits:
        factor, unit = fits[0]
        return (
            f"if the file is in {unit}, give --mesh-scale {factor:g} "
            f"({size * factor:.3g} m), or set the size with --mesh-size"
        )
    return "set the size in metres with --mesh-size (e.g. --mesh-size 0.2)"


def _single_mesh(loaded: object, where: str) -> trimesh.Trimesh:
    """Flatten what :func:`trimesh.load` returned into one :class:`trimesh.Trimesh`."""
    if isinstance(loaded, trimesh.Trimesh):
        return loaded
    if isinstance(loaded, trimesh.Scene):
        parts = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        if not parts:
            raise MeshError(f"{where}: the file contains no triangle mesh")
        if len(parts) == 1:
            return parts[0]
        merged = trimesh.util.concatenate(parts)
        if not isinstance(merged, trimesh.Trimesh):
            raise MeshError(f"{where}: could not merge the scene's meshes")
        return merged
    raise MeshError(f"{where}: the file contains no triangle mesh (got {type(loaded).__name__})")


def _count(n: int, noun: str) -> str:
    """``"1 edge"``, ``"3 edges"``, ``"2 vertices"``."""
    plural = "vertices" if noun == "vertex" else f"{noun}s"
    return f"{n} {noun if n == 1 else plural}"


def _edge_counts(faces: IntArray) -> tuple[IntArray, IntArray]:
    """The undirected edges of ``faces`` (m, 3) and how many faces hold each.

    Returns ``(edges (e, 2) int64 sorted rows, counts (e,) int64)``; an edge from a vertex to
    itself (a collapsed face) is left out.
    """
    e = np.sort(np.asarray(faces, dtype=np.int64)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    e = e[e[:, 0] != e[:, 1]]
    if len(e) == 0:
        return e, np.zeros(0, dtype=np.int64)
    edges, counts = np.unique(e, axis=0, return_counts=True)
    return edges.astype(np.int64), counts.astype(np.int64)


def _nonmanifold_vertices(faces: IntArray) -> IntArray:
    """Vertices around which the faces form more than one fan (sheets touching at a point).

    ``faces`` (m, 3) with every edge shared by exactly two faces and no repeated index in a
    face. The corners (face, vertex) of one vertex are linked when their faces share an edge
    at that vertex; on a 2-manifold each vertex's corners form a single ring, so a vertex
    whose corners fall into more than one group is non-manifold.
    """
    f = np.asarray(faces, dtype=np.int64)
    n = 3 * len(f)
    corner = np.arange(n, dtype=np.int64)
    start = f.reshape(-1)  # the vertex at each corner, and the edge leaving it:
    end = f[:, [1, 2, 0]].reshape(-1)  # from corner c to the next corner of its face
    nxt = corner.reshape(-1, 3)[:, [1, 2, 0]].reshape(-1)
    lo, hi = np.minimum(start, end), np.maximum(start, end)
    order = np.lexsort((hi, lo))
    p, q = order[0::2], order[1::2]  # the two face sides of each edge
    rows, cols = [], []
    for v in (lo[p], hi[p]):
        rows.append(np.where(start[p] == v, p, nxt[p]))
        cols.append(np.where(start[q] == v, q, nxt[q]))
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r), dtype=np.int8), (r, c)), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    fans = np.unique(np.column_stack((start, label)), axis=0)
    verts, count = np.unique(fans[:, 0], return_counts=True)
    return verts[count > 1].astype(np.int64)


def _bodies(n_vertices: int, faces: IntArray) -> IntArray:
    """Faces per connected body of a closed manifold mesh, largest first. Shape (bodies,)."""
    f = np.asarray(faces, dtype=np.int64)
    e = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    graph = coo_matrix(
        (np.ones(len(e), dtype=np.int8), (e[:, 0], e[:, 1])), shape=(n_vertices, n_vertices)
    )
    _, label = connected_components(graph, directed=False)
    sizes = np.bincount(label[f[:, 0]])
    return np.sort(sizes[sizes > 0])[::-1].astype(np.int64)


def repair_report_of(mesh: trimesh.Trimesh) -> RepairReport | None:
    """What ``--mesh-repair`` changed in ``mesh`` (None: it was not repaired)."""
    report = mesh.metadata.get(REPAIR_KEY)
    return report if isinstance(report, RepairReport) else None


def repair_mesh(
    mesh: trimesh.Trimesh, where: str = "mesh", repair: bool = False
) -> trimesh.Trimesh:
    """Repair and validate a triangle mesh; the input is copied, never modified.

    Merges seam-split vertices, drops degenerate/duplicate faces and unreferenced vertices,
    makes the winding consistent and outward, then checks it is closed, manifold, one body
    and encloses a volume (module docstring: what is refused and why). With ``repair``
    (``--mesh-repair``), :func:`server.objects.repair.repair_mesh_topology` first makes it one
    closed body, logs what it changed and keeps that in ``metadata["mesh_repair"]``.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Any triangle mesh; it is copied, not modified.
    where : str
        Name used in error messages (a file path, say).
    repair : bool
        Mend an open, non-manifold or several-body mesh instead of refusing it.

    Returns
    -------
    trimesh.Trimesh
        A watertight, manifold, single-body mesh with outward normals and positive
        ``volume``, in the input's units.

    Raises
    ------
    MeshError
        No faces, non-finite coordinates, more than :data:`MAX_DEGENERATE_FRACTION` of the
        faces degenerate or a surface closed only through its degenerate faces, open surface
        (not watertight), non-manifold edges or vertices, several bodies, or zero volume.
    """
    m = trimesh.Trimesh(
        vertices=np.asarray(mesh.vertices, dtype=np.float64),
        faces=np.asarray(mesh.faces, dtype=np.int64),
        process=False,
        validate=False,
    )
    if len(m.faces) == 0 or len(m.vertices) == 0:
        raise MeshError(f"{where}: the mesh has no faces")
    if not np.all(np.isfinite(m.vertices)):
        raise MeshError(f"{where}: vertex coordinates contain NaN or infinity")
    report: RepairReport | None = None
    if repair:
        try:
            m, report = repair_mesh_topology(m)
        except RepairError as exc:
            raise MeshError(f"{where}: --mesh-repair could not mend it: {exc}") from None
        log.info("%s: %s", where, report.summary())
    m.merge_vertices(merge_tex=True, merge_norm=True)
    n_faces = len(m.faces)
    keep = np.asarray(m.nondegenerate_faces(), dtype=bool)
    n_degenerate = int(n_faces - np.count_nonzero(keep))
    if n_degenerate == n_faces:
        raise MeshError(f"{where}: every face is degenerate (zero area)")
    if n_degenerate > MAX_DEGENERATE_FRACTION * n_faces:
        raise MeshError(
            f"{where}: {n_degenerate} of {n_faces} faces ({100.0 * n_degenerate / n_faces:.2g} %)"
            f" are degenerate (zero area: collapsed or collinear vertices), more than the "
            f"{100.0 * MAX_DEGENERATE_FRACTION:g} % that are dropped silently; the export is "
            "probably broken (coordinates rounded to too few digits?): export it again or clean "
            "it in a mesh editor"
        )
    closed_before = False
    if n_degenerate:
        closed_before = bool(np.all(_edge_counts(m.faces)[1] == 2))
        m.update_faces(keep)
    m.update_faces(m.unique_faces())
    m.remove_unreferenced_vertices()
    faces = np.asarray(m.faces, dtype=np.int64)
    _, counts = _edge_counts(faces)
    n_open = int(np.count_nonzero(counts == 1))
    n_shared = int(np.count_nonzero(counts > 2))
    if n_open and closed_before:
        raise MeshError(
            f"{where}: the surface is closed only through {n_degenerate} degenerate (zero-area) "
            f"faces: dropping them leaves {n_open} open edges (they fill cracks at T-junctions); "
            f"repair the mesh in a mesh editor (weld the T-junctions){REPAIR_HINT}"
        )
    if n_open:
        shared = f", and {n_shared} to more than two" if n_shared else ""
        raise MeshError(
            f"{where}: the surface is not closed (not watertight: {_count(n_open, 'edge')} "
            f"belonging to one face only{shared}); a deformable object needs a closed mesh"
            f"{REPAIR_HINT}"
        )
    if n_shared:
        raise MeshError(
            f"{where}: the surface is not manifold: {_count(n_shared, 'edge')} shared by more "
            "than two faces (non-manifold edges: a fin, an inner wall, or parts touching along an edge); "
            "a deformable object needs a closed mesh where every edge joins exactly two faces"
            f"{REPAIR_HINT}"
        )
    pinched = _nonmanifold_vertices(faces)
    if len(pinched):
        raise MeshError(
            f"{where}: the surface is not manifold: at {_count(len(pinched), 'vertex')} pieces "
            "of surface meet only at that point (non-manifold vertices, e.g. two parts touching at a "
            f"corner); separate or weld the parts in a mesh editor{REPAIR_HINT}"
        )
    bodies = _bodies(len(m.vertices), faces)
    if len(bodies) > 1:
        raise MeshError(
            f"{where}: the mesh has {len(bodies)} separate bodies (connected pieces of surface; "
            f"the largest has {bodies[0]} of {len(faces)} faces); a deformable object is one "
            "closed surface: keep the largest body (delete the others in a mesh editor) or join "
            f"them into one{REPAIR_HINT}"
        )
    extents = np.asarray(m.extents, dtype=np.float64)
    box_volume = float(np.prod(extents))
    with np.errstate(all="ignore"):  # trimesh divides by the volume for the centre of mass
        trimesh.repair.fix_normals(m, multibody=True)
        volume = float(m.volume)
    if (
        not math.isfinite(volume)
        or box_volume <= 0.0
        or abs(volume) <= _MIN_VOLUME_FRACTION * box_volume
    ):
        raise MeshError(f"{where}: the mesh is degenerate (it encloses zero volume)")
    if volume < 0.0:
        m.invert()
    if report is not None:
        m.metadata[REPAIR_KEY] = report
    return m


def refine_mesh(mesh: trimesh.Trimesh, max_edge_m: float, where: str = "mesh") -> trimesh.Trimesh:
    """Split every edge longer than ``max_edge_m`` at its midpoint until none is left.

    :func:`trimesh.remesh.subdivide_to_size`: new vertices lie on the old edges, so the shape,
    its volume and its sharp edges are kept exactly (no smoothing); only faces with a long edge
    are split, so a mesh already fine enough is returned unchanged. ``--mesh-max-edge``.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        A closed mesh as :func:`repair_mesh` returns it, in metres.
    max_edge_m : float
        Longest edge wanted [m], finite and > 0 (half the finger-pad radius, 0.0075 m, gives
        at least 7 vertices under a 15 mm patch).
    where : str
        Name used in error messages.

    Returns
    -------
    trimesh.Trimesh
        A new closed mesh, ``vertices`` (n', 3) [m] (the old ones first), ``faces`` (m', 3),
        every edge at most ``max_edge_m``, same winding and volume.

    Raises
    ------
    ValueError
        ``max_edge_m`` not finite and > 0.
    MeshError
        The refinement would make more than :data:`MAX_REFINED_FACES` faces (estimated before
        any work), or the result is not closed (a trimesh whose ``subdivide_to_size`` splits a
        face without its neighbour).
    """
    h = _positive_finite("max_edge_m", max_edge_m)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    longest = np.max(np.linalg.norm(v[f] - v[f[:, [1, 2, 0]]], axis=2), axis=1)
    levels = np.ceil(np.log2(np.maximum(longest / h, 1.0))).astype(np.int64)
    estimate = float(np.sum(4.0 ** np.minimum(levels, 30)))
    if estimate > MAX_REFINED_FACES:
        raise MeshError(
            f"{where}: refining to edges of at most {h * 1000:.3g} mm would make about "
            f"{estimate:.3g} faces (more than {MAX_REFINED_FACES}); give a larger "
            "--mesh-max-edge or a finer mesh"
        )
    if not np.any(levels):
        return mesh.copy()
    nv, nf = trimesh.remesh.subdivide_to_size(v, f, max_edge=h, max_iter=int(levels.max()) + 1)
    out = trimesh.Trimesh(nv, nf, process=False)
    if np.any(_edge_counts(np.asarray(out.faces))[1] != 2):
        raise MeshError(
            f"{where}: refining to edges of at most {h * 1000:.3g} mm opened the surface "
            f"(trimesh {trimesh.__version__} splits faces without their neighbours: update "
            "trimesh, or refine the mesh in a mesh editor)"
        )
    return out


def prepare_mesh(
    mesh: trimesh.Trimesh,
    where: str = "mesh",
    scale: float | None = None,
    target_size_m: float | None = None,
    max_edge_m: float | None = None,
    repair: bool = False,
) -> trimesh.Trimesh:
    """Repair, validate, scale, size-check and optionally refine a mesh in memory.

    What :func:`load_mesh` does once the file is read: :func:`repair_mesh`, then ``scale`` or
    ``target_size_m``, then the size check (:data:`MIN_SIZE_ERROR_M` - :data:`MAX_SIZE_ERROR_M`
    after scaling), then :func:`refine_mesh` with ``max_edge_m``.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Any triangle mesh (copied, not modified), in file units.
    where : str
        Name used in error messages (the file, or a shape's name).
    scale : float, optional
        Uniform factor from the mesh's units to metres.
    target_size_m : float, optional
        Rescale so the largest bounding-box extent equals this [m]. Exclusive with ``scale``.
    max_edge_m : float, optional
        Split edges until none is longer than this [m] (after scaling).
    repair : bool
        ``--mesh-repair``: mend an open, non-manifold or several-body mesh
        (:func:`repair_mesh`); :func:`repair_report_of` the result says what changed.

    Returns
    -------
    trimesh.Trimesh
        ``vertices`` (n, 3) float64 [m], ``faces`` (m, 3) int64; watertight, manifold, one
        body, outward winding, positive volume.

    Raises
    ------
    MeshError
        As :func:`repair_mesh` and :func:`refine_mesh`; an object smaller than 1 mm or larger
        than 20 m after scaling (the message suggests ``--mesh-scale`` or ``--mesh-size``).
    ValueError
        ``scale``, ``target_size_m`` or ``max_edge_m`` not finite and positive, or both
        ``scale`` and ``target_size_m`` given.
    """
    if scale is not None and target_size_m is not None:
        raise ValueError("give either scale or target_size_m, not both")
    factor = None if scale is None else _positive_finite("scale", scale)
    target = None if target_size_m is None else _positive_finite("target_size_m", target_size_m)
    h = None if max_edge_m is None else _positive_finite("max_edge_m", max_edge_m)
    m = repair_mesh(mesh, where, repair=repair)
    if factor is None and target is not None:
        m.vertices = scale_mesh_to_size(m.vertices, target)
    elif factor is not None and factor != 1.0:
        m.apply_scale(factor)
    size = mesh_size_m(m.vertices)
    if not MIN_SIZE_ERROR_M <= size <= MAX_SIZE_ERROR_M:
        scaled = "after scaling" if factor is not None or target is not None else "read as metres"
        raise MeshError(
            f"{where}: the object is {size:.3g} m across {scaled} (largest bounding-box "
            f"extent), outside {MIN_SIZE_ERROR_M * 1000:g} mm - {MAX_SIZE_ERROR_M:g} m: not an "
            f"object a hand can touch; {_size_hint(size)}"
        )
    if h is not None:
        report = repair_report_of(m)
        m = refine_mesh(m, h, where)
        if report is not None:
            m.metadata[REPAIR_KEY] = report
    return m


def load_mesh(
    path: str | Path,
    scale: float | None = None,
    target_size_m: float | None = None,
    max_edge_m: float | None = None,
    repair: bool = False,
) -> trimesh.Trimesh:
    """Load, repair and validate a closed triangle mesh file (STL, OBJ, PLY, OFF, GLB).

    DESIGN section 5 ("any closed triangle mesh"); repairs as listed in the module docstring.

    Parameters
    ----------
    path : str or pathlib.Path
        The mesh file. Its suffix selects the format.
    scale : float, optional
        Uniform factor from file units to metres (0.001 for a file in millimetres).
    target_size_m : float, optional
        Rescale so the largest bounding-box extent equals this [m]. Exclusive with ``scale``.
    max_edge_m : float, optional
        Refine (:func:`refine_mesh`, after scaling) until no edge is longer than this [m]
        (``--mesh-max-edge``); None leaves the mesh as it is.
    repair : bool
        ``--mesh-repair`` (:func:`prepare_mesh`).

    Returns
    -------
    trimesh.Trimesh
        ``vertices`` (n, 3) float64 [m], ``faces`` (m, 3) int64; watertight, manifold, one
        body, outward winding, positive volume, 1 mm - 20 m across.

    Raises
    ------
    MeshError
        The file does not exist, has an unsupported suffix, cannot be parsed, or fails a check
        of :func:`prepare_mesh`: no faces, NaN/inf, too many degenerate faces, not closed
        after merging seams (not watertight), not manifold, several bodies, zero volume, an
        absurd size after scaling, or a refinement too fine.
    ValueError
        ``scale``, ``target_size_m`` or ``max_edge_m`` not finite and positive, or both
        ``scale`` and ``target_size_m`` given.
    """
    if scale is not None and target_size_m is not None:
        raise ValueError("give either scale or target_size_m, not both")
    for name, value in (
        ("scale", scale),
        ("target_size_m", target_size_m),
        ("max_edge_m", max_edge_m),
    ):
        if value is not None:
            _positive_finite(name, value)

    p = Path(path)
    where = str(p)
    if not p.is_file():
        raise MeshError(f"{where}: mesh file does not exist")
    suffix = p.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise MeshError(
            f"{where}: unsupported mesh format {suffix or '(no suffix)'!r}; "
            f"use one of {', '.join(SUPPORTED_SUFFIXES)}"
        )
    try:
        loaded = trimesh.load(p, file_type=suffix[1:], process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        detail = "unreadable content" if isinstance(exc, ImportError) else f"{exc}"
        raise MeshError(
            f"{where}: could not parse the file as {suffix[1:].upper()} ({detail})"
        ) from exc
    return prepare_mesh(
        _single_mesh(loaded, where),
        where,
        scale=scale,
        target_size_m=target_size_m,
        max_edge_m=max_edge_m,
        repair=repair,
    )
