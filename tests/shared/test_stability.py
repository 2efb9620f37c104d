"""Stability analysis: lifting, the slow-rate loop, the paper's closed forms and gain selection."""

from __future__ import annotations

import math

import numpy as np
import pytest

from haptic_collab.research.multirate import simulate
from haptic_collab.shared.local_model import LocalModel, LocalModelParams, ThresholdParams
from haptic_collab.shared.stability import (
    StateSpace,
    analyze,
    closed_loop_matrix,
    common_timebase,
    eq8_stable,
    eq10_stable,
    eq15_stable,
    eq16_stable,
    lift,
    local_model_state_space,
    object_state_space,
    rate_ratio,
    select_gains,
    slow_rate_model,
    spectral_radius_grid,
)

T = 1e-3


def _fast_rate_simulation(k_h, i_gain, k_o, b_o, n, x_h, blocks, delay=0, sample_tick=0):
    """Direct fast-rate simulation of Fig. 4 with the state-space L(z), independent of lifting."""
    ss = local_model_state_space(k_h, i_gain, T)
    lam = np.zeros(ss.n_states)
    x_obj, x_seen, f_sample = 0.0, 0.0, 0.0
    pipeline = [0.0] * delay
    seen = []
    for i in range(blocks * n):
        if i % n == 0:
            if i > 0:
                x_obj = (f_sample + b_o * x_obj) / (k_o + b_o)
                pipeline.append(x_obj)
                x_seen = pipeline.pop(0)
            seen.append(x_seen)
        u = x_h - x_seen
        f = float((ss.C @ lam)[0] if ss.n_states else 0.0) + ss.D[0, 0] * u
        if ss.n_states:
            lam = ss.A @ lam + ss.B[:, 0] * u
        if i % n == sample_tick:
            f_sample = f
    return np.array(seen)


def _slow_rate_simulation(k_h, i_gain, k_o, b_o, n, x_h, blocks, delay=0, sample_tick=0):
    """The slow-rate LTI loop of Fig. 6 built from the lifted model, driven by a held x_h."""
    l_h = slow_rate_model(local_model_state_space(k_h, i_gain, T), n, sample_tick)
    obj = object_state_space(k_o, b_o)
    lam = np.zeros(l_h.n_states)
    xi = np.zeros(obj.n_states)
    line = [0.0] * (1 + delay)
    out = []
    for _ in range(blocks):
        y = line[-1]
        out.append(y)
        u = x_h - y
        f = float((l_h.C @ lam)[0] if l_h.n_states else 0.0) + l_h.D[0, 0] * u
        p = float((obj.C @ xi)[0] if obj.n_states else 0.0) + obj.D[0, 0] * f
        if l_h.n_states:
            lam = l_h.A @ lam + l_h.B[:, 0] * u
        if obj.n_states:
            xi = obj.A @ xi + obj.B[:, 0] * f
        line = [p] + line[:-1]
    return np.array(out)


def test_lifted_matrices_follow_eq5():
    ss = local_model_state_space(120.0, 800.0, T)
    lt = lift(ss, 4)
    # PI: A = 1, B = 1, C = T I, D = K_h
    assert lt.A.shape == (1, 1) and lt.A[0, 0] == pytest.approx(1.0)
    assert lt.B.shape == (1, 4) and np.allclose(lt.B, 1.0)
    assert lt.C.shape == (4, 1) and np.allclose(lt.C, T * 800.0)
    expected_d = np.tril(np.full((4, 4), T * 800.0), -1) + np.eye(4) * 120.0
    assert np.allclose(lt.D, expected_d)
    l_h = slow_rate_model(ss, 50)
    assert l_h.B[0, 0] == pytest.approx(50.0)  # L_h(z) = K_h + N T I/(z-1), eq. 13


