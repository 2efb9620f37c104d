"""One declaration of the servo and simulation rates (shared.rates.Rates): N must be whole."""

from __future__ import annotations

import math

import pytest

from haptic_collab.shared.rates import Rates, dividing_rates, rate_ratio


def test_rates_give_the_periods_and_n():
    r = Rates(1000.0, 20.0)
    assert r.ratio == 50
    assert r.servo_period_s == pytest.approx(1e-3, rel=1e-15)
    assert r.sim_period_s == pytest.approx(0.05, rel=1e-15)
    assert r.sim_period_s == pytest.approx(r.ratio * r.servo_period_s, rel=1e-12)
    assert Rates(1000, 1000).ratio == 1
    assert Rates(1000, 20) == r  # equal declarations compare equal


def test_a_fractional_n_is_refused_with_the_rates_that_divide_the_servo_rate():
    with pytest.raises(ValueError, match="whole multiple") as err:
        Rates(1000.0, 30.0)
    msg = str(err.value)
    assert "1000 Hz" in msg and "30 Hz" in msg and "N = 33.3" in msg
    assert "10, 20, 25, 40, 50, 100, 125, 200, 250, 500 Hz" in msg
    # the simulation faster than the servo loop (N < 1) is refused the same way
    with pytest.raises(ValueError, match="whole multiple"):
        Rates(10.0, 20.0)


def test_rate_ratio_delegates_to_rates():
    assert rate_ratio(1000, 20) == Rates(1000, 20).ratio == 50
    with pytest.raises(ValueError, match=r"whole multiple.*25, 40"):
        rate_ratio(1000, 30)


@pytest.mark.parametrize(
    "servo, sim", [(0.0, 20.0), (1000.0, -20.0), (math.inf, 20.0), (1000.0, math.nan)]
)
def test_rates_must_be_positive_and_finite(servo, sim):
    with pytest.raises(ValueError, match="finite number > 0"):
        Rates(servo, sim)


def test_a_period_declared_elsewhere_must_agree():
    r = Rates(1000.0, 20.0)
    r.check_sim_period(0.05, "the object")  # the same N*T
    r.check_sim_period(50 * 1e-3, "the object")  # computed another way
    with pytest.raises(ValueError, match=r"the object steps every 40 ms \(25 Hz\).*20 Hz"):
        r.check_sim_period(0.04, "the object")


def test_dividing_rates_lists_only_whole_divisors():
    assert dividing_rates(1000.0, 10.0, 250.0) == [10, 20, 25, 40, 50, 100, 125, 200, 250]
    assert all(Rates(1000.0, r).ratio * r == 1000.0 for r in dividing_rates(1000.0))
