"""The stability margin's eigenvalue measure, solved only where it can matter.

What a user would notice: none of it, by design. A design or a verified plane is accepted on the
same verdict and reports the same worst spectral radius whether every monodromy matrix's
eigenvalues are taken or only those a norm bound cannot rule out; the check just finishes sooner.
"""

from __future__ import annotations

import math

import numpy as np

from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX, monodromy
from haptic_collab.shared.gains.policy import MIN_DECAY_RATE_PER_S
from haptic_collab.shared.stability_margin import group_mode_radii, mode_radii, radius_bounds


def _loops() -> tuple[np.ndarray, float, int, float]:
    """Monodromy matrices of a plane at 50 Hz with 100 ms, every hand of the box, K_o' 300-700
    N/m, dampers from none (rings) to 3.5 N*s/m: (K, n, n)."""
    n, T = 20, 1e-3
    hands = DEFAULT_HAND_BOX.hands()
    mats = []
    for b_h in (0.0, 1.0, 3.5):
        for k_o in (300.0, 700.0):
            M = monodromy(
                hand=hands, k_o=k_o, k_h=500.0, i_gain=0.0, b_h=b_h,
                own_gain=1.0 / 500.0, servo_period_s=T, rate_ratio=n, delay_ticks=5,
            )  # fmt: skip
            mats.append(M.reshape(-1, *M.shape[-2:]))
    return np.concatenate(mats), math.exp(-MIN_DECAY_RATE_PER_S * n * T), n, T


def test_the_bound_is_never_below_the_spectral_radius_and_is_tight_for_most():
    M, lim, n, T = _loops()
    _, rad = mode_radii(M, lim, n, T)
    b = radius_bounds(M)
    assert np.all(b >= rad * (1.0 - 1e-9))
    assert np.mean(b < 1.05 * rad) > 0.5


def test_each_groups_maxima_are_those_of_every_matrix_solved():
    M, lim, n, T = _loops()
    marg, rad = mode_radii(M, lim, n, T)
    rng = np.random.default_rng(3)
    # every matrix, and those within the margin alone (where no failure settles a group's maxima)
    for sub in (np.ones(len(M), bool), marg < lim):
        for n_groups in (1, 7, 40):
            group = rng.integers(0, n_groups, size=int(sub.sum())).astype(np.intp)
            gm, gr = group_mode_radii(M[sub], lim, n, T, group, n_groups)
            for g in range(n_groups):
                assert gm[g] == marg[sub][group == g].max()
                assert gr[g] == rad[sub][group == g].max()
    # some groups fail the margin, some pass: the verdicts are not all alike
    group = (np.arange(len(M)) // 500).astype(np.intp)
    gm, _ = group_mode_radii(M, lim, n, T, group, int(group.max()) + 1)
    assert np.any(gm >= lim) and np.any(gm < lim)


def test_a_matrix_that_overflows_is_solved_not_bounded():
    M = np.array([[[1e200, 1.0], [0.0, 0.5]], [[0.2, 0.0], [0.0, 0.1]]])
    b = radius_bounds(M)
    assert not np.isfinite(b[0]) or b[0] >= 1e200
    gm, gr = group_mode_radii(M, 0.9, 20, 1e-3, np.array([0, 1], np.intp), 2)
    assert gr[0] == 1e200 and gr[1] == mode_radii(M[1:], 0.9, 20, 1e-3)[1][0]


def test_a_loose_bound_above_a_tight_one_does_not_hide_the_larger_radius():
    # a non-normal matrix (radius 0.5, a huge transient: bounded near 0.8) ranks first by bound;
    # the normal one (radius 0.7) must still be solved, or the group's radius would read 0.5
    a = np.array([[0.5, 2e49], [0.0, 0.5]])
    b = np.diag([0.7, 0.1])
    M = np.stack([a, b])
    bounds = radius_bounds(M)
    assert bounds[0] > bounds[1] > 0.69
    gm, gr = group_mode_radii(M, 0.9, 20, 1e-3, np.zeros(2, np.intp), 1)
    marg_b, rad_b = mode_radii(M[1:], 0.9, 20, 1e-3)
    assert gr[0] == rad_b[0] == 0.7 and gm[0] == marg_b[0]
