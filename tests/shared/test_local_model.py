"""The local model L(z) (eq. 12, 17, 18, section 5.1) and the primitives it is rendered against."""

from __future__ import annotations

import math

import numpy as np
import pytest

from haptic_collab.research.multirate import simulate, step_metrics
from haptic_collab.shared.local_model import (
    LocalModel,
    LocalModelParams,
    ThresholdParams,
    encoder_speed_bound,
)
from haptic_collab.shared.primitives import make_plane, make_sphere


def test_proportional_force_is_stiffness_times_penetration():
    lm = LocalModel(LocalModelParams(k_h=250.0))
    assert lm.step(0.004) == pytest.approx(1.0)
    assert lm.in_contact
    assert lm.step(-0.002) == 0.0  # a contact never pulls
    assert not lm.in_contact


def test_pi_difference_equation_of_eq12():
    """f(n) = K_h e(n) + s(n), s(n+1) = s(n) + T I e(n) (no threshold, bilateral)."""
    lm = LocalModel(
        LocalModelParams(
            k_h=100.0, i_gain=2000.0, unilateral=False, threshold=ThresholdParams(mode="none")
        )
    )
    e = [0.01, 0.01, 0.02, -0.005]
    s, expected = 0.0, []
    for x in e:
        expected.append(100.0 * x + s)
        s += 1e-3 * 2000.0 * x
    assert [lm.step(x) for x in e] == pytest.approx(expected)


def test_fixed_threshold_eq17_holds_the_tolerated_penetration():
    """Against a spring object the PI model leaves exactly theta as steady-state penetration."""
    theta = 0.004
    lm = LocalModel(
        LocalModelParams(
            k_h=100.0, i_gain=3000.0, threshold=ThresholdParams(mode="fixed", theta_m=theta)
        )
    )
    tr = simulate(lm, np.full(6000, 0.03), k_o=300.0, n_ticks=6000)
    m = step_metrics(tr)
    assert m.settled
    assert m.steady_state_error_m == pytest.approx(theta, abs=2e-4)
    p_only = step_metrics(
        simulate(
            LocalModel(LocalModelParams(k_h=100.0)), np.full(6000, 0.03), k_o=300.0, n_ticks=6000
        )
    )
    # eq. 11: x_o = K_h/(K_h+K_o) x_h, error 0.75 * 30 mm
    assert p_only.steady_state_error_m == pytest.approx(0.0225, rel=1e-3)


def test_variable_threshold_eq18_small_entering_larger_exiting():
    th = ThresholdParams(mode="variable", theta_1_m=0.001, theta_2_m=0.004, i_tot_bar_n=2.0)
    lm = LocalModel(LocalModelParams(k_h=100.0, i_gain=1000.0, threshold=th))
    for depth in np.linspace(0.001, 0.02, 50):  # penetrating
        lm.step(float(depth))
        assert lm.theta_m == pytest.approx(0.001)
    assert lm.integral_n > 0.0
    s = lm.integral_n
    lm.step(0.019)  # exiting: theta grows with the integral up to theta_2
    assert lm.theta_m == pytest.approx(0.004 * min(1.0, s / 2.0), rel=0.05)
    lm.step(-0.001)  # no contact: theta = 0
    assert lm.theta_m == 0.0


def _variable(deadband_m_s: float = 0.01) -> LocalModel:
    th = ThresholdParams(
        mode="variable", theta_1_m=0.0005, theta_2_m=0.003, i_tot_bar_n=1.0,
        direction_deadband_m_s=deadband_m_s, direction_filter_s=0.02,
    )  # fmt: skip
    return LocalModel(LocalModelParams(k_h=300.0, i_gain=3000.0, threshold=th))


def test_eq18_exits_only_while_the_probe_moves_out_faster_than_the_deadband():
    """Eq. 18 is a function of the penetration speed now: theta_2 while the user pulls out, back
    to theta_1 as soon as the motion stops (no branch is latched: a latched branch is a relay in
    the loop and sustained a hold limit cycle)."""
    lm = _variable()
    e = 0.005
    for _ in range(300):  # held still, 5 mm in: the integral builds up past i_tot_bar
        lm.step(e, 0.0)
    assert lm.theta_m == pytest.approx(0.0005) and lm.integral_n > 1.0
    for _ in range(60):  # pulling out at 40 mm/s
        e -= 0.04e-3
        lm.step(e, -0.04)
    assert lm.theta_m == pytest.approx(0.003)  # exiting, integral >= i_tot_bar: theta_2
    for _ in range(200):  # stopped
        lm.step(e, 0.0)
    assert lm.theta_m == pytest.approx(0.0005)  # theta_1 again, nothing left switched
    for _ in range(200):  # moving out slower than the deadband (5 mm/s): a hold, not an exit
        e -= 0.005e-3
        lm.step(e, -0.005)
        assert lm.theta_m == pytest.approx(0.0005)


