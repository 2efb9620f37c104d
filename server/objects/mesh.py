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
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import trimesh

#: File suffixes :func:`load_mesh` accepts (lower case, with the dot).
SUPPORTED_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".glb")

#: Enclosed volume below this fraction of the bounding-box volume counts as degenerate.
_MIN_VOLUME_FRACTION = 1e-9


class MeshError(ValueError):
    """A mesh file or mesh that cannot be used as a closed deformable surface.

    The message names the file (when there is one) and the failed check: missing file,
    unsupported format, unparsable content, no faces, non-finite coordinates, not watertight
    (with the number of open edges), or zero enclosed volume.
    """


def _positive_finite(name: str, value: float) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return v


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
        factor = target / float(np.max(mesh.extents))
    if factor is not None and factor != 1.0:
        mesh.apply_scale(factor)
    return mesh