@pytest.mark.parametrize(
    "k_h,i_gain,k_o,b_o,delay",
    [
        (100.0, 0.0, 900.0, 0.0, 0),
        (190.0, 0.0, 200.0, 0.0, 0),
        (100.0, 3000.0, 300.0, 0.0, 0),
        (150.0, 2000.0, 300.0, 60.0, 0),
        (80.0, 1000.0, 300.0, 0.0, 2),
        (250.0, 0.0, 200.0, 40.0, 1),
    ],
)
def test_lifting_matches_direct_fast_rate_simulation(k_h, i_gain, k_o, b_o, delay):
    """The slow-rate model of Fig. 6 reproduces the multirate loop exactly at the slow instants."""
    n, blocks = 50, 40
    direct = _fast_rate_simulation(k_h, i_gain, k_o, b_o, n, 0.02, blocks, delay)
    lifted = _slow_rate_simulation(k_h, i_gain, k_o, b_o, n, 0.02, blocks, delay)
    assert np.allclose(direct, lifted, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize(
    "k_h,i_gain,k_o,damping", [(100.0, 0.0, 900.0, 0.0), (120.0, 2500.0, 300.0, 2.0)]
)
def test_client_local_model_code_matches_the_analysed_loop(k_h, i_gain, k_o, damping):
    """The multirate simulator runs LocalModel (the servo's code): same proxy as the LTI model."""
    lm = LocalModel(
        LocalModelParams(
            k_h=k_h, i_gain=i_gain, unilateral=False, threshold=ThresholdParams(mode="none")
        )
    )
    tr = simulate(lm, np.full(2000, 0.02), k_o=k_o, n_ticks=2000, damping=damping)
    proxy_at_sim_ticks = tr.proxy_m[::50]
    lifted = _slow_rate_simulation(k_h, i_gain, k_o, damping * 20.0, 50, 0.02, 40)
    assert np.allclose(proxy_at_sim_ticks, lifted, rtol=1e-9, atol=1e-12)


def test_proportional_verdicts_follow_eq8():
    assert analyze(900.0, 100.0).stable
    assert analyze(200.0, 190.0).stable
    assert not analyze(200.0, 220.0).stable
    a = analyze(200.0, 190.0)
    assert a.spectral_radius == pytest.approx(190.0 / 200.0)  # pole at -K_h/K_o (eq. 7)
    assert a.analytic_stable is True and "eq. 8" in a.condition


def test_damping_enlarges_the_region_eq10():
    # K_h above K_o is unstable on a spring but stable with enough damping (eq. 10)
    assert not analyze(200.0, 220.0).stable
    d = analyze(200.0, 220.0, damping=1.0)  # B_o = 1 * 20 = 20 N/m: K_h < K_o + 2 B_o = 240
    assert d.stable and d.analytic_stable and "eq. 10" in d.condition


@pytest.mark.parametrize("seed", range(4))
def test_closed_forms_agree_with_numeric_verdict_on_random_parameters(seed):
    rng = np.random.default_rng(seed)
    disagreements = 0
    count = 0
    for _ in range(150):
        k_o = float(rng.uniform(50.0, 2000.0))
        k_h = float(rng.uniform(0.01, 3.0) * k_o)
        servo = float(rng.choice([500.0, 1000.0, 2000.0]))
        sim = servo / float(rng.choice([5, 10, 25, 50, 100]))
        n = rate_ratio(servo, sim)
        nti = float(rng.uniform(0.0, 3.5) * k_o) if rng.random() < 0.7 else 0.0
        i_gain = nti * servo / n
        damping = float(rng.uniform(0.0, 0.5) * k_o / sim) if rng.random() < 0.5 else 0.0
        res = analyze(
            k_o, k_h, i_gain=i_gain, damping=damping, servo_rate_hz=servo, sim_rate_hz=sim
        )
        b_o = damping * sim
        if i_gain == 0.0:
            closed = eq8_stable(k_h, k_o) if b_o == 0.0 else eq10_stable(k_h, k_o, b_o)
        else:
            closed = (
                eq15_stable(k_h, k_o, res.nti)
                if b_o == 0.0
                else eq16_stable(k_h, k_o, res.nti, b_o)
            )
        assert res.analytic_stable == closed
        # skip points within round-off of the boundary
        if abs(res.spectral_radius - 1.0) > 1e-6:
            count += 1
            disagreements += int(res.stable != closed)
    assert count > 100
    assert disagreements == 0


def test_pi_region_of_eq15_has_the_shape_of_fig8():
    k_o = 300.0
    assert analyze(k_o, 100.0, i_gain=3000.0).stable  # INT = 150
    assert not analyze(k_o, 100.0, i_gain=0.0 + 9000.0).stable  # INT = 450 > K_h + K_o
    assert not analyze(k_o, 700.0, i_gain=1000.0).stable  # INT - 2K_h < -2K_o
    # the region scales with K_o: the same normalised point has the same verdict
    for scale in (0.5, 2.0, 7.0):
        a = analyze(k_o * scale, 100.0 * scale, i_gain=3000.0 * scale)
        assert a.stable and a.spectral_radius == pytest.approx(
            analyze(k_o, 100.0, i_gain=3000.0).spectral_radius
        )


def test_delay_shrinks_the_pi_region_but_not_the_p_condition():
    # P: poles satisfy |z|^(1+d) = K_h/K_o, stable for any delay iff K_h < K_o
    for d in (0, 1, 3, 6):
        assert analyze(300.0, 290.0, delay_ticks=d).stable
        assert not analyze(300.0, 310.0, delay_ticks=d).stable
    # PI near the deadbeat point is stable without delay and unstable with it
    assert analyze(300.0, 280.0, i_gain=280.0 * 20.0).stable
    delayed = analyze(300.0, 280.0, i_gain=280.0 * 20.0, delay_ticks=2)
    assert not delayed.stable and delayed.analytic_stable is None


def test_grid_radius_equals_matrix_radius():
    rng = np.random.default_rng(7)
    for _ in range(40):
        k_o, k_h = rng.uniform(100, 1000), rng.uniform(10, 1500)
        i_gain, damping, d = rng.uniform(0, 20000), rng.uniform(0, 10), int(rng.integers(0, 4))
        a = analyze(k_o, k_h, i_gain=i_gain, damping=damping, delay_ticks=d)
        g = spectral_radius_grid(k_o, np.array([k_h]), np.array([a.nti]), a.b_o, d)[0]
        assert g == pytest.approx(a.spectral_radius, rel=1e-6, abs=1e-9)
    acl = closed_loop_matrix(
        slow_rate_model(local_model_state_space(100.0, 0.0, T), 50), object_state_space(900.0), 0
    )
    assert acl.shape == (1, 1) and acl[0, 0] == pytest.approx(-100.0 / 900.0)


@pytest.mark.parametrize("delay", [0, 1, 3])
@pytest.mark.parametrize("mode", ["p", "pi"])
def test_selected_gains_are_stable_with_margin_and_device_cap(mode, delay):
    for k_o in (150.0, 400.0, 1500.0):
        g = select_gains(
            k_o,
            rate_ratio=50,
            servo_period_s=T,
            delay_ticks=delay,
            margin=0.3,
            k_h_max=1000.0,
            mode=mode,
        )
        assert g.stable
        assert 0.0 < g.k_h <= min(1000.0, 0.7 * k_o) + 1e-9
        verdict = analyze(k_o, g.k_h, i_gain=g.i_gain, delay_ticks=delay)
        assert verdict.stable
        # with the margin the loop also holds when K_o was overestimated by 30 %
        assert (
            analyze(0.7 * k_o * 1.001, g.k_h, i_gain=g.i_gain, delay_ticks=delay).spectral_radius
            <= 1.0 + 1e-6
        )
        if mode == "pi":
            assert g.i_gain > 0.0 and g.worst_spectral_radius < 1.0
        else:
            assert g.i_gain == 0.0


@pytest.mark.parametrize("sample_tick", [1, 17, 49])
def test_lifting_with_a_later_force_sample_matches_the_direct_simulation(sample_tick):
    """Step 3 over a network samples the force at any servo tick j of the block: L_h,j."""
    direct = _fast_rate_simulation(120.0, 2500.0, 300.0, 0.0, 50, 0.02, 40, 1, sample_tick)
    lifted = _slow_rate_simulation(120.0, 2500.0, 300.0, 0.0, 50, 0.02, 40, 1, sample_tick)
    assert np.allclose(direct, lifted, rtol=1e-9, atol=1e-12)
    lm = LocalModel(
        LocalModelParams(
            k_h=120.0, i_gain=2500.0, unilateral=False, threshold=ThresholdParams(mode="none")
        )
    )
    tr = simulate(
        lm, np.full(2000, 0.02), k_o=300.0, n_ticks=2000, delay_ticks=1, sample_tick=sample_tick
    )
    assert np.allclose(tr.proxy_m[::50], lifted, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("delay", [0, 2])
def test_selected_pi_gains_hold_for_every_force_sampling_tick(delay):
    g = select_gains(300.0, rate_ratio=50, servo_period_s=T, delay_ticks=delay)
    radii = [
        analyze(300.0, g.k_h, i_gain=g.i_gain, delay_ticks=delay, sample_tick=j).spectral_radius
        for j in range(50)
    ]
    assert max(radii) < 0.95
    assert max(radii) == pytest.approx(g.spectral_radius, abs=0.05)


def test_deadbeat_gains_oscillate_when_the_force_is_sampled_late():
    """K_h = INT = 0.7 K_o is deadbeat for the paper's decimator but unstable for the last tick."""
    k_o, kh, n = 300.0, 210.0, 50
    i_gain = kh / (n * T)
    assert analyze(k_o, kh, i_gain=i_gain).stable
    assert not analyze(k_o, kh, i_gain=i_gain, sample_tick=49).stable

    def hold_oscillation(k_h, i):
        lm = LocalModel(
            LocalModelParams(
                k_h=k_h, i_gain=i, threshold=ThresholdParams(mode="fixed", theta_m=0.001)
            )
        )
        tr = simulate(lm, np.full(8000, 0.02), k_o=k_o, n_ticks=8000, sample_tick=49)
        return float(np.ptp(tr.proxy_m[-1000:]))

    assert hold_oscillation(kh, i_gain) > 0.002  # a sustained oscillation of millimetres
    g = select_gains(k_o, rate_ratio=n, servo_period_s=T)
    assert hold_oscillation(g.k_h, g.i_gain) < 1e-5  # the selected gains hold still


@pytest.mark.parametrize(
    "kwargs",
    [
        {"k_o": -1.0, "k_h": 100.0},
        {"k_o": math.nan, "k_h": 100.0},
        {"k_o": 100.0, "k_h": 0.0},
        {"k_o": 100.0, "k_h": 10.0, "i_gain": -1.0},
        {"k_o": 100.0, "k_h": 10.0, "sim_rate_hz": 30.0},
        {"k_o": 100.0, "k_h": 10.0, "delay_ticks": -1},
        {"k_o": 100.0, "k_h": 10.0, "servo_rate_hz": math.inf},
    ],
)
def test_bad_parameters_raise_clear_errors(kwargs):
    k_o, k_h = kwargs.pop("k_o"), kwargs.pop("k_h")
    with pytest.raises(ValueError):
        analyze(k_o, k_h, **kwargs)


def test_rate_ratio():
    assert rate_ratio(1000, 20) == 50
    assert rate_ratio(1000, 1000) == 1
    with pytest.raises(ValueError, match="whole multiple"):
        rate_ratio(1000, 30)
    with pytest.raises(ValueError):
        rate_ratio(10, 20)


# ------------------------------------------------------------------ sample times


def test_models_carry_their_sample_time():
    servo = local_model_state_space(120.0, 800.0, T)
    assert servo.dt == T
    assert local_model_state_space(120.0, 0.0, T).dt == T  # a static P model is still at T
    assert lift(servo, 4).dt == pytest.approx(4 * T, rel=1e-15)
    assert slow_rate_model(servo, 50, sample_tick=49).dt == pytest.approx(0.05, rel=1e-12)
    assert object_state_space(300.0, 60.0, 0.05).dt == 0.05
    assert object_state_space(300.0).dt is None  # unspecified: connects to any rate
    assert lift(object_state_space(300.0), 3).dt is None
    with pytest.raises(ValueError, match="sample time"):
        StateSpace(servo.A, servo.B, servo.C, servo.D, 0.0)
    with pytest.raises(ValueError, match="simulation period"):
        object_state_space(300.0, 0.0, -0.05)


@pytest.mark.parametrize("i_gain", [0.0, 800.0])
def test_a_servo_rate_model_is_not_wired_to_the_slow_object(i_gain):
    servo = local_model_state_space(120.0, i_gain, T)
    obj = object_state_space(300.0, 60.0, 50 * T)
    with pytest.raises(ValueError, match="different timebases") as err:
        closed_loop_matrix(servo, obj)
    msg = str(err.value)
    assert "local model L_h has dt = 0.001 s (1000 Hz)" in msg
    assert "object D(z) has dt = 0.05 s (20 Hz)" in msg
    # lifted to the object's rate first, it connects, and gives the loop without sample times
    l_h = slow_rate_model(servo, 50)
    with_dt = closed_loop_matrix(l_h, obj, 2)
    untimed = StateSpace(l_h.A, l_h.B, l_h.C, l_h.D, None)
    assert np.array_equal(with_dt, closed_loop_matrix(untimed, object_state_space(300.0, 60.0), 2))
    # lifted by the wrong N, it is on another slow timebase: refused too
    with pytest.raises(ValueError, match="different timebases"):
        closed_loop_matrix(slow_rate_model(servo, 25), obj)


def test_common_timebase_follows_python_control():
    a = local_model_state_space(100.0, 0.0, T)
    free = object_state_space(300.0)
    assert common_timebase(a, free) == T and common_timebase(free, a) == T
    assert common_timebase(free, free) is None
    # 1 / 20 Hz and 50 * 1 ms are the same period, however rounded
    assert common_timebase(lift(a, 50), object_state_space(300.0, 0.0, 1.0 / 20.0)) is not None
    with pytest.raises(ValueError, match="'A' has dt = 0.001 s.*'B' has dt = 0.05 s"):
        common_timebase(a, object_state_space(300.0, 0.0, 0.05), ("'A'", "'B'"))
