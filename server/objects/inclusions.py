"""Inclusions of the FEM solid: a stiffer or softer region inside it, for palpation (docs/palpation.md).

A tumour or a vessel inside soft tissue is felt through the tissue above it: the surface over a
stiff lump is stiffer under the finger than the surface beside it at the same depth. An
*inclusion* is a second closed surface inside the solid's surface (``--inclusion FILE``) with a
material of its own (``--inclusion-material NAME``); several may be given, paired in order.

What this module does, for :class:`server.objects.fem.FemSolid`:

- :func:`load_inclusions` reads each file (:func:`server.objects.mesh.load_mesh`, coordinates in
  metres in the object's own frame) and its material (:func:`inclusion_material`: a solid preset,
  a TOML file, or ``PRESET*K``, the preset with its Young's modulus times ``K``);
- :func:`check_inclusions` refuses an inclusion that is not inside the solid, crosses its
  surface or another inclusion, with a message that says which and where;
- :func:`volume_with_inclusions` tetrahedralises the solid with the inclusions' surfaces as
  internal facets (TetGen's piecewise linear complex keeps them), so the elements *conform* to
  each inclusion: its volume is the volume of the tetrahedra labelled as it, to rounding,
  however coarse the mesh (a centroid test on a mesh that does not conform would give a
  staircase lump whose size depends on the mesh);
- :func:`element_labels` labels each tetrahedron by its centroid with the generalised winding
  number (Jacobson, Kavan and Sorkine-Hornung 2013), which is exact for a closed surface and
  needs no ray-casting library; :func:`element_materials` turns the labels into per-element
  Young's modulus, Poisson's ratio and density (:class:`ElementMaterials`, with Lame's
  constants per element);
- :func:`stiffness_by_groups` and :func:`mass_by_groups` assemble the stiffness and the lumped
  mass with per-element materials from the one-material
  :func:`server.objects.fem_elements.element_stiffness_matrix` and ``element_lumped_mass`` (P1
  or P2 elements): one assembly per
  material group, summed. That is exact for any element whose stiffness is a sum over elements
  (P1, P2, selective reduced integration), and is what the palpation measurement
  (:mod:`haptic_collab.research.palpation`) uses until the solid takes per-element materials
  itself (docs/palpation.md: the hook).

- :func:`inclusion_surfaces` reads each inclusion's surface back from a solid meshed with it
  (:func:`region_boundary` of its labelled tetrahedra), with its material's name and its Young's
  modulus over the solid's, for the browser viewer's "show lump" (:mod:`server.viewer_stream`,
  ``INC1``); :func:`cluster_decimate` bounds the triangles a viewer is sent.

The inclusion's Rayleigh damping is the solid's (``C = alpha M + beta K`` with the per-element
``K`` already carries the stiffer element's larger ``beta K`` term); its own ``beta`` is not used.

References
----------
- Jacobson, A., Kavan, L., & Sorkine-Hornung, O. (2013). Robust inside-outside segmentation
  using generalized winding numbers. *ACM Transactions on Graphics* 32(4), 33.
- Van Oosterom, A., & Strackee, J. (1983). The solid angle of a plane triangle. *IEEE
  Transactions on Biomedical Engineering* 30(2), 125-126.
- Rossignac, J., & Borrel, P. (1993). Multi-resolution 3D approximations for rendering complex
  scenes. *Modeling in Computer Graphics*, Springer, 455-465 (vertex clustering).
- Si, H. (2015). TetGen, a Delaunay-based quality tetrahedral mesh generator. *ACM TOMS* 41(2), 11.

Nothing here uses threads, sockets or clocks; :func:`volume_with_inclusions` runs TetGen in a
child process (:func:`server.objects.volume.volume_mesh`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
import trimesh

from haptic_collab.server.materials import MaterialError
from haptic_collab.server.objects.fem_elements import element_lumped_mass, element_stiffness_matrix
from haptic_collab.server.objects.mesh import MeshError, load_mesh
from haptic_collab.server.objects.volume import tetgen_switches, volume_mesh
from haptic_collab.server.solid_materials import SOLID_PRESETS, SolidMaterial, load_solid_material
from haptic_collab.shared.types import FloatArray, IntArray

#: ``PRESET*K``: a solid preset with its Young's modulus multiplied by K (a lump K times as stiff).
_SCALED = re.compile(r"^(?P<name>[A-Za-z0-9_.-]+)\s*\*\s*(?P<k>[0-9.eE+-]+)$")

#: Points per chunk of the winding-number test (memory: chunk x faces x 3 x 8 bytes, several).
_CHUNK = 2048


class InclusionError(ValueError):
    """An inclusion that cannot be used: its file, its material, or where it lies."""


@dataclass(frozen=True)
class Inclusion:
    """A region of the solid with a material of its own.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Its closed surface, outward wound, coordinates [m] in the solid's frame.
    material : SolidMaterial
        Its material (Young's modulus, Poisson's ratio, density used; damping is the solid's).
    where : str
        The file (or a name) it came from, for messages.
    """

    mesh: trimesh.Trimesh
    material: SolidMaterial
    where: str


@dataclass(frozen=True)
class ElementMaterials:
    """Per-element materials of a volume mesh of T tetrahedra.

    Parameters
    ----------
    labels : (T,) int
        0: the solid's own material; ``i + 1``: inclusion ``i``.
    young_pa : (T,) float [Pa]
    poisson : (T,) float [1]
    density_kg_m3 : (T,) float [kg/m^3]
    names : tuple of str
        Each label's region and material, ``solid (liver)``, ``lump.stl (liver*10)``
        (``names[0]`` the solid's).
    regions : tuple of str
        Each label's region alone, without folders: ``solid``, ``lump.stl`` (what a viewer is
        told: never a path on the server); empty when not known.
    materials : tuple of str
        Each label's material name: ``liver``, ``liver*10``; empty when not known.
    """

    labels: IntArray
    young_pa: FloatArray
    poisson: FloatArray
    density_kg_m3: FloatArray
    names: tuple[str, ...]
    regions: tuple[str, ...] = ()
    materials: tuple[str, ...] = ()

    @property
    def lame(self) -> tuple[FloatArray, FloatArray]:
        """Lame's ``(lambda, mu)`` per element, each (T,) [Pa]:
        ``lambda = E nu / ((1 + nu)(1 - 2 nu))``, ``mu = E / (2 (1 + nu))``."""
        e, nu = self.young_pa, self.poisson
        return e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)), e / (2.0 * (1.0 + nu))

    def counts(self) -> dict[str, int]:
        """Tetrahedra per region (``names[label]``: two inclusions of one material stay apart)."""
        found = np.bincount(self.labels, minlength=len(self.names))
        return {self.names[i]: int(found[i]) for i in range(len(self.names))}


def inclusion_material(spec: str | Path) -> SolidMaterial:
    """The material of ``--inclusion-material``: a solid preset (``liver``, ``skin``,
    ``ecoflex-0030``, ``sylgard-184``), a TOML file (:func:`server.solid_materials.
    load_solid_material`), or ``PRESET*K``: the preset with its Young's modulus times K (> 0),
    e.g. ``liver*10`` for a lump ten times as stiff as liver (a tumour is 3-20 times as stiff as
    the tissue around it; docs/palpation.md).

    Raises
    ------
    MaterialError
        An unknown preset or file, a file :func:`load_solid_material` refuses, or a factor that
        is not a finite number > 0.
    """
    text = str(spec).strip()
    m = _SCALED.match(text)
    if m is None:
        return load_solid_material(spec)
    name, k_text = m.group("name"), m.group("k")
    try:
        k = float(k_text)
    except ValueError:
        k = math.nan
    if not (math.isfinite(k) and k > 0.0):
        raise MaterialError(f"inclusion material {text!r}: the factor must be a number > 0")
    if name not in SOLID_PRESETS:
        raise MaterialError(
            f"inclusion material {text!r}: {name!r} is not a solid preset "
            f"({', '.join(SOLID_PRESETS)}); PRESET*K scales a preset's Young's modulus"
        )
    base = SOLID_PRESETS[name]
    return replace(
        base,
        name=f"{name}*{k:g}",
        young_pa=base.young_pa * k,
        source=f"{base.source}; Young's modulus x {k:g}",
    )


def load_inclusions(
    files: Sequence[str | Path], materials: Sequence[str | Path]
) -> list[Inclusion]:
    """The inclusions of ``--inclusion FILE`` and ``--inclusion-material NAME``, paired in order.

    Parameters
    ----------
    files : sequence of path
        Closed surface meshes (STL, OBJ, PLY, OFF, GLB), coordinates in metres in the solid's
        frame (the frame the server uses, after ``--mesh-scale`` or ``--mesh-size``).
    materials : sequence of str
        One :func:`inclusion_material` spec per file.

    Raises
    ------
    InclusionError
        Not as many materials as files, a file that cannot be loaded or is not one closed body
        (:class:`server.objects.mesh.MeshError`'s reason), or a material refused.
    """
    if len(files) != len(materials):
        raise InclusionError(
            f"{len(files)} --inclusion file(s) but {len(materials)} --inclusion-material(s): "
            "give one material per inclusion, in the same order"
        )
    out = []
    for f, spec in zip(files, materials, strict=True):
        try:
            mesh = load_mesh(f)
        except MeshError as exc:
            raise InclusionError(f"--inclusion {f}: {exc}") from None
        try:
            material = inclusion_material(spec)
        except MaterialError as exc:
            raise InclusionError(f"--inclusion-material {spec}: {exc}") from None
        out.append(Inclusion(mesh=mesh, material=material, where=str(f)))
    return out


def winding_number(
    points: npt.ArrayLike, vertices: npt.ArrayLike, faces: npt.ArrayLike
) -> FloatArray:
    """The generalised winding number of a triangle surface at each point (Jacobson et al. 2013).

    The sum of the signed solid angles the faces subtend at the point (Van Oosterom and
    Strackee 1983) over 4 pi: 1 inside a closed outward-wound surface, 0 outside, 1/2 on it.

    Parameters
    ----------
    points : (P, 3) float [m]; vertices : (n, 3) float [m]; faces : (m, 3) int

    Returns
    -------
    (P,) float [1]
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    out = np.empty(len(p))
    for s in range(0, len(p), _CHUNK):
        c = p[s : s + _CHUNK, None, :]
        a, b, d = tri[None, :, 0] - c, tri[None, :, 1] - c, tri[None, :, 2] - c
        la, lb, ld = (np.linalg.norm(x, axis=2) for x in (a, b, d))
        num = np.einsum("ijk,ijk->ij", a, np.cross(b, d))
        den = (
            la * lb * ld
            + np.einsum("ijk,ijk->ij", a, b) * ld
            + np.einsum("ijk,ijk->ij", b, d) * la
            + np.einsum("ijk,ijk->ij", d, a) * lb
        )
        out[s : s + _CHUNK] = 2.0 * np.arctan2(num, den).sum(axis=1) / (4.0 * math.pi)
    return out


def _inside(points: FloatArray, mesh: trimesh.Trimesh) -> npt.NDArray[np.bool_]:
    """Whether each point (P, 3) [m] is inside ``mesh`` (winding number above 1/2); only the
    points in its bounding box are tested."""
    lo, hi = mesh.bounds
    box = np.all((points >= lo) & (points <= hi), axis=1)
    inside = np.zeros(len(points), dtype=bool)
    if box.any():
        inside[box] = winding_number(points[box], mesh.vertices, mesh.faces) > 0.5
    return inside


def check_inclusions(solid: trimesh.Trimesh, inclusions: Sequence[Inclusion]) -> None:
    """Refuse inclusions that are not wholly inside the solid and apart from each other.

    Every vertex of an inclusion must be strictly inside the solid's surface (winding number
    above 1/2), no vertex of the solid inside an inclusion (a surface that crosses the solid's
    would give TetGen intersecting facets), and no vertex of one inclusion inside another.

    Parameters
    ----------
    solid : trimesh.Trimesh
        The solid's closed surface [m].
    inclusions : sequence of Inclusion

    Raises
    ------
    InclusionError
        Says which inclusion, how many of its vertices are outside, and the first one [m].
    """
    for i, inc in enumerate(inclusions):
        v = np.asarray(inc.mesh.vertices, dtype=np.float64)
        if not inc.mesh.is_watertight or not float(inc.mesh.volume) > 0.0:
            raise InclusionError(f"inclusion {inc.where}: not a closed surface enclosing a volume")
        out = winding_number(v, solid.vertices, solid.faces) <= 0.5
        if out.any():
            first = np.round(v[np.flatnonzero(out)[0]] * 1000.0, 2)
            raise InclusionError(
                f"inclusion {inc.where}: {int(out.sum())} of its {len(v)} vertices are outside the "
                f"solid (the first at {first.tolist()} mm); an inclusion must lie wholly inside, "
                "in the solid's frame in metres"
            )
        crossed = _inside(np.asarray(solid.vertices, dtype=np.float64), inc.mesh)
        if crossed.any():
            raise InclusionError(
                f"inclusion {inc.where}: it crosses the solid's surface ({int(crossed.sum())} of "
                "the solid's vertices are inside it)"
            )
        for j, other in enumerate(inclusions[:i]):
            if (
                _inside(v, other.mesh).any()
                or _inside(np.asarray(other.mesh.vertices, dtype=np.float64), inc.mesh).any()
            ):
                raise InclusionError(
                    f"inclusions {other.where} (#{j + 1}) and {inc.where} (#{i + 1}) overlap"
                )


def combined_surface(
    solid: trimesh.Trimesh, inclusions: Sequence[Inclusion]
) -> tuple[FloatArray, IntArray]:
    """The solid's surface then each inclusion's, as one vertex and face list: the piecewise
    linear complex TetGen meshes. The solid's ``n`` vertices come first, unchanged.

    Returns
    -------
    (vertices (n + sum n_i, 3) float64 [m], faces (m + sum m_i, 3) int64)
    """
    verts = [np.asarray(solid.vertices, dtype=np.float64)]
    faces = [np.asarray(solid.faces, dtype=np.int64)]
    offset = len(verts[0])
    for inc in inclusions:
        verts.append(np.asarray(inc.mesh.vertices, dtype=np.float64))
        faces.append(np.asarray(inc.mesh.faces, dtype=np.int64) + offset)
        offset += len(verts[-1])
    return np.vstack(verts), np.vstack(faces)


def volume_with_inclusions(
    solid: trimesh.Trimesh,
    inclusions: Sequence[Inclusion],
    cache_dir: str | Path | None = None,
    max_edge_m: float | None = None,
) -> tuple[FloatArray, IntArray]:
    """The solid's volume mesh with the inclusions' surfaces as internal facets (conforming);
    ``max_edge_m`` [m] limits the tetrahedra's size (:func:`server.objects.volume.
    tetgen_switches`; :attr:`server.objects.fem.FemParams.volume_edge_pads`).

    :func:`check_inclusions` first, then :func:`server.objects.volume.volume_mesh` on
    :func:`combined_surface` (TetGen, cached like any volume mesh). With no inclusions it is the
    solid's own volume mesh.

    Returns
    -------
    (nodes (N, 3) float64 [m], tets (T, 4) int64)
        ``nodes[:n]`` are the solid's ``n`` surface vertices, as
        :class:`server.objects.fem.FemSolid` needs (its ``volume`` argument).

    Raises
    ------
    InclusionError
        As :func:`check_inclusions`.
    MeshError
        As :func:`server.objects.volume.volume_mesh`.
    """
    check_inclusions(solid, inclusions)
    v, f = combined_surface(solid, inclusions)
    return volume_mesh(v, f, switches=tetgen_switches(max_edge_m), cache_dir=cache_dir)


def element_labels(
    nodes: npt.ArrayLike, tets: npt.ArrayLike, inclusions: Sequence[Inclusion]
) -> IntArray:
    """Each tetrahedron's region by its centroid: 0 the solid, ``i + 1`` inclusion ``i``.

    Returns
    -------
    (T,) int64
    """
    p = np.asarray(nodes, dtype=np.float64)
    t = np.asarray(tets, dtype=np.int64)
    centroids = p[t].mean(axis=1)
    labels = np.zeros(len(t), dtype=np.int64)
    for i, inc in enumerate(inclusions):
        labels[_inside(centroids, inc.mesh)] = i + 1
    return labels


def element_materials(
    nodes: npt.ArrayLike,
    tets: npt.ArrayLike,
    base: SolidMaterial,
    inclusions: Sequence[Inclusion],
    young_scale: float = 1.0,
) -> ElementMaterials:
    """Per-element Young's modulus, Poisson's ratio and density (:func:`element_labels`).

    Parameters
    ----------
    nodes : (N, 3) float [m]; tets : (T, 4) int
    base : SolidMaterial
        The solid's material.
    inclusions : sequence of Inclusion
    young_scale : float
        Every Young's modulus times this (``--stiffness-scale``), > 0.

    Returns
    -------
    ElementMaterials
    """
    labels = element_labels(nodes, tets, inclusions)
    mats = [base, *(inc.material for inc in inclusions)]
    e = np.array([m.young_pa * young_scale for m in mats])
    nu = np.array([m.poisson for m in mats])
    rho = np.array([m.density_kg_m3 for m in mats])
    return ElementMaterials(
        labels=labels,
        young_pa=e[labels],
        poisson=nu[labels],
        density_kg_m3=rho[labels],
        names=(
            f"solid ({base.name})",
            *(f"{inc.where} ({inc.material.name})" for inc in inclusions),
        ),
        regions=(
            "solid",
            *(Path(inc.where).name or f"inclusion {i + 1}" for i, inc in enumerate(inclusions)),
        ),
        materials=tuple(m.name for m in mats),
    )


def stiffness_by_groups(
    nodes: FloatArray, tets: IntArray, materials: ElementMaterials
) -> sp.csr_matrix:
    """The stiffness ``K`` (3N, 3N) [N/m] with per-element materials, from the one-material
    :func:`server.objects.fem_elements.element_stiffness_matrix` (``tets`` (T, 4) P1 or (T, 10)
    P2 elements): one assembly per distinct ``(lambda, mu)``, summed (exact for any element
    whose stiffness is a sum over elements)."""
    lam, mu = materials.lame
    pairs = np.stack([lam, mu], axis=1)
    unique, group = np.unique(pairs, axis=0, return_inverse=True)
    n = 3 * len(nodes)
    k = sp.csr_matrix((n, n))
    for g, (lam_g, mu_g) in enumerate(unique):
        k = k + element_stiffness_matrix(nodes, tets[group.ravel() == g], float(lam_g), float(mu_g))
    return k.tocsr()


def mass_by_groups(nodes: FloatArray, tets: IntArray, materials: ElementMaterials) -> FloatArray:
    """Lumped nodal masses (N,) [kg] with per-element density, from the one-density
    :func:`server.objects.fem_elements.element_lumped_mass` (P1 or P2 elements), one call per
    distinct density, summed."""
    out = np.zeros(len(nodes))
    for rho in np.unique(materials.density_kg_m3):
        out += element_lumped_mass(nodes, tets[materials.density_kg_m3 == rho], float(rho))
    return out


@dataclass(frozen=True)
class InclusionSurface:
    """One inclusion's closed surface at rest, as the viewer draws it (docs/palpation.md).

    Parameters
    ----------
    name : str
        Its region (the file name, no folders: ``lump.stl``).
    material : str
        Its material's name (``liver*10``).
    young_ratio : float [1]
        Its Young's modulus over the solid's (10 for ``liver*10`` in liver).
    vertices : (k, 3) float64 [m]
        Rest positions, in the solid's frame.
    faces : (m, 3) int64
        Triangles, counter-clockwise seen from outside the inclusion.
    """

    name: str
    material: str
    young_ratio: float
    vertices: FloatArray
    faces: IntArray


def region_boundary(
    nodes: npt.ArrayLike, tets: npt.ArrayLike, inside: npt.ArrayLike
) -> tuple[FloatArray, IntArray]:
    """The boundary of a set of tetrahedra: the faces that only one of them has.

    On a volume mesh that conforms to an inclusion (:func:`volume_with_inclusions`) the
    tetrahedra labelled as the inclusion are bounded by its surface as TetGen kept it, so this
    gives that surface back from the solid itself, with no second copy of it to keep.

    Parameters
    ----------
    nodes : (N, 3) float [m]; tets : (T, 4) int
    inside : (T,) bool
        The tetrahedra of the region.

    Returns
    -------
    (vertices (k, 3) float64 [m], faces (m, 3) int64)
        Only the nodes the faces use, renumbered; each face wound counter-clockwise seen from
        outside the region (its normal points away from the fourth node of its tetrahedron).
        Empty arrays for an empty region.
    """
    p = np.asarray(nodes, dtype=np.float64)
    t = np.asarray(tets, dtype=np.int64)[np.asarray(inside, dtype=bool)]
    if len(t) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    # the four faces of each tetrahedron, with the node opposite each
    local = np.array([[1, 2, 3, 0], [0, 3, 2, 1], [0, 1, 3, 2], [0, 2, 1, 3]])
    all_faces = t[:, local[:, :3]].reshape(-1, 3)
    opposite = t[:, local[:, 3]].reshape(-1)
    key = np.sort(all_faces, axis=1)
    _, first, count = np.unique(key, axis=0, return_index=True, return_counts=True)
    once = first[count == 1]
    faces = all_faces[once]
    a, b, c = p[faces[:, 0]], p[faces[:, 1]], p[faces[:, 2]]
    away = np.einsum("ij,ij->i", np.cross(b - a, c - a), p[opposite[once]] - a) > 0.0
    faces[away] = faces[away][:, ::-1]  # the normal pointed into the tetrahedron: flip
    used, renumbered = np.unique(faces, return_inverse=True)
    return p[used], renumbered.reshape(-1, 3).astype(np.int64)


def inclusion_surfaces(
    nodes: npt.ArrayLike, tets: npt.ArrayLike, materials: ElementMaterials
) -> list[InclusionSurface]:
    """Each inclusion's surface at rest, read from a solid meshed with its inclusions.

    The surface is :func:`region_boundary` of the tetrahedra labelled as the inclusion (the
    labels of :func:`element_materials`), so it is what the solid simulates. Its Young's
    modulus ratio is the inclusion's elements' over the solid's own (label 0).

    Parameters
    ----------
    nodes : (N, 3) float [m]; tets : (T, 4) int
    materials : ElementMaterials
        The per-element materials the solid was built with.

    Returns
    -------
    list of InclusionSurface
        In label order (the order of ``--inclusion``); an inclusion with no tetrahedra is left
        out. Empty for a solid of one material.
    """
    labels = np.asarray(materials.labels, dtype=np.int64)
    young = np.asarray(materials.young_pa, dtype=np.float64)
    solid = young[labels == 0]
    e_solid = float(np.median(solid)) if len(solid) else math.nan
    out = []
    for label in range(1, int(labels.max(initial=0)) + 1):
        inside = labels == label
        if not inside.any():
            continue
        v, f = region_boundary(nodes, tets, inside)
        if len(f) == 0:
            continue
        e = float(np.median(young[inside]))
        ratio = e / e_solid if e_solid > 0.0 else math.nan
        name = materials.regions[label] if label < len(materials.regions) else f"inclusion {label}"
        material = materials.materials[label] if label < len(materials.materials) else ""
        out.append(InclusionSurface(name, material, ratio, v, f))
    return out


def cluster_decimate(
    vertices: npt.ArrayLike, faces: npt.ArrayLike, max_faces: int
) -> tuple[FloatArray, IntArray, bool]:
    """A surface with at most ``max_faces`` triangles, by vertex clustering.

    Vertex clustering (Rossignac and Borrel 1993): the vertices in one cell of a cubic grid
    become one, at their mean; triangles whose corners fall in fewer than three cells go, and
    so do repeated ones. The cell starts at ``sqrt(2.3 A / max_faces)`` (``A`` the area: a
    uniform mesh of edge ``h`` has about ``2.3 A / h^2`` triangles) and grows by a quarter
    until the count fits. It keeps the shape to about a cell and the winding of what is left;
    the result need not be a closed manifold (for drawing, not for simulating).

    Parameters
    ----------
    vertices : (n, 3) float [m]; faces : (m, 3) int
    max_faces : int
        At most this many triangles, >= 0.

    Returns
    -------
    (vertices (k, 3) float64 [m], faces (<= max_faces, 3) int64, decimated: bool)
        The input itself (``decimated`` False) when it already fits.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    cap = max(int(max_faces), 0)
    if len(f) <= cap:
        return v, f, False
    lo = v.min(axis=0)
    extent = float(np.max(v.max(axis=0) - lo))
    area = 0.5 * float(
        np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum()
    )
    cell = math.sqrt(2.3 * area / max(cap, 1)) if cap else math.inf
    cell = max(cell, extent * 1e-6, 1e-12)
    while True:
        if not math.isfinite(cell) or cell > 4.0 * extent:
            return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), True
        grid = np.floor((v - lo) / cell).astype(np.int64)
        _, cluster = np.unique(grid, axis=0, return_inverse=True)
        cluster = cluster.reshape(-1)
        k = int(cluster.max()) + 1
        g = cluster[f]
        keep = (g[:, 0] != g[:, 1]) & (g[:, 1] != g[:, 2]) & (g[:, 0] != g[:, 2])
        g = g[keep]
        _, first = np.unique(np.sort(g, axis=1), axis=0, return_index=True)
        g = g[np.sort(first)]
        if len(g) <= cap:
            break
        cell *= 1.25
    sums = np.zeros((k, 3))
    np.add.at(sums, cluster, v)
    centres = sums / np.bincount(cluster, minlength=k)[:, None]
    used, renumbered = np.unique(g, return_inverse=True)
    return centres[used], renumbered.reshape(-1, 3).astype(np.int64), True
