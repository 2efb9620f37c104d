"""The rest plane's gains: the object's stiffness, and the damper that makes it felt as the object."""

from __future__ import annotations

import math

import numpy as np
import pytest

from haptic_collab.shared.gains.rest_plane import rest_plane_dampers, rest_plane_gains

T = 1e-3  # the servo period [s]


def test_a_spring_is_rendered_with_its_own_stiffness_and_the_least_damper() -> None:
    g = rest_plane_gains(300.0, 0.0, 20.0, 1000.0, 10.0, servo_period_s=T)
    # the least damper, K_h T / 2 (0.15 N*s/m), felt 1.0003 times the spring at 8 Hz
    assert (g.k_h, g.b_h) == (300.0, pytest.approx(0.5 * 300.0 * T))
    assert g.felt_error < 1e-3


def test_a_spring_stiffer_than_the_device_stops_at_the_devices_stiffness() -> None:
    g = rest_plane_gains(3000.0, 0.0, 20.0, 1000.0, 10.0, servo_period_s=T)
    assert g.k_h == 1000.0
    # felt a third of the object at 0.5 Hz whatever the damper; the whole damper brings 8 Hz a
    # little closer to it
    assert g.felt_error == pytest.approx(math.log(3.0), rel=1e-3)
    assert g.b_h == 10.0


def test_a_damped_object_gets_the_damper_that_is_felt_closest_to_it() -> None:
    # eq. 9's object at 100 N/m with B_o = 200 N/m at 100 Hz resists a 8 Hz push about 1.5 times
    # its spring; the plane without a damper is felt 0.4 (ln) off, with the closest damper less
    none = rest_plane_gains(100.0, 0.0, 100.0, 1000.0, 10.0, servo_period_s=T)
    g = rest_plane_gains(100.0, 200.0, 100.0, 1000.0, 10.0, servo_period_s=T)
    assert g.k_h == 100.0 and g.b_h > 0.0
    assert none.b_h == pytest.approx(0.5 * 100.0 * T)
    obj = abs(
        100.0 + 200.0 * (1.0 - complex(math.cos(2 * math.pi * 0.08), -math.sin(2 * math.pi * 0.08)))
    )
    assert math.log(obj / 100.0) > 0.35  # without a damper it would be felt this far off
    assert g.felt_error < 0.6 * math.log(obj / 100.0)
    # and a device without a damper renders none
    assert rest_plane_gains(100.0, 200.0, 100.0, 1000.0, 0.0, servo_period_s=T).b_h == 0.0


def test_a_servo_period_that_is_not_a_period_is_refused() -> None:
    for bad in (0.0, -1e-3, math.nan):
        with pytest.raises(ValueError):
            rest_plane_gains(300.0, 0.0, 20.0, 1000.0, 10.0, servo_period_s=bad)


@pytest.mark.parametrize(
    "args",
    [
        (0.0, 0.0, 20.0, 1000.0, 10.0),
        (math.nan, 0.0, 20.0, 1000.0, 10.0),
        (300.0, -1.0, 20.0, 1000.0, 10.0),
        (300.0, 0.0, 0.0, 1000.0, 10.0),
        (300.0, 0.0, 20.0, math.inf, 10.0),
        (300.0, 0.0, 20.0, 1000.0, math.nan),
    ],
)
def test_absurd_parameters_are_refused(args: tuple[float, ...]) -> None:
    with pytest.raises(ValueError):
        rest_plane_gains(*args, servo_period_s=T)


@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf])
def test_a_batch_with_an_absurd_b_o_is_refused(bad: float) -> None:
    with pytest.raises(ValueError, match="b_o"):
        rest_plane_dampers(
            np.array([100.0, 300.0]), np.array([10.0, bad]), np.array([20.0, 20.0]), 1000.0, 10.0,
            servo_period_s=T,
        )  # fmt: skip
