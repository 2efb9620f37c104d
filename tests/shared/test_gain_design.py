"""Gain design with the hand in the loop, checked independently of how it was designed.

The design (shared.gains.design) checks its candidates on the hands of ``HandBox.hands()`` (the
box's corners, face centres and centre). Here every design is re-checked on a *finer* lattice of
hands spanning the same ranges (4 x 4 x 4 points plus the simulated hand,
:mod:`tests.support.hand_lattice`), at every force-sampling tick and at K_o' = (1 - margin) K_o,
the middle of the range and K_o. Where the lattice finds an
unstable hand, a time-domain reference written here (exact hand discretisation, its own local
model, decimator, object, delay line and proxy hold) confirms that the instability is real.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections import deque
from dataclasses import replace

import numpy as np
import pytest
from scipy.linalg import expm

from haptic_collab.shared.full_loop import DEFAULT_HAND, Hand
from haptic_collab.shared.gains.design import GainDesign, design_gains
from haptic_collab.shared.gains.policy import MIN_DECAY_RATE_PER_S
from tests.support.hand_lattice import T, worst_on_lattice

MARGIN = 0.15  # design_gains' default
K_H_MAX = 1000.0  # Phantom Desktop limits (client.devices.profiles)
B_H_MAX = 10.0


def _margin_range(k_o: float, k_o_hi: float | None = None) -> list[float]:
    lo, hi = (1.0 - MARGIN) * k_o, k_o if k_o_hi is None else k_o_hi
    return [lo, 0.5 * (lo + hi), hi]


@functools.cache
def _design(
    k_o: float,
    sim_rate_hz: float,
    delay_ticks: int,
    mode: str,
    k_h_max: float = K_H_MAX,
    b_h_max: float = B_H_MAX,
    own_force: bool = False,
) -> GainDesign:
    return design_gains(
        k_o,
        sim_rate_hz=sim_rate_hz,
        delay_ticks=delay_ticks,
        mode=mode,  # type: ignore[arg-type]
        k_h_max=k_h_max,
        b_h_max=b_h_max,
        own_force=own_force,
    )


def _simulate_peaks(
    hand: Hand,
    *,
    k_o: float,
    k_h: float,
    i_gain: float,
    b_h: float,
    n: int,
    delay: int,
    j: int,
    hold: str,
    seconds: float,
    filter_s: float = 0.005,
    own_gain: float = 0.0,
) -> np.ndarray:
    """Largest |probe depth| [m] in each simulation period after a 1 mm push (linear contact).

    Independent of shared.full_loop: the hand ``m x'' = -b x' - k x - f`` is discretised exactly
    for a force held over each servo tick; the local model is K_h e + s + B_h u with u the
    first-order filtered backward difference of the probe; the simulation takes the force of
    servo tick j, the object is x_o = F / K_o, ``delay`` periods later it is the new surface,
    reached at once (zoh) or linearly over the period (foh), moved out by ``own_gain`` times the
    force sampled (own-force compensation).
    """
    m, b, k = hand.mass_kg, hand.damping_n_s_per_m, hand.stiffness_n_per_m
    e = expm(np.array([[0.0, 1.0, 0.0], [-k / m, -b / m, -1.0 / m], [0.0, 0.0, 0.0]]) * T)
    p00, p01, p10, p11, g0, g1 = e[0, 0], e[0, 1], e[1, 0], e[1, 1], e[0, 2], e[1, 2]
    a = T / (T + filter_s)
    x, v, x_prev, u, s = 1e-3, 0.0, 1e-3, 0.0, 0.0
    line: deque[float] = deque([0.0] * delay)
    p_new = p_old = f_sample = 0.0
    peaks = []
    for blk in range(round(seconds / (n * T))):
        if blk > 0:
            line.append(f_sample / k_o - own_gain * f_sample)
            p_old, p_new = p_new, line.popleft()
        peak = 0.0
        for i in range(n):
            p = p_old + (p_new - p_old) * ((i + 1) / n if hold == "foh" else 1.0)
            u += a * ((x - x_prev) / T - u)
            f = k_h * (x - p) + s + b_h * u
            if i == j:
                f_sample = f
            s += T * i_gain * (x - p)
            x_prev = x
            x, v = p00 * x + p01 * v + g0 * f, p10 * x + p11 * v + g1 * f
            peak = max(peak, abs(x))
        peaks.append(peak)
    return np.array(peaks)


# ------------------------------------------------------------- designs, verified on a finer box
K_OS = (50.0, 300.0, 1000.0, 5000.0)
SIM_RATES = (10.0, 20.0, 100.0)
DELAYS = (0, 2, 4)
# A design takes up to a few seconds each on a fresh checkout: a subset covering every K_o, rate
# and delay runs by default for both local models, the rest of the grid is marked slow (CI runs
# it: make test-slow), and the five costliest PI cells (2-4 s each; they passed this check when
# the test was written) are left out
FAST = {
    (50.0, 10.0, 0),
    (50.0, 100.0, 0),
    (50.0, 100.0, 2),
    (300.0, 20.0, 4),
    (300.0, 100.0, 0),
    (1000.0, 10.0, 2),
    (1000.0, 20.0, 0),
    (5000.0, 10.0, 4),
    (5000.0, 100.0, 0),
}
PI_LEFT_OUT = {
    (1000.0, 20.0, 2),
    (1000.0, 100.0, 4),
    (5000.0, 20.0, 2),
    (5000.0, 100.0, 2),
    (5000.0, 100.0, 4),
}
GRID = [
    pytest.param(
        k_o,
        sim,
        delay,
        mode,
        id=f"{mode}-Ko{k_o:g}-{sim:g}Hz-D{delay}",
        marks=[] if (k_o, sim, delay) in FAST else [pytest.mark.slow],
    )
    for mode in ("p", "pi")
    for k_o, sim, delay in itertools.product(K_OS, SIM_RATES, DELAYS)
    if mode == "p" or (k_o, sim, delay) not in PI_LEFT_OUT
]


@pytest.mark.parametrize(("k_o", "sim_rate_hz", "delay_ticks", "mode"), GRID)
def test_designed_gains_are_stable_for_every_hand_of_a_finer_lattice(
    k_o: float, sim_rate_hz: float, delay_ticks: int, mode: str
) -> None:
    d = _design(k_o, sim_rate_hz, delay_ticks, mode)
    assert 0.0 < d.k_h <= K_H_MAX
    assert 0.0 <= d.b_h <= B_H_MAX
    assert d.i_gain >= 0.0 and (mode == "pi" or d.i_gain == 0.0)
    rho, where = worst_on_lattice(
        d, _margin_range(k_o), sim_rate_hz=sim_rate_hz, delay_ticks=delay_ticks
    )
    assert rho < 1.0, f"unstable full loop (spectral radius {rho:.4f}) for {where}"


INTERIOR_HAND = Hand(0.1 + 0.5 / 3.0, 2.0, 1000.0)  # a lattice point on an edge of the box


@pytest.mark.parametrize(
    ("hand", "own_force"),
    [
        pytest.param(DEFAULT_HAND, False, id="paper-simulated-hand", marks=pytest.mark.slow),
        pytest.param(Hand(0.6, 2.0, 1000.0), False, id="paper-box-corner"),
        pytest.param(INTERIOR_HAND, False, id="paper-box-edge", marks=pytest.mark.slow),
        pytest.param(DEFAULT_HAND, True, id="compensated-simulated-hand", marks=pytest.mark.slow),
        pytest.param(
            Hand(0.6, 2.0, 1000.0), True, id="compensated-box-corner", marks=pytest.mark.slow
        ),
        pytest.param(INTERIOR_HAND, True, id="compensated-box-edge"),
    ],
)
def test_design_decays_in_the_time_domain_for_hands_of_the_box(hand: Hand, own_force: bool) -> None:
    """K_o = 50 N/m at 100 Hz with 4 ticks of delay (P), at the low end of the margin."""
    d = _design(50.0, 100.0, 4, "p", own_force=own_force)
    assert (d.own_gain > 0.0) == own_force
    peaks = _simulate_peaks(
        hand,
        k_o=(1.0 - MARGIN) * 50.0,
        k_h=d.k_h,
        i_gain=d.i_gain,
        b_h=d.b_h,
        n=10,
        delay=4,
        j=0,
        hold=d.proxy_hold,
        seconds=30.0,
        own_gain=d.own_gain,
    )
    early, late = peaks[500:1000].max(), peaks[2500:3000].max()  # 5-10 s vs 25-30 s
    assert late < early, (
        f"vibration grows from {early * 1e3:.3g} mm to {late * 1e3:.3g} mm for {hand} "
        f"(K_h = {d.k_h:g}, B_h = {d.b_h:g}, {d.proxy_hold})"
    )


def test_issue_goal_half_the_object_stiffness_with_a_p_model_at_20_hz() -> None:
    d = _design(1000.0, 20.0, 0, "p")
    assert d.mode == "p" and d.i_gain == 0.0
    assert d.k_h >= 0.5 * 1000.0
    assert d.k_h <= K_H_MAX and d.b_h <= B_H_MAX


@pytest.mark.parametrize("mode", ["p", "pi"])
def test_device_limits_bound_the_gains(mode: str) -> None:
    d = _design(5000.0, 10.0, 4, mode, k_h_max=200.0, b_h_max=2.5)
    assert d.k_h <= 200.0
    assert d.b_h <= 2.5
    rho, where = worst_on_lattice(d, _margin_range(5000.0), sim_rate_hz=10.0, delay_ticks=4)
    assert rho < 1.0, where


def test_pi_without_a_stable_integral_falls_back_to_p_instead_of_raising() -> None:
    d = _design(300.0, 20.0, 4, "pi", b_h_max=0.0)
    assert d.mode == "p"
    assert d.i_gain == 0.0
    assert d.b_h == 0.0
    rho, where = worst_on_lattice(d, _margin_range(300.0), sim_rate_hz=20.0, delay_ticks=4)
    assert rho < 1.0, where


def test_design_without_a_damper_never_uses_one() -> None:
    d = _design(1000.0, 20.0, 0, "p", b_h_max=0.0)
    assert d.b_h == 0.0
    assert d.k_h < 1000.0


@pytest.mark.parametrize("rate", [20.0, 100.0])
def test_with_no_model_error_allowed_the_design_is_the_objects_own_plane(rate: float) -> None:
    # a range of one K_o' (no margin, not stiffer) once crashed the check of the range's other
    # points ("zero-size array"); with the object known exactly the most transparent stable
    # design is model-mediated teleoperation's plane: K_h = K_o, C_h K_h = 1, no damper, felt
    # as the object at every frequency of the band
    d = design_gains(
        300.0, sim_rate_hz=rate, mode="p", margin=0.0, own_force=True, k_h_max=K_H_MAX,
        b_h_max=B_H_MAX,
    )  # fmt: skip
    assert d.k_o_range == (300.0, 300.0)
    assert d.k_h == pytest.approx(300.0) and d.own_gain * d.k_h == pytest.approx(1.0)
    assert d.b_h == 0.0
    assert d.felt_stiffness_ratio_8hz == pytest.approx(1.0, abs=1e-6)
    assert d.worst_spectral_radius < d.rho_limit


@pytest.mark.parametrize(
    "kwargs",
    [
        {"k_o": -1.0},
        {"k_o": 0.0},
        {"k_o": math.nan},
        {"k_o": math.inf},
        {"k_o": 300.0, "sim_rate_hz": 30.0},  # N = 33.3
        {"k_o": 300.0, "sim_rate_hz": 0.0},
        {"k_o": 300.0, "margin": 1.0},
        {"k_o": 300.0, "margin": -0.1},
        {"k_o": 300.0, "delay_ticks": -1},
        {"k_o": 300.0, "delay_ticks": 1.5},
        {"k_o": 300.0, "mode": "pd"},
        {"k_o": 300.0, "b_h_max": -1.0},
        {"k_o": 300.0, "k_h_max": 0.0},
        {"k_o": 300.0, "holds": ()},
        {"k_o": 300.0, "holds": ("soh",)},
    ],
    ids=lambda kw: ",".join(f"{k}={v}" for k, v in kw.items()),
)
def test_bad_inputs_raise_value_error(kwargs: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        design_gains(**kwargs)  # type: ignore[arg-type]


def test_design_at_scales_and_clamps() -> None:
    d = design_gains(100.0, mode="p", sim_rate_hz=50.0, own_force=True, k_h_max=1000.0)
    assert d.scale_max == 1.0 and d.at(109.0) is d  # not a scaled design: the same gains
    s = replace(d, k_o_range=(85.0, 110.0), scale_max=1.1)
    up = s.at(105.0)
    assert up.k_h == pytest.approx(1.05 * d.k_h) and up.own_gain == pytest.approx(d.own_gain / 1.05)
    assert (up.b_h, up.k_o, up.k_o_range) == (
        d.b_h,
        pytest.approx(105.0),
        pytest.approx((89.25, 110.0)),
    )
    assert (
        up.at(105.0) == up and s.at(100.0) is s and s.at(90.0) is s
    )  # below the cell: as designed
    assert s.at(200.0).k_h == pytest.approx(1.1 * d.k_h)  # clamped at the top
    with pytest.raises(ValueError):
        s.at(math.nan)


# ------------------------------------------- the soft end: an object softer than reported (issue 58)
def test_a_compensated_design_holds_on_an_object_as_much_softer_as_its_feel_is_judged_on() -> None:
    """The design judges how it feels on objects 1.25 times softer than reported; where that
    costs less than a JND it is also checked there (shared.gains.design.softest_k_o). Issue
    58's two-user ring: 100 N/m at 10 Hz with one tick of delay; on a spring 20 % softer than
    reported, the design checked down to 0.85 K_o let a loose heavy hand ring at 0.69/s
    (spectral radius 0.93 over a simulation period), under the margin's 1/s."""
    d = design_gains(
        100.0, sim_rate_hz=10.0, delay_ticks=1, mode="p", k_h_max=K_H_MAX, b_h_max=B_H_MAX,
        own_force=True, stiffer_by=0.25,
    )  # fmt: skip
    soft = 100.0 / 1.25
    assert d.k_o_range[0] == pytest.approx(soft)
    assert d.own_gain * d.k_h == pytest.approx(1.0)  # still compensated: felt as the object
    # every hand of a lattice finer than the box rings down at 1/s or faster on the softer spring
    rho, where = worst_on_lattice(d, [soft, 0.5 * (soft + 100.0)], sim_rate_hz=10.0, delay_ticks=1)
    assert rho < math.exp(-MIN_DECAY_RATE_PER_S / 10.0), f"spectral radius {rho:.4f} for {where}"


