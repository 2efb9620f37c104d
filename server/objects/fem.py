"""A tetrahedral finite-element solid: soft tissue or silicone, beside the water balloon (docs/fem.md).

The paper's method does not depend on how the object is simulated (section 6); this is the
second object model, a linear elastic solid meshed from a closed surface. It offers the same
admittance interface as :class:`server.objects.balloon.Balloon` (forces in at contact patches,
surface out, ``K_o``, ``B_o`` and the contacts' compliance matrix), so the World, the room, the
gain design and the viewer use it unchanged.

**Volume mesh.** :func:`server.objects.volume.volume_mesh` tetrahedralises the surface keeping
its ``n`` vertices as the first ``n`` nodes.

**Elements** (``FemParams.element``). Quadratic (P2, ten-node, straight-sided) tetrahedra on
that mesh (:func:`server.objects.fem_elements.quadratic_mesh`): linear ones lock near
incompressibility and resolve the finger pad's rim poorly, so their ``K_o`` was 9-37 % too stiff
at nu 0.45-0.49. P2 was chosen over a mixed u-p, F-bar or selectively reduced P1 element because
the error left with averaged nodal pressure (which fixes locking) was the surface's resolution
under the pad, which P2's quadratic surface supplies. Its ``lambda`` term is taken on each
element's mean dilatation (P2/P0, :func:`server.objects.fem_elements.p2_stiffness_matrix`):
plain P2 over-constrains the volume change near incompressibility (+6 % at nu 0.49 on the
default sphere), P2/P0 is within 2.3 % of a solution refined in surface and volume at nu
0.3-0.49 (docs/fem.md, "Converged stiffness"). The nodes are ordered so that the surface shown
comes first: the mesh's ``n`` corner vertices, then its edges' midpoints; the shown surface is
the given one with every face split in four, and the patches, the viewer stream and the World
work on it. "auto" (the default) takes P2 when it has at most :data:`P2_MAX_NODES` nodes and
otherwise linear, four-node tetrahedra with averaged nodal pressure ("anp", Bonet and Burton
1998; :func:`server.objects.fem_elements.nodal_pressure_operators`), the surface shown as
given: plain linear ones ("p1", kept for comparison) lock, 37 % too stiff at nu 0.49 on the
default sphere, where these are 4-6 % soft at nu 0.3-0.49 (docs/fem.md, "Linear tetrahedra
with averaged nodal pressure"). Their stiffness ``K_dev + D^T C^-1 D`` is factored in its mixed
form (:class:`server.objects.sparse_factor.SaddlePointFactor`), about twice P1's factor;
:func:`sphere_for_solid` builds the default sphere of ``N`` shown vertices from its parent
icosphere with P2.

**Elasticity.** Isotropic, small strain: Young's modulus ``E`` [Pa] and Poisson's ratio ``nu``,
Lame ``lambda = E nu / ((1 + nu)(1 - 2 nu))`` and ``mu = E / (2 (1 + nu))``; each element's
stiffness is ``integral B^T D B dV`` (Zienkiewicz, Taylor and Zhu 2013, ch. 6; for P2 by a
four-point rule, exact for its linear strain, the ``lambda`` term on the mean dilatation), assembled into ``K`` (3N x 3N) [N/m]. The supported base is fixed (``u = 0``):
every node within ``base_share`` (20 %) of the object's height of its lowest point, as if it sat
in a cradle (a flat bottom is always fixed). ``K`` on the free nodes is factored once at start (geometric nested
dissection, the balloon's: :mod:`server.objects.sparse_factor`).

**Contacts.** A push ``f`` [N] at a contact is a *rigid flat punch* of radius ``a``
(``patch_radius_m``, the 15 mm finger pad) pressing along the patch normal ``n_p`` (the centre
vertex's rest normal): nodal loads ``-f beta_i n_p`` on the surface nodes of the patch with
the flat punch's pressure distribution ``~ 1 / sqrt(1 - (d/a)^2)`` (``d`` the distance from the
centre; Boussinesq's rigid punch, Johnson 1985, section 3.8), summing to 1. On P2 elements the
pressure is integrated over the surface faces against their six-node shape functions, the rim's
singularity integrated (:func:`p2_punch_loads`); on P1 ``beta_i`` is ``a_i / sqrt(1 -
(d_i/a)^2)`` at the vertices (``a_i`` the vertex's area). With ``b_j`` the load vector of patch ``j``, the normal
compliance is ``C_ij = b_i^T K^-1 b_j`` [m/N] and ``K_o,i = 1 / C_ii``: under the punch's
pressure the weighted mean displacement is the punch's displacement, so on an elastic half-space
``K_o = 2 a E / (1 - nu^2)`` (a rigid flat punch; Johnson 1985, eq. 3.38), and it stays finite
as the mesh is refined (a single node's compliance does not).

**Dynamics** (so the object is not the gain design's model): a lumped mass (P1: ``rho V / 4``
per node and per element; P2: HRZ lumping, Hinton, Rock and Zienkiewicz 1976, 1/36 of the
element's mass at a corner and 4/27 at a mid-edge node), and Rayleigh damping ``C = alpha M + beta K`` (``beta`` is Kelvin-Voigt
viscosity over E). The response is split by the mode-acceleration method (Craig and Kurdila
2006, ch. 14): every mode that does not settle within one simulation period
(:func:`settle_frequency`; at most ``n_modes``; ``K phi = omega^2 M phi``, mass-normalised,
found once by shift-invert Lanczos on the factored ``K``) moves dynamically, with modal damping
``zeta_k = alpha / (2 omega_k) + beta omega_k / 2``, stepped exactly for a force held over the
simulation period (zero-order hold); every other mode follows statically::

    u = K^-1 F + Phi (q - Lambda^-1 Phi^T F),    q'' + 2 zeta Omega q' + Lambda q = Phi^T F

The statics is exact whatever ``n_modes``. The modes left out answer a held force statically,
which is right for those that settle within a period: the first ticks of a step then agree with
a full Newmark integration of the same model to 0.1 % (``tests/server/test_fem_dynamics.py``;
the 24 lowest modes alone left modes of 10-17 Hz, still ringing after one 50 ms tick, static:
the first tick 2.6 % short and ``B_o`` twice the solid's). With too little damping for the
period no frequency settles, and ``n_modes`` bounds the count. ``density 0`` (or ``n_modes 0``) gives the static model ``u = K^-1 F``, the
paper's eq. (6): the limit where the object's inertia (and so its damping) plays no part.

``K_o`` is the static stiffness ``1 / C_ii``. ``B_o`` follows the balloon's definition (paper eq.
9): the first simulation tick of a step force ``f`` from rest moves the patch by
``f / (K_o + B_o)``; here the object's mass and damping both hold it back in that tick
(``B_o >= 0``; 0 for the static model).

**Large deformation: modal warping** (Choi and Ko 2005; ``warp``, on by default). The linear
displacement of a part that rotates is the rotation's tangent: a bar bent 4.6 cm sideways grows
by 7 % in volume. The warped surface carries each vertex's displacement along its own rotation.
That rotation is ``w = curl(u) / 2`` of the same linear solution
(:func:`server.objects.fem_elements.rotation_operator`, on the tetrahedra at the surface). It is
precomputed per patch and per mode, next to the displacement, so it costs the tick one more sum
and a closed-form rotation per vertex (:func:`server.objects.fem_elements.warped`). The same bent
bar then keeps its volume to 0.5 %.

A push is applied along its patch's rest normal and its response warped: the precomputed
compliance warped with the patch's rotation (SOFA's precomputed constraint correction). For
normal pushes the scalar compliances ``b_i^T K^-1 b_j`` do not change under that rotation as long
as each patch's normal turns with it, so ``K_o`` and the coupling stay valid. What it is not:
co-rotational FEM (Mueller et al. 2002), which re-solves with each element's rotation every
step. The rotation is estimated from the linear solution (moderate rotations, about 0.5 rad; the
bar above reaches 0.4), the strain stays linear, and a rotation that varies across one patch is
not one rotation. docs/fem.md has the measurements.

**Gravity** (``gravity_m_s2``, off by default; ``haptic server --gravity``). The solid's rest state
is the one it sags to under its own weight, ``g`` along -z of the object's frame: the consistent
body-force loads (P1: ``rho g V / 4`` on each node of each tetrahedron; P2: ``-1/20`` of the
element's weight at a corner, ``1/5`` at a mid-edge node; per-element densities with
inclusions; :func:`server.objects.fem_elements.element_gravity_loads`) solved once with the factored
``K`` at start, ``u_g = K^-1 F_g``. The fixed base carries the weight. What follows from that:

- The sagged surface is the solid's :attr:`FemSolid.rest_vertices`: what the viewer draws, what
  the World indexes contacts and rest planes on, and what every reported displacement is
  measured from. ``reset`` returns to it; :meth:`FemSolid.state` and ``set_state`` carry it.
- Users' forces add on top: the load is ``F_g + F`` and the model linear, so the linear
  displacement is ``u_g`` plus today's response to ``F``. The weight has always been there, so
  the modes start at rest in the sagged equilibrium and only users' forces move them.
- ``K_o``, ``B_o`` and the compliance are those of the unloaded mesh, unchanged by gravity: a
  linear solid's stiffness does not depend on a preload, so the linear model about the sagged
  state is the linear model itself. Left out is stress stiffening (the initial-stress matrix of
  geometrically nonlinear FEM), as is every large-deformation effect but warping. The punch
  patches keep the unloaded mesh's geometry and normals; only the lookup of a contact's patch
  centre (:meth:`FemSolid.patch_key`) is on the sagged surface, where the World finds it.
- With modal warping the sag is one more load: its rotation ``w_g = curl(u_g) / 2`` enters the
  rotation estimate, and the surface shown is ``warped(u_g + u, w_g + w)``. So the sagged shape
  is the one a user pushing with the same weight would make, and loads combine as users' loads
  do (summed, then warped).
- The linear model is good for small strain: when the sag exceeds :data:`SAG_WARN_SHARE` of the
  object's height a warning names it (:attr:`FemSolid.sag_m`). A massless solid
  (``density_kg_m3`` 0, the static model) weighs nothing and does not sag.

References
----------
- Johnson, K. L. (1985). *Contact Mechanics*. Cambridge University Press.
- Hinton, E., Rock, T., & Zienkiewicz, O. C. (1976). A note on mass lumping and related
  processes in the finite element method. *Earthq. Eng. Struct. Dyn.* 4, 245-249.
- Zienkiewicz, O. C., Taylor, R. L., & Zhu, J. Z. (2013). *The Finite Element Method: Its Basis
  and Fundamentals*, 7th ed. Butterworth-Heinemann.
- Craig, R. R., & Kurdila, A. J. (2006). *Fundamentals of Structural Dynamics*, 2nd ed. Wiley.
- Mueller, M., Dorsey, J., McMillan, L., Jagnow, R., & Cutler, B. (2002). Stable real-time
  deformations. *Proc. ACM SIGGRAPH/Eurographics SCA*, 49-54.
- Choi, M. G., & Ko, H.-S. (2005). Modal warping: real-time simulation of large rotational
  deformation and manipulation. *IEEE TVCG* 11(1), 91-101.

Nothing here uses threads, sockets or clocks (the volume mesh may come from a child process).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import numpy as np
import numpy.typing as npt
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import trimesh
from pydantic import Field
from scipy.spatial import cKDTree

from haptic_collab.server.contact_stiffness import K_O_MAX
from haptic_collab.server.objects.balloon import vertex_areas
from haptic_collab.server.objects.fem_elements import (
    P2_EDGES,
    element_gravity_loads,
    element_lumped_mass,
    element_stiffness_matrix,
    nodal_pressure_operators,
    quadratic_mesh,
    rotation_operator,
    warped,
)
from haptic_collab.server.objects.mesh import MeshError
from haptic_collab.server.objects.mode_cache import load_modes, modes_key, store_modes
from haptic_collab.server.objects.patches import PatchCache, PatchCentres, PatchedSurface
from haptic_collab.server.objects.sparse_factor import (
    SaddlePointFactor,
    factor_spd,
    nested_dissection,
)
from haptic_collab.server.objects.volume import (
    check_volume_mesh,
    default_cache_dir,
    tetgen_switches,
    volume_mesh,
)
from haptic_collab.shared.checks import NonNegFinite, PositiveFinite, params_dataclass
from haptic_collab.shared.modal_loop import ContactModes
from haptic_collab.shared.types import FloatArray, IntArray

if TYPE_CHECKING:  # inclusions imports solid_materials, which imports this module
    from haptic_collab.server.objects.inclusions import ElementMaterials

log = logging.getLogger("haptic.server.fem")

#: The largest gravitational acceleration [m/s^2] the solid takes (about 10 g): beyond it the
#: number is a mistake (a unit slip, cm/s^2), not a laboratory; the linear model fails well before.
GRAVITY_MAX_M_S2 = 100.0

#: A sag under the solid's own weight above this share of its height is logged as a warning:
#: the linear (small-strain) model is a first-order one, and at strains of 10-15 % on average
#: over the height (more near the base) it no longer describes a rubber-like solid; the default
#: liver sphere sags 10 % of its height and is not warned about.
SAG_WARN_SHARE = 0.15

#: The FEM solid's tetrahedra (:attr:`FemParams.element`).
Element = Literal["auto", "p1", "anp", "p2"]

#: Poisson's ratio: above -1 and below 0.5 (0.5 is incompressible, which P1 elements cannot do).
Poisson = Annotated[float, Field(gt=-1.0, lt=0.5, allow_inf_nan=False, strict=True)]

#: A flat bottom: nodes within this share of the object's height of its lowest z are fixed.
_FLAT_BOTTOM = 1e-6

#: A patch solve's rotation without modal warping.
_NO_ROTATION = np.zeros(0)

#: A mode settles within a period when its slowest pole decays by this many e-folds (to 5 %):
#: the modes below that are stepped dynamically (measured on the default liver sphere: the
#: first tick of a step within 0.1 % of a full Newmark run with them, 2.8 % off with 24 modes).
_SETTLE = 3.0

#: Up to this many free degrees of freedom the modes come from LAPACK's dense symmetric solver
#: (the lowest ``n_modes``, of which those below the settle frequency are kept: 1.8 s for 2202
#: unknowns, where ARPACK took 11 s for 142 modes) when at least one in :data:`_DENSE_SHARE` of
#: them is wanted; otherwise from ARPACK's shift-invert Lanczos on the sparse factor. A few
#: modes of many are ARPACK's: on the 162-vertex ball's P2 solid (2859 unknowns) it took 0.3 s
#: for 24 modes where the dense solver took 9.3 s.
_DENSE_MODES = 3000

#: The dense solver is used when the modes wanted are at least this share (1 in 8) of the
#: unknowns (module constant :data:`_DENSE_MODES`).
_DENSE_SHARE = 8

#: The first batch of modes (and the fewest kept); more follow (a Weyl estimate, count ~ omega^3) up to the settle
#: frequency.
_FIRST_MODES = 32

#: The punch pressure ``1 / sqrt(1 - r^2)`` is evaluated at most at this ``r = d / a`` (its rim
#: singularity is integrable; a vertex near the rim stands for the area around it).
_RIM = 0.95

#: P2 punch loads: each face of the solid's surface under the pad is split this many ways along
#: each edge (``_SPLITS^2`` parts) to integrate the pressure against the shape functions.
_SPLITS = 12

#: ``element = "auto"`` takes quadratic (P2) tetrahedra when they have at most this many nodes,
#: else linear ones with averaged nodal pressure: the liver sphere's P2 solid on its 642-vertex
#: parent has 5744 nodes and a factor of about 14 M non-zeros; a mesh of 12000 P2 nodes is about
#: three times that (docs/fem.md, "Quadratic tetrahedra").
P2_MAX_NODES = 12000


def p2_node_count(tets: npt.ArrayLike) -> int:
    """How many nodes quadratic (P2) elements on the linear tetrahedra ``tets`` (T, 4) have:
    the corners used and one node on every edge (:func:`server.objects.fem_elements.
    quadratic_mesh`), without building them."""
    t = np.asarray(tets, dtype=np.int64)
    edges = np.unique(np.sort(t[:, P2_EDGES], axis=2).reshape(-1, 2), axis=0)
    return int(len(np.unique(t)) + len(edges))


#: :attr:`FemParams.volume_edge_pads`' default [pad radii].
VOLUME_EDGE_PADS = 2.5

#: The volume size limit is relaxed so that at most this many regular tetrahedra of the limit's
#: size fill the object (a 1 m box at the 15 mm pad's 2.5 radii would need 160000).
VOLUME_LIMIT_MAX_TETS = 60000


def tet_edge_limit_m(params: FemParams, volume_m3: float) -> float | None:
    """The largest tetrahedron's edge [m] for a solid of ``volume_m3`` [m^3]:
    :attr:`FemParams.max_tet_edge_m`, made longer where more than
    :data:`VOLUME_LIMIT_MAX_TETS` regular tetrahedra of it would fill the solid; None: no limit."""
    edge = params.max_tet_edge_m
    if edge is None:
        return None
    v = float(volume_m3)
    if not (math.isfinite(v) and v > 0.0):
        return edge
    relaxed = (6.0 * math.sqrt(2.0) * v / VOLUME_LIMIT_MAX_TETS) ** (1.0 / 3.0)
    if relaxed <= edge:
        return edge
    log.info(
        "FEM solid: tetrahedra up to %.0f mm across, not %.0f mm (%g pad radii): at most %d of "
        "that size fill this object",
        1e3 * relaxed,
        1e3 * edge,
        params.volume_edge_pads,
        VOLUME_LIMIT_MAX_TETS,
    )
    return relaxed


@params_dataclass(frozen=True, slots=True)
class FemParams:
    """Material and numerical parameters of the FEM solid (SI units; docs/fem.md).

    Defaults: healthy liver (E 5.5 kPa by transient elastography, Roulot et al. 2008; nu 0.45;
    1060 kg/m^3), K_o about 190 N/m under the 15 mm finger pad on a large flat surface.

    Parameters
    ----------
    young_pa : float
        Young's modulus E [Pa] (> 0).
    poisson : float
        Poisson's ratio nu, in (-1, 0.5).
    density_kg_m3 : float
        Mass density rho [kg/m^3] (>= 0; 0 is the static model).
    rayleigh_alpha : float
        Mass-proportional damping alpha [1/s] (>= 0).
    rayleigh_beta : float
        Stiffness-proportional (Kelvin-Voigt) damping beta [s] (>= 0): viscosity over E.
    n_modes : int
        At most this many modes move dynamically (>= 0; 0 is the static model): every mode
        that does not settle within one period (:func:`settle_frequency`), up to this count.
    patch_radius_m : float
        Radius a [m] of the finger pad, a rigid flat punch (> 0).
    patch_spacing_m : float
        Spacing [m] of the patch centres (cache keys) (> 0).
    base_share : float
        The supported base: every node within this share of the object's height of its lowest
        point is fixed, in [0, 1) (0.2: the object sits in a cradle a fifth of its height deep; a
        solid held at a point would rock on it; at least the lowest node is always fixed).
    sim_period_s : float
        Simulation period N*T [s] (> 0) of one :meth:`FemSolid.step`.
    cache_mb : float
        Memory budget [MB] of the patch-solve cache (> 0; at least 16 patches are kept).
    warp : bool
        Modal warping (module docstring, Choi and Ko 2005): each surface vertex's displacement
        is carried along its local rotation, so a bent or twisted part keeps its volume (True,
        the default); False: the linear displacement.
    gravity_m_s2 : float
        Gravitational acceleration g [m/s^2] along -z of the object's frame, in [0,
        :data:`GRAVITY_MAX_M_S2`] (0, the default: no weight). With g > 0 the solid's rest state
        is the one it sags to under its own weight (module docstring, "Gravity").
    element : {"auto", "p1", "anp", "p2"}
        The tetrahedra (module docstring, "Elements"): "p2" quadratic, ten-node, the surface
        shown split four ways; "anp" linear, four-node, with averaged nodal pressure, the
        surface shown as meshed; "p1" the same without (it locks near incompressibility);
        "auto" (the default) P2 when its mesh has at most :data:`P2_MAX_NODES` nodes, else
        "anp".
    volume_edge_pads : float or None
        A volume size limit tied to the finger pad: no tetrahedron larger than the regular one
        of edge ``volume_edge_pads * patch_radius_m`` (TetGen's switch ``a``), > 0; None:
        TetGen's quality bounds only. The default, :data:`VOLUME_EDGE_PADS` (2.5), costs the
        default sphere nothing (its interior is finer) and keeps a coarse surface's interior
        from being one layer of large tetrahedra: the 162-vertex sphere's K_o at the top went
        273 -> 248 N/m, within 1 % of its interior at 1.5 pad radii (docs/fem.md, "Converged
        stiffness"). On a large object the limit is relaxed to at most
        :data:`VOLUME_LIMIT_MAX_TETS` tetrahedra of that size (:func:`tet_edge_limit_m`). Used
        when the solid meshes its own volume (no ``volume`` given) and for inclusions.

    Raises
    ------
    pydantic.ValidationError
        (a ValueError naming the field) A field out of its range above.
    """

    young_pa: PositiveFinite = 5.5e3
    poisson: Poisson = 0.45
    density_kg_m3: NonNegFinite = 1060.0
    rayleigh_alpha: NonNegFinite = 0.0
    rayleigh_beta: NonNegFinite = 0.01
    n_modes: Annotated[int, Field(ge=0, le=400, strict=True)] = 240
    patch_radius_m: PositiveFinite = 0.015
    patch_spacing_m: PositiveFinite = 0.006
    base_share: Annotated[float, Field(ge=0.0, lt=1.0, allow_inf_nan=False, strict=True)] = 0.2
    sim_period_s: PositiveFinite = 0.05
    cache_mb: PositiveFinite = 128.0
    warp: Annotated[bool, Field(strict=True)] = True
    gravity_m_s2: Annotated[
        float, Field(ge=0.0, le=GRAVITY_MAX_M_S2, allow_inf_nan=False, strict=True)
    ] = 0.0
    element: Element = "auto"
    volume_edge_pads: PositiveFinite | None = VOLUME_EDGE_PADS

    @property
    def max_tet_edge_m(self) -> float | None:
        """The largest tetrahedron's edge [m] (:attr:`volume_edge_pads` pad radii), or None."""
        if self.volume_edge_pads is None:
            return None
        return float(self.volume_edge_pads) * float(self.patch_radius_m)

    @property
    def lame(self) -> tuple[float, float]:
        """Lame's ``(lambda, mu)`` [Pa]."""
        e, nu = self.young_pa, self.poisson
        return e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)), e / (2.0 * (1.0 + nu))


