"""The sparse factorisation both deformable objects make once at start: ordering, factor, solves.

The water balloon (:mod:`server.objects.balloon`) and the FEM solid (:mod:`server.objects.fem`)
each factor one symmetric positive definite stiffness matrix at construction and then only solve
with it (patch solves, paper eq. 6; the damped step of eq. 9): this module owns how. The unknowns
are ordered by geometric nested dissection (:func:`nested_dissection`: median-plane splits,
separators last), the matrix is factored without pivoting and the factor checked
(:func:`factor_spd`), and :class:`SpdFactor` adds the balloon's rank-one water term by
Sherman-Morrison::

    (M + kappa a a^T)^-1 b = M^-1 b - kappa (a^T M^-1 b) / (1 + kappa a^T M^-1 a) * M^-1 a

The FEM solid's linear elements with averaged nodal pressure solve ``(A + B^T C^-1 B) x = f``
through the factor of their mixed form (:class:`SaddlePointFactor`).

Nothing here uses threads, sockets or clocks.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from haptic_collab.shared.types import FloatArray, IntArray

#: Relative residual above which the no-pivoting factorization is rejected (then pivoted LU).
_FACTOR_RESIDUAL_TOL = 1e-6

#: Nested dissection stops splitting below this many vertices.
_ND_LEAF = 64


def nested_dissection(graph: sp.csr_matrix, points: FloatArray, leaf: int = _ND_LEAF) -> IntArray:
    """Fill-reducing ordering by geometric nested dissection.

    Recursively splits the vertex set by the median plane across its largest extent; the
    vertices on one side adjacent to the other (the smaller such set) form the separator,
    ordered after both halves. For a surface mesh the separators are curves of O(sqrt(n))
    vertices, so the Cholesky/LU fill is O(n log n). A numerical ordering, no equation of the
    paper: it makes the one factorisation of the object's stiffness (eq. 6) cheap.

    Parameters
    ----------
    graph : (n, n) sparse, symmetric sparsity pattern of the matrix to factor.
    points : (n, 3) float, coordinates of the unknowns [m].
    leaf : int, subsets at most this big are not split.

    Returns
    -------
    (n,) int64 permutation: ``order[k]`` is the unknown eliminated k-th.
    """
    g = sp.csr_matrix(graph, copy=True)
    g.data[:] = 1.0
    out: list[IntArray] = []

    def split(subset: IntArray) -> None:
        if len(subset) <= leaf:
            out.append(subset)
            return
        q = points[subset]
        axis = int(np.argmax(q.max(axis=0) - q.min(axis=0)))
        median = float(np.median(q[:, axis]))
        lower = q[:, axis] < median
        left, right = subset[lower], subset[~lower]
        if len(left) == 0 or len(right) == 0:
            out.append(subset)
            return
        touches_right = np.diff(g[left][:, right].indptr) > 0
        touches_left = np.diff(g[right][:, left].indptr) > 0
        if touches_right.sum() <= touches_left.sum():
            separator, left = left[touches_right], left[~touches_right]
        else:
            separator, right = right[touches_left], right[~touches_left]
        split(left)
        split(right)
        out.append(separator)

    split(np.arange(g.shape[0], dtype=np.int64))
    return np.concatenate(out).astype(np.int64)


class SpdFactor:
    """One symmetric positive definite sparse matrix factored once, plus a Sherman-Morrison term.

    Solves ``(M + kappa a a^T) x = b`` for the free unknowns, in the matrix's own row order (the
    balloon's ``K = K0 + kappa a a^T``, paper eq. 6; with the damping term, eq. 9).

    Parameters
    ----------
    matrix : (nf, nf) scipy.sparse.csc_matrix
        ``M``, SPD, already in fill-reducing order (:func:`nested_dissection`) [N/m].
    a : (nf,) float
        The rank-one term's vector (the balloon's vertex areas [m^2]).
    kappa : float
        Its weight (the water's bulk term [N/m^5]); 0: no rank-one term.
    """

    def __init__(self, matrix: sp.csc_matrix, a: FloatArray, kappa: float) -> None:
        self.lu = factor_spd(matrix)
        self.z = self.lu.solve(a)
        self.a = a
        self.kappa = kappa
        self.denominator = 1.0 + kappa * float(a @ self.z)

    def solve(self, rhs: FloatArray) -> FloatArray:
        """``(M + kappa a a^T)^-1 rhs`` for rhs (nf,) or (nf, k) [N]; the result in [m]."""
        y = np.asarray(self.lu.solve(rhs), dtype=np.float64)
        if self.kappa == 0.0:
            return y
        coef = self.kappa * (self.a @ y) / self.denominator
        if y.ndim == 1:
            return y - coef * self.z
        return y - np.outer(self.z, coef)


def factor_spd(matrix: sp.csc_matrix) -> spla.SuperLU:
    """Factor an SPD matrix already in fill-reducing order, without pivoting (checked). A
    symmetric quasi-definite one factors the same way (:class:`SaddlePointFactor`).

    The no-pivoting LU in the given order keeps the fill of :func:`nested_dissection`; it is
    checked on one solve (relative residual below :data:`_FACTOR_RESIDUAL_TOL`), and otherwise
    redone with threshold pivoting and SuperLU's own ordering. The object's stiffness of paper
    eq. 6 (or its damped form, eq. 9) is factored this way once.

    Parameters
    ----------
    matrix : (n, n) scipy.sparse.csc_matrix
        Symmetric positive definite [N/m].

    Returns
    -------
    scipy.sparse.linalg.SuperLU
        Its factor; ``.solve(b)`` for b (n,) or (n, k).

    Raises
    ------
    RuntimeError
        From SuperLU when even the pivoted factorisation finds the matrix singular.
    """
    lu = spla.splu(
        matrix, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
    )
    probe = np.ones(matrix.shape[0])
    x = lu.solve(probe)
    residual = np.linalg.norm(matrix @ x - probe) / np.linalg.norm(probe)
    if np.all(np.isfinite(x)) and residual < _FACTOR_RESIDUAL_TOL:
        return lu
    # Not expected for an SPD matrix; fall back to threshold pivoting with its own ordering.
    return spla.splu(matrix, permc_spec="MMD_AT_PLUS_A")


class SaddlePointFactor:
    """Solves ``(A + B^T C^-1 B) x = f`` by one factor of the mixed form ``[[A, B^T], [B, -C]]``.

    ``A`` symmetric positive definite, ``C`` positive diagonal: the mixed matrix is symmetric
    quasi-definite, so it has a factorisation without pivoting in any symmetric order
    (Vanderbei 1995, "Symmetric quasidefinite matrices", SIAM J. Optim. 5(1)), which
    :func:`factor_spd` makes and checks. Eliminating the second block gives back ``x``; the
    condensed matrix is never factored (it couples every unknown's neighbours' neighbours: 6.7
    times P1's fill on the 11200-node box, where this form has 1.8 times). Used for the FEM
    solid's averaged nodal pressure (:func:`server.objects.fem_elements.nodal_pressure_operators`:
    ``A = K_dev``, ``B = D``, ``C = diag(c)``).

    Parameters
    ----------
    a : (n, n) sparse, SPD [N/m]; b : (m, n) sparse; c : (m,) float, > 0
        The blocks, in the caller's row order of ``x``.
    order : (n + m,) int
        A fill-reducing permutation of the mixed unknowns (``x`` first, then the ``m``
        multipliers): ``order[k]`` is eliminated k-th.

    Raises
    ------
    ValueError
        ``c`` not all finite and > 0, or the shapes disagree.
    """

    def __init__(self, a: sp.spmatrix, b: sp.spmatrix, c: FloatArray, order: IntArray) -> None:
        n, m = a.shape[0], b.shape[0]
        c = np.asarray(c, dtype=np.float64)
        if a.shape != (n, n) or b.shape != (m, n) or c.shape != (m,) or len(order) != n + m:
            raise ValueError("saddle-point blocks: shapes disagree")
        if not (np.all(np.isfinite(c)) and np.all(c > 0.0)):
            raise ValueError("saddle-point blocks: C must be finite and > 0")
        mixed = sp.bmat([[a, b.T], [b, -sp.diags(c)]], format="csc")
        self.lu = factor_spd(sp.csc_matrix(mixed[order][:, order]))
        position = np.empty(n + m, dtype=np.int64)
        position[order] = np.arange(n + m)
        self._x_rows = position[:n]
        self._size = n + m

    @property
    def L(self) -> sp.csc_matrix:  # noqa: N802 (SuperLU's name)
        """The factor's lower triangle (as SuperLU's ``L``)."""
        return self.lu.L

    @property
    def U(self) -> sp.csc_matrix:  # noqa: N802 (SuperLU's name)
        """The factor's upper triangle (as SuperLU's ``U``)."""
        return self.lu.U

    def solve(self, rhs: FloatArray) -> FloatArray:
        """``x`` (n,) or (n, k) [m] for ``f`` = ``rhs`` of the same shape [N]."""
        rhs = np.asarray(rhs, dtype=np.float64)
        full = np.zeros((self._size, *rhs.shape[1:]))
        full[self._x_rows] = rhs
        return np.asarray(self.lu.solve(full), dtype=np.float64)[self._x_rows]
