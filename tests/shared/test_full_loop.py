"""The full loop (hand + device, local model, slow delayed object) against the paper and the clock.

The time-domain reference below is written independently of shared.full_loop: its own hand
integrator (semi-implicit Euler with fine sub-steps, like the simulated device), its own local
model, decimator, object, delay line and proxy hold, stepped tick by tick.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
import pytest

from haptic_collab.shared.full_loop import (
    DAMPER_FILTER_S,
    DEFAULT_HAND,
    DEFAULT_HAND_BOX,
    Hand,
    HandBox,
    analyze_full_loop,
    monodromy,
    spectral_radius,
)
from haptic_collab.shared.stability import analyze


def _simulate(
    hand: Hand,
    *,
    k_o: float,
    k_h: float,
    i_gain: float = 0.0,
    b_h: float = 0.0,
    b_o: float = 0.0,
    n: int = 50,
    delay: int = 0,
    j: int = 0,
    hold: str = "zoh",
    periods: int = 60,
    substeps: int = 200,
    own_gain: float = 0.0,
) -> np.ndarray:
    """Probe depth at each block start after a 1 mm push, linear bilateral contact."""
    T = 1e-3
    m, b, k = hand.mass_kg, hand.damping_n_s_per_m, hand.stiffness_n_per_m
    x, v = 0.001, 0.0  # the hand starts 1 mm in, target at 0: a disturbance
    x_prev = x
    u = 0.0  # the damper's filtered probe velocity
    a_u = T / (T + DAMPER_FILTER_S)
    s = 0.0
    x_obj = 0.0
    line: deque[float] = deque([0.0] * delay)
    p_new = p_old = 0.0
    f_sample = 0.0
    out = []
    h = T / substeps
    for blk in range(periods):
        if blk > 0:
            x_obj = (f_sample + b_o * x_obj) / (k_o + b_o)  # eq. 9
            line.append(x_obj - own_gain * f_sample)  # own-force compensation
            p_old, p_new = p_new, line.popleft()
        out.append(math.hypot(x, v * 0.01) + abs(s) / 1000.0 + abs(p_new))
        for i in range(n):
            w = (i + 1) / n if hold == "foh" else 1.0
            p = p_old + (p_new - p_old) * w
            e = x - p
            u += a_u * ((x - x_prev) / T - u)
            f = k_h * e + s + b_h * u
            if i == j:
                f_sample = f
            s += T * i_gain * e
            x_prev = x
            for _ in range(substeps):
                a = (-k * x - b * v - f) / m
                v += h * a
                x += h * v
    return np.array(out)


def _growth(trace: np.ndarray) -> float:
    """Per-period growth ratio from the log-slope over the second half of the run."""
    tail = np.log(trace[len(trace) // 2 :])
    slope = np.polyfit(np.arange(tail.size), tail, 1)[0]
    return float(math.exp(slope))


@pytest.mark.parametrize(
    ("k_o", "k_h", "i_gain", "b_h", "damping", "delay", "tick"),
    [
        (300.0, 200.0, 3000.0, 0.0, 0.0, 0, 0),
        (300.0, 70.0, 3000.0, 0.0, 0.0, 2, 17),
        (1000.0, 500.0, 0.0, 0.0, 0.0, 1, 0),
        (300.0, 100.0, 2000.0, 0.0, 0.5, 3, 49),
        (500.0, 450.0, 0.0, 0.0, 0.2, 0, 10),
    ],
)
def test_rigid_probe_reduces_to_the_papers_loop(k_o, k_h, i_gain, b_h, damping, delay, tick):
    paper = analyze(k_o, k_h, i_gain=i_gain, damping=damping, delay_ticks=delay, sample_tick=tick)
    full = analyze_full_loop(
        None,
        k_o=k_o,
        k_h=k_h,
        i_gain=i_gain,
        damping=damping,
        delay_ticks=delay,
        sample_tick=tick,
    )
    assert full.spectral_radius == pytest.approx(paper.spectral_radius, abs=1e-9)
    assert full.stable == paper.stable


def test_very_heavy_hand_converges_to_the_position_source():
    # a 10-tonne hand barely moves: the loop's own modes are the paper's, the hand's sit near 1
    heavy = Hand(mass_kg=1e4, damping_n_s_per_m=5.0, stiffness_n_per_m=300.0)
    M = monodromy(hand=heavy, k_o=300.0, k_h=200.0, rate_ratio=50, sample_ticks=[0])[0, 0]
    eig = np.sort(np.abs(np.linalg.eigvals(M)))
    paper = analyze(300.0, 200.0).spectral_radius
    assert np.min(np.abs(eig - paper)) < 1e-3


@pytest.mark.parametrize(
    ("k_o", "k_h", "i_gain", "b_h", "delay", "j", "hold", "alpha"),
    [
        (1000.0, 700.0, 0.0, 0.0, 0, 15, "zoh", 0.0),  # the paper's Fig. 10 gain: unstable
        (1000.0, 300.0, 0.0, 0.0, 0, 0, "zoh", 0.0),
        (300.0, 70.0, 3045.0, 0.0, 0, 0, "zoh", 0.0),  # the old select_gains PI pick: unstable
        (1000.0, 500.0, 0.0, 10.0, 0, 30, "foh", 0.0),
        (300.0, 100.0, 4000.0, 10.0, 2, 49, "foh", 0.0),
        (300.0, 150.0, 0.0, 3.0, 1, 5, "zoh", 0.0),
        # own-force compensation C_h = alpha / K_o
        (300.0, 300.0, 0.0, 3.0, 2, 10, "zoh", 1.0),  # K_h = K_o: the paper's loop would ring
        (3000.0, 1000.0, 0.0, 10.0, 1, 25, "foh", 3.0),  # K_o above the device, C_h = 1/K_h
        (300.0, 600.0, 0.0, 0.0, 0, 0, "zoh", 1.0),
        (300.0, 450.0, 0.0, 0.0, 1, 40, "zoh", 0.25),  # too little compensation for K_h > K_o
    ],
)
def test_spectral_radius_matches_a_direct_time_domain_simulation(
    k_o, k_h, i_gain, b_h, delay, j, hold, alpha
):
    own = alpha / k_o
    rho = spectral_radius(
        hand=DEFAULT_HAND,
        k_o=k_o,
        k_h=k_h,
        i_gain=i_gain,
        b_h=b_h,
        own_gain=own,
        rate_ratio=50,
        delay_ticks=delay,
        sample_ticks=[j],
        proxy_hold=hold,  # type: ignore[arg-type]
    )[0, 0]
    trace = _simulate(DEFAULT_HAND, k_o=k_o, k_h=k_h, i_gain=i_gain, b_h=b_h, delay=delay, j=j,
                      hold=hold, own_gain=own)  # fmt: skip
    assert _growth(trace) == pytest.approx(rho, rel=0.03)
    # and the verdict is what a user would see: growth or decay of the hold
    assert (trace[-1] > trace[len(trace) // 2]) == (rho > 1.0)


def test_exact_own_force_compensation_opens_the_simulation_loop():
    # rigid probe, K_h = K_o, C_h = 1/K_o: the proxy the servo renders is the rest surface
    # whatever the force, so nothing circulates through the simulation (nilpotent monodromy)
    M = monodromy(hand=None, k_o=500.0, k_h=500.0, own_gain=1 / 500.0, rate_ratio=20,
                  delay_ticks=3)  # fmt: skip
    assert np.max(np.abs(np.linalg.eigvals(M))) < 1e-6
    # the paper's local model with the same K_h sits on eq. 8's margin
    M0 = monodromy(hand=None, k_o=500.0, k_h=500.0, rate_ratio=20, delay_ticks=3)
    assert np.max(np.abs(np.linalg.eigvals(M0))) == pytest.approx(1.0, abs=1e-6)


def test_the_products_old_gains_oscillate_with_the_simulated_hand():
    # the measurement that started the full-loop design: select_gains' PI at K_o = 300, 500, 1000 N/m is unstable in full
    radii = [
        analyze_full_loop(DEFAULT_HAND, k_o=k, k_h=k_h, i_gain=i).spectral_radius
        for k, k_h, i in ((300.0, 70.0, 3045.0), (500.0, 116.7, 5075.0), (1000.0, 233.3, 10150.0))
    ]
    assert radii == pytest.approx([1.009, 1.108, 1.282], abs=0.005)


def test_sampling_tick_matters_and_the_worst_is_reported():
    per_tick = spectral_radius(hand=DEFAULT_HAND, k_o=1000.0, k_h=700.0, rate_ratio=50)[0]
    res = analyze_full_loop(DEFAULT_HAND, k_o=1000.0, k_h=700.0)
    assert per_tick.max() - per_tick.min() > 0.01
    assert res.spectral_radius == pytest.approx(per_tick.max())
    assert res.worst_sample_tick == int(np.argmax(per_tick))


def test_hand_box_covers_the_required_ranges_and_the_simulated_hand():
    box = DEFAULT_HAND_BOX
    assert box.mass_kg[0] <= 0.15 and box.mass_kg[1] >= 0.6
    assert box.stiffness_n_per_m[0] <= 50.0 and box.stiffness_n_per_m[1] >= 800.0
    assert box.damping_n_s_per_m[0] <= 2.0 and box.damping_n_s_per_m[1] >= 8.0
    hands = box.hands()
    assert DEFAULT_HAND in hands
    assert all(c in hands for c in box.corners())


@pytest.mark.parametrize(
    "bad",
    [
        {"mass_kg": 0.0, "damping_n_s_per_m": 1.0, "stiffness_n_per_m": 1.0},
        {"mass_kg": 1.0, "damping_n_s_per_m": -1.0, "stiffness_n_per_m": 1.0},
        {"mass_kg": float("nan"), "damping_n_s_per_m": 1.0, "stiffness_n_per_m": 1.0},
    ],
)
def test_bad_hands_are_refused(bad):
    with pytest.raises(ValueError):
        Hand(**bad)


def test_bad_box_and_analysis_inputs_are_refused():
    with pytest.raises(ValueError):
        HandBox(mass_kg=(0.6, 0.1))
    with pytest.raises(ValueError):
        analyze_full_loop(DEFAULT_HAND, k_o=-1.0, k_h=100.0)
    with pytest.raises(ValueError):
        analyze_full_loop(DEFAULT_HAND, k_o=100.0, k_h=100.0, sim_rate_hz=30.0)
    with pytest.raises(ValueError):
        monodromy(hand=DEFAULT_HAND, k_o=1.0, k_h=1.0, rate_ratio=10, sample_ticks=[10])