@dataclass(frozen=True, slots=True)
class PunchPatch:
    """A finger-pad patch: ``indices`` (k,) surface vertices, ``weights`` (k,) beta, ``normal`` (3,).

    The load of a push ``f`` [N] is ``-f * weights[i] * normal`` at vertex ``indices[i]``;
    ``key`` is the centre vertex (the cache key).
    """

    key: int
    indices: IntArray
    weights: FloatArray
    normal: FloatArray


@dataclass(slots=True)
class _Solve:
    """One patch's cached responses: static surface displacement and modal load."""

    patch: PunchPatch
    static: FloatArray  # (3n,) K^-1 b on the surface vertices [m/N]
    modal: FloatArray  # (m,) Phi^T b
    c_static: float  # b^T K^-1 b [m/N]
    c_tick: float  # the patch's one-tick compliance from rest [m/N] (contact_damping)
    rotation: FloatArray  # (3n,) the surface vertices' small rotation under K^-1 b [rad/N]


def _zoh_modes(omega: FloatArray, zeta: FloatArray, h: float) -> tuple[FloatArray, FloatArray]:
    """Exact one-step maps of ``q'' + 2 zeta w q' + w^2 q = p`` for p held over ``h`` [s].

    Returns ``A`` (m, 2, 2) and ``B`` (m, 2): ``[q, q']_{k+1} = A [q, q']_k + B p_k``.
    """
    a_out = np.empty((len(omega), 2, 2))
    b_out = np.empty((len(omega), 2))
    for k, (w, z) in enumerate(zip(omega, zeta, strict=True)):
        sys_ = np.zeros((3, 3))
        sys_[0, 1] = 1.0
        sys_[1, 0] = -w * w
        sys_[1, 1] = -2.0 * z * w
        sys_[1, 2] = 1.0
        e = sla.expm(sys_ * h)
        a_out[k] = e[:2, :2]
        b_out[k] = e[:2, 2]
    return a_out, b_out


