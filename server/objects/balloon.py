"""The water balloon: an admittance model of a closed membrane filled with water (DESIGN section 5).

State: one normal displacement ``w`` [m] per vertex, outward positive; the current surface is
``rest + w * rest_normal``. Static equilibrium under a load vector ``q`` [N per vertex]::

    K w = q,    K = tau * L + D * L A^-1 L + k_f * A + kappa * a a^T

- ``L``: cotangent Laplacian (P1 finite-element stiffness, dimensionless), so ``tau * L`` is a
  membrane under tension ``tau`` [N/m];
- ``D * L A^-1 L``: a bending term ``D`` [N*m] (discrete bi-Laplacian); it makes short
  wavelengths stiffer, widens the dent under a finger and so strengthens the coupling between
  contacts through the water (DESIGN section 5);
- ``k_f * A``: a weak skin/foundation [N/m^3], ``A = diag(a)`` the lumped vertex areas [m^2];
- ``kappa * a a^T``: the enclosed water. ``a^T w`` is the volume change [m^3] and
  ``dp = -kappa * a^T w`` the pressure change [Pa] (a smaller volume, a higher pressure; it acts
  outward on every vertex as the load ``-kappa * a (a^T w)``), so ``kappa`` is in N/m^5. For a
  liquid of bulk modulus ``K_w`` [Pa] (``dp = -K_w dV / V``) filling the mesh's rest volume
  ``V`` [m^3], ``kappa = K_w / V`` (:func:`server.materials.bulk_term`). This rank-one term
  couples every contact: pushing the top in raises the pressure and bulges the sides out.

A supported base holds the balloon: vertices within ``base_radius_m`` of the lowest point
(smallest z) are fixed (``w = 0``), like a balloon resting on a table.

The sparse part ``K0 = tau L + D L A^-1 L + k_f A`` (free vertices only) is factored ONCE at
construction with a geometric nested-dissection ordering (splits by median planes, separators
ordered last; :mod:`server.objects.sparse_factor`), and the water term is applied by
Sherman-Morrison::

    K^-1 q = K0^-1 q - kappa (a^T K0^-1 q) / (1 + kappa a^T K0^-1 a) * K0^-1 a

Contacts (paper section 6, Step 3): a push of magnitude ``f`` [N] along the inward normal is
spread over a finger-pad patch of radius ``patch_radius_m`` with weights ``beta`` (sum 1,
area-weighted raised-cosine falloff of the Euclidean rest distance), i.e. the load is
``q = -beta * f``. With ``X = K^-1 B`` for the contacts' patches ``B = [beta_1 ... beta_m]``:

- displacement ``w = -X f`` (static step);
- normal compliance ``C = B^T X`` [m/N] (symmetric positive definite), ``K_o,i = 1 / C_ii``
  [N/m], the paper's object stiffness of eq. (6)-(8) at contact ``i``.

Patches are cached by the *patch centre* nearest to the contact (centres are a subset of
vertices about ``patch_spacing_m`` apart, with hysteresis), so a contact that moves slowly needs
no new solve. Snapping the load to a centre a few millimetres from the contact changes the
surface under a 15 mm finger pad by hundredths of a millimetre (about 0.2 mm on the coarse
2562-vertex mesh, where centres are its vertices, 6.6 mm apart).

Visco-elastic option (paper eq. 9), ``damping = b > 0``: a damping pressure
``b * dw/dt`` [Pa] stepped implicitly with the simulation period ``dt = N*T``::

    (K + b A / dt) w_{k+1} = q_k + (b A / dt) w_k

with ``K + b A/dt`` factored once as well; each damped step costs one full sparse solve for the
memory term (a few ms at 10k vertices), the static step none. The paper's ``B_o`` (local damping divided by ``N*T``)
is then defined by the object's one-tick response at the contact: the first tick of a step
force ``f`` moves the patch by ``f / (K_o + B_o)``, so ``B_o = 1 / (beta^T (K + b A/dt)^-1 beta)
- K_o`` [N/m]. For a single mass-less spring-damper this is exactly ``b_local / (N*T)``.
Without damping ``B_o = 0``.

Nothing here uses threads, sockets or clocks.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
import trimesh
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from haptic_collab.server.contact_stiffness import K_O_MAX
from haptic_collab.server.objects.mesh import MeshError, default_balloon
from haptic_collab.server.objects.patches import PatchCache, PatchCentres, PatchedSurface
from haptic_collab.server.objects.sparse_factor import SpdFactor, nested_dissection
from haptic_collab.shared.checks import NonNegFinite, PositiveFinite, params_dataclass
from haptic_collab.shared.types import FloatArray, IntArray


@params_dataclass(frozen=True, slots=True)
class BalloonParams:
    """Physical and numerical parameters of the water balloon (SI units; DESIGN section 5).

    Defaults, measured on the default 0.1 m icosphere (2562 vertices; within 2 % on 10242 and
    40962): K_o = 308 N/m at the top and 270 N/m at the equator (paper range 200-1000 N/m); a
    top-to-equator cross compliance of 13.2 % of the equator's diagonal (15 % of the top's); a
    user resting 1.5 mm into the equator feels 44 % more force when another presses 10 mm into
    the top. Two contacts 2 cm apart (overlapping patches) are coupled at about 90 %.

    Physically these defaults are a thick silicone shell filled with water (a 7 mm Sylgard 184
    wall, 1 kPa overpressure), not a latex water balloon, whose 18 um film bends about 6e7 times
    more easily: see the presets of :mod:`server.materials` (``silicone-ball``,
    ``water-balloon``, ``soft-tissue``) and :func:`server.materials.material_to_params`.

    Parameters
    ----------
    tension : float
        Membrane tension tau [N/m] (> 0): weight of the cotangent Laplacian.
    bending : float
        Bending stiffness D [N*m] (>= 0): weight of the bi-Laplacian ``L A^-1 L``.
    foundation : float
        Skin/foundation stiffness k_f [N/m^3] (>= 0): a spring per unit area pulling each point
        back to rest. Keep it small: it holds the sides in place and kills the water coupling.
    bulk : float
        Water bulk term kappa [N/m^5] (>= 0): pressure rise [Pa] per m^3 of enclosed volume
        lost, ``dp = -kappa * dV``. ``kappa = K_w / V`` for a liquid of bulk modulus K_w [Pa]
        filling the rest volume V [m^3] (the default 1e12 is 4.2 GPa on the default mesh,
        V = 4.18e-3 m^3; water is 2.2 GPa). Large means nearly incompressible water.
    damping : float
        Visco-elastic damping b [N*s/m^3] (>= 0): damping pressure [Pa] per normal speed [m/s],
        paper eq. (9). 0 gives the static admittance of eq. (6).
    patch_radius_m : float
        Finger-pad patch radius [m] over which a contact force is spread (> 0).
    patch_spacing_m : float
        Spacing [m] of the patch centres used as cache keys (> 0); smaller is more precise,
        larger gives more cache hits.
    base_radius_m : float
        Vertices within this distance [m] of the lowest point are fixed (>= 0; at least the
        lowest vertex is always fixed).
    sim_period_s : float
        Simulation period N*T [s] (> 0): one :meth:`Balloon.step`; damping adds ``b*A/dt`` with
        this dt. The server takes it from its one :class:`shared.rates.Rates`
        (``rates.sim_period_s``, :func:`server.main.build_world`); :class:`server.world.World`
        and :class:`server.room.Room` refuse rates that disagree with it.
    cache_mb : float
        Memory budget [MB] of the patch-solve cache (> 0; at least 16 patches are kept).

    Raises
    ------
    pydantic.ValidationError
        (a ValueError naming the class and the field) A field that is not a finite number (a
        bool is not one), or out of its range above.
    """

    tension: PositiveFinite = 50.0
    bending: NonNegFinite = 0.05
    foundation: NonNegFinite = 100.0
    bulk: NonNegFinite = 1.0e12
    damping: NonNegFinite = 0.0
    patch_radius_m: PositiveFinite = 0.015
    patch_spacing_m: PositiveFinite = 0.006
    base_radius_m: NonNegFinite = 0.02
    sim_period_s: PositiveFinite = 0.05
    cache_mb: PositiveFinite = 128.0

    def with_stiffness_scale(self, scale: float) -> BalloonParams:
        """The same balloon with every stiffness term multiplied by ``scale`` (``--stiffness-scale``).

        Tension, bending, foundation and water bulk are all multiplied, so ``K`` becomes
        ``scale * K``: the compliance ``C = K^-1`` scales by ``1 / scale`` and every contact's
        ``K_o = 1 / C_ii`` by ``scale`` (up to :data:`server.contact_stiffness.K_O_MAX`); the shape of a
        dent under a given push depth is unchanged. Damping ``b`` (eq. 9) is not a stiffness and
        is kept.

        Parameters
        ----------
        scale : float
            Finite and > 0 (1 returns equal parameters).

        Raises
        ------
        ValueError
            ``scale`` not a finite number > 0.
        """
        s = float(scale)
        if not (math.isfinite(s) and s > 0.0):
            raise ValueError(f"stiffness scale must be a finite number > 0, got {scale!r}")
        return replace(
            self,
            tension=self.tension * s,
            bending=self.bending * s,
            foundation=self.foundation * s,
            bulk=self.bulk * s,
        )


@dataclass(frozen=True, slots=True)
class LoadPatch:
    """A finger-pad load patch: ``indices`` (k,) int64 vertices, ``weights`` (k,) float64 beta.

    ``weights`` sum to 1; the load of a push ``f`` [N] is ``-weights * f`` on those vertices.
    ``key`` is the patch-centre vertex index (the cache key).
    """

    key: int
    indices: IntArray
    weights: FloatArray


@dataclass(slots=True)
class _Solve:
    """Cached solve of one patch: ``x = K^-1 beta`` and, with damping, ``xd = Kd^-1 beta``."""

    patch: LoadPatch
    x: FloatArray
    xd: FloatArray | None


def cotangent_laplacian(vertices: FloatArray, faces: npt.ArrayLike) -> sp.csr_matrix:
    """Cotangent Laplacian (P1 finite-element stiffness) of a triangle mesh.

    ``w^T L w`` is the integral of ``|grad w|^2`` over the surface; L is symmetric positive
    semi-definite with rows summing to 0.

    Parameters
    ----------
    vertices : (n, 3) float [m]
    faces : (m, 3) int

    Returns
    -------
    scipy.sparse.csr_matrix
        (n, n), dimensionless.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    n = len(v)
    rows, cols, vals = [], [], []
    for k in range(3):
        o, i, j = f[:, k], f[:, (k + 1) % 3], f[:, (k + 2) % 3]
        e1 = v[i] - v[o]
        e2 = v[j] - v[o]
        cross = np.linalg.norm(np.cross(e1, e2), axis=1)
        cot = np.einsum("ij,ij->i", e1, e2) / np.maximum(cross, 1e-300)
        rows += [i, j]
        cols += [j, i]
        vals += [-0.5 * cot, -0.5 * cot]
    off = sp.coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    ).tocsr()
    diag = -np.asarray(off.sum(axis=1)).ravel()
    return (off + sp.diags(diag)).tocsr()