def test_a_new_contact_starts_on_the_penetrating_branch():
    lm = _variable()
    for _ in range(100):
        lm.step(0.004, 0.0)
    for _ in range(30):
        lm.step(0.004, -0.05)  # leaving fast
    assert lm.theta_m == pytest.approx(0.003 * min(1.0, lm.integral_n))
    lm.step(-0.001, -0.05)  # out
    lm.step(0.0005, 0.02)  # back in at once
    assert lm.theta_m == pytest.approx(0.0005)


@pytest.mark.parametrize("counts", [1, 2, 3])
def test_quantization_noise_never_filters_past_the_encoder_speed_bound(counts):
    """Any position sequence within ``counts`` encoder counts gives a filtered speed of at most
    counts * q / (T + tau): random noise and the worst pattern (creep up, drop at once)."""
    q, T, tau = 23e-6, 1e-3, 0.02
    bound = encoder_speed_bound(q, counts, tau, T)
    assert bound == pytest.approx(counts * q / (T + tau))
    rng = np.random.default_rng(counts)
    phase = [(k // 5) % (2 * counts + 2) for k in range(4000)]
    creep = [p if p <= counts else 0 for p in phase]  # up a count every 5 ticks, then all down
    for levels in (rng.integers(0, counts + 1, size=4000), np.array(creep)):
        th = ThresholdParams(
            mode="variable", direction_deadband_m_s=1.01 * bound, direction_filter_s=tau
        )
        lm = LocalModel(LocalModelParams(k_h=300.0, i_gain=3000.0, threshold=th))
        x = 0.005 + levels * q
        v = np.diff(x, prepend=x[0]) / T
        worst = 0.0
        v_f = 0.0
        for vi in v:
            v_f += T / (T + tau) * (vi - v_f)
            worst = max(worst, abs(v_f))
            lm.step(0.005, float(vi))
            assert lm.theta_m == pytest.approx(th.theta_1_m)  # never the exiting branch
        assert worst <= bound + 1e-12
    with pytest.raises(ValueError):
        encoder_speed_bound(q, counts, 0.0, T)


def test_release_drives_the_integral_to_zero_linearly():
    lm = LocalModel(
        LocalModelParams(
            k_h=100.0, i_gain=5000.0, release_time_s=0.1, threshold=ThresholdParams(mode="none")
        )
    )
    for _ in range(300):
        lm.step(0.01)
    s0 = lm.integral_n
    assert s0 > 1.0
    forces = [lm.step(-0.001) for _ in range(150)]
    # never dropped at once: the first release force is the integral, then linear steps to zero
    assert forces[0] == pytest.approx(s0)
    steps = -np.diff(forces[:99])
    assert np.allclose(steps, s0 / 100.0, rtol=1e-6)
    assert forces[100] == pytest.approx(0.0, abs=1e-9) and forces[-1] == 0.0
    assert max(abs(d) for d in np.diff(forces)) <= s0 / 100.0 + 1e-12


def test_integral_is_limited_so_a_release_never_pushes_more_than_the_device_can():
    lm = LocalModel(
        LocalModelParams(
            k_h=200.0,
            i_gain=5000.0,
            integral_limit_n=3.3,
            release_time_s=0.1,
            threshold=ThresholdParams(mode="none"),
        )
    )
    for _ in range(3000):  # held 10 mm in for 3 s: the integral would reach 150 N
        lm.step(0.01)
    assert lm.integral_n == pytest.approx(3.3)
    forces = [lm.step(-0.002) for _ in range(120)]
    assert forces[0] == pytest.approx(3.3) and forces[-1] == 0.0
    assert max(abs(d) for d in np.diff(forces)) <= 3.3 / 100 + 1e-9  # a ramp over 0.1 s


def test_gain_change_keeps_the_integral_force():
    lm = LocalModel(
        LocalModelParams(k_h=100.0, i_gain=3000.0, threshold=ThresholdParams(mode="none"))
    )
    for _ in range(100):
        f_before = lm.step(0.005)
    lm.set_gains(110.0, 2500.0)
    f_after = lm.step(0.005)
    assert (
        abs(f_after - f_before) < 0.1
    )  # K_h change adds 10 N/m * 5 mm = 0.05 N plus one integral step


def test_a_stiffer_coupling_mid_press_changes_the_force_smoothly_not_in_one_tick():
    """A's hold in the demo: K_h 43 -> 127 N/m at 6.6 mm was a 0.56 N step in one tick."""
    e = 0.0066
    old, new = 43.0, 127.0
    lm = LocalModel(LocalModelParams(k_h=old, gain_transfer_s=0.25))
    f_before = lm.step(e)
    lm.set_gains(new, 0.0)
    forces = np.array([lm.step(e) for _ in range(400)])
    # the first tick renders the force the hand already held, then the force moves linearly
    assert forces[0] == pytest.approx(f_before)
    steps = np.diff(np.concatenate([[f_before], forces]))
    assert steps.max() <= (new - old) * e / 250 * 1.0001
    # and after 0.25 s the force is the new gains' own (eq. 12), with nothing left over
    assert forces[250:] == pytest.approx(new * e)
    assert lm.transfer_n == 0.0

    # a softer coupling comes down the same way (eq. 12 alone drops it in one tick)
    lm.set_gains(old, 0.0)
    f_soft = np.array([lm.step(e) for _ in range(300)])
    assert f_soft[0] == pytest.approx(new * e)
    assert np.diff(f_soft).min() >= -(new - old) * e / 250 * 1.0001
    assert f_soft[-1] == pytest.approx(old * e)

    plain = LocalModel(LocalModelParams(k_h=old))  # gain_transfer_s = 0: the paper's eq. 12
    plain.step(e)
    plain.set_gains(new, 0.0)
    assert plain.step(e) == pytest.approx(new * e)


def test_the_gain_transfer_keeps_the_integral_and_ends_with_the_contact():
    lm = LocalModel(
        LocalModelParams(
            k_h=100.0, i_gain=3000.0, threshold=ThresholdParams(mode="none"), gain_transfer_s=0.1
        )
    )
    for _ in range(100):
        f_before = lm.step(0.005)
    integral = lm.integral_n
    lm.set_gains(300.0, 3000.0)
    assert lm.step(0.005) - f_before == pytest.approx(3000.0 * 1e-3 * 0.005)  # one integral step
    assert lm.integral_n > integral
    assert lm.transfer_n < 0.0  # carrying -200 N/m * 5 mm, being driven to zero
    # the probe leaves: the transfer is gone with the contact, a new touch is plain eq. 12
    for _ in range(200):
        lm.step(-0.001)
    assert lm.transfer_n == 0.0
    assert lm.step(0.002) == pytest.approx(300.0 * 0.002)
    # out of contact a change of gains carries nothing
    for _ in range(200):
        lm.step(-0.001)
    lm.set_gains(100.0, 3000.0)
    assert lm.transfer_n == 0.0


def test_non_finite_penetration_is_treated_as_release():
    lm = LocalModel(LocalModelParams(k_h=100.0))
    lm.step(0.01)
    assert lm.step(math.nan) == 0.0
    assert lm.step(math.inf) == 0.0


@pytest.mark.parametrize(
    "kwargs",
    [
        {"k_h": 0.0},
        {"k_h": -5.0},
        {"k_h": math.nan},
        {"k_h": 10.0, "i_gain": -1.0},
        {"k_h": 10.0, "servo_period_s": 0.0},
        {"k_h": 10.0, "release_time_s": 0.0},
        {"k_h": 10.0, "gain_transfer_s": -0.1},
        {"k_h": 10.0, "gain_transfer_s": math.inf},
    ],
)
def test_bad_parameters_are_refused(kwargs):
    with pytest.raises(ValueError):
        LocalModelParams(**kwargs)


def test_bad_threshold_is_refused():
    with pytest.raises(ValueError):
        ThresholdParams(mode="bogus")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        ThresholdParams(theta_m=-0.001)
    with pytest.raises(ValueError):
        ThresholdParams(mode="variable", i_tot_bar_n=0.0)


def test_plane_penetration_and_proxy():
    plane = make_plane((0.0, 0.0, 0.1), (0.0, 0.0, 2.0))
    assert plane.normal == (0.0, 0.0, 1.0)
    assert plane.penetration(0.01, 0.0, 0.095) == pytest.approx(0.005)
    e, nx, ny, nz = plane.contact(0.0, 0.0, 0.12)
    assert e == pytest.approx(-0.02) and (nx, ny, nz) == (0.0, 0.0, 1.0)
    assert plane.proxy(0.01, 0.02, 0.09) == pytest.approx((0.01, 0.02, 0.1))


def test_sphere_penetration_and_normal():
    sphere = make_sphere((0.0, 0.0, 0.0), 0.1)
    e, nx, ny, nz = sphere.contact(0.0, 0.095, 0.0)
    assert e == pytest.approx(0.005) and (nx, ny, nz) == pytest.approx((0.0, 1.0, 0.0))
    assert sphere.proxy(0.0, 0.0, 0.5) == pytest.approx((0.0, 0.0, 0.1))
    assert sphere.penetration(0.0, 0.0, 0.0) == pytest.approx(0.1)


@pytest.mark.parametrize(
    "make",
    [
        lambda: make_plane((0, 0, 0), (0, 0, 0)),
        lambda: make_plane((0, 0, math.nan), (0, 0, 1)),
        lambda: make_plane((0, 0), (0, 0, 1)),
        lambda: make_sphere((0, 0, 0), -1.0),
        lambda: make_sphere((0, 0, 0), math.inf),
        lambda: make_sphere(("a", 0, 0), 0.1),
    ],
)
def test_bad_primitives_are_refused(make):
    with pytest.raises(ValueError):
        make()