def _sub_triangles(splits: int) -> tuple[FloatArray, FloatArray]:
    """A triangle split ``splits`` ways along each edge: the parts' corners (S, 3, 3) and
    centroids (S, 3), in barycentric coordinates (S = splits^2)."""
    tri = []
    for i in range(splits):
        for j in range(splits - i):
            tri.append([(i, j), (i + 1, j), (i, j + 1)])
            if i + j < splits - 1:
                tri.append([(i + 1, j), (i, j + 1), (i + 1, j + 1)])
    ij = np.asarray(tri, dtype=np.float64) / splits
    corners = np.concatenate([1.0 - ij.sum(axis=2, keepdims=True), ij], axis=2)
    return corners, corners.mean(axis=1)


def p2_punch_loads(
    nodes: FloatArray,
    faces6: IntArray,
    centre: FloatArray,
    normal: FloatArray,
    radius: float,
    splits: int = _SPLITS,
) -> tuple[IntArray, FloatArray]:
    """The rigid flat punch's pressure on quadratic surface faces, as consistent nodal loads.

    The pressure ``p(r) ~ 1 / sqrt(1 - (r / a)^2)`` (``r`` the distance from ``centre`` across
    ``normal``; Johnson 1985, eq. 3.38's distribution) is integrated against each six-node
    face's shape functions (``l_c (2 l_c - 1)`` at a corner, ``4 l_i l_j`` at a mid-edge node;
    Zienkiewicz, Taylor and Zhu 2013, ch. 6) over the faces facing ``normal``. Each face is split
    ``splits^2`` ways; a part is weighted by its area times the pressure's mean over its radial
    extent ``[r1, r2]``, ``a (asin(r2 / a) - asin(r1 / a)) / (r2 - r1)``, so the rim's
    integrable singularity is integrated, not sampled, and the shape functions are taken at the
    part's centroid. Only faces within ``2 a`` (plus their own size) of ``centre`` are loaded,
    so on a non-convex surface a far face that also faces ``normal`` inside the pad's cylinder
    takes none of the push.

    Parameters
    ----------
    nodes : (N, 3) float [m]
    faces6 : (F, 6) int
        Each surface face's corners (outward) and the midpoints of its edges 01, 12, 20.
    centre : (3,) float [m]; normal : (3,) float, unit, outward.
    radius : float
        The punch's radius a [m].
    splits : int

    Returns
    -------
    (indices (k,) int64, weights (k,) float64)
        The loaded surface nodes and their shares of a unit push (summing to 1; negative at
        some corners, as P2's consistent loads are).
    """
    x = nodes[faces6[:, :3]]  # (F, 3, 3) straight-sided faces: the corners fix the geometry
    fn = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    area = 0.5 * np.linalg.norm(fn, axis=1)

    def planar(pts: FloatArray) -> FloatArray:
        rel = pts - centre
        return np.asarray(np.linalg.norm(rel - (rel @ normal)[..., None] * normal, axis=-1))

    centroid = x.mean(axis=1)
    reach = np.linalg.norm(x - centroid[:, None, :], axis=2).max(axis=1)
    # the faces the pad's disc may reach, and only near the pad: its cylinder alone also holds
    # far surfaces facing the same way (a torus's far inner wall, behind its outer side)
    near = np.linalg.norm(centroid - centre, axis=1) < 2.0 * radius + reach
    cand = np.flatnonzero((planar(centroid) < radius + reach) & (fn @ normal > 0.0) & near)
    corners, mids = _sub_triangles(splits)
    xs = x[cand]
    r_c = planar(np.einsum("kcb,fbd->fkcd", corners, xs))  # (F, S, 3)
    r1, r2 = r_c.min(axis=2), r_c.max(axis=2)
    s1, s2 = np.minimum(r1, radius) / radius, np.minimum(r2, radius) / radius
    mean_p = np.where(
        r2 - r1 > 1e-9 * radius,
        radius * (np.arcsin(s2) - np.arcsin(s1)) / np.maximum(r2 - r1, 1e-12 * radius),
        1.0 / np.sqrt(np.maximum(1.0 - s1 * s1, 1e-12)),
    )
    w = np.where(r1 >= radius, 0.0, mean_p) * (area[cand] / len(mids))[:, None]  # (F, S)
    l0, l1, l2 = mids[:, 0], mids[:, 1], mids[:, 2]
    shape = np.stack(
        [l0 * (2 * l0 - 1), l1 * (2 * l1 - 1), l2 * (2 * l2 - 1), 4 * l0 * l1, 4 * l1 * l2,
         4 * l2 * l0], axis=1,
    )  # fmt: skip
    loads = w @ shape  # (F, 6)
    idx, inv = np.unique(faces6[cand].ravel(), return_inverse=True)
    out = np.bincount(inv.ravel(), weights=loads.ravel(), minlength=len(idx))
    return idx.astype(np.int64), out / w.sum()


