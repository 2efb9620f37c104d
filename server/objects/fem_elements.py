"""The FEM solid's tetrahedra, P1 and P2: gradients, stiffness, lumped mass, loads, warping.

Pure functions of a volume mesh (``nodes`` (N, 3) [m], ``tets`` (T, 4) positively oriented, or
ten-node ``elements`` (T, 10) from :func:`quadratic_mesh`), used once when
:class:`server.objects.fem.FemSolid` is built and, for :func:`warped`, every tick:

- :func:`element_gradients`: the barycentric coordinates' constant gradients and the volume of
  each tetrahedron (the P1 shape functions'); :func:`p2_gradients` the ten P2 shape functions'
  at a point;
- :func:`quadratic_mesh`: the straight-sided P2 mesh, the surface's corner and mid-edge nodes
  first, and the surface it shows (each face split in four);
- :func:`stiffness_matrix` (P1, ``V B^T D B``) and :func:`p2_stiffness_matrix` (P2, a
  four-point rule exact for its linear strain, the volumetric term on each element's mean
  dilatation: P2/P0), :func:`element_stiffness_matrix` either: the
  isotropic small-strain elastic stiffness ``K`` (3N x 3N) [N/m] with Lame's constants
  (Zienkiewicz, Taylor and Zhu 2013, ch. 6), the object's stiffness behind the paper's eq. (6);
- :func:`nodal_pressure_operators`: the linear tetrahedron with averaged nodal pressure (Bonet
  and Burton 1998), which does not lock near incompressibility: the deviatoric stiffness and
  the nodal volume change and compliance of its mixed form;
- :func:`lumped_mass` (a quarter of each P1 element's mass on each node) and
  :func:`element_lumped_mass` (P2: HRZ lumping, Hinton, Rock and Zienkiewicz 1976);
- :func:`gravity_loads` and :func:`element_gravity_loads`: the consistent nodal loads of the
  solid's own weight;
- :func:`rotation_operator` and :func:`warped`: modal warping (Choi and Ko 2005), the surface
  vertices' small rotation ``curl(u) / 2`` from the linear displacement and the displacement
  carried along it.

The solid itself (contacts, dynamics, the patch cache) is :mod:`server.objects.fem`, whose
docstring has the model and its references.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from haptic_collab.shared.types import FloatArray, IntArray


def element_gradients(nodes: FloatArray, tets: IntArray) -> tuple[FloatArray, FloatArray]:
    """Shape-function gradients and volumes of P1 tetrahedra.

    Parameters
    ----------
    nodes : (N, 3) float [m]; tets : (T, 4) int, positively oriented.

    Returns
    -------
    (grads (T, 4, 3) [1/m], volumes (T,) [m^3])
    """
    x = nodes[tets]
    d = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=2)  # columns
    inv = np.linalg.inv(d)  # rows: gradients of N1, N2, N3
    grads = np.concatenate([-inv.sum(axis=1, keepdims=True), inv], axis=1)
    return grads, np.linalg.det(d) / 6.0


def rotation_operator(
    nodes: FloatArray, tets: IntArray, n_surface: int, columns: IntArray
) -> sp.csr_matrix:
    """The surface vertices' small rotation ``w = curl(u) / 2`` from the nodal displacement.

    Each element's displacement gradient is taken at the surface vertex (constant on a P1
    element; on a P2 element the quadratic field's gradient at that node, :func:`p2_gradients`);
    its rotation vector is averaged at each vertex over the elements around it, weighted by
    volume. Only the elements touching the surface are used.

    Parameters
    ----------
    nodes : (N, 3) float [m]; tets : (T, 4) or (T, 10) int, positively oriented (P1 or P2
        elements, :func:`quadratic_mesh`).
    n_surface : int
        The surface vertices are nodes ``0 .. n_surface - 1``.
    columns : (3N,) int
        Column of each nodal dof ``3 * node + axis`` in the result's input (-1: dropped, a
        fixed dof whose displacement is 0).

    Returns
    -------
    (3 n_surface, max(columns) + 1) sparse [1/m]: ``w[3 i + k]``, rotation of vertex i about
    axis k [rad], from the displacement [m] on the columns.
    """
    width = tets.shape[1]
    touch = np.flatnonzero((tets < n_surface).any(axis=1))
    t = tets[touch]
    g1, vol = element_gradients(nodes, t[:, :4])
    bary = _node_bary(width)
    weight = np.zeros(n_surface)
    for b in range(width):
        ok = t[:, b] < n_surface
        np.add.at(weight, t[ok, b], vol[ok])
    # w_k = 1/2 sum_a (g_a,j u_a,i - g_a,i u_a,j) for (k, i, j) cyclic, g at the receiving node
    rows, cols, vals = [], [], []
    for b in range(width):  # node t[:, b] receives the element's rotation there
        ok = t[:, b] < n_surface
        if not ok.any():
            continue
        g = g1[ok] if width == 4 else p2_gradients(g1[ok], bary[b])
        scale = 0.5 * vol[ok] / weight[t[ok, b]]
        for k, i, j in ((0, 2, 1), (1, 0, 2), (2, 1, 0)):
            for a in range(width):
                for axis, sign, grad in ((i, 1.0, j), (j, -1.0, i)):
                    rows.append(3 * t[ok, b] + k)
                    cols.append(columns[3 * t[ok, a] + axis])
                    vals.append(sign * scale * g[:, a, grad])
    r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    keep = c >= 0
    shape = (3 * n_surface, int(columns.max()) + 1)
    return sp.coo_matrix((v[keep], (r[keep], c[keep])), shape=shape).tocsr()


def warped(u: FloatArray, w: FloatArray) -> FloatArray:
    """Displacements ``u`` (n, 3) [m] carried along their vertices' rotations ``w`` (n, 3) [rad].

    Modal warping (Choi and Ko 2005): with the rotation growing in proportion to the load, the
    displacement is ``integral_0^1 exp(s [w]x) ds u = u + (1 - cos t)/t^2 w x u + (t - sin t)/t^3
    w x (w x u)`` (t = |w|). A rigid rotation is reproduced exactly where the linear
    displacement, its tangent, stretches the part; small rotations leave ``u`` as it is.
    """
    t = np.linalg.norm(w, axis=1)
    small = t < 1e-4
    ts = np.where(small, 1.0, t)
    a = np.where(small, 0.5 - t * t / 24.0, (1.0 - np.cos(ts)) / ts**2)
    b = np.where(small, 1.0 / 6.0 - t * t / 120.0, (ts - np.sin(ts)) / ts**3)
    wu = np.cross(w, u)
    return u + a[:, None] * wu + b[:, None] * np.cross(w, wu)


def stiffness_matrix(
    nodes: FloatArray, tets: IntArray, lam: float | FloatArray, mu: float | FloatArray
) -> sp.csr_matrix:
    """Linear elastic stiffness of P1 tetrahedra, ``K`` (3N, 3N) [N/m], dof ``3 * node + axis``.

    ``K_e[a i, b j] = V (lambda g_ai g_bj + mu g_aj g_bi + mu (g_a . g_b) delta_ij)``: the
    element stiffness ``V B^T D B`` written with Lame's constants (Zienkiewicz et al. 2013).

    Parameters
    ----------
    nodes : (N, 3) float [m]; tets : (T, 4) int, positively oriented.
    lam, mu : float or (T,) float
        Lame's constants [Pa], one pair for every element or one per element (an inclusion's
        own material: :mod:`server.objects.inclusions`).
    """
    g, vol = element_gradients(nodes, tets)
    lam = np.broadcast_to(np.asarray(lam, dtype=np.float64), vol.shape)[:, None, None]
    mu = np.broadcast_to(np.asarray(mu, dtype=np.float64), vol.shape)[:, None, None]
    eye = np.eye(3)
    ke = np.empty((len(tets), 4, 3, 4, 3))
    for a in range(4):
        for b in range(a, 4):
            ga, gb = g[:, a], g[:, b]
            block = (
                lam * ga[:, :, None] * gb[:, None, :]
                + mu * gb[:, :, None] * ga[:, None, :]
                + mu * np.einsum("tk,tk->t", ga, gb)[:, None, None] * eye
            ) * vol[:, None, None]
            ke[:, a, :, b, :] = block
            ke[:, b, :, a, :] = block.transpose(0, 2, 1)
    dof = (3 * tets[:, :, None] + np.arange(3)[None, None, :]).reshape(len(tets), 12)
    rows = np.repeat(dof, 12, axis=1).ravel()
    cols = np.tile(dof, (1, 12)).ravel()
    n = 3 * len(nodes)
    k = sp.coo_matrix((ke.reshape(-1), (rows, cols)), shape=(n, n)).tocsr()
    return (0.5 * (k + k.T)).tocsr()


def nodal_pressure_operators(
    nodes: FloatArray, tets: IntArray, lam: float | FloatArray, mu: float | FloatArray
) -> tuple[sp.csr_matrix, sp.csr_matrix, FloatArray]:
    """The averaged nodal pressure tetrahedron (Bonet and Burton 1998): linear tetrahedra whose
    volume change is averaged over each node's elements, so they do not lock as nu -> 0.5.

    Each element's strain energy is split into a deviatoric part, kept per element (``mu``), and
    a volumetric part, which lives at the nodes: node ``a``'s volume change is ``(D u)_a = sum_e
    (V_e / 4) div(u)_e`` over its elements, and its pressure ``p_a = (D u)_a / c_a`` with the
    compliance ``c_a = sum_e V_e / (4 kappa_e)`` (``kappa = lambda + 2 mu / 3``, the bulk modulus;
    for one material ``c_a = V_a / kappa``, ``V_a`` the node's quarter-volumes). The stiffness
    is ``K = K_dev + D^T diag(1 / c) D``; the solid factors its mixed form ``[[K_dev, D^T], [D,
    -diag(c)]]`` instead (:class:`server.objects.sparse_factor.SaddlePointFactor`), whose fill is
    about that of P1 while ``K`` itself couples every node's neighbours' neighbours.

    Parameters
    ----------
    nodes : (N, 3) float [m]; tets : (T, 4) int, positively oriented.
    lam, mu : float or (T,) float
        Lame's constants [Pa], one pair for every element or one per element (inclusions).

    Returns
    -------
    (k_dev (3N, 3N) csr [N/m], d (N, 3N) csr [m^2], c (N,) float [m^3/Pa])
        ``k_dev`` is :func:`stiffness_matrix` with ``lambda = -2 mu / 3`` (the deviatoric
        energy ``mu |dev eps|^2``); ``d`` maps displacements [m] to nodal volume changes [m^3].
    """
    g, vol = element_gradients(nodes, tets)
    lam_e = np.broadcast_to(np.asarray(lam, dtype=np.float64), vol.shape)
    mu_e = np.broadcast_to(np.asarray(mu, dtype=np.float64), vol.shape)
    k_dev = stiffness_matrix(nodes, tets, -2.0 * mu_e / 3.0, mu_e)
    kappa = lam_e + 2.0 * mu_e / 3.0
    n = len(nodes)
    dof = (3 * tets[:, :, None] + np.arange(3)[None, None, :]).reshape(len(tets), 12)
    quarter = g.reshape(len(tets), 12) * (vol / 4.0)[:, None]  # (V_e / 4) div_e, per dof
    rows = np.repeat(tets, 12, axis=1).ravel()  # each corner a of e gets e's whole row
    cols = np.tile(dof, (1, 4)).ravel()
    vals = np.tile(quarter, (1, 4)).ravel()
    d = sp.coo_matrix((vals, (rows, cols)), shape=(n, 3 * n)).tocsr()
    c = np.bincount(tets.ravel(), weights=np.repeat(vol / (4.0 * kappa), 4), minlength=n)
    return k_dev, d, np.asarray(c, dtype=np.float64)


def lumped_mass(nodes: FloatArray, tets: IntArray, density: float | FloatArray) -> FloatArray:
    """Lumped nodal masses [kg], (N,): a quarter of each element's ``rho V`` (``density``
    [kg/m^3], one for every element or (T,) one per element)."""
    _, vol = element_gradients(nodes, tets)
    return np.asarray(
        np.bincount(tets.ravel(), weights=np.repeat(density * vol / 4.0, 4), minlength=len(nodes)),
        dtype=np.float64,
    )


def gravity_loads(
    nodes: FloatArray, tets: IntArray, density: float | FloatArray, g_m_s2: float
) -> FloatArray:
    """The consistent nodal loads [N] of the solid's own weight, ``g`` along -z, (N, 3).

    A body force ``rho g`` [N/m^3] on a P1 tetrahedron loads node ``i`` with ``integral N_i rho
    g dV = rho g V / 4`` (each linear shape function integrates to a quarter of the volume;
    Zienkiewicz, Taylor and Zhu 2013, ch. 6): for a constant body force the consistent load and
    the lumped one are the same. With per-element densities each element adds its own weight.

    Parameters
    ----------
    nodes : (N, 3) float [m]; tets : (T, 4) int, positively oriented.
    density : float or (T,) float
        Mass density [kg/m^3], one for every element or one per element (inclusions).
    g_m_s2 : float
        Gravitational acceleration [m/s^2] along -z of the nodes' frame (>= 0).

    Returns
    -------
    (N, 3) float64 [N]: x and y zero, z ``-g`` times each node's share of the mass; the loads
    sum to ``-g sum(rho_e V_e)``, the solid's weight.
    """
    _, vol = element_gradients(nodes, tets)
    share = np.repeat(np.broadcast_to(np.asarray(density, dtype=np.float64), vol.shape) * vol, 4)
    out = np.zeros((len(nodes), 3))
    out[:, 2] = -float(g_m_s2) * np.bincount(
        tets.ravel(), weights=share / 4.0, minlength=len(nodes)
    )
    return out


# ---------------------------------------------------------------------- quadratic (P2) tetrahedra

#: The six mid-edge nodes of a ten-node tetrahedron (local nodes 4..9): the corners they join.
P2_EDGES = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]], dtype=np.int64)

#: A four-point rule on the tetrahedron exact for polynomials of degree 2 (Zienkiewicz, Taylor and
#: Zhu 2013, table 6.4): barycentric points (4, 4), each weighted a quarter of the volume. The
#: strain of a straight-sided P2 element is linear, so the stiffness integrand is quadratic and
#: this rule integrates it exactly.
_QA, _QB = (5.0 + 3.0 * np.sqrt(5.0)) / 20.0, (5.0 - np.sqrt(5.0)) / 20.0
P2_QUADRATURE = np.full((4, 4), _QB) + np.eye(4) * (_QA - _QB)

#: HRZ lumping of a straight-sided P2 tetrahedron (Hinton, Rock and Zienkiewicz 1976): the
#: consistent mass's diagonal, ``integral N_i^2 dV``, is V/70 at a corner and 8V/105 at a mid-edge
#: node; scaled to the element's mass these are shares 1/36 and 4/27 (4/36 + 24/27 = 1). The
#: consistent row sums (``integral N_i dV``, -V/20 at a corner) are negative, so row-sum lumping
#: cannot be used.
P2_HRZ_SHARES = np.array([1.0 / 36.0] * 4 + [4.0 / 27.0] * 6)

#: ``integral N_i dV / V`` of the ten P2 shape functions: -1/20 at a corner, 1/5 at a mid-edge
#: node (they sum to 1): the consistent load of a constant body force.
P2_LOAD_SHARES = np.array([-1.0 / 20.0] * 4 + [1.0 / 5.0] * 6)


def quadratic_mesh(
    nodes: FloatArray, tets: IntArray, faces: IntArray
) -> tuple[FloatArray, IntArray, int, IntArray]:
    """Ten-node (P2) tetrahedra from a linear volume mesh, straight-sided (mid-edge nodes at the
    edges' midpoints).

    The nodes are ordered so that the shown surface comes first: the surface's ``n`` corner
    vertices (``nodes[:n]``, unchanged), then the mid-edge nodes of the surface's edges, then the
    interior corner nodes, then the interior mid-edge nodes. The shown surface is the P2
    surface with every face split in four at its edge midpoints (on the chords).

    Parameters
    ----------
    nodes : (N, 3) float [m]; tets : (T, 4) int, positively oriented, ``nodes[:n]`` the surface's
        vertices.
    faces : (m, 3) int
        The closed surface's triangles (outward), each a face of a tetrahedron.

    Returns
    -------
    (nodes2 (N2, 3) float64 [m], elements (T, 10) int64, n_shown, shown_faces (4m, 3) int64)
        ``elements[:, :4]`` the corners, ``elements[:, 4 + e]`` the midpoint of the corners
        :data:`P2_EDGES` ``[e]``; the shown surface is ``nodes2[:n_shown]`` with
        ``shown_faces``, outward as ``faces``.

    Raises
    ------
    ValueError
        A surface edge that is no tetrahedron's edge (the volume mesh does not fit the surface).
    """
    n_nodes = len(nodes)
    n = int(faces.max()) + 1
    pairs = np.sort(tets[:, P2_EDGES], axis=2).reshape(-1, 2)
    codes = pairs[:, 0] * n_nodes + pairs[:, 1]
    edge_codes, inverse = np.unique(codes, return_inverse=True)
    fpairs = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]], axis=2).reshape(-1, 2)
    surf_codes = np.unique(fpairs[:, 0] * n_nodes + fpairs[:, 1])
    is_surf = np.isin(edge_codes, surf_codes)
    if int(is_surf.sum()) != len(surf_codes):
        raise ValueError("quadratic mesh: a surface edge is no tetrahedron's edge")
    n_surf_edges = len(surf_codes)
    # new index of every old node and of every edge
    old = np.arange(n_nodes)
    node_index = np.where(old < n, old, old + n_surf_edges)
    edge_index = np.empty(len(edge_codes), dtype=np.int64)
    edge_index[is_surf] = n + np.arange(n_surf_edges)  # edge_codes sorted, so surf_codes' order
    edge_index[~is_surf] = n_nodes + n_surf_edges + np.arange(int((~is_surf).sum()))
    ends = np.stack([edge_codes // n_nodes, edge_codes % n_nodes], axis=1)
    out = np.empty((n_nodes + len(edge_codes), 3))
    out[node_index] = nodes
    out[edge_index] = 0.5 * (nodes[ends[:, 0]] + nodes[ends[:, 1]])
    elements = np.concatenate(
        [node_index[tets], edge_index[inverse.ravel()].reshape(len(tets), 6)], axis=1
    )
    mid = n + np.searchsorted(surf_codes, fpairs[:, 0] * n_nodes + fpairs[:, 1]).reshape(-1, 3)
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    m_ab, m_bc, m_ca = mid[:, 0], mid[:, 1], mid[:, 2]
    shown = np.concatenate(
        [
            np.stack([a, m_ab, m_ca], axis=1),
            np.stack([m_ab, b, m_bc], axis=1),
            np.stack([m_ca, m_bc, c], axis=1),
            np.stack([m_ab, m_bc, m_ca], axis=1),
        ]
    )
    return out, elements, n + n_surf_edges, shown.astype(np.int64)


def p2_gradients(grads: FloatArray, bary: FloatArray) -> FloatArray:
    """The ten P2 shape functions' gradients (T, 10, 3) [1/m] at barycentric point ``bary`` (4,).

    ``N_c = l_c (2 l_c - 1)`` at corner c and ``N_ij = 4 l_i l_j`` at the midpoint of edge ij
    (Zienkiewicz, Taylor and Zhu 2013, ch. 6), so ``grad N_c = (4 l_c - 1) grad l_c`` and
    ``grad N_ij = 4 (l_i grad l_j + l_j grad l_i)``; ``grads`` (T, 4, 3) are the barycentric
    coordinates' gradients (:func:`element_gradients`), constant on a straight-sided element.
    """
    out = np.empty((grads.shape[0], 10, 3))
    out[:, :4] = (4.0 * bary - 1.0)[None, :, None] * grads
    for e, (i, j) in enumerate(P2_EDGES):
        out[:, 4 + e] = 4.0 * (bary[i] * grads[:, j] + bary[j] * grads[:, i])
    return out


def _node_bary(width: int) -> FloatArray:
    """The barycentric coordinates (width, 4) of an element's own nodes (P1: 4, P2: 10)."""
    eye = np.eye(4)
    if width == 4:
        return eye
    return np.concatenate([eye, 0.5 * (eye[P2_EDGES[:, 0]] + eye[P2_EDGES[:, 1]])])


def p2_mean_gradients(grads: FloatArray) -> FloatArray:
    """The element means (T, 10, 3) [1/m] of the ten P2 shape functions' gradients.

    ``grad N_c = (4 l_c - 1) grad l_c`` averages to zero (``l_c`` averages to 1/4) and
    ``grad N_ij = 4 (l_i grad l_j + l_j grad l_i)`` to ``grad l_i + grad l_j``; ``grads``
    (T, 4, 3) as in :func:`p2_gradients`. The mean dilatation of a displacement ``u`` is
    ``sum_a u_a . mean grad N_a``.
    """
    out = np.zeros((grads.shape[0], 10, 3))
    for e, (i, j) in enumerate(P2_EDGES):
        out[:, 4 + e] = grads[:, i] + grads[:, j]
    return out


def _element_block_stiffness(
    g: FloatArray, vol: FloatArray, lam: FloatArray, mu: FloatArray
) -> FloatArray:
    """``K_e`` (T, 10, 3, 10, 3) [N/m] of straight-sided P2 elements: the shear (``mu``) terms by
    :data:`P2_QUADRATURE`, the ``lambda`` term on the element's mean dilatation
    (:func:`p2_stiffness_matrix`)."""
    eye = np.eye(3)
    ke = np.zeros((len(vol), 10, 3, 10, 3))
    for bary in P2_QUADRATURE:
        gq = p2_gradients(g, bary)
        w = (vol / 4.0 * mu)[:, None, None, None, None]
        dots = np.einsum("tak,tbk->tab", gq, gq)
        ke += w * (
            np.einsum("taj,tbi->taibj", gq, gq)
            + dots[:, :, None, :, None] * eye[None, None, :, None, :]
        )
    gm = p2_mean_gradients(g)
    ke += (vol * lam)[:, None, None, None, None] * np.einsum("tai,tbj->taibj", gm, gm)
    return ke


def p2_stiffness_matrix(
    nodes: FloatArray, elements: IntArray, lam: float | FloatArray, mu: float | FloatArray
) -> sp.csr_matrix:
    """Linear elastic stiffness of straight-sided ten-node (P2) tetrahedra, ``K`` (3N, 3N) [N/m],
    with the volumetric (``lambda``) term on each element's mean dilatation (P2/P0).

    ``K_e = integral (2 mu eps(u) : eps(v) + lambda div(u) div(v)) dV`` (Zienkiewicz, Taylor
    and Zhu 2013, ch. 6) with the shear term integrated exactly (the strain of the quadratic
    displacement is linear in the element, so the four-point rule :data:`P2_QUADRATURE` is exact)
    and the ``lambda`` term at the element's mean divergence, ``lambda V mean(div u)
    mean(div v)`` (:func:`p2_mean_gradients`; on a straight-sided element the divergence is
    linear, so this is its one-point, centroid rule). That is selective reduced integration of
    the ``lambda`` term, equivalent to a mixed displacement-pressure element with a constant
    pressure on each element, condensed (Malkus and Hughes 1978, "Mixed finite element methods -
    reduced and selective integration techniques: a unification of concepts"): near
    incompressibility the full ``lambda`` term asks each element's linear divergence to vanish
    everywhere, which over-stiffens P2 (its ``K_o`` was 5-6 % above a refined solution at nu
    0.49 on the default sphere); the mean asks one constraint per element. ``K`` stays symmetric
    positive definite on the fixed solid for every nu below 0.5 (docs/fem.md, "Converged
    stiffness").

    Parameters
    ----------
    nodes : (N, 3) float [m]; elements : (T, 10) int, the corners positively oriented, then the
        mid-edge nodes in :data:`P2_EDGES` order (:func:`quadratic_mesh`).
    lam, mu : float or (T,) float
        Lame's constants [Pa], one pair for every element or one per element.
    """
    g, vol = element_gradients(nodes, elements[:, :4])
    lam_t = np.broadcast_to(np.asarray(lam, dtype=np.float64), vol.shape)
    mu_t = np.broadcast_to(np.asarray(mu, dtype=np.float64), vol.shape)
    n = 3 * len(nodes)
    k = sp.csr_matrix((n, n))
    chunk = 2000  # 2000 elements' 30 x 30 blocks at a time: about 15 MB
    for start in range(0, len(elements), chunk):
        sl = slice(start, start + chunk)
        ke = _element_block_stiffness(g[sl], vol[sl], lam_t[sl], mu_t[sl])
        el = elements[sl]
        dof = (3 * el[:, :, None] + np.arange(3)[None, None, :]).reshape(len(el), 30)
        rows = np.repeat(dof, 30, axis=1).ravel()
        cols = np.tile(dof, (1, 30)).ravel()
        k = k + sp.coo_matrix((ke.reshape(-1), (rows, cols)), shape=(n, n)).tocsr()
    return (0.5 * (k + k.T)).tocsr()


def element_stiffness_matrix(
    nodes: FloatArray, elements: IntArray, lam: float | FloatArray, mu: float | FloatArray
) -> sp.csr_matrix:
    """:func:`stiffness_matrix` for (T, 4) elements, :func:`p2_stiffness_matrix` for (T, 10)."""
    if elements.shape[1] == 10:
        return p2_stiffness_matrix(nodes, elements, lam, mu)
    return stiffness_matrix(nodes, elements, lam, mu)


def element_lumped_mass(
    nodes: FloatArray, elements: IntArray, density: float | FloatArray
) -> FloatArray:
    """Lumped nodal masses [kg], (N,): :func:`lumped_mass` for (T, 4) elements; for (T, 10) the
    HRZ lumping (Hinton, Rock and Zienkiewicz 1976), :data:`P2_HRZ_SHARES` of each element's
    ``rho V``: positive at every node, the element's mass kept."""
    if elements.shape[1] != 10:
        return lumped_mass(nodes, elements, density)
    _, vol = element_gradients(nodes, elements[:, :4])
    mass = np.broadcast_to(np.asarray(density, dtype=np.float64), vol.shape) * vol
    return np.asarray(
        np.bincount(
            elements.ravel(), weights=(mass[:, None] * P2_HRZ_SHARES).ravel(), minlength=len(nodes)
        ),
        dtype=np.float64,
    )


def element_gravity_loads(
    nodes: FloatArray, elements: IntArray, density: float | FloatArray, g_m_s2: float
) -> FloatArray:
    """The consistent nodal loads [N] of the solid's own weight, (N, 3), ``g`` [m/s^2] along -z:
    :func:`gravity_loads` for (T, 4) elements; for (T, 10) ``integral N_i rho g dV``,
    :data:`P2_LOAD_SHARES` of each element's weight (upward at the corners, downward at the
    mid-edge nodes; Zienkiewicz, Taylor and Zhu 2013, ch. 6). They sum to the solid's weight."""
    if elements.shape[1] != 10:
        return gravity_loads(nodes, elements, density, g_m_s2)
    _, vol = element_gradients(nodes, elements[:, :4])
    mass = np.broadcast_to(np.asarray(density, dtype=np.float64), vol.shape) * vol
    out = np.zeros((len(nodes), 3))
    out[:, 2] = -float(g_m_s2) * np.bincount(
        elements.ravel(), weights=(mass[:, None] * P2_LOAD_SHARES).ravel(), minlength=len(nodes)
    )
    return out
