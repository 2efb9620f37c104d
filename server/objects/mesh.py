"""Closed triangle meshes for deformable objects: the default balloon and validated mesh files.

DESIGN section 5: the default object is "any closed triangle mesh (icosphere from trimesh by
default, or a mesh file)". An admittance model needs a *closed* (watertight), consistently wound
surface enclosing a positive volume: the water term of the balloon is the enclosed volume, and the
outward normals define which way "pushing in" is. This module is the one place where mesh files
are read; everything past it receives a repaired, validated :class:`trimesh.Trimesh` in metres.

Repairs applied by :func:`load_mesh`, in order:

1. a scene (several geometries, e.g. a GLB) is flattened into one mesh with its transforms;
2. vertices split at texture or normal seams are merged (``merge_tex``/``merge_norm``);
3. degenerate (zero-area) and duplicate faces, then unreferenced vertices, are dropped;
4. winding and normals are made consistent and outward (positive volume);
5. a uniform scale is applied (``scale``, or ``target_size_m`` for the largest extent).

A mesh that stays open after this, has no faces, contains NaN/inf, or encloses no volume is
refused with a :class:`MeshError` whose message says which check failed.

A mesh that is valid but probably not what the user meant is accepted, and
:func:`mesh_warnings` says why (the server logs it): a size outside 1 cm - 2 m (a file in
millimetres read as metres, say), a model too coarse for a 15 mm finger-pad patch, or a box of
a few vertices that cannot dent.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import numpy.typing as npt
import trimesh
from scipy.spatial import cKDTree

from haptic_collab.shared.checks import positive as _positive_finite
from haptic_collab.shared.types import FloatArray

#: File suffixes :func:`load_mesh` accepts (lower case, with the dot).
SUPPORTED_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".glb")

#: Enclosed volume below this fraction of the bounding-box volume counts as degenerate.
_MIN_VOLUME_FRACTION = 1e-9

#: Object sizes [m] (largest bounding-box extent) outside which :func:`mesh_warnings` warns.
MIN_SIZE_M = 0.01
MAX_SIZE_M = 2.0

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
    unsupported format, unparsable content, no faces, non-finite coordinates, not watertight
    (with the number of open edges), or zero enclosed volume.
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
      from vertex to vertex. The default icosphere (2562 vertices, r = 0.1 m) has 15 vertices
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
        fits = [(f, unit) for f, unit in _UNIT_GUESSES if MIN_SIZE_M <= size * f <= MAX_SIZE_M]
        if size > MAX_SIZE_M and fits:
            factor, unit = fits[0]
            hint = (
                f"if the file is in {unit}, give --mesh-scale {factor:g} "
                f"({size * factor:.3g} m), or set the size with --mesh-size"
            )
        else:
            hint = "set the size in metres with --mesh-size (e.g. --mesh-size 0.2)"
        out.append(
            f"{where}: the object is {size:.3g} m across (largest bounding-box extent), "
            f"outside {MIN_SIZE_M * 100:g} cm - {MAX_SIZE_M:g} m; {hint}"
        )
    if n < MIN_VERTICES:
        out.append(
            f"{where}: only {n} vertices (a box or a low-poly model?): the surface cannot dent "
            f"under a finger; subdivide it to edges of at most {r / 2 * 1000:.3g} mm"
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
                f"between vertices. Subdivide the mesh (edges of at most {r / 2 * 1000:.3g} mm)"
            )
    return out


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


def repair_mesh(mesh: trimesh.Trimesh, where: str = "mesh") -> trimesh.Trimesh:
    """Repair and validate a triangle mesh; the input is copied, never modified.

    Merges seam-split vertices, drops degenerate/duplicate faces and unreferenced vertices,
    makes the winding consistent and outward, then checks it is closed and encloses a volume.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Any triangle mesh; it is copied, not modified.
    where : str
        Name used in error messages (a file path, say).

    Returns
    -------
    trimesh.Trimesh
        A watertight mesh with outward normals and positive ``volume``.

    Raises
    ------
    MeshError
        No faces, non-finite coordinates, open surface (not watertight), or zero volume.
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
    m.merge_vertices(merge_tex=True, merge_norm=True)
    m.update_faces(m.nondegenerate_faces())
    m.update_faces(m.unique_faces())
    m.remove_unreferenced_vertices()
    if len(m.faces) == 0:
        raise MeshError(f"{where}: every face is degenerate (zero area)")
    if not m.is_watertight:
        edges = np.sort(m.edges, axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        open_edges = int(np.sum(counts != 2))
        raise MeshError(
            f"{where}: the surface is not closed (not watertight: {open_edges} edges are not "
            "shared by exactly two faces); a deformable object needs a closed mesh"
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
    return m


def load_mesh(
    path: str | Path, scale: float | None = None, target_size_m: float | None = None
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

    Returns
    -------
    trimesh.Trimesh
        ``vertices`` (n, 3) float64 [m], ``faces`` (m, 3) int64; watertight, outward winding,
        positive volume.

    Raises
    ------
    MeshError
        The file does not exist, has an unsupported suffix, cannot be parsed, has no faces,
        contains NaN/inf, stays open after merging seams (not watertight), or encloses zero
        volume.
    ValueError
        ``scale`` or ``target_size_m`` not finite and positive, or both given.
    """
    if scale is not None and target_size_m is not None:
        raise ValueError("give either scale or target_size_m, not both")
    factor = None if scale is None else _positive_finite("scale", scale)
    target = None if target_size_m is None else _positive_finite("target_size_m", target_size_m)

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
    mesh = repair_mesh(_single_mesh(loaded, where), where)
    if factor is None and target is not None:
        mesh.vertices = scale_mesh_to_size(mesh.vertices, target)
    elif factor is not None and factor != 1.0:
        mesh.apply_scale(factor)
    return mesh