@pytest.mark.slow  # a gain-table cell's design at 20 ticks of delay (10-20 s)
def test_where_the_soft_end_costs_more_than_a_jnd_the_design_keeps_compensation() -> None:
    """1000 N/m at 50 Hz with 200 ms each way: checked down to 0.8 K_o no compensated model
    passes and the paper's P (about a fifth as stiff) would win; a press on a stiffening object
    then cycled between it and the compensated verified planes. The design keeps the margin's
    end there, and its compensation."""
    from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX
    from haptic_collab.shared.gains.key import make_gain_key
    from haptic_collab.shared.gains.table import GainTable, design_cell

    table = GainTable()
    key = make_gain_key(
        servo_rate_hz=1000.0, sim_rate_hz=50.0, delay_ticks=20, mode="p", margin=MARGIN,
        k_h_max=K_H_MAX, b_h_max=B_H_MAX, b_o=0.0, stiff_ratio=1.0,
    )  # fmt: skip
    cell = table.cell(1000.0)
    d = design_cell(key, cell, table.grid_ratio, DEFAULT_HAND_BOX)
    assert d.k_o_range[0] == pytest.approx((1.0 - MARGIN) * table.grid_point(cell))
    assert d.own_gain * d.k_h == pytest.approx(1.0)
    assert d.k_h > 0.9 * table.grid_point(cell)
