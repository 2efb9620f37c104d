"""Gain design with the hand in the loop, checked independently of how it was designed.

The design (shared.gain_design) checks its candidates on the hands of ``HandBox.hands()`` (the
box's corners, face centres and centre). Here every design is re-checked on a *finer* lattice of
hands spanning the same ranges (4 x 4 x 4 points plus the simulated hand), at every force-sampling
tick and at K_o' = (1 - margin) K_o, the middle of the range and K_o. Where the lattice finds an
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

from haptic_collab.shared.full_loop import (
    DEFAULT_HAND,
    DEFAULT_HAND_BOX,
    Hand,
    ProxyHold,
    spectral_radius,
)
from haptic_collab.shared.gain_design import (
    GainDesign,
    GainTable,
    cell_k_o_range,
    design_gains,
    felt_responses,
    felt_stiffness,
    verify_gains,
)
from haptic_collab.shared.gain_key import GainKey

SERVO_HZ = 1000.0
T = 1.0 / SERVO_HZ
MARGIN = 0.15  # design_gains' default
K_H_MAX = 1000.0  # Phantom Desktop limits (client.devices.profiles)
B_H_MAX = 10.0


def _lattice(n: int = 4) -> list[Hand]:
    box = DEFAULT_HAND_BOX
    ms, bs, ks = (
        [float(v) for v in np.linspace(lo, hi, n)]
        for lo, hi in (box.mass_kg, box.damping_n_s_per_m, box.stiffness_n_per_m)
    )
    return [Hand(m, b, k) for m in ms for b in bs for k in ks] + [DEFAULT_HAND]


FINE_HANDS = _lattice(4)


def _worst_on_lattice(
    d: GainDesign,
    k_os: list[float],
    *,
    sim_rate_hz: float,
    delay_ticks: int,
    hands: list[Hand] = FINE_HANDS,
) -> tuple[float, str]:
    """Largest full-loop spectral radius over hands x K_o' x every sampling tick, and where."""
    n = round(SERVO_HZ / sim_rate_hz)
    hs = [h for h in hands for _ in k_os]
    ko = np.tile(np.asarray(k_os, float), len(hands))
    rho = spectral_radius(
        hand=hs,
        k_o=ko,
        k_h=d.k_h,
        i_gain=d.i_gain,
        b_h=d.b_h,
        own_gain=d.own_gain,
        servo_period_s=T,
        rate_ratio=n,
        delay_ticks=delay_ticks,
        proxy_hold=d.proxy_hold,
        integral=d.i_gain > 0.0,
    )
    b, j = np.unravel_index(int(np.argmax(rho)), rho.shape)
    where = (
        f"hand {hs[b]}, K_o' = {ko[b]:g} N/m, sampling tick {j}; gains K_h = {d.k_h:g}, "
        f"I = {d.i_gain:g}, B_h = {d.b_h:g}, C_h = {d.own_gain:g}, {d.proxy_hold}"
    )
    return float(rho[b, j]), where


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


# ----------------------------------------------------------------------------- felt stiffness
@pytest.mark.parametrize("hold", ["zoh", "foh"])
@pytest.mark.parametrize(("n", "delay"), [(50, 0), (50, 3), (10, 0)])
@pytest.mark.parametrize(("k_o", "k_h"), [(1000.0, 300.0), (300.0, 200.0), (50.0, 40.0)])
def test_p_coupling_feels_like_springs_in_series_at_low_frequency(
    k_o: float, k_h: float, n: int, delay: int, hold: ProxyHold
) -> None:
    felt = felt_stiffness(0.05, k_o=k_o, k_h=k_h, rate_ratio=n, delay_ticks=delay, proxy_hold=hold)
    assert felt.shape == (1,)
    assert felt[0] == pytest.approx(k_h * k_o / (k_h + k_o), rel=5e-3)


@pytest.mark.parametrize("hold", ["zoh", "foh"])
@pytest.mark.parametrize("delay", [0, 2])
@pytest.mark.parametrize(
    ("k_o", "k_h", "i_gain"), [(1000.0, 300.0, 7000.0), (300.0, 100.0, 3000.0)]
)
def test_pi_coupling_feels_the_object_itself_at_low_frequency(
    k_o: float, k_h: float, i_gain: float, delay: int, hold: ProxyHold
) -> None:
    felt = felt_stiffness(
        0.05, k_o=k_o, k_h=k_h, i_gain=i_gain, rate_ratio=50, delay_ticks=delay, proxy_hold=hold
    )
    assert felt[0] == pytest.approx(k_o, rel=0.02)
    # while P with the same K_h feels much softer: the integral is what brings K_o back
    p_only = felt_stiffness(0.05, k_o=k_o, k_h=k_h, rate_ratio=50, delay_ticks=delay)
    assert p_only[0] < 0.8 * k_o


