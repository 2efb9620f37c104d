"""Multipoint stability of coupled contacts: the object stiffness the server reports per contact.

Several users on one object are coupled through its compliance: the slow loop (DESIGN section 6)
``x(k+1) = C diag(K_h) (x_h - x(k))`` is stable iff ``rho(C diag(K_h)) < 1``
(:func:`spectral_radius`; for one contact ``K_h / K_o``, paper eq. 8). From the contacts'
normal compliance ``C`` [m/N] (the object's ``contact_compliance``) this module computes, per
contact, the coupling-aware ``K_o_eff <= K_o`` (:func:`effective_stiffness`: any
``K_h <= K_o_eff`` keeps that loop stable) and the stiffest modal stiffness ``K_o_stiff >= K_o``
(:func:`stiff_stiffness`) that a PI local model must also be checked at
(docs/coupled-users.md, :mod:`shared.coupled_loop`). The contact geometry on the surface is
:mod:`server.contacts`.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.sparse import csr_array
from scipy.sparse.csgraph import connected_components

from haptic_collab.shared.types import FloatArray, IntArray

#: Stiffness [N/m] reported for a contact that cannot move (zero compliance, e.g. a fixed base).
K_O_MAX = 1.0e6

#: Off-diagonal compliance below this fraction of sqrt(C_ii C_jj) counts as uncoupled.
_COUPLING_TOL = 1e-9


def spectral_radius(compliance: npt.ArrayLike, k_h: npt.ArrayLike) -> float:
    """``rho(C diag(K_h))``: the slow-loop gain of coupled contacts (DESIGN section 6).

    The loop ``x(k+1) = C diag(K_h) (x_h - x(k))`` is asymptotically stable iff this is < 1
    (for one contact it is K_h / K_o, paper eq. 8).

    Parameters
    ----------
    compliance : (m, m) float [m/N], symmetric positive semi-definite
    k_h : (m,) float [N/m], >= 0

    Returns
    -------
    float, dimensionless.

    Raises
    ------
    ValueError
        Shapes mismatch, non-finite entries, negative gains.
    """
    c, k = _check_ck(compliance, k_h, "k_h")
    if len(k) == 0:
        return 0.0
    s = np.sqrt(k)
    return float(max(0.0, np.linalg.eigvalsh(s[:, None] * c * s[None, :])[-1]))


def _check_ck(
    compliance: npt.ArrayLike, k: npt.ArrayLike, name: str
) -> tuple[FloatArray, FloatArray]:
    c = np.asarray(compliance, dtype=np.float64)
    kk = np.asarray(k, dtype=np.float64).reshape(-1)
    m = len(kk)
    if c.shape != (m, m):
        raise ValueError(f"compliance must be ({m}, {m}) for {m} gains, got {c.shape}")
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(kk))):
        raise ValueError("compliance and gains must be finite")
    if np.any(kk < 0.0):
        raise ValueError(f"{name} must be >= 0")
    return 0.5 * (c + c.T), kk


def _coupled_groups(coupled: npt.NDArray[np.bool_]) -> list[IntArray]:
    """Connected components of a symmetric boolean (m, m) coupling matrix, m >= 1.

    Returns
    -------
    list of int64 index arrays, each sorted ascending; the groups are ordered by their smallest
    index. Source: :func:`scipy.sparse.csgraph.connected_components` (undirected).
    """
    m = len(coupled)
    if coupled.all():  # the usual case on one object (and a single contact): one group
        return [np.arange(m, dtype=np.int64)]
    rows, cols = np.nonzero(coupled)
    indptr = np.searchsorted(rows, np.arange(m + 1)).astype(np.int32)
    graph = csr_array((np.ones(len(cols)), cols.astype(np.int32), indptr), shape=(m, m))
    count, labels = connected_components(graph, directed=False)
    order = np.argsort(labels, kind="stable").astype(np.int64)
    groups = np.split(order, np.cumsum(np.bincount(labels, minlength=count))[:-1])
    groups.sort(key=lambda g: int(g[0]))
    return groups


def coupled_groups(compliance: npt.ArrayLike) -> list[IntArray]:
    """The groups of mutually coupled contacts (connected through non-zero ``C_ij``, as
    :func:`effective_stiffness` and :func:`stiff_stiffness` group them) of an (m, m) compliance
    [m/N]: int64 index arrays, each sorted, ordered by their smallest index; [] for m = 0.

    Raises
    ------
    ValueError
        A non-square or non-finite compliance.
    """
    c = np.asarray(compliance, dtype=np.float64)
    if c.ndim != 2 or c.shape[0] != c.shape[1] or not np.all(np.isfinite(c)):
        raise ValueError(f"compliance must be a finite square matrix, got shape {c.shape}")
    if len(c) == 0:
        return []
    c = 0.5 * (c + c.T)
    scale = np.sqrt(np.abs(np.diag(c)))
    coupled = np.abs(c) > _COUPLING_TOL * np.outer(scale, scale)
    np.fill_diagonal(coupled, True)
    return _coupled_groups(coupled)


def effective_stiffness(compliance: npt.ArrayLike, k_o: npt.ArrayLike) -> FloatArray:
    """Coupling-aware object stiffness ``K_o_eff <= K_o`` per contact (DESIGN section 6).

    For each group of mutually coupled contacts (connected through non-zero ``C_ij``),
    ``K_o_eff = K_o / max(1, rho(C diag(K_o)))`` on that group; an uncoupled contact with
    ``K_o = 1 / C_ii`` keeps ``K_o_eff = K_o``. Since ``C_ii K_o,i = 1``, ``rho(C diag K_o) >= 1`` whenever ``C`` is
    PSD, and ``rho(C diag K_o_eff) = 1`` on a coupled group.

    Guarantee (monotonicity): if ``0 <= K_h <= K_o_eff`` elementwise then
    ``rho(C diag K_h) <= 1``, strictly below 1 when ``K_h < K_o_eff`` everywhere. Proof: with
    ``D = diag(K)``, ``C D`` is similar to the symmetric PSD ``D^1/2 C D^1/2``, so
    ``rho(C D) = max_x x^T D^1/2 C D^1/2 x / x^T x = max_y y^T C y / y^T D^-1 y`` (``y = D^1/2 x``,
    for K > 0). ``K_h <= K_o_eff`` gives ``y^T D_h^-1 y >= y^T D_eff^-1 y``, and ``y^T C y >= 0``,
    so every quotient, hence ``rho(C D_h)``, is at most ``rho(C D_eff) = 1`` (strict when all
    ``K_h`` are strictly smaller, as then ``y^T D_h^-1 y > y^T D_eff^-1 y``). A zero gain
    removes its contact from the quotient and cannot raise it.

    Parameters
    ----------
    compliance : (m, m) float [m/N]
        ``C_ij = beta_i^T K^-1 beta_j`` of the contacts taking part (symmetric PSD).
    k_o : (m,) float [N/m]
        ``K_o,i = 1 / C_ii`` (or any positive stiffness).

    Returns
    -------
    (m,) float64 [N/m]

    Raises
    ------
    ValueError
        Shapes mismatch, non-finite entries, negative stiffness.
    """
    c, k = _check_ck(compliance, k_o, "k_o")
    out = k.copy()
    for members in coupled_groups(c):
        rho = spectral_radius(c[np.ix_(members, members)], k[members])
        if rho > 1.0:
            out[members] = k[members] / rho
    return out


def stiff_stiffness(compliance: npt.ArrayLike, k_o: npt.ArrayLike) -> FloatArray:
    """Stiffest modal object stiffness ``K_o_stiff >= K_o`` per contact (docs/coupled-users.md).

    For each group of mutually coupled contacts (as in :func:`effective_stiffness`),
    ``K_o_stiff = K_o / lambda_min(D^1/2 C D^1/2)`` with ``D = diag(K_o)`` on that group, capped at
    :data:`K_O_MAX` (a rigid mode when ``lambda_min`` is 0); an uncoupled contact keeps ``K_o``.
    With identical users the modal stiffnesses of the group lie in ``[K_o_eff, K_o_stiff]``
    (``K_o_eff`` from :func:`effective_stiffness`): a PI local model checked over that whole range
    is stable in every mode of the coupled loop (:mod:`shared.coupled_loop`), whereas the
    ``K_o_eff`` argument alone holds for a proportional one only.

    Parameters
    ----------
    compliance : (m, m) float [m/N]
        ``C_ij`` of the contacts taking part (symmetric PSD).
    k_o : (m,) float [N/m]
        ``K_o,i = 1 / C_ii`` (or any positive stiffness).

    Returns
    -------
    (m,) float64 [N/m], ``K_o <= K_o_stiff <= max(K_o, K_O_MAX)``.

    Raises
    ------
    ValueError
        Shapes mismatch, non-finite entries, negative stiffness.
    """
    c, k = _check_ck(compliance, k_o, "k_o")
    out = k.copy()
    for members in coupled_groups(c):
        if len(members) < 2:
            continue
        s = np.sqrt(k[members])
        lam = float(np.linalg.eigvalsh(s[:, None] * c[np.ix_(members, members)] * s[None, :])[0])
        cap = np.maximum(k[members], K_O_MAX)
        # a unit-diagonal S has lambda_min <= 1: round-off must not move a contact below K_o
        stiff = k[members] / lam if lam > 0.0 else cap
        out[members] = np.clip(stiff, k[members], cap)
    return out