def vertex_areas(vertices: FloatArray, faces: npt.ArrayLike) -> FloatArray:
    """Lumped (barycentric) vertex areas: a third of each incident face's area.

    Parameters
    ----------
    vertices : (n, 3) float [m]
    faces : (m, 3) int

    Returns
    -------
    (n,) float64 [m^2], summing to the surface area.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    face_area = 0.5 * np.linalg.norm(
        np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1
    )
    areas = np.bincount(f.ravel(), weights=np.repeat(face_area / 3.0, 3), minlength=len(v))
    return np.asarray(areas, dtype=np.float64)


class Balloon(PatchedSurface):
    """Water-balloon admittance model: loads in, normal displacements out (DESIGN section 5).

    Parameters
    ----------
    mesh : trimesh.Trimesh, optional
        A closed, consistently wound, single-body surface in metres (see
        :func:`server.objects.mesh.load_mesh`). Default :func:`default_balloon` (r = 0.1 m,
        2562 vertices).
    params : BalloonParams, optional

    Raises
    ------
    MeshError
        The mesh is not watertight, not consistently wound, encloses no volume, contains
        NaN/inf, or has more than one connected body.

    Notes
    -----
    Cost: the construction builds the operators and factors them once (about 0.1 s for 10k
    vertices, about 1-2 s for 40k). A step is ``m`` axpys of length n for m loaded contacts
    (plus one full solve per step with damping). A contact whose patch is not cached costs one
    sparse solve (batched across contacts within a call).
    """

    #: Vertices move only along their rest normals: the viewer stream's normal form (``DSP1``).
    tangential_motion: bool = False

    def __init__(
        self, mesh: trimesh.Trimesh | None = None, params: BalloonParams | None = None
    ) -> None:
        self.params = params if params is not None else BalloonParams()
        m = mesh if mesh is not None else default_balloon()
        verts = np.ascontiguousarray(m.vertices, dtype=np.float64)
        faces = np.ascontiguousarray(m.faces, dtype=np.int64)
        self._check_mesh(m, verts, faces)
        p = self.params
        n = len(verts)
        self._rest = verts
        self._rest.setflags(write=False)
        self._faces = faces.astype(np.int32)
        self._faces.setflags(write=False)
        normals = np.asarray(m.vertex_normals, dtype=np.float64)
        self._normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        self._normals.setflags(write=False)
        self._areas = vertex_areas(verts, faces)
        self._areas.setflags(write=False)
        self._tree = cKDTree(verts)

        # Supported base: a cap around the lowest point.
        lowest = int(np.argmin(verts[:, 2]))
        fixed = np.linalg.norm(verts - verts[lowest], axis=1) <= p.base_radius_m
        fixed[lowest] = True
        self._fixed = fixed
        self._fixed.setflags(write=False)
        free = np.flatnonzero(~fixed)

        # K0 = tau L + D L A^-1 L + k_f A on the free vertices, in nested-dissection order.
        lap = cotangent_laplacian(verts, faces)
        k0 = p.tension * lap + p.foundation * sp.diags(self._areas)
        if p.bending > 0.0:
            floor = 1e-3 * float(np.mean(self._areas))
            inv_a = sp.diags(1.0 / np.maximum(self._areas, floor))
            k0 = k0 + p.bending * (lap @ inv_a @ lap)
        k0_free = sp.csr_matrix(k0)[free][:, free]
        k0_free = 0.5 * (k0_free + k0_free.T)
        perm = nested_dissection(k0_free.tocsr(), verts[free])
        self._order = free[perm]  # vertex index of each factored row
        self._row_of = np.full(n, -1, dtype=np.int64)
        self._row_of[self._order] = np.arange(len(self._order))
        a_rows = self._areas[self._order]
        k0_perm = sp.csc_matrix(k0_free[perm][:, perm])
        kappa = float(p.bulk)
        self._static = SpdFactor(k0_perm, a_rows, kappa)
        self._damped: SpdFactor | None = None
        self._damping_per_tick = np.zeros(0)
        if p.damping > 0.0:
            self._damping_per_tick = p.damping * self._areas / p.sim_period_s
            kd = k0_perm + sp.diags(self._damping_per_tick[self._order])
            self._damped = SpdFactor(sp.csc_matrix(kd), a_rows, kappa)

        self._centres = PatchCentres(verts, self._normals, p.patch_spacing_m)

        per_patch = n * 8 * (2 if self._damped is not None else 1)
        capacity = max(16, int(p.cache_mb * 1e6 // per_patch))
        self._cache: PatchCache[_Solve] = PatchCache(capacity, self._solve_patches)
        self._w = np.zeros(n)
        self._max_disp = 0.0

    # ------------------------------------------------------------------ validation
    @staticmethod
    def _check_mesh(m: trimesh.Trimesh, verts: FloatArray, faces: IntArray) -> None:
        if len(faces) == 0:
            raise MeshError("balloon mesh has no faces")
        if not np.all(np.isfinite(verts)):
            raise MeshError("balloon mesh vertex coordinates contain NaN or infinity")
        if not m.is_watertight:
            raise MeshError("balloon mesh is not closed (not watertight); repair it with load_mesh")
        if not m.is_winding_consistent:
            raise MeshError("balloon mesh winding is inconsistent; repair it with load_mesh")
        if not float(m.volume) > 0.0:
            raise MeshError("balloon mesh encloses no positive volume (inside out or degenerate)")
        edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        graph = sp.coo_matrix(
            (np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(len(verts),) * 2
        )
        count, _ = connected_components(graph, directed=False)
        if count != 1:
            raise MeshError(
                f"balloon mesh must be one connected closed surface, got {count} bodies"
            )

    # ------------------------------------------------------------------ geometry

    @property
    def vertex_areas(self) -> FloatArray:
        """(n,) float64 [m^2] lumped vertex areas a."""
        return self._areas

    @property
    def fixed_mask(self) -> npt.NDArray[np.bool_]:
        """(n,) bool, True for the supported base vertices (w = 0)."""
        return self._fixed

    @property
    def displacement(self) -> FloatArray:
        """(n,) float64 [m] current normal displacement w, outward positive (a copy)."""
        return self._w.copy()

    @property
    def vertices(self) -> FloatArray:
        """(n, 3) float64 [m] current positions ``rest + w * rest_normal`` (a new array)."""
        return self._rest + self._w[:, None] * self._normals

    def vertices_at(self, indices: npt.ArrayLike) -> FloatArray:
        """Current positions (k, 3) float64 [m] of the vertices ``indices`` (k,)."""
        idx = np.asarray(indices, dtype=np.int64)
        return self._rest[idx] + self._w[idx, None] * self._normals[idx]

    @property
    def max_displacement_m(self) -> float:
        """max |w| [m]: a bound on how far any vertex is from its rest position."""
        return self._max_disp

    @property
    def volume_change_m3(self) -> float:
        """Enclosed volume change ``a^T w`` [m^3] (about 0 for nearly incompressible water)."""
        return float(self._areas @ self._w)

    def state(self) -> dict[str, FloatArray]:
        """The dynamic state a snapshot keeps (:mod:`server.snapshots`): ``w`` (n,) [m], a copy."""
        return {"w": self._w.copy()}

    def set_state(self, state: dict[str, FloatArray]) -> None:
        """Take a state :meth:`state` gave of this balloon (the same mesh).

        Raises
        ------
        ValueError
            Keys other than ``w``, a ``w`` of another shape, or a value not finite.
        """
        if set(state) != {"w"}:
            raise ValueError(f"balloon state: keys {sorted(state)}, expected ['w']")
        w = np.array(state["w"], dtype=np.float64)
        if w.shape != (self.n_vertices,) or not np.all(np.isfinite(w)):
            raise ValueError(
                f"balloon state: w of shape {w.shape}, expected ({self.n_vertices},), all finite"
            )
        self._w = w
        self._max_disp = float(np.max(np.abs(w))) if len(w) else 0.0

    def reset(self, clear_cache: bool = False) -> None:
        """Return to the rest shape (w = 0); optionally drop the patch cache."""
        self._w = np.zeros(self.n_vertices)
        self._max_disp = 0.0
        if clear_cache:
            self._cache.clear()

    # ------------------------------------------------------------------ patches
    def patch(self, key: int) -> LoadPatch:
        """The load patch (vertices and weights beta) centred at vertex ``key``.

        Weights: ``a_i * (1 + cos(pi d_i / r)) / 2`` for rest distance ``d_i < r`` to the centre
        (``r`` = patch radius), normalized to sum 1.

        Raises
        ------
        ValueError
            ``key`` is not a vertex index.
        """
        solved = self._cache.peek(int(key))
        if solved is not None:
            return solved.patch
        return self._make_patch(int(key))

    def _make_patch(self, key: int) -> LoadPatch:
        if not 0 <= key < self.n_vertices:
            raise ValueError(
                f"patch key must be a vertex index in [0, {self.n_vertices}), got {key}"
            )
        r = self.params.patch_radius_m
        idx = np.asarray(self._tree.query_ball_point(self._rest[key], r), dtype=np.int64)
        d = np.linalg.norm(self._rest[idx] - self._rest[key], axis=1)
        wts = self._areas[idx] * 0.5 * (1.0 + np.cos(np.pi * np.minimum(d / r, 1.0)))
        # the finger pad presses one side: not the far side of a part thinner than the patch
        keep = (wts > 0.0) & (self._normals[idx] @ self._normals[key] > 0.0)
        idx, wts = idx[keep], wts[keep]
        return LoadPatch(key=key, indices=idx, weights=wts / wts.sum())

    def _solve_patches(self, keys: list[int]) -> list[_Solve]:
        """One batched solve of the patches centred at ``keys`` (the cache's misses)."""
        patches = [self._make_patch(k) for k in keys]
        rhs = np.zeros((len(self._order), len(patches)))
        for j, pt in enumerate(patches):
            rows = self._row_of[pt.indices]
            ok = rows >= 0
            rhs[rows[ok], j] = pt.weights[ok]
        xs = self._static.solve(rhs)
        xds = self._damped.solve(rhs) if self._damped is not None else None
        out = []
        for j, pt in enumerate(patches):
            x = np.zeros(self.n_vertices)
            x[self._order] = xs[:, j]
            xd = None
            if xds is not None:
                xd = np.zeros(self.n_vertices)
                xd[self._order] = xds[:, j]
            out.append(_Solve(pt, x, xd))
        return out

    # ------------------------------------------------------------------ physics
    def step(self, keys: Sequence[int], forces_n: npt.ArrayLike) -> None:
        """Advance one simulation period N*T under pushes ``forces_n`` at patches ``keys``.

        Static (eq. 6): ``w = -sum_i f_i K^-1 beta_i``. Damped (eq. 9):
        ``(K + b A/dt) w_{k+1} = -sum_i f_i beta_i + (b A/dt) w_k``.

        Parameters
        ----------
        keys : sequence of int, length m
            Patch keys from :meth:`patch_key`.
        forces_n : (m,) float [N]
            Push magnitudes along the inward normal (>= 0 for a unilateral contact; negative
            values pull).

        Raises
        ------
        ValueError
            Lengths differ or a force is not finite. The state is unchanged.
        """
        f, solves = self._pushes(keys, forces_n)
        if self._damped is None:
            w = np.zeros(self.n_vertices)
            for s, fi in zip(solves, f, strict=True):
                if fi != 0.0:
                    w -= fi * s.x
        else:
            memory = np.zeros(self.n_vertices)
            rhs = (self._damping_per_tick * self._w)[self._order]
            memory[self._order] = self._damped.solve(rhs)
            w = memory
            for s, fi in zip(solves, f, strict=True):
                if fi != 0.0 and s.xd is not None:
                    w -= fi * s.xd
        self._w = w
        self._max_disp = float(np.max(np.abs(w))) if len(w) else 0.0

    def contact_compliance(self, keys: Sequence[int]) -> FloatArray:
        """Normal compliance matrix ``C_ij = beta_i^T K^-1 beta_j`` [m/N] of the contacts.

        DESIGN sections 5-6: ``K_o,i = 1 / C_ii``; the coupled slow loop is
        ``x(k+1) = C diag(K_h) (x_h - x(k))``.

        Parameters
        ----------
        keys : sequence of int, length m

        Returns
        -------
        (m, m) float64 [m/N], symmetric positive semi-definite (a zero row for a patch lying
        entirely on the fixed base).
        """
        m = len(keys)
        if m == 0:
            return np.zeros((0, 0))
        solves = self._cache.get(keys)
        rows = np.unique(np.concatenate([s.patch.indices for s in solves]))
        xs = np.empty((len(rows), m))  # the solves, only on the patches' vertices
        for j, s in enumerate(solves):
            xs[:, j] = s.x[rows]
        c = np.empty((m, m))
        for i, s in enumerate(solves):
            c[i] = s.patch.weights @ xs[np.searchsorted(rows, s.patch.indices)]
        return 0.5 * (c + c.T)

    def contact_stiffness(self, keys: Sequence[int]) -> FloatArray:
        """``K_o,i = 1 / C_ii`` [N/m] per contact (paper eq. 6-8), at most :data:`K_O_MAX`."""
        c = np.diag(self.contact_compliance(keys))
        return np.where(c > 1.0 / K_O_MAX, 1.0 / np.maximum(c, 1e-300), K_O_MAX)

    def contact_damping(self, keys: Sequence[int]) -> FloatArray:
        """Paper's ``B_o`` [N/m] per contact (eq. 9): local damping divided by ``N*T``.

        ``B_o = 1 / (beta^T (K + b A/dt)^-1 beta) - 1 / (beta^T K^-1 beta)``: the one-tick
        stiffness minus the static one (see the module docstring). Zeros without damping.

        Returns
        -------
        (m,) float64 [N/m], >= 0.
        """
        m = len(keys)
        if self._damped is None or m == 0:
            return np.zeros(m)
        solves = self._cache.get(keys)
        out = np.empty(m)
        for i, s in enumerate(solves):
            wts, idx = s.patch.weights, s.patch.indices
            c_static = float(wts @ s.x[idx])
            c_tick = float(wts @ s.xd[idx]) if s.xd is not None else c_static
            if c_static <= 1.0 / K_O_MAX or c_tick <= 0.0:
                out[i] = 0.0
            else:
                out[i] = max(0.0, 1.0 / c_tick - 1.0 / c_static)
        return out