@pytest.mark.parametrize("freq_hz", [0.05, 1.0])
@pytest.mark.parametrize("k_o", [100.0, 1000.0, 5000.0])
def test_simulation_at_servo_rate_with_k_h_near_k_o(k_o: float, freq_hz: float) -> None:
    k_h = 0.99 * k_o
    felt = felt_stiffness(freq_hz, k_o=k_o, k_h=k_h, rate_ratio=1)
    assert felt[0] == pytest.approx(k_h * k_o / (k_h + k_o), rel=5e-3)  # about K_o / 2


def test_felt_stiffness_is_vectorised_over_gains() -> None:
    k_h = np.array([100.0, 300.0, 600.0])
    felt = felt_stiffness(0.05, k_o=1000.0, k_h=k_h)
    assert felt == pytest.approx(k_h * 1000.0 / (k_h + 1000.0), rel=5e-3)
    assert np.all(np.diff(felt) > 0)  # stiffer coupling, stiffer feel


@pytest.mark.parametrize(("k_o", "k_h"), [(1000.0, 300.0), (5000.0, 10.0)])
@pytest.mark.parametrize("b_h", [2.0, 10.0])
def test_probe_damper_is_felt_as_viscosity_not_stiffness(
    k_o: float, k_h: float, b_h: float
) -> None:
    """Quasi-statically F = (K_h + j w B_h) x - K_h p with p = F / K_o, so the damper adds
    j w B_h K_o / (K_h + K_o) (-> j w B_h when K_h << K_o) and leaves the real part alone."""
    f = 0.05
    w = 2.0 * math.pi * f
    with_damper = felt_stiffness(f, k_o=k_o, k_h=k_h, b_h=b_h, complex_response=True)[0]
    without = felt_stiffness(f, k_o=k_o, k_h=k_h, complex_response=True)[0]
    assert (with_damper - without).imag == pytest.approx(b_h * w * k_o / (k_h + k_o), rel=0.01)
    assert with_damper.real == pytest.approx(without.real, rel=1e-3)
    if k_h < 0.01 * k_o:
        assert (with_damper - without).imag == pytest.approx(b_h * w, rel=0.01)


@pytest.mark.parametrize("freq_hz", [0.0, -1.0, 500.0, 2000.0])
def test_felt_stiffness_refuses_frequencies_outside_the_servo_band(freq_hz: float) -> None:
    with pytest.raises(ValueError):
        felt_stiffness(freq_hz, k_o=1000.0, k_h=300.0)


