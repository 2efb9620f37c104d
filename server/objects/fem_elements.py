"""The FEM solid's P1 tetrahedra: element gradients, stiffness, lumped mass, modal warping.

Pure functions of a volume mesh (``nodes`` (N, 3) [m], ``tets`` (T, 4) positively oriented), used
once when :class:`server.objects.fem.FemSolid` is built and, for :func:`warped`, every tick:

- :func:`element_gradients`: the constant shape-function gradients and the volume of each linear
  four-node tetrahedron;
- :func:`stiffness_matrix`: the isotropic small-strain elastic stiffness ``K`` (3N x 3N) [N/m],
  element by element ``V B^T D B`` with Lame's constants (Zienkiewicz, Taylor and Zhu 2013,
  ch. 6): the object's stiffness behind the paper's eq. (6);
- :func:`lumped_mass`: a quarter of each element's mass on each of its nodes;
- :func:`gravity_loads`: the consistent nodal loads of the solid's own weight;
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

    Per tetrahedron the displacement gradient of P1 elements is constant; its rotation vector is
    averaged at each vertex over the tetrahedra around it, weighted by volume. Only the
    tetrahedra touching the surface are used.

    Parameters
    ----------
    nodes : (N, 3) float [m]; tets : (T, 4) int, positively oriented.
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
    touch = np.flatnonzero((tets < n_surface).any(axis=1))
    t = tets[touch]
    g, vol = element_gradients(nodes, t)
    weight = np.zeros(n_surface)
    for a in range(4):
        ok = t[:, a] < n_surface
        np.add.at(weight, t[ok, a], vol[ok])
    # w_k = 1/2 sum_a (g_a,j u_a,i - g_a,i u_a,j) for (k, i, j) cyclic
    rows, cols, vals = [], [], []
    for k, i, j in ((0, 2, 1), (1, 0, 2), (2, 1, 0)):
        for a in range(4):
            for b in range(4):  # vertex t[:, b] receives the element's rotation
                ok = t[:, b] < n_surface
                scale = 0.5 * vol[ok] / weight[t[ok, b]]
                for axis, sign, grad in ((i, 1.0, j), (j, -1.0, i)):
                    rows.append(3 * t[ok, b] + k)
                    cols.append(columns[3 * t[ok, a] + axis])
                    vals.append(sign * scale * g[ok, a, grad])
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