#: The finest icosphere whose FEM solid is built from its parent (one subdivision coarser) with
#: P2 elements: 2562 vertices (the default), P2 on the 642-vertex parent; finer ones are P1.
P2_SPHERE_MAX_SUBDIVISIONS = 4


def sphere_for_solid(subdivisions: int, radius_m: float = 0.1) -> tuple[trimesh.Trimesh, Element]:
    """The surface to build a FEM solid on that shows the icosphere of ``subdivisions``, and
    the :attr:`FemParams.element` to build it with.

    With P2 elements (:attr:`FemParams.element`) a solid shows its surface split four ways, so
    for 1 to :data:`P2_SPHERE_MAX_SUBDIVISIONS` this is the parent icosphere (one subdivision
    coarser): the solid shows the same number of vertices, ``10 * 4^s + 2``, as the balloon's
    sphere, the mid-edge vertices on the parent's chords (at most 0.3 mm inside the sphere at
    r 0.1 m and 2562 vertices), and the element is "p2" whatever the node count (inclusions
    refine the volume mesh; P1 on the parent would show a quarter of the vertices and be far
    too stiff). Otherwise the icosphere itself and "auto" (P1 above, 12 vertices at 0).

    Raises
    ------
    ValueError
        As :func:`server.objects.mesh.default_balloon`.
    """
    from haptic_collab.server.objects.mesh import default_balloon

    if isinstance(subdivisions, int) and 1 <= subdivisions <= P2_SPHERE_MAX_SUBDIVISIONS:
        return default_balloon(radius_m, subdivisions - 1), "p2"
    return default_balloon(radius_m, subdivisions), "auto"


def settle_frequency(params: FemParams) -> float:
    """The angular frequency [rad/s] above which every mode settles within one period.

    A mode of frequency ``omega`` under Rayleigh damping has poles
    ``s^2 + (alpha + beta omega^2) s + omega^2 = 0``; it *settles* when its slowest pole decays by
    ``_SETTLE`` e-folds (to 5 %) over one simulation period ``h``. The modes above the returned
    frequency may answer a held force statically, within a few per cent of their own share
    (the mode-acceleration method's assumption); the ones below must be stepped. ``inf`` when
    no frequency settles (too little damping for the period: with ``alpha = 0`` the slow pole
    tends to ``1 / beta``, so ``h / beta < _SETTLE`` never settles).

    Returns
    -------
    float
        ``omega_c`` [rad/s] (0: every mode settles; ``inf``: none is known to).
    """
    h, alpha, beta = params.sim_period_s, params.rayleigh_alpha, params.rayleigh_beta
    grid = np.logspace(-1.0, 6.0, 1400)
    c = alpha + beta * grid**2  # s^2 + c s + omega^2
    disc = c * c - 4.0 * grid**2
    # overdamped: the slow pole (c - sqrt(disc)) / 2, written as omega^2 / ((c + sqrt(disc)) / 2)
    # so that it does not cancel
    fast = (c + np.sqrt(np.maximum(disc, 0.0))) / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        slow = np.where(disc < 0.0, c / 2.0, np.where(fast > 0.0, grid**2 / fast, 0.0))
    late = np.flatnonzero(slow * h < _SETTLE)
    if len(late) == 0:
        return 0.0
    if late[-1] == len(grid) - 1:
        return math.inf
    return float(grid[late[-1] + 1])


