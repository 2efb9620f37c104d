"""The peak-force time limit: peak force for moments, the continuous force for ever, no steps."""

from __future__ import annotations

import math

import numpy as np
import pytest

from haptic_collab.client.thermal import ThermalLimit, ThermalParams

T = 1e-3
DESKTOP = ThermalParams(peak_force_n=7.9, continuous_force_n=1.75, time_constant_s=15.0)


def hold(lim: ThermalLimit, wanted_n: float, seconds: float) -> np.ndarray:
    """The force displayed while a user asks for ``wanted_n``, clamped by the limit each tick."""
    out = np.empty(round(seconds / T))
    for k in range(out.size):
        f = min(wanted_n, lim.limit_n)
        out[k] = f
        lim.step(f)
    return out


def test_the_continuous_force_is_given_for_ever():
    lim = ThermalLimit(DESKTOP)
    forces = hold(lim, 1.75, 120.0)
    assert forces.min() == pytest.approx(1.75)
    assert not lim.hot and lim.heat <= 1.0


def test_the_peak_lasts_as_long_as_the_model_says_then_comes_down_to_continuous_smoothly():
    lim = ThermalLimit(DESKTOP)
    forces = hold(lim, 7.9, 12.0)
    # full peak from cold for -tau ln(1 - (Fc/Fp)^2) = 0.75 s
    t_peak = -15.0 * math.log(1.0 - (1.75 / 7.9) ** 2)
    at_peak = np.nonzero(forces < 7.9)[0][0] * T
    assert at_peak == pytest.approx(t_peak, abs=0.01)
    # then it comes down at 1 N/s (no step), and stays at the continuous force
    steps = np.diff(forces)
    assert steps.min() >= -1.0 * T * 1.0001
    assert forces[-1000:] == pytest.approx(1.75)
    assert lim.hot


def test_a_hold_a_little_above_continuous_gets_there_after_tens_of_seconds():
    lim = ThermalLimit(DESKTOP)
    forces = hold(lim, 2.0, 40.0)
    t_hot = np.nonzero(forces < 2.0)[0][0] * T
    assert t_hot == pytest.approx(-15.0 * math.log(1.0 - (1.75 / 2.0) ** 2), abs=0.05)  # 21.9 s
    assert forces[-1] == pytest.approx(1.75)


def test_after_easing_off_the_peak_comes_back_gradually():
    lim = ThermalLimit(DESKTOP)
    hold(lim, 7.9, 10.0)
    assert lim.limit_n == pytest.approx(1.75)
    rest = hold(lim, 0.5, 30.0)  # a light touch: cools below 0.8 within seconds
    assert not lim.hot
    assert rest.max() == pytest.approx(0.5)
    assert lim.limit_n == pytest.approx(7.9)  # 6.15 N back at 1 N/s: about 6 s after cooling


def test_a_warm_device_brings_the_limit_down_even_when_the_model_is_cold():
    lim = ThermalLimit(DESKTOP)
    for _ in range(100):
        lim.step(3.0, device_temperature=0.4)
    assert not lim.hot
    lim.step(3.0, device_temperature=0.75)  # the device says a motor is warm
    assert lim.hot and lim.limit_n < 3.0 + 1e-9
    for _ in range(2000):
        lim.step(min(3.0, lim.limit_n), device_temperature=0.6)  # still above the cool threshold
    assert lim.hot and lim.limit_n == pytest.approx(1.75)
    for _ in range(20000):
        lim.step(0.2, device_temperature=0.3)
    assert not lim.hot and lim.limit_n == pytest.approx(7.9)


def test_a_non_finite_force_or_temperature_counts_as_the_worst_case():
    lim = ThermalLimit(DESKTOP)
    for _ in range(2000):
        lim.step(math.nan)
    assert lim.hot  # the peak, for 2 s: past the 0.75 s budget
    lim2 = ThermalLimit(DESKTOP)
    lim2.step(1.0, device_temperature=math.inf)
    assert lim2.hot


@pytest.mark.parametrize(
    "kwargs",
    [
        {"continuous_force_n": 0.0},
        {"continuous_force_n": 9.0},
        {"time_constant_s": 0.0},
        {"time_constant_s": math.inf},
        {"release_heat": 1.0},
        {"device_cool": 0.8},
        {"clamp_rate_n_s": -1.0},
    ],
)
def test_bad_parameters_are_refused(kwargs):
    args = {"peak_force_n": 7.9, "continuous_force_n": 1.75, **kwargs}
    with pytest.raises(ValueError):
        ThermalParams(**args)
