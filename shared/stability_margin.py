"""The stability margin every local model's gains are held to on the full loop.

A design (:func:`shared.gains.design.design_gains`), interim gains
(:func:`shared.gains.interim.verify_gains`) and coupled users' gains
(:func:`shared.coupled_loop.verify_coupled`) are accepted only if every *oscillating* mode of the
full loop (:mod:`shared.full_loop`) decays at :data:`MIN_DECAY_RATE_PER_S` or faster, while creep
(modes slower than :data:`CREEP_FREQUENCY_HZ`) need only be stable. This module owns that margin,
the eigenvalue measure of it (:func:`mode_radii`), the same measure's maxima over groups of
matrices with eigenvalues solved only where a norm bound cannot rule a matrix out
(:func:`group_mode_radii`, :func:`radius_bounds`: Gelfand's formula; docs/gains.md, "What a check
costs") and the object stiffnesses K_o' a range of K_o is checked at (:func:`k_o_points`).
"""

from __future__ import annotations

import math

import numpy as np

from haptic_collab.shared.gains.policy import (
    CREEP_FREQUENCY_HZ,
    K_O_CHECK_RATIO,
)
from haptic_collab.shared.types import FloatArray, IndexArray


def mode_radii(
    M: FloatArray, rho_limit: float, rate_ratio: int, servo_period_s: float
) -> tuple[FloatArray, FloatArray]:
    """``(margin_radius, radius)`` of each monodromy matrix of ``M`` (..., n, n), each shape (...).

    ``radius`` is the spectral radius; ``margin_radius`` the largest eigenvalue magnitude with
    creep eigenvalues (slower than :data:`CREEP_FREQUENCY_HZ`: angle below
    ``2 pi CREEP_FREQUENCY_HZ N T`` per simulation period) counted as ``|lambda| * rho_limit``.
    """
    creep_angle = 2.0 * math.pi * CREEP_FREQUENCY_HZ * rate_ratio * servo_period_s
    ev = np.linalg.eigvals(M)
    mag = np.abs(ev)
    slow = np.abs(np.angle(ev)) < creep_angle
    return np.max(np.where(slow, mag * rho_limit, mag), axis=-1), np.max(mag, axis=-1)


#: Squarings of a monodromy matrix whose norm bounds its spectral radius (:func:`radius_bounds`):
#: rho(M) <= ||M^(2^p)||^(1/2^p) (Gelfand's formula). Eight bounded 96 % of a passing design's
#: matrices below the margin (50 Hz with 200 ms, 27 states) at a third of their eigenvalues' cost.
BOUND_SQUARINGS = 8

#: Relative slack between a bound and what it is compared with: a matrix is taken as bounded only
#: this far below (rounding in the squarings, as in an eigenvalue solver's own result).
BOUND_SLACK = 1e-6


def radius_bounds(M: FloatArray) -> FloatArray:
    """Upper bounds on the spectral radius of each matrix of ``M`` (..., n, n), shape (...):
    ``||M^(2^p)||_F^(1/2^p)`` with p = :data:`BOUND_SQUARINGS` (Gelfand's formula; the
    Frobenius norm is at least the spectral one). Each square is scaled to unit norm and the
    scale kept as a logarithm, so neither a decaying nor a growing matrix under- or overflows;
    a matrix with a non-finite entry gets NaN (bounds nothing)."""
    P = np.array(M, dtype=float)
    log_norm = np.zeros(P.shape[:-2])
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        for _ in range(BOUND_SQUARINGS):
            P = P @ P
            nrm = np.sqrt(np.einsum("...ij,...ij->...", P, P))
            log_norm = 2.0 * log_norm + np.log(nrm)
            P = P / np.where(nrm > 0.0, nrm, 1.0)[..., None, None]
        return np.exp(log_norm / 2.0**BOUND_SQUARINGS)


def group_mode_radii(
    M: FloatArray,
    rho_limit: float,
    rate_ratio: int,
    servo_period_s: float,
    group: IndexArray,
    n_groups: int,
) -> tuple[FloatArray, FloatArray]:
    """The largest ``(margin_radius, radius)`` of :func:`mode_radii` over each group of the
    matrices of ``M`` (K, n, n) (``group`` (K,) in [0, ``n_groups``)), each shape (n_groups,),
    the same values as taking every matrix's eigenvalues, at a fraction of the cost.

    A matrix whose :func:`radius_bounds` lies below ``rho_limit`` and below the largest margin
    radius its group has among the matrices solved can change neither maximum, and is not
    solved: first every matrix not bounded below ``rho_limit`` (all that can fail), then, in a
    group with none of those, the one with the largest bound, then all whose bound reaches their
    group's largest margin radius so far. A group with no matrices gets 0.
    """
    K = M.shape[0]
    marg = np.full(K, -np.inf)
    rad = np.full(K, -np.inf)
    solved = np.zeros(K, dtype=bool)
    b = radius_bounds(M)
    b_up = np.where(np.isfinite(b), b * (1.0 + BOUND_SLACK), np.inf)

    def solve(idx: IndexArray) -> None:
        if idx.size:
            marg[idx], rad[idx] = mode_radii(M[idx], rho_limit, rate_ratio, servo_period_s)
            solved[idx] = True

    def group_max(v: FloatArray) -> FloatArray:
        out = np.full(n_groups, -np.inf)
        np.maximum.at(out, group[solved], v[solved])
        return out

    solve(np.flatnonzero(~(b_up < rho_limit)))
    m_star = group_max(marg)
    # a group none of whose matrices had to be solved: the one bounded highest (the first of
    # equals)
    best = np.full(n_groups, -np.inf)
    np.maximum.at(best, group, b_up)
    at_best = np.flatnonzero((b_up == best[group]) & (m_star[group] == -np.inf))
    _, first = np.unique(group[at_best], return_index=True)
    solve(at_best[first])
    m_star = group_max(marg)
    solve(np.flatnonzero(~solved & (b_up >= m_star[group])))
    return np.maximum(group_max(marg), 0.0), np.maximum(group_max(rad), 0.0)


def k_o_points(lo: float, hi: float) -> list[float]:
    """The K_o values [N/m] a design over ``[lo, hi]`` is checked at.

    ``lo``, the geometric middle and ``hi`` for a range up to :data:`K_O_CHECK_RATIO` wide; a
    geometric grid with a ratio of at most :data:`K_O_CHECK_RATIO` between neighbours beyond
    (a coupled contact's range reaches ``K_O_RIGID`` = 1e6 N/m: about 8 points from 150 N/m).
    """
    if hi <= lo:
        return [float(lo)]
    n = max(3, 1 + math.ceil(math.log(hi / lo) / math.log(K_O_CHECK_RATIO) - 1e-9))
    return [float(v) for v in np.geomspace(lo, hi, n)]
