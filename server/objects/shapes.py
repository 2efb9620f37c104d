"""The stress set: closed object meshes that are harder than the default balloon.

DESIGN section 5 allows "any closed triangle mesh". The default icosphere is the easiest case
there is (regular, convex, uniform); these shapes are what a real mesh brings instead, each built
here with numpy and trimesh (no files), in metres, 0.15 - 0.25 m across (a hand-sized object, as
the balloon), closed (watertight), one body, wound outward (positive volume), with no edge
longer than :data:`STRESS_MAX_EDGE_M` (7 mm), so a finger-pad patch of radius 15 mm covers at
least 7 vertices everywhere:

``torus``
    genus 1 (a hole through it): major radius 70 mm, tube radius 30 mm, 0.2 m across.
``box``
    0.20 x 0.16 x 0.12 m with sharp 90 degree edges and corners, every face a fine grid.
``plate``
    a thin plate 0.20 x 0.15 m and 9 mm thick, sharp edges (two rows of vertices on its rim).
``bowl``
    concave: a hemispherical bowl, outer radius 0.1 m, wall 20 mm thick, a closed solid whose
    sharp rim joins the outer and inner surfaces.
``noisy-sphere``
    a scan-like sphere of radius 75 mm whose vertices carry seeded radial noise (Gaussian,
    standard deviation 0.5 mm, clipped at 1.5 mm: about 1 mm of roughness), deterministic.
``uneven``
    a sphere of radius 80 mm whose upper hemisphere is meshed 4 times finer (edges about
    1.5 mm) than the lower one (about 6 mm), joined at the equator without a crack.

:func:`stress_mesh` builds one by name (:data:`STRESS_MESHES`); ``haptic server --mesh NAME``
takes these names besides ``balloon`` and a mesh file (:func:`load_object_mesh`). :func:`write_textured_obj` writes one of
them as a textured OBJ whose vertices are split at UV seams, as exporters write them, to check
that :func:`server.objects.mesh.load_mesh` merges the seams back.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import cache
from pathlib import Path

import numpy as np
import trimesh

from haptic_collab.server.objects.mesh import SUPPORTED_SUFFIXES, MeshError, load_mesh, prepare_mesh
from haptic_collab.shared.types import FloatArray, IntArray

#: The names :func:`stress_mesh` builds, in the order of the module docstring.
STRESS_MESHES = ("torus", "box", "plate", "bowl", "noisy-sphere", "uneven")

#: No edge of a stress shape is longer than this [m]: with it a 15 mm finger-pad patch covers at
#: least 7 vertices (a vertex and its ring), the smallest stencil on which a dent has a shape.
STRESS_MAX_EDGE_M = 0.007

#: Grid and ring spacing [m]: a quad of two such sides has a diagonal of 6.9 mm.
_SPACING_M = 0.0049

#: Seed and size of the noisy sphere's radial noise [m].
_NOISE_SEED = 20050101
_NOISE_SIGMA_M = 0.0005
_NOISE_CLIP_M = 0.0015


# ---------------------------------------------------------------------------------- building blocks
def _arc(
    center: tuple[float, float], radius: float, a0: float, a1: float, spacing: float
) -> FloatArray:
    """Points ``(rho, z)`` [m] on a circular arc from angle ``a0`` to ``a1`` [rad], both ends
    included, no further apart than ``spacing`` along the arc. Shape (k, 2)."""
    n = max(1, math.ceil(abs(a1 - a0) * radius / spacing))
    a = np.linspace(a0, a1, n + 1)
    return np.column_stack((center[0] + radius * np.cos(a), center[1] + radius * np.sin(a)))


def _line(p0: tuple[float, float], p1: tuple[float, float], spacing: float) -> FloatArray:
    """Points ``(rho, z)`` [m] on the segment ``p0``-``p1``, ends included. Shape (k, 2)."""
    n = max(1, math.ceil(math.dist(p0, p1) / spacing))
    t = np.linspace(0.0, 1.0, n + 1)[:, None]
    return (1.0 - t) * np.asarray(p0, dtype=np.float64) + t * np.asarray(p1, dtype=np.float64)


def _join(*parts: FloatArray) -> FloatArray:
    """Profile pieces joined end to start (the shared point kept once). Shape (k, 2)."""
    return np.vstack([parts[0], *(p[1:] for p in parts[1:])])


def _zipper(a: IntArray, pa: FloatArray, b: IntArray, pb: FloatArray) -> list[list[int]]:
    """Triangles stitching ring ``a`` (vertex ids, positions ``pa`` (n, 3) [m]) to ring ``b``.

    Both rings run the same way round and start at about the same angle. The walk goes once
    round both, each step adding the triangle whose new edge across the strip is the shorter
    one, so rings of different vertex counts join without a crack (``len(a) + len(b)``
    triangles). Ring ``a`` precedes ``b`` along the profile; the winding follows from that.
    """
    na, nb = len(a), len(b)
    out: list[list[int]] = []
    j = k = 0
    while j < na or k < nb:
        if k < nb and j < na:
            via_a = np.linalg.norm(pa[(j + 1) % na] - pb[k % nb])
            via_b = np.linalg.norm(pa[j % na] - pb[(k + 1) % nb])
            advance_a = bool(via_a <= via_b)
        else:
            advance_a = j < na
        if advance_a:
            out.append([int(a[j % na]), int(a[(j + 1) % na]), int(b[k % nb])])
            j += 1
        else:
            out.append([int(a[j % na]), int(b[(k + 1) % nb]), int(b[k % nb])])
            k += 1
    return out


def _revolve(profile: FloatArray, spacing: FloatArray, closed: bool) -> trimesh.Trimesh:
    """The closed surface swept by a profile ``(rho, z)`` turning about the z axis.

    Parameters
    ----------
    profile : (k, 2) float [m]
        ``(rho, z)`` points. ``closed``: a loop off the axis (a torus); otherwise the first and
        last points lie on the axis (rho = 0) and become poles.
    spacing : (k,) float [m]
        Wanted distance between neighbours around each point's ring; each ring gets
        ``ceil(2 pi rho / spacing)`` vertices (at least 6), alternate rings turned by half a
        step, and neighbouring rings are stitched with :func:`_zipper`.
    closed : bool

    Returns
    -------
    trimesh.Trimesh
        Watertight, wound outward (positive volume).
    """
    rings = profile if closed else profile[1:-1]
    ring_spacing = spacing if closed else spacing[1:-1]
    verts: list[FloatArray] = []
    ids: list[IntArray] = []
    ring_xyz: list[FloatArray] = []
    start = 0 if closed else 2  # the poles are vertices 0 and 1
    if not closed:
        verts.append(np.array([[0.0, 0.0, profile[0, 1]], [0.0, 0.0, profile[-1, 1]]]))
    for i, ((rho, z), h) in enumerate(zip(rings, ring_spacing, strict=True)):
        n = max(6, math.ceil(2.0 * math.pi * rho / h))
        theta = 2.0 * math.pi * (np.arange(n) + 0.5 * (i % 2)) / n
        xyz = np.column_stack((rho * np.cos(theta), rho * np.sin(theta), np.full(n, z)))
        verts.append(xyz)
        ring_xyz.append(xyz)
        ids.append(np.arange(start, start + n, dtype=np.int64))
        start += n
    faces: list[list[int]] = []
    for i in range(len(ids) - 1):
        faces += _zipper(ids[i], ring_xyz[i], ids[i + 1], ring_xyz[i + 1])
    if closed:
        faces += _zipper(ids[-1], ring_xyz[-1], ids[0], ring_xyz[0])
    else:
        first, last = ids[0], ids[-1]
        faces += [[0, int(first[(j + 1) % len(first)]), int(first[j])] for j in range(len(first))]
        faces += [[1, int(last[j]), int(last[(j + 1) % len(last)])] for j in range(len(last))]
    mesh = trimesh.Trimesh(np.vstack(verts), np.asarray(faces, dtype=np.int64), process=False)
    if mesh.volume < 0.0:
        mesh.invert()
    return mesh


def _grid_box(extents: tuple[float, float, float], spacing: float) -> trimesh.Trimesh:
    """A box centred at the origin whose six faces are grids no coarser than ``spacing``.

    The edges and corners stay sharp (90 degrees); vertices on them are shared by the faces
    that meet there, so the box is watertight. Wound outward.
    """
    ext = np.asarray(extents, dtype=np.float64)
    counts = [max(1, math.ceil(e / spacing)) for e in ext]
    axes = [np.linspace(-e / 2.0, e / 2.0, n + 1) for e, n in zip(ext, counts, strict=True)]
    points: list[FloatArray] = []
    tris: list[IntArray] = []
    offset = 0
    for k in range(3):
        u, v = (k + 1) % 3, (k + 2) % 3  # e_u x e_v = e_k
        nu, nv = counts[u], counts[v]
        gu, gv = np.meshgrid(axes[u], axes[v], indexing="ij")
        idx = np.arange((nu + 1) * (nv + 1), dtype=np.int64).reshape(nu + 1, nv + 1)
        p00, p10 = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
        p11, p01 = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        quad = np.vstack((np.column_stack((p00, p10, p11)), np.column_stack((p00, p11, p01))))
        for sign in (-1.0, 1.0):
            pts = np.zeros((gu.size, 3))
            pts[:, k] = sign * ext[k] / 2.0
            pts[:, u], pts[:, v] = gu.ravel(), gv.ravel()
            points.append(pts)
            tris.append(offset + (quad if sign > 0 else quad[:, ::-1]))
            offset += len(pts)
    allpts = np.vstack(points)
    unique, inverse = np.unique(allpts, axis=0, return_inverse=True)
    faces = inverse.reshape(-1)[np.vstack(tris)]
    return trimesh.Trimesh(unique, faces, process=False)


# ---------------------------------------------------------------------------------------- the shapes
def _torus() -> trimesh.Trimesh:
    major, minor = 0.07, 0.03
    profile = _arc((major, 0.0), minor, 0.0, 2.0 * math.pi, _SPACING_M)[:-1]  # a loop
    return _revolve(profile, np.full(len(profile), _SPACING_M), closed=True)


def _box() -> trimesh.Trimesh:
    return _grid_box((0.20, 0.16, 0.12), _SPACING_M)


def _plate() -> trimesh.Trimesh:
    return _grid_box((0.20, 0.15, 0.009), _SPACING_M)


def _bowl() -> trimesh.Trimesh:
    outer, inner = 0.10, 0.08
    profile = _join(
        _arc((0.0, 0.0), outer, -math.pi / 2.0, 0.0, _SPACING_M),  # outside, bottom to rim
        _line((outer, 0.0), (inner, 0.0), _SPACING_M),  # the flat rim
        _arc((0.0, 0.0), inner, 0.0, -math.pi / 2.0, _SPACING_M),  # inside, rim to bottom
    )
    return _revolve(profile, np.full(len(profile), _SPACING_M), closed=False)


def _noisy_sphere() -> trimesh.Trimesh:
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.075)
    rng = np.random.default_rng(_NOISE_SEED)
    noise = np.clip(
        rng.normal(0.0, _NOISE_SIGMA_M, len(sphere.vertices)), -_NOISE_CLIP_M, _NOISE_CLIP_M
    )
    v = np.asarray(sphere.vertices, dtype=np.float64)
    r = np.linalg.norm(v, axis=1)
    # radial moves keep every triangle's projection on the sphere, so none turns inside out
    return trimesh.Trimesh(v * ((r + noise) / r)[:, None], sphere.faces, process=False)


def _uneven() -> trimesh.Trimesh:
    radius, coarse, fine = 0.076, 0.0048, 0.0012
    lower = _arc((0.0, 0.0), radius, -math.pi / 2.0, 0.0, coarse)
    upper = _arc((0.0, 0.0), radius, 0.0, math.pi / 2.0, fine)
    profile = _join(lower, upper)
    spacing = np.where(profile[:, 1] < -1e-12, coarse, fine)  # the equator ring is fine
    return _revolve(profile, spacing, closed=False)


_BUILDERS: dict[str, Callable[[], trimesh.Trimesh]] = {
    "torus": _torus,
    "box": _box,
    "plate": _plate,
    "bowl": _bowl,
    "noisy-sphere": _noisy_sphere,
    "uneven": _uneven,
}


@cache
def _arrays(name: str) -> tuple[FloatArray, IntArray]:
    mesh = _BUILDERS[name]()
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    v.flags.writeable = False
    f.flags.writeable = False
    return v, f


def stress_mesh(name: str) -> trimesh.Trimesh:
    """One shape of the stress set, built in memory.

    Parameters
    ----------
    name : str
        One of :data:`STRESS_MESHES`: ``torus``, ``box``, ``plate``, ``bowl``,
        ``noisy-sphere``, ``uneven`` (module docstring).

    Returns
    -------
    trimesh.Trimesh
        A new mesh each call (built once per process): ``vertices`` (n, 3) float64 [m] centred
        near the origin, ``faces`` (m, 3) int64; watertight, one body, outward winding,
        0.15 - 0.25 m across, no edge longer than :data:`STRESS_MAX_EDGE_M`.

    Raises
    ------
    ValueError
        An unknown name; the message lists the names.
    """
    if name not in _BUILDERS:
        raise ValueError(
            f"unknown stress shape {name!r}; the shapes are {', '.join(STRESS_MESHES)}"
        )
    v, f = _arrays(name)
    return trimesh.Trimesh(v.copy(), f.copy(), process=False)


def load_object_mesh(
    spec: str,
    scale: float | None = None,
    target_size_m: float | None = None,
    max_edge_m: float | None = None,
    repair: bool = False,
) -> trimesh.Trimesh:
    """The object of ``--mesh SPEC`` (other than ``balloon``): a stress shape or a mesh file.

    A name of :data:`STRESS_MESHES` is built (:func:`stress_mesh`) and goes through the same
    checks, scaling and refinement as a file (:func:`server.objects.mesh.prepare_mesh`);
    anything else is a path for :func:`server.objects.mesh.load_mesh`. A name wins over a file
    of the same name in the working folder (such a file has no mesh suffix anyway).

    Parameters
    ----------
    spec : str
        A shape name or a mesh file path.
    scale, target_size_m, max_edge_m : float, optional
        ``--mesh-scale`` (a factor to metres), ``--mesh-size`` [m] and ``--mesh-max-edge`` [m],
        as :func:`server.objects.mesh.load_mesh`.
    repair : bool
        ``--mesh-repair`` (:func:`server.objects.mesh.prepare_mesh`): mend an open,
        non-manifold or several-body file instead of refusing it.

    Returns
    -------
    trimesh.Trimesh
        Watertight, manifold, one body, outward winding, in metres.

    Raises
    ------
    MeshError
        ``spec`` neither a shape name nor an existing file (the message lists the names), or
        any failure of :func:`server.objects.mesh.load_mesh`.
    ValueError
        Bad ``scale``, ``target_size_m`` or ``max_edge_m``.
    """
    if spec in _BUILDERS:
        return prepare_mesh(
            stress_mesh(spec),
            spec,
            scale=scale,
            target_size_m=target_size_m,
            max_edge_m=max_edge_m,
            repair=repair,
        )
    if not Path(spec).exists():
        raise MeshError(
            f"{spec}: no such mesh file, and not an object name; give balloon, one of "
            f"{', '.join(STRESS_MESHES)}, or a mesh file ({' '.join(SUPPORTED_SUFFIXES)})"
        )
    return load_mesh(
        spec, scale=scale, target_size_m=target_size_m, max_edge_m=max_edge_m, repair=repair
    )


def write_textured_obj(path: str | Path, name: str = "torus") -> Path:
    """Write a stress shape as a textured OBJ whose vertices are split at UV seams.

    Texture coordinates are a cylindrical map: ``u`` the angle about the z axis over 2 pi,
    ``v`` the height over the object's height. Where a face straddles the cut at angle pi its
    corners get ``u + 1``, so every vertex on the cut is written twice (once per side, with
    its own ``vt``), as exporters write textured models; on the z axis (the poles of ``bowl``
    and ``uneven``) every face gets its own copy of the pole. Positions of the copies are
    written identically, so merging by position restores the closed mesh. A material file
    (same stem, ``.mtl``, a flat colour, no image) is written beside it.

    Parameters
    ----------
    path : str or pathlib.Path
        The ``.obj`` file to write (its folder must exist).
    name : str
        A name of :data:`STRESS_MESHES`.

    Returns
    -------
    pathlib.Path
        ``path``. The file holds more ``v`` lines than :func:`stress_mesh` ``(name)`` has
        vertices, one ``vt`` per ``v``, and faces ``f a/a b/b c/c``.

    Raises
    ------
    ValueError
        An unknown name.
    OSError
        The file cannot be written.
    """
    mesh = stress_mesh(name)
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.faces)
    u = (np.arctan2(v[:, 1], v[:, 0]) + math.pi) / (2.0 * math.pi)  # in [0, 1], cut at angle pi
    h = v[:, 2]
    tv = (h - h.min()) / max(float(np.ptp(h)), 1e-12)
    on_axis = np.hypot(v[:, 0], v[:, 1]) < 1e-12
    # a pole has no angle of its own: it takes its face's other corners' mean, after the cut
    corner_u = np.where(on_axis[f], np.nan, u[f])
    straddles = np.nanmax(corner_u, axis=1) - np.nanmin(corner_u, axis=1) > 0.5
    corner_u = np.where(straddles[:, None] & (corner_u < 0.5), corner_u + 1.0, corner_u)
    corner_u = np.where(on_axis[f], np.nanmean(corner_u, axis=1)[:, None], corner_u)
    # one written vertex per distinct (vertex, u): two on the cut, one per face at a pole
    keys = np.column_stack((f.reshape(-1), corner_u.reshape(-1)))
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    src = unique[:, 0].astype(np.int64)
    out_u = unique[:, 1]
    p = Path(path)
    mtl = p.with_suffix(".mtl")
    mtl.write_text("newmtl skin\nKa 1 1 1\nKd 0.8 0.3 0.3\nKs 0 0 0\nd 1\nillum 1\n")
    lines = [f"# stress shape {name}: vertices split at UV seams", f"mtllib {mtl.name}"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in v[src]]
    lines += [f"vt {a:.9g} {b:.9g}" for a, b in zip(out_u, tv[src], strict=True)]
    lines.append("usemtl skin")
    corners = np.asarray(inverse).reshape(f.shape) + 1
    lines += [f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in corners]
    p.write_text("\n".join(lines) + "\n")
    return p