class FemSolid(PatchedSurface):
    """Linear elastic tetrahedral solid: loads in, surface displacements out (module docstring).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        A closed, outward-wound, single-body surface in metres
        (:func:`server.objects.mesh.load_mesh`).
    params : FemParams, optional
    volume : (nodes (N, 3), tets (T, 4)), optional
        A volume mesh whose first ``n`` nodes are the surface's vertices; default
        :func:`server.objects.volume.volume_mesh` (TetGen, cached).
    cache_dir : path, optional
        Where volume meshes and modes are cached (:func:`server.objects.volume.
        default_cache_dir`; :mod:`server.objects.mode_cache`: a solid built again loads its
        modes, verified, instead of solving them).

    Raises
    ------
    MeshError
        The surface is not closed or not one body; no volume mesh can be made; a degenerate
        tetrahedron; every node fixed or none.

    Notes
    -----
    Cost at start: the volume mesh (TetGen, or the cache), one sparse factorisation of ``K``,
    with gravity one solve with it (``timings["gravity_s"]``), and ``n_modes`` eigenpairs
    (``haptic bench server --object fem`` measures them). A step is one
    small product per loaded contact and one of the surface's modal shapes (3n x n_modes); a
    contact whose patch is not cached costs one sparse solve (batched).
    """

    #: Vertices also move tangentially: the viewer stream's vector form (``DSV1``).
    tangential_motion: bool = True

    def __init__(
        self,
        mesh: trimesh.Trimesh,
        params: FemParams | None = None,
        volume: tuple[npt.ArrayLike, npt.ArrayLike] | None = None,
        cache_dir: str | None = None,
        materials: ElementMaterials | None = None,
    ) -> None:
        self.params = p = params if params is not None else FemParams()
        self._cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
        #: whether the modes came from the cache (:mod:`server.objects.mode_cache`)
        self.modes_cached = False
        verts = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
        faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        if len(faces) == 0 or not np.all(np.isfinite(verts)):
            raise MeshError("FEM mesh has no faces or non-finite coordinates")
        if not mesh.is_watertight or not float(mesh.volume) > 0.0:
            raise MeshError("FEM mesh must be a closed surface enclosing a positive volume")
        clock = time.perf_counter()
        #: seconds of each start-up step (``haptic bench server`` reports them)
        self.timings: dict[str, float] = {}
        if volume is None:
            edge = tet_edge_limit_m(p, float(mesh.volume))
            nodes, tets = volume_mesh(
                verts, faces, switches=tetgen_switches(edge), cache_dir=cache_dir
            )
        else:
            nodes, tets = check_volume_mesh(volume[0], volume[1], verts)
        if materials is not None and len(materials.labels) != len(tets):
            raise MeshError(
                f"FEM solid: {len(materials.labels)} element materials for {len(tets)} tetrahedra"
            )
        #: the P1 volume mesh the solid was built from (TetGen's, or ``volume``)
        self.linear_nodes, self.linear_tets = nodes, tets
        #: the element used: "p1" (linear), "anp" (linear, averaged nodal pressure) or "p2"
        #: (quadratic; module docstring, "Elements")
        self.element = "p1"
        elements = tets
        n = len(verts)
        self._faces6: IntArray | None = None  # P2: each surface face's 6 nodes
        if p.element in ("auto", "p2"):
            nodes2, elements2, n2, shown = quadratic_mesh(nodes, tets, faces)
            if p.element == "p2" or len(nodes2) <= P2_MAX_NODES:
                m = len(faces)
                self._faces6 = np.stack(
                    [shown[:m, 0], shown[m : 2 * m, 1], shown[2 * m : 3 * m, 2],
                     shown[:m, 1], shown[m : 2 * m, 2], shown[:m, 2]], axis=1,
                )  # fmt: skip
                self.element = "p2"
                nodes, elements, n, faces = nodes2, elements2, n2, shown
                verts = np.ascontiguousarray(nodes[:n])
                mesh = trimesh.Trimesh(verts, faces, process=False)
            else:
                self.element = "anp"
                log.info(
                    "FEM solid: linear tetrahedra with averaged nodal pressure: quadratic ones "
                    'would have %d nodes, more than %d (docs/fem.md, "Quadratic tetrahedra")',
                    len(nodes2),
                    P2_MAX_NODES,
                )
        elif p.element == "anp":
            self.element = "anp"
        #: (N, 3) [m] every node (P2: corners and mid-edge nodes); the first ``n_vertices`` are
        #: the surface shown
        self.nodes = nodes
        #: (T, 4) the elements' corner nodes (indices into :attr:`nodes`), the linear mesh
        self.tets = elements[:, :4]
        #: (T, 4) or (T, 10) the elements (P2: corners, then mid-edge nodes)
        self.elements = elements
        n_nodes = len(nodes)
        self._rest = verts
        self._rest.setflags(write=False)
        self._faces = faces.astype(np.int32)
        self._faces.setflags(write=False)
        normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
        self._normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        self._areas = vertex_areas(verts, faces)
        self._tree = cKDTree(verts)
        #: per-element materials (inclusions: docs/palpation.md), None for one material
        self.materials = materials
        self.timings["volume_mesh_s"] = time.perf_counter() - clock

        # supported base: a ball around the lowest point and a flat bottom
        z = nodes[:, 2]
        lowest = int(np.argmin(z))
        height = float(np.ptp(z)) or 1.0
        fixed = z - z[lowest] <= max(p.base_share, _FLAT_BOTTOM) * height
        fixed[lowest] = True
        if fixed.all():
            raise MeshError("FEM solid: every node is on the fixed base (base_share too large)")
        self.fixed_nodes = fixed

        lam, mu = materials.lame if materials is not None else p.lame
        width = elements.shape[1]
        adjacency = sp.coo_matrix(
            (
                np.ones(elements.size * width),
                (np.repeat(elements, width, axis=1).ravel(), np.tile(elements, width).ravel()),
            ),
            shape=(n_nodes, n_nodes),
        ).tocsr()
        mixed: tuple[sp.csc_matrix, sp.csr_matrix, FloatArray, IntArray] | None = None
        if self.element == "anp":
            # every node carries a pressure, the fixed ones too: order all nodes, each node's
            # free displacements then its pressure (the mixed form's fill is P1's)
            k_dev, d, c = nodal_pressure_operators(nodes, elements, lam, mu)
            every = nested_dissection(adjacency, nodes)
            rank = np.empty(n_nodes, dtype=np.int64)
            rank[every] = np.arange(n_nodes)
            node_order = every[~fixed[every]]
            self._dofs = (3 * node_order[:, None] + np.arange(3)).ravel()
            a = sp.csc_matrix(k_dev[self._dofs][:, self._dofs])
            b = sp.csr_matrix(d[:, self._dofs])
            k_free = sp.csc_matrix(a + b.T @ sp.diags(1.0 / c) @ b)
            mixed_key = np.concatenate([4 * rank[self._dofs // 3] + self._dofs % 3, 4 * rank + 3])
            mixed = (a, b, c, np.argsort(mixed_key, kind="stable"))
        else:
            k_full = element_stiffness_matrix(nodes, elements, lam, mu)
            free_nodes = np.flatnonzero(~fixed)
            node_order = free_nodes[
                nested_dissection(adjacency[free_nodes][:, free_nodes], nodes[free_nodes])
            ]
            self._dofs = (3 * node_order[:, None] + np.arange(3)).ravel()  # free dof of each row
            k_free = sp.csc_matrix(k_full[self._dofs][:, self._dofs])
        #: the stiffness on the free degrees of freedom, in the factor's row order [N/m]
        self._k_free = k_free
        self.timings["assembly_s"] = time.perf_counter() - clock - self.timings["volume_mesh_s"]
        clock = time.perf_counter()
        self._lu = SaddlePointFactor(*mixed) if mixed is not None else factor_spd(k_free)
        self.timings["factor_s"] = time.perf_counter() - clock
        # surface dof (3n) -> factored row, -1 if fixed
        row_of = np.full(3 * n_nodes, -1, dtype=np.int64)
        row_of[self._dofs] = np.arange(len(self._dofs))
        self._surface_rows = row_of[: 3 * n]
        # the surface's small rotations from the factored rows (modal warping)
        self._w_op = rotation_operator(nodes, elements, n, row_of) if p.warp else None

        # modes: K phi = w^2 M phi on the free dofs (mass-normalised)
        self._omega = np.zeros(0)
        self._phi_surface = np.zeros((3 * n, 0))
        self._phi_rotation = np.zeros((3 * n, 0))
        self._phi_rows = np.zeros((len(self._dofs), 0))
        density = materials.density_kg_m3 if materials is not None else p.density_kg_m3
        masses = element_lumped_mass(nodes, elements, density)
        m_modes = min(p.n_modes, len(self._dofs) - 2)
        clock = time.perf_counter()
        if p.density_kg_m3 > 0.0 and m_modes > 0:
            self._modes(np.repeat(masses, 3)[self._dofs], m_modes, settle_frequency(p))
        self.timings["modes_s"] = time.perf_counter() - clock
        zeta = p.rayleigh_alpha / (2.0 * self._omega) + p.rayleigh_beta * self._omega / 2.0
        self._zeta = zeta
        self._a_modes, self._b_modes = _zoh_modes(self._omega, zeta, p.sim_period_s)
        self._q = np.zeros((len(self._omega), 2))  # modal displacement and velocity
        self.mass_kg = float(masses.sum())

        clock = time.perf_counter()
        self._sag(density, p.gravity_m_s2, n, height)
        self.timings["gravity_s"] = time.perf_counter() - clock

        self._centres = PatchCentres(self._sag_rest, self._sag_normals, p.patch_spacing_m)
        per_patch = 3 * n * 8 * (2 if p.warp else 1)
        capacity = max(16, int(p.cache_mb * 1e6 // per_patch))
        self._cache: PatchCache[_Solve] = PatchCache(capacity, self._solve_patches)
        # linear surface displacement and the surface vertices' small rotations from the
        # unloaded mesh (the sag's included), the displacement shown (warped) from the rest state
        self._u = self._u0.copy()
        self._w = self._w0.copy()
        self._shown = np.zeros((n, 3))
        self._max_disp = 0.0

    def _sag(self, density: float | FloatArray, g: float, n: int, height: float) -> None:
        """The rest state under the solid's own weight (module docstring, "Gravity"): ``u_g =
        K^-1 F_g`` by the factor, its surface rotation, the sagged surface and its normals.

        Sets ``sag_nodes``, ``sag_m``, ``_u0``, ``_w0`` (3n,) and ``_sag_shown``, ``_sag_rest``,
        ``_sag_normals`` (n, 3); without gravity (or mass) the sag is zeros and the rest state is
        the mesh, bit for bit. Logs a warning when the sag exceeds :data:`SAG_WARN_SHARE` of
        ``height`` [m].
        """
        n_nodes = len(self.nodes)
        full = np.zeros(3 * n_nodes)
        rows = np.zeros(len(self._dofs))
        if g > 0.0:
            loads = element_gravity_loads(self.nodes, self.elements, density, g).ravel()
            rows = np.asarray(self._lu.solve(loads[self._dofs]), dtype=np.float64).reshape(-1)
            full[self._dofs] = rows
        #: (N, 3) [m] every node's linear displacement under the solid's own weight (zeros on
        #: the fixed base, and everywhere without gravity)
        self.sag_nodes = full.reshape(-1, 3)
        self.sag_nodes.setflags(write=False)
        self._u0 = full[: 3 * n].copy()
        self._w0 = (
            np.asarray(self._w_op @ rows, dtype=np.float64)
            if self._w_op is not None
            else np.zeros(3 * n)
        )
        shown = self._u0.reshape(-1, 3)
        if self._w_op is not None and g > 0.0:
            shown = warped(shown, self._w0.reshape(-1, 3))
        self._sag_shown = np.array(shown)
        self._sag_shown.setflags(write=False)
        self._sag_rest = self._rest + self._sag_shown if g > 0.0 else self._rest
        self._sag_rest.setflags(write=False)
        self._sag_normals = self._normals
        if g > 0.0:
            sagged = trimesh.Trimesh(self._sag_rest, self._faces, process=False)
            normals = np.asarray(sagged.vertex_normals, dtype=np.float64)
            self._sag_normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
            self._sag_normals.setflags(write=False)
        #: [m] the largest downward displacement of the surface under its own weight (0
        #: without gravity)
        self.sag_m = float(max(0.0, -float(self._sag_shown[:, 2].min()))) if n else 0.0
        if self.sag_m > SAG_WARN_SHARE * height:
            log.warning(
                "FEM solid: it sags %.1f mm under its own weight (g %.4g m/s^2), %.0f %% of its "
                "height (%.0f mm): beyond about %.0f %% the linear model does not hold; use a "
                "stiffer material or less gravity",
                1e3 * self.sag_m,
                g,
                100.0 * self.sag_m / height,
                1e3 * height,
                100.0 * SAG_WARN_SHARE,
            )

    def _modes(self, m_rows: FloatArray, count: int, omega_c: float) -> None:
        """The lowest modes by shift-invert Lanczos (``sigma = 0``) on the factor: every mode
        below ``omega_c`` [rad/s] (:func:`settle_frequency`), at most ``count``.

        With at most :data:`_DENSE_MODES` unknowns, of which ``count`` is at least one in
        :data:`_DENSE_SHARE`, LAPACK's dense solver finds the lowest ``count`` at once, and those below ``omega_c`` are kept (at least
        :data:`_FIRST_MODES`). Otherwise a first batch of :data:`_FIRST_MODES` by ARPACK; if its
        highest is below ``omega_c``, one more solve for the count Weyl's law estimates (modes up
        to ``omega`` grow as ``omega^3``) with a 20 % margin, and so on. Modes this solid was
        built with before come from :mod:`server.objects.mode_cache`, verified.
        """
        key = modes_key(self._k_free, m_rows, count, omega_c)
        cached = load_modes(self._cache_dir, key, self._k_free, m_rows)
        if cached is not None:
            self.modes_cached = True
            self._set_modes(*cached)
            return
        s = 1.0 / np.sqrt(m_rows)  # K' = M^-1/2 K M^-1/2, eigenvectors psi = M^1/2 phi
        size = len(m_rows)
        k_scaled = spla.LinearOperator(
            (size, size), matvec=lambda x: s * (self._k_free @ (s * x)), dtype=np.float64
        )
        k_inv = spla.LinearOperator(
            (size, size), matvec=lambda x: self._lu.solve(x / s) / s, dtype=np.float64
        )
        least = min(count, _FIRST_MODES)
        if size <= _DENSE_MODES and count * _DENSE_SHARE >= size:  # LAPACK's dense solver
            dense = np.asarray(self._k_free.toarray()) * s[:, None] * s[None, :]
            vals, vecs = sla.eigh(dense, subset_by_index=(0, count - 1), driver="evr")
            keep = max(least, int(np.count_nonzero(vals < omega_c**2)))
            vals, vecs = vals[:keep], vecs[:, :keep]
        else:
            k = least
            while True:
                vals, vecs = spla.eigsh(k_scaled, k=k, sigma=0.0, OPinv=k_inv, which="LM")
                top = math.sqrt(max(float(vals.max()), 1e-12))
                if top >= omega_c or k >= count:
                    break
                k = min(count, max(k + 16, math.ceil(1.2 * k * min(omega_c / top, 10.0) ** 3)))
        order = np.argsort(vals)
        vals, vecs = np.maximum(vals[order], 1e-12), vecs[:, order]
        phi = vecs * s[:, None]  # mass-normalised: phi^T M phi = I
        store_modes(self._cache_dir, key, vals, phi)
        self._set_modes(vals, phi)

    def _set_modes(self, vals: FloatArray, phi: FloatArray) -> None:
        """Take the modes ``w^2`` (m,) ascending [rad^2/s^2] and ``phi`` (rows, m),
        mass-normalised, and their surface and rotation shapes."""
        count = len(vals)
        self._omega = np.sqrt(vals)
        self._phi_rows = phi
        surface = np.zeros((len(self._surface_rows), count))
        ok = self._surface_rows >= 0
        surface[ok] = phi[self._surface_rows[ok]]
        self._phi_surface = surface
        if self._w_op is not None:
            self._phi_rotation = np.asarray(self._w_op @ phi, dtype=np.float64)

    # ------------------------------------------------------------------ geometry

    @property
    def rest_vertices(self) -> FloatArray:
        """(n, 3) float64 [m] surface positions at rest (read-only): the mesh's, or with gravity
        the sagged ones (module docstring, "Gravity")."""
        return self._sag_rest

    @property
    def rest_normals(self) -> FloatArray:
        """(n, 3) float64 outward unit vertex normals of the rest surface (read-only; with
        gravity the sagged surface's)."""
        return self._sag_normals

    @property
    def mesh_vertices(self) -> FloatArray:
        """(n, 3) float64 [m] the surface as meshed, unloaded (read-only): the FEM model's
        geometry, which gravity leaves as it is."""
        return self._rest

    @property
    def sag(self) -> FloatArray:
        """(n, 3) float64 [m] the surface's displacement under its own weight, from the mesh to
        the rest state (warped; zeros without gravity; read-only)."""
        return self._sag_shown

    @property
    def vertices(self) -> FloatArray:
        """(n, 3) float64 [m] current surface positions (a new array)."""
        return self._sag_rest + self._shown

    @property
    def displacement(self) -> FloatArray:
        """(n, 3) float64 [m] current surface displacement from the rest state, warped (a
        copy)."""
        return self._shown.copy()

    @property
    def linear_displacement(self) -> FloatArray:
        """(n, 3) float64 [m] current surface displacement of the linear model from the rest
        state: the users' loads' share (a copy)."""
        return (self._u - self._u0).reshape(-1, 3)

    @property
    def rotation(self) -> FloatArray:
        """(n, 3) float64 [rad] the surface vertices' current small rotations from the rest
        state (zeros without warping; a copy)."""
        return (self._w - self._w0).reshape(-1, 3)

    @property
    def max_displacement_m(self) -> float:
        """Largest surface displacement [m]."""
        return self._max_disp

    @property
    def factor_nnz(self) -> int:
        """Non-zeros of the stiffness factor (L and U) on the free degrees of freedom."""
        return int(self._lu.L.nnz + self._lu.U.nnz)

    @property
    def natural_frequencies_hz(self) -> FloatArray:
        """(n_modes,) the dynamic modes' natural frequencies [Hz], ascending."""
        return self._omega / (2.0 * math.pi)

    def reset(self, clear_cache: bool = False) -> None:
        """Return to rest, the sagged state with gravity (and, optionally, drop the patch
        cache)."""
        self._u = self._u0.copy()
        self._w = self._w0.copy()
        self._shown = np.zeros((self.n_vertices, 3))
        self._q = np.zeros_like(self._q)
        self._max_disp = 0.0
        if clear_cache:
            self._cache.clear()

    def _show(self) -> None:
        """The surface shown from ``_u`` and ``_w``: warped, less the rest state's own sag."""
        shown = self._u.reshape(-1, 3)
        if self._w_op is not None:
            shown = warped(shown, self._w.reshape(-1, 3))
        self._shown = shown - self._sag_shown if self.params.gravity_m_s2 > 0.0 else shown
        self._max_disp = (
            float(np.max(np.linalg.norm(self._shown, axis=1))) if len(self._shown) else 0.0
        )

    def state(self) -> dict[str, FloatArray]:
        """The solid's whole dynamic state (copies), what a step goes on from: saved by a
        draining server (:mod:`server.snapshots`) and given back by :meth:`set_state`.

        The modes' part is given in space, not as modal coordinates: the modes of a solid built
        again are the same subspace but may come out with other signs, or turned within a group
        of equal frequencies (the eigensolver starts from a random vector).

        With gravity ``u`` and ``w`` are measured from the unloaded mesh (the sag included: a
        state is taken back to the last bit only by a solid of the same parameters, which fix
        the sag), the modes' motion from the sagged rest state (zeros at rest).

        Returns
        -------
        dict
            ``u`` (3n,) [m] the surface's linear displacement, ``w`` (3n,) [rad] its vertices'
            small rotations (zeros without warping), ``modal_x`` and ``modal_v`` (3N,) [m] and
            [m/s] the modes' displacement and velocity at every node (N nodes; zeros on the
            fixed base and for the static model).
        """
        dyn = np.zeros((3 * len(self.nodes), 2))
        dyn[self._dofs] = self._phi_rows @ self._q
        return {
            "u": self._u.copy(),
            "w": self._w.copy(),
            "modal_x": dyn[:, 0].copy(),
            "modal_v": dyn[:, 1].copy(),
        }

    def set_state(self, state: Mapping[str, npt.ArrayLike]) -> None:
        """Take a state :meth:`state` returned (of this same solid, or one built alike): the
        surface shown is then that solid's to the last bit, and the steps that follow agree
        with its own to rounding (the modal coordinates are found again by least squares).

        Raises
        ------
        ValueError
            A key missing, an array of another shape or with a non-finite value, or a motion
            that is not one of this solid's modes (more than 1e-6 of it off their span). The
            state is unchanged.
        """
        n_all = 3 * len(self.nodes)
        arrays = {}
        for key, size in (("u", len(self._u)), ("w", len(self._w)), ("modal_x", n_all),
                          ("modal_v", n_all)):  # fmt: skip
            if key not in state:
                raise ValueError(f"FEM state: {key!r} missing")
            arr = np.array(state[key], dtype=np.float64)
            if arr.shape != (size,):
                raise ValueError(f"FEM state: {key!r} has shape {arr.shape}, expected ({size},)")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"FEM state: {key!r} holds a non-finite value")
            arrays[key] = arr
        rows = np.stack([arrays["modal_x"][self._dofs], arrays["modal_v"][self._dofs]], axis=1)
        q = np.zeros_like(self._q)
        if len(self._omega):
            q = np.linalg.lstsq(self._phi_rows, rows, rcond=None)[0]
        off = float(np.linalg.norm(rows - self._phi_rows @ q))
        if not off <= 1e-6 * float(np.linalg.norm(rows)) + 1e-300:
            raise ValueError("FEM state: the modal motion is not one of this solid's modes")
        self._u, self._w, self._q = arrays["u"], arrays["w"], q
        self._show()

    def checkpoint(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The dynamic state as it is now (copies), for :meth:`rewind` on this same solid.

        Cheap, unlike :meth:`state` (which a draining server saves for a solid built again, and
        whose :meth:`set_state` finds the modal coordinates by least squares): a look-ahead step,
        such as the one-tick response a direct 1 kHz coupling solves its contact force with
        (``tools/landing_reference.py``), is undone in microseconds.
        """
        return self._q.copy(), self._u.copy(), self._w.copy()

    def rewind(self, checkpoint: tuple[FloatArray, FloatArray, FloatArray]) -> None:
        """Go back to a :meth:`checkpoint` of this solid.

        Raises
        ------
        ValueError
            The checkpoint's arrays are not this solid's shapes.
        """
        q, u, w = (np.array(a, dtype=np.float64) for a in checkpoint)
        if q.shape != self._q.shape or u.shape != self._u.shape or w.shape != self._w.shape:
            raise ValueError("FEM checkpoint: not this solid's state")
        self._q, self._u, self._w = q, u, w
        self._show()

    # ------------------------------------------------------------------ patches
    def patch(self, key: int) -> PunchPatch:
        """The punch patch centred at surface vertex ``key`` (module docstring).

        Raises
        ------
        ValueError
            ``key`` is not a vertex index.
        """
        if not 0 <= int(key) < self.n_vertices:
            raise ValueError(
                f"patch key must be a vertex index in [0, {self.n_vertices}), got {key}"
            )
        key = int(key)
        a = self.params.patch_radius_m
        normal = self._normals[key]
        if self._faces6 is not None:
            idx, wts = p2_punch_loads(self.nodes, self._faces6, self._rest[key], normal, a, _SPLITS)
            return PunchPatch(key=key, indices=idx, weights=wts, normal=normal.copy())
        idx = np.asarray(self._tree.query_ball_point(self._rest[key], a), dtype=np.int64)
        d = np.linalg.norm(self._rest[idx] - self._rest[key], axis=1)
        keep = self._normals[idx] @ normal > 0.0  # the side pressed, not the far side
        idx, d = idx[keep], d[keep]
        wts = self._areas[idx] / np.sqrt(1.0 - np.minimum(d / a, _RIM) ** 2)
        return PunchPatch(key=key, indices=idx, weights=wts / wts.sum(), normal=normal.copy())

    def _load_rows(self, patches: Sequence[PunchPatch]) -> FloatArray:
        """The patches' load vectors ``b`` on the factored rows, (rows, k)."""
        rhs = np.zeros((len(self._dofs), len(patches)))
        for j, pt in enumerate(patches):
            dofs = (3 * pt.indices[:, None] + np.arange(3)).ravel()
            vals = (pt.weights[:, None] * pt.normal[None, :]).ravel()
            rows = self._surface_rows[dofs]
            ok = rows >= 0
            np.add.at(rhs[:, j], rows[ok], vals[ok])
        return rhs

    def _solve_patches(self, keys: list[int]) -> list[_Solve]:
        """One batched solve of the patches centred at ``keys`` (the cache's misses)."""
        patches = [self.patch(k) for k in keys]
        rhs = self._load_rows(patches)
        xs = np.asarray(self._lu.solve(rhs), dtype=np.float64).reshape(len(rhs), -1)
        modal = self._phi_rows.T @ rhs
        ok = self._surface_rows >= 0
        out = []
        for j, pt in enumerate(patches):
            static = np.zeros(len(self._surface_rows))
            static[ok] = xs[self._surface_rows[ok], j]
            rotation = (
                np.asarray(self._w_op @ xs[:, j], dtype=np.float64)
                if self._w_op is not None
                else _NO_ROTATION
            )
            psi = modal[:, j].copy()
            c_static = float(rhs[:, j] @ xs[:, j])
            c_tick = c_static
            if len(self._omega):
                c_tick += float(psi @ ((self._b_modes[:, 0] - 1.0 / self._omega**2) * psi))
            out.append(_Solve(pt, static, psi, c_static, c_tick, rotation))
        return out

    # ------------------------------------------------------------------ physics
    def step(self, keys: Sequence[int], forces_n: npt.ArrayLike) -> None:
        """Advance one simulation period under pushes ``forces_n`` [N] at patches ``keys``.

        ``u = K^-1 F + Phi_s (q - Lambda^-1 Phi^T F)`` with the modes stepped exactly for the
        force held over the period (module docstring); ``F = -sum_i f_i b_i``; with gravity the
        weight's ``u_g`` is added (its modes rest in the sagged equilibrium).

        Parameters
        ----------
        keys : sequence of int, length m
            Patch keys from :meth:`patch_key`.
        forces_n : (m,) float [N]
            Push magnitudes along the inward patch normal (negative values pull).

        Raises
        ------
        ValueError
            Lengths differ or a force is not finite. The state is unchanged.
        """
        f, solves = self._pushes(keys, forces_n)
        warp = self._w_op is not None
        u = self._u0.copy()  # the weight's share (zeros without gravity)
        w = self._w0.copy()
        p_modal = np.zeros(len(self._omega))
        for s, fi in zip(solves, f, strict=True):
            if fi != 0.0:
                u -= fi * s.static
                if warp:
                    w -= fi * s.rotation
                p_modal -= fi * s.modal
        if len(self._omega):
            self._q = (
                np.einsum("kij,kj->ki", self._a_modes, self._q) + self._b_modes * p_modal[:, None]
            )
            dyn = self._q[:, 0] - p_modal / self._omega**2
            u += self._phi_surface @ dyn
            if warp:
                w += self._phi_rotation @ dyn
        self._u = u
        self._w = w
        self._show()

    @property
    def has_contact_modes(self) -> bool:
        """Whether any mode is stepped (:meth:`contact_modes` has a mode to give): the server
        then checks each contact's gains on them (:mod:`shared.gains.modal_guard`)."""
        return len(self._omega) > 0

    def contact_modes(self, key: int) -> ContactModes:
        """The contact's response to a push, mode by mode, as :meth:`step` moves it: the object
        of :func:`shared.modal_loop.modal_monodromy` (the full loop on this solid's slow modes,
        where the gain design sees K_o and B_o only).

        ``z(k+1) = a z(k) + b F(k)``, the depth under the patch (along its inward normal)
        ``c . z(k+1) + d F(k)`` for a push F [N] held over each period: each mode's
        displacement and velocity (``a`` its exact step, ``b`` its load ``-Phi^T b`` times the
        step's input), ``c`` the patch's share of each mode's surface motion, and ``d`` the
        static compliance less the stepped modes' static share (:meth:`step`'s ``K^-1 F -
        Phi_s Lambda^-1 Phi^T F``).
        """
        (s,) = self._cache.get([key])
        patch = s.patch
        dofs = (3 * patch.indices[:, None] + np.arange(3)).ravel()
        b = (patch.weights[:, None] * patch.normal[None, :]).ravel()
        m = len(self._omega)
        psi = b @ self._phi_surface[dofs] if m else np.zeros(0)  # the patch's share of each mode
        load = s.modal  # Phi^T b: a push f loads mode i by -f load_i
        a = np.zeros((2 * m, 2 * m))
        bz = np.zeros(2 * m)
        c = np.zeros(2 * m)
        for i in range(m):
            a[2 * i : 2 * i + 2, 2 * i : 2 * i + 2] = self._a_modes[i]
            bz[2 * i : 2 * i + 2] = -load[i] * self._b_modes[i]
            c[2 * i] = -psi[i]  # depth = -b^T u, u's modal part Phi_s q
        c0 = float(b @ s.static[dofs])
        d = c0 - float(np.sum(psi * load / self._omega**2)) if m else c0
        return ContactModes(a=a, b=bz, c=c, d=d)

    def contact_compliance(self, keys: Sequence[int]) -> FloatArray:
        """Normal compliance ``C_ij = b_i^T K^-1 b_j`` [m/N] of the contacts' punches.

        Returns
        -------
        (m, m) float64 [m/N], symmetric positive semi-definite.
        """
        m = len(keys)
        if m == 0:
            return np.zeros((0, 0))
        solves = self._cache.get(keys)
        c = np.empty((m, m))
        for i, si in enumerate(solves):
            dofs = (3 * si.patch.indices[:, None] + np.arange(3)).ravel()
            b = (si.patch.weights[:, None] * si.patch.normal[None, :]).ravel()
            for j, sj in enumerate(solves):
                c[i, j] = float(b @ sj.static[dofs])
        return 0.5 * (c + c.T)

    def contact_stiffness(self, keys: Sequence[int]) -> FloatArray:
        """``K_o,i = 1 / C_ii`` [N/m] per contact (paper eq. 6-8), at most :data:`K_O_MAX`."""
        c = np.diag(self.contact_compliance(keys))
        return np.where(c > 1.0 / K_O_MAX, 1.0 / np.maximum(c, 1e-300), K_O_MAX)

    def contact_damping(self, keys: Sequence[int]) -> FloatArray:
        """The paper's ``B_o`` [N/m] per contact: the one-tick stiffness less the static one.

        From rest, a step push ``f`` moves the patch in one period by ``c_tick f`` with
        ``c_tick = C_ii - psi^T Lambda^-1 psi + psi^T diag(B_q) psi`` (``psi = Phi^T b``, ``B_q``
        the modes' zero-order-hold step response), so ``B_o = 1 / c_tick - K_o`` (>= 0; 0 for the
        static model). Both compliances are computed once, when the patch is solved.

        Returns
        -------
        (m,) float64 [N/m].
        """
        m = len(keys)
        if m == 0 or len(self._omega) == 0:
            return np.zeros(m)
        out = np.zeros(m)
        for i, s in enumerate(self._cache.get(keys)):
            if s.c_static > 1.0 / K_O_MAX and s.c_tick > 0.0:
                out[i] = max(0.0, 1.0 / s.c_tick - 1.0 / s.c_static)
        return out