# ------------------------------------------------------------- designs, verified on a finer box
K_OS = (50.0, 300.0, 1000.0, 5000.0)
SIM_RATES = (10.0, 20.0, 100.0)
DELAYS = (0, 2, 4)
# PI designs take up to a few seconds each: a subset covering every K_o, rate and delay runs by
# default, the rest of the grid is marked slow, and the five costliest (2-4 s each; they passed
# this check when the test was written) are left out to keep the file within a minute
PI_FAST = {
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
        marks=[pytest.mark.slow] if mode == "pi" and (k_o, sim, delay) not in PI_FAST else [],
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
    rho, where = _worst_on_lattice(
        d, _margin_range(k_o), sim_rate_hz=sim_rate_hz, delay_ticks=delay_ticks
    )
    assert rho < 1.0, f"unstable full loop (spectral radius {rho:.4f}) for {where}"


INTERIOR_HAND = Hand(0.1 + 0.5 / 3.0, 2.0, 1000.0)  # a lattice point on an edge of the box


@pytest.mark.parametrize(
    "hand",
    [DEFAULT_HAND, Hand(0.6, 2.0, 1000.0), INTERIOR_HAND],
    ids=["simulated-hand", "box-corner", "box-edge"],
)
@pytest.mark.parametrize("own_force", [False, True], ids=["paper", "compensated"])
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
    rho, where = _worst_on_lattice(d, _margin_range(5000.0), sim_rate_hz=10.0, delay_ticks=4)
    assert rho < 1.0, where


def test_pi_without_a_stable_integral_falls_back_to_p_instead_of_raising() -> None:
    d = _design(300.0, 20.0, 4, "pi", b_h_max=0.0)
    assert d.mode == "p"
    assert d.i_gain == 0.0
    assert d.b_h == 0.0
    rho, where = _worst_on_lattice(d, _margin_range(300.0), sim_rate_hz=20.0, delay_ticks=4)
    assert rho < 1.0, where


def test_design_without_a_damper_never_uses_one() -> None:
    d = _design(1000.0, 20.0, 0, "p", b_h_max=0.0)
    assert d.b_h == 0.0
    assert d.k_h < 1000.0


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


# ----------------------------------------------------------------------------------- GainTable
def _key(mode: str = "p") -> GainKey:
    return GainKey(
        servo_rate_hz=SERVO_HZ,
        sim_rate_hz=20.0,
        delay_ticks=0,
        mode=mode,  # type: ignore[arg-type]
        margin=MARGIN,
        k_h_max=K_H_MAX,
        b_h_max=B_H_MAX,
    )


def test_table_lookup_is_none_until_the_cell_is_designed() -> None:
    table = GainTable()
    key = _key()
    assert table.lookup(key, 1000.0) is None
    assert table.fallback(key, 1000.0) is None
    assert len(table) == 0
    d = table.design(key, 1000.0)
    i = table.cell(1000.0)
    g0, g1 = table.grid_point(i), table.grid_point(i + 1)
    assert g0 <= 1000.0 < g1
    assert table.lookup(key, 1000.0) == d
    base = table.lookup(key, g0)
    assert base is not None and base.scale_max > 1.0
    for k_o in (g0, 1000.0, 0.5 * (g0 + g1), g1 * (1.0 - 1e-9)):
        # anywhere in the cell: the cell's design scaled to the reported K_o, K_h within the
        # device's stiffness
        got = table.lookup(key, k_o)
        assert got is not None and got == got.at(k_o)
        s = min(k_o / g0, base.scale_max)
        assert got.k_h == pytest.approx(base.k_h * s) and got.k_h <= K_H_MAX
        assert got.own_gain * got.k_h == pytest.approx(base.own_gain * base.k_h)
        assert (got.b_h, got.proxy_hold) == (base.b_h, base.proxy_hold)
        assert got.k_o_range == pytest.approx((base.k_o_range[0] * s, base.k_o_range[1]))
    assert table.lookup(key, g1 * 1.0001) is None  # the next cell is not designed
    assert table.lookup(_key("pi"), 1000.0) is None  # nor another key's
    assert len(table) == 1


@pytest.mark.parametrize("mode", ["p", "pi"])
def test_table_design_covers_its_whole_cell(mode: str) -> None:
    table = GainTable()
    key = _key(mode)
    table.design(key, 1000.0)
    i = table.cell(1000.0)
    g0, g1 = table.grid_point(i), table.grid_point(i + 1)
    for k_o in (g0, 1000.0, g1 * (1.0 - 1e-9)):  # the gains served for it, on a finer lattice
        d = table.lookup(key, k_o)
        assert d is not None and d.k_h <= K_H_MAX and d.b_h <= B_H_MAX
        rho, where = _worst_on_lattice(
            d, [(1.0 - MARGIN) * k_o, k_o, g1], sim_rate_hz=20.0, delay_ticks=0
        )
        assert rho < 1.0, where


def _felt_spread_over_cell(d: GainDesign | GainTable, g0: float, g1: float, key: GainKey) -> float:
    """How much the felt stiffness |dF/dx| / K_o at 0.5, 1 and 2 Hz (below where a damper is felt)
    changes over K_o = g0, sqrt(g0 g1) and the top of the cell, the largest over the three
    frequencies: fixed gains ``d``, or the gains a table ``d`` serves for each K_o."""
    q = []
    for k_o in (g0, math.sqrt(g0 * g1), g1 * (1.0 - 1e-9)):
        served = d.lookup(key, k_o) if isinstance(d, GainTable) else d
        assert served is not None
        r = felt_responses(
            (0.5, 1.0, 2.0),
            k_o=k_o,
            k_h=served.k_h,
            i_gain=served.i_gain,
            b_h=served.b_h,
            own_gain=served.own_gain,
            servo_period_s=T,
            rate_ratio=key.rates.ratio,
            delay_ticks=key.delay_ticks,
            proxy_hold=served.proxy_hold,
        )[:, 0]
        q.append(np.abs(r) / k_o)
    qs = np.array(q)
    return float(np.max(qs.max(axis=0) - qs.min(axis=0)))


@pytest.mark.slow
def test_table_design_feels_like_the_object_across_its_whole_cell() -> None:
    # a table design serves every K_o reported in its cell, scaled to it; with 4 ticks of delay
    # the felt response depends on K_h / K_o: the same gains for the whole cell (judged across
    # it) feel 5-10 % softer at its top than at its lower end (300 N/m's cell at 20 Hz, 0.5-2
    # Hz), scaled ones the same within 0.5 %
    key = replace(_key("p"), delay_ticks=4)
    table = GainTable()
    i = table.cell(300.0)
    g0, g1 = table.grid_point(i), table.grid_point(i + 1)
    table.design(key, 300.0)
    fixed = design_gains(
        g0,
        sim_rate_hz=20.0,
        delay_ticks=4,
        mode="p",
        margin=MARGIN,
        k_o_hi=cell_k_o_range(key, i, table.grid_ratio)[1],
        k_h_max=K_H_MAX,
        b_h_max=B_H_MAX,
        own_force=True,
        felt_k_os=[g0, math.sqrt(g0 * g1), g1],
        stiffer_by=key.stiffer_by,
    )
    assert fixed.scale_max == 1.0
    assert _felt_spread_over_cell(table, g0, g1, key) < 0.005
    assert _felt_spread_over_cell(fixed, g0, g1, key) > 0.03
    for k_o in (g0, 300.0, g1 * (1.0 - 1e-9)):  # each stable on a finer hand lattice
        d = table.lookup(key, k_o)
        assert d is not None
        rho, where = _worst_on_lattice(
            d, [(1.0 - MARGIN) * k_o, k_o, g1], sim_rate_hz=20.0, delay_ticks=4
        )
        assert rho < 1.0, where


def test_scaled_design_serves_the_gains_it_checked() -> None:
    # every scale a cell's design is served at passes the design's own acceptance test, and the
    # design's top scale keeps K_h within the device's stiffness
    key = _key("p")
    table = GainTable()
    for k_o in (100.0, 900.0):
        i = table.cell(k_o)
        g0, g1 = table.grid_point(i), table.grid_point(i + 1)
        table.design(key, k_o)
        for k in (g0, math.sqrt(g0 * g1), g1 * (1.0 - 1e-9)):
            d = table.lookup(key, k)
            assert d is not None and d.k_h <= K_H_MAX
            ok, rho = verify_gains(
                key,
                i,
                table.grid_ratio,
                table.hand_box,
                k_h=d.k_h,
                i_gain=d.i_gain,
                b_h=d.b_h,
                proxy_hold=d.proxy_hold,
                own_gain=d.own_gain,
                k_o_scale=min(k / g0, table.grid_ratio),
            )
            assert ok, (k_o, k, rho)


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


def _relative(d: GainDesign, k_o: float) -> tuple[float, float, float]:
    return d.k_h / k_o, d.i_gain / k_o, d.b_h / k_o


def test_table_fallback_is_never_stiffer_relative_to_k_o_than_a_designed_cell() -> None:
    table = GainTable()
    key = _key()
    for k in (300.0, 3000.0):
        table.design(key, k)
    # each designed cell's own gains, at its grid point
    designed = {k: table.lookup(key, table.grid_point(table.cell(k))) for k in (300.0, 3000.0)}
    for k_o in (120.0, 200.0, 299.0, 500.0, 1000.0, 2900.0, 5000.0, 20000.0):
        fb = table.fallback(key, k_o)
        assert fb is not None
        # the worst case over the requested cell: K_o at its lower grid point
        got = _relative(fb, table.grid_point(table.cell(k_o)))
        assert any(
            all(a <= b * (1.0 + 1e-12) for a, b in zip(got, _relative(d, d.k_o), strict=True))
            for d in designed.values()
            if d is not None
        ), (k_o, fb)
        assert fb.k_h <= K_H_MAX and fb.b_h <= B_H_MAX


@pytest.mark.parametrize("mode", ["p", "pi"])
def test_table_fallback_gains_are_stable_for_the_box_at_the_stiffness_they_are_served_for(
    mode: str,
) -> None:
    """Only the 277 N/m cell is designed; the object stiffens to 539 N/m (six cells up) while that
    cell is being designed: the fallback renders the 277 N/m gains on a 539 N/m object."""
    table = GainTable()
    key = _key(mode)
    table.design(key, 300.0)
    k_o = table.grid_point(table.cell(300.0) + 6) * 1.0999
    fb = table.fallback(key, k_o)
    assert fb is not None
    rho, where = _worst_on_lattice(
        fb, [k_o], sim_rate_hz=20.0, delay_ticks=0, hands=DEFAULT_HAND_BOX.hands()
    )
    assert rho < 1.0, f"fallback unstable (spectral radius {rho:.4f}) for {where}"


def test_table_refuses_bad_grid_and_stiffness() -> None:
    with pytest.raises(ValueError):
        GainTable(grid_ratio=1.0)
    table = GainTable()
    for bad in (0.0, -5.0, math.nan, math.inf):
        with pytest.raises(ValueError):
            table.cell(bad)
        with pytest.raises(ValueError):
            table.lookup(_key(), bad)
