"""The fidelity benchmark's 1-D simulator, schemes and metrics on cases with a known answer."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from haptic_collab.client.session import ClientSession, DeviceInfo
from haptic_collab.research.fidelity_1d import passivity_step, simulate
from haptic_collab.research.fidelity_cases import (
    IMPACT,
    PRESS,
    TAP,
    Cell,
    Trajectory,
    felt_depth_m,
    felt_trajectory,
)
from haptic_collab.research.fidelity_metrics import (
    FELT_DISTORTION_MAX,
    cell_metrics,
    felt_response,
    felt_stiffness_ratio,
    force_distortion,
)
from haptic_collab.research.fidelity_schemes import (
    SCHEMES,
    DeviceModel,
    Rendering,
    design_delay_ticks,
    peer_renderings,
    rendering_for,
    scheme_tuning,
)
from haptic_collab.shared.felt_stiffness import felt_stiffness
from haptic_collab.shared.full_loop import DEFAULT_HAND, Hand, spectral_radius
from haptic_collab.shared.local_model import LocalModel, LocalModelParams, ThresholdParams
from haptic_collab.shared.passivity import PassivityController, PassivityParams
from haptic_collab.shared.protocol import Welcome, encode
from tests.support.sessions import WELCOME_OBJECT as OBJ

P500 = Rendering("local-p", "coupling", k_h=500.0)
DIRECT = Rendering("direct", "direct")


def _felt(r: Rendering, k_o: float, rate: float, delay_ms: float, hz: float) -> float | None:
    cell = Cell(r, k_o, rate, delay_ms, None, felt_trajectory(hz, felt_depth_m(k_o, 7.9)))
    return felt_stiffness_ratio(simulate([cell]), [cell])[0]


def test_p_coupling_on_a_rigid_probe_feels_k_h_in_series_with_k_o() -> None:
    # the paper's steady state: f = K_h K_o / (K_h + K_o) x
    got = _felt(P500, 1000.0, 100.0, 0.0, 1.0)
    assert got is not None
    assert got == pytest.approx(500.0 / 1500.0, rel=2e-3)


def test_felt_stiffness_matches_the_exact_lifted_analysis() -> None:
    # probe damper, first-order hold and two ticks of delay at 8 Hz: the simulator measures what
    # shared.felt_stiffness.felt_stiffness computes exactly for the linear loop
    r = Rendering("local-p", "coupling", k_h=300.0, b_h=8.0, proxy_hold="foh")
    got = _felt(r, 1000.0, 20.0, 50.0, 8.0)
    # 50 ms each way at 20 Hz: the force the simulation reads left the servo 2 periods earlier
    want = felt_stiffness(
        8.0,
        k_o=1000.0,
        k_h=300.0,
        b_h=8.0,
        rate_ratio=50,
        delay_ticks=2,
        proxy_hold="foh",
        sample_tick=48,
    )[0]
    assert got is not None
    assert got == pytest.approx(want / 1000.0, rel=0.01)


def test_direct_rendering_at_zero_delay_and_high_rate_approaches_k_o() -> None:
    got = _felt(DIRECT, 1000.0, 100.0, 0.0, 1.0)
    assert got is not None
    assert got == pytest.approx(1.0, abs=0.01)


def test_a_saturated_force_is_not_read_as_stiffness() -> None:
    # the felt-stiffness depth keeps K_o x inside the device's force on a stiff object
    assert 3000.0 * (felt_depth_m(3000.0, 7.9) + 0.25e-3) <= 0.8 * 7.9 + 1e-9
    assert felt_depth_m(100.0, 7.9) == pytest.approx(5e-3)


def test_an_unsettled_response_has_no_felt_stiffness() -> None:
    # P with K_h above K_o violates eq. 8 (paper Fig. 11): the unilateral contact bounds the
    # divergence into a limit cycle, and no stiffness can be read from it, nor from the longer
    # probe the benchmark measures such a response again with
    cells = [
        Cell(Rendering("local-p", "coupling", k_h=1500.0), 1000.0, 20.0, 0.0, None,
             felt_trajectory(1.0, 2e-3, longer=longer))
        for longer in (False, True)
    ]  # fmt: skip
    assert cells[1].trajectory.duration_s > cells[0].trajectory.duration_s
    assert [felt_stiffness_ratio(simulate([c]), [c]) for c in cells] == [[None], [None]]


def test_the_distortion_of_a_force_is_what_is_not_at_the_probes_frequency() -> None:
    t = np.arange(0.0, 4.0, 1e-3)
    w = 2.0 * math.pi * 0.5
    spring = 3.0 + 0.1 * t + 0.75 * np.sin(w * t)
    assert force_distortion(t, spring, 0.5) < 1e-9
    # a chatter at 40 Hz with the fundamental's power: the limit of what is read
    chatter = spring + 0.75 / math.sqrt(2.0) * np.sign(np.sin(2.0 * math.pi * 40.0 * t))
    assert force_distortion(t, chatter, 0.5) == pytest.approx(1.0, rel=0.02)
    assert force_distortion(t, np.full_like(t, 2.0), 0.5) == math.inf


def test_a_chattering_force_is_not_read_as_a_stiffness() -> None:
    # the uncapped one-port passivity controller on 3000 N/m at 20 Hz, 200 ms each way: the
    # force switches between the clamp's 6.3 N and zero; its fundamental read 2.3 times the
    # object at 0.5 Hz and 0.6 times at 1 Hz, and ranked it best on the spring. It is refused;
    # the plane beside it, whose force follows the probe, is read
    dev = DeviceModel()
    tdpa = peer_renderings("direct-tdpa", k_o=3000.0, sim_rate_hz=20.0, device=dev)[0]
    wall = peer_renderings("static-local", k_o=3000.0, sim_rate_hz=20.0, device=dev)[0]
    depth = felt_depth_m(3000.0, dev.max_force_n)
    cells = [
        Cell(r, 3000.0, 20.0, 200.0, None, felt_trajectory(hz, depth))
        for r in (tdpa, wall)
        for hz in (0.5, 1.0)
    ]
    run = simulate(cells)
    got = felt_response(run, cells)
    assert got[:2] == [None, None]
    assert got[2] is not None and got[3] is not None
    assert abs(got[2]) == pytest.approx(1000.0 / 3000.0, rel=0.01)
    for i, c in enumerate(cells):
        a, b = c.trajectory.hold_window_s
        m = (run.t >= a) & (run.t < b)
        d = force_distortion(run.t[m], run.f[i][m], c.trajectory.sine_hz)
        assert (d > FELT_DISTORTION_MAX) == (i < 2)


def test_passivity_step_is_the_products_controller() -> None:
    """The simulator's vectorised copy of the passivity observer and controller (kept for speed:
    fidelity_1d's docstring) against shared.passivity.PassivityController, one controller per
    cell of a batch, each with its own damping cap, energy bias and switch, on every tick; the
    inputs reach every branch of the controller."""
    rng = np.random.default_rng(3)
    caps = np.array([10.0, 2.0, 40.0, 10.0, 10.0])
    biases = np.array([1e-4, 0.0, 1e-3, 1e-4, 0.0])
    on = np.array([True, True, True, False, True])
    fmax, T = 7.9, 1e-3
    pcs = [
        PassivityController(
            PassivityParams(
                max_damping_n_s_per_m=float(c),
                energy_bias_j=float(b),
                servo_period_s=T,
                max_force_n=fmax,
                enabled=bool(o),
            )
        )
        for c, b, o in zip(caps, biases, on, strict=True)
    ]
    e, fa = np.zeros(caps.size), np.zeros(caps.size)
    seen = dict.fromkeys(("capped", "below_cap", "clamped", "reset", "still", "off"), 0)
    for _ in range(3000):
        f_d = rng.normal(0.0, 5.0, caps.size)
        f_d = np.where(rng.random(caps.size) < 0.05, 0.0, f_d)  # out of contact: reset
        v = rng.normal(0.0, 0.05, caps.size)
        v = np.where(rng.random(caps.size) < 0.05, 0.0, v)  # a still handle: nothing to damp
        before = [pc.dissipated_energy_j for pc in pcs]
        want = [
            pc.step(f, 0.0, 0.0, vi, 0.0, 0.0)[0] for pc, f, vi in zip(pcs, f_d, v, strict=True)
        ]
        e, fa, dissipated = passivity_step(
            e,
            fa,
            f_d,
            v,
            servo_period_s=T,
            max_damping_n_s_per_m=caps,
            energy_bias_j=biases,
            max_force_n=fmax,
            on=on,
        )
        np.testing.assert_allclose(fa, want, rtol=0.0, atol=1e-12)
        np.testing.assert_allclose(e, [pc.observed_energy_j for pc in pcs], rtol=0.0, atol=1e-12)
        np.testing.assert_allclose(
            dissipated,
            [pc.dissipated_energy_j - d0 for pc, d0 in zip(pcs, before, strict=True)],
            rtol=0.0,
            atol=1e-15,
        )
        alpha = np.array([pc.alpha_n_s_per_m for pc in pcs])
        seen["capped"] += int(np.sum((alpha > 0.0) & (alpha == caps)))
        seen["below_cap"] += int(np.sum((alpha > 0.0) & (alpha < caps)))
        seen["clamped"] += int(np.sum((alpha > 0.0) & (np.abs(fa) == fmax)))
        seen["reset"] += int(np.sum((f_d == 0.0) & (e == 0.0)))
        seen["still"] += int(np.sum((v == 0.0) & (f_d != 0.0)))
        seen["off"] += int(np.sum(~on & (fa != np.clip(f_d, -fmax, fmax))))
    assert seen.pop("off") == 0  # a controller that is off only clamps the force
    assert all(k > 0 for k in seen.values()), seen


def _local_model_reference(
    run_x: np.ndarray, r: Rendering, k_o: float, n_ratio: int, d: int
) -> tuple[list[float], dict[str, int]]:
    """shared.local_model.LocalModel, probe as a position source, against an independently written
    spring object at the simulation rate with ``d`` servo ticks of delay each way; the forces and
    how often each branch of the model was taken."""
    lm = LocalModel(
        LocalModelParams(
            k_h=r.k_h,
            i_gain=r.i_gain,
            threshold=ThresholdParams(mode="fixed", theta_m=r.theta_m),
            release_time_s=r.release_time_s,
            integral_limit_n=7.9,
            recovery_m_per_n=1.0 / k_o if r.i_gain > 0.0 else 0.0,
        )
    )
    sent: list[float] = []
    published: dict[int, float] = {}  # servo tick from which the servo sees it: x_o
    proxy = 0.0
    forces = []
    seen = dict.fromkeys(("released", "recovery_band", "integral_limit", "force_clamp"), 0)
    for n, x in enumerate(run_x.tolist()):
        proxy = published.pop(n, proxy)
        was = lm.in_contact
        f_lm = lm.step(x - proxy)
        f = min(max(f_lm, -7.9), 7.9)
        forces.append(f)
        sent.append(f)
        seen["released"] += int(was and not lm.in_contact and lm.integral_n > 0.0)
        seen["recovery_band"] += int(lm.in_contact and x - proxy <= 0.0)
        seen["integral_limit"] += int(lm.integral_n == 7.9)
        seen["force_clamp"] += int(f != f_lm)
        if n % n_ratio == 0:
            got = sent[n - d] if n - d >= 0 else 0.0
            published[n + 1 + d] = max(got, 0.0) / k_o
    return forces, seen


def test_the_local_model_is_the_products_local_model() -> None:
    """The simulator's vectorised copy of the local model (kept for speed: fidelity_1d's
    docstring) against shared.local_model.LocalModel, cell by cell of one batch of P and PI
    couplings with their own gains, thresholds, release times, rates and delays: eq. 12, eq. 17's
    threshold, the release ramp, the recovery band and the integral limit are all reached."""
    in_out = Trajectory(  # in, hold, out (release), back in
        "in-out",
        duration_s=2.0,
        y0_m=-2e-3,
        y1_m=6e-3,
        ramp_start_s=0.1,
        ramp_s=0.3,
        sine_amplitude_m=7e-3,
        sine_hz=1.0,
        sine_start_s=1.0,
        sine_end_s=2.0,
    )
    deep = replace(in_out, name="deep", y1_m=25e-3, sine_amplitude_m=26e-3, sine_hz=0.75)
    cases = [  # rendering, K_o, simulation rate, one-way delay [ticks], trajectory
        (
            Rendering("local-pi", "coupling", k_h=120.0, i_gain=2000.0, theta_m=1e-3),
            400.0,
            20.0,
            10,
            in_out,
        ),
        (Rendering("local-p", "coupling", k_h=300.0), 400.0, 20.0, 10, in_out),
        (
            Rendering(
                "local-pi",
                "coupling",
                k_h=200.0,
                i_gain=5000.0,
                theta_m=0.5e-3,
                release_time_s=0.05,
            ),
            400.0,
            50.0,
            0,
            deep,
        ),
        (
            Rendering(
                "local-pi",
                "coupling",
                k_h=60.0,
                i_gain=800.0,
                theta_m=2e-3,
                release_time_s=0.3,
            ),
            150.0,
            10.0,
            30,
            in_out,
        ),
    ]
    cells = [Cell(r, k_o, rate, float(d), None, tr) for r, k_o, rate, d, tr in cases]
    run = simulate(cells)
    seen_all: dict[str, int] = {}
    for i, (r, k_o, rate, d, tr) in enumerate(cases):
        n_i = round(tr.duration_s * 1000.0)
        forces, seen = _local_model_reference(run.x[i, :n_i], r, k_o, round(1000.0 / rate), d)
        np.testing.assert_allclose(run.f[i, :n_i], forces, rtol=0.0, atol=1e-9)
        assert max(forces) > 1.0  # the case exercised contact
        for k, v in seen.items():
            seen_all[k] = seen_all.get(k, 0) + v
    assert all(v > 0 for v in seen_all.values()), seen_all


def test_the_delay_is_honoured_both_ways() -> None:
    # direct rendering: the probe enters at t0; the force comes back after the uplink delay, the
    # wait for the next simulation tick, one tick of computation and the downlink delay
    step = Trajectory("step", duration_s=1.0, y0_m=-1e-3, y1_m=2e-3, ramp_start_s=0.2, ramp_s=1e-3)
    cells = [Cell(DIRECT, 1000.0, 100.0, float(d), None, step) for d in (0, 50)]
    run = simulate(cells)
    t_in = run.t[np.argmax(run.x[0] > 0.0)]
    first = [run.t[np.argmax(run.f[i] > 0.0)] - t_in for i in range(2)]
    assert 0.0 < first[0] <= 0.012
    assert 0.1 <= first[1] <= 0.112


@pytest.mark.parametrize("hand", [DEFAULT_HAND, Hand(0.1, 2.0, 1000.0)])
def test_the_hand_in_the_loop_agrees_with_the_full_loop_analysis(hand: Hand) -> None:
    # with no delay the simulation takes the freshest force (servo tick N - 1 of the block the new
    # surface replaces): the lifted full loop's verdict at that tick is the simulator's
    k_h = np.array([800.0, 1500.0])
    rho = spectral_radius(hand=hand, k_o=1000.0, k_h=k_h, rate_ratio=50, sample_ticks=[49])[:, 0]
    cells = [
        Cell(Rendering("local-p", "coupling", k_h=float(k)), 1000.0, 20.0, 0.0, hand, PRESS)
        for k in k_h
    ]
    run = simulate(cells)
    m = cell_metrics(run, cells)
    assert rho[0] < 1.0 and m[0].stable and m[0].hold_p2p_mm < 0.01
    assert rho[1] > 1.0 and not m[1].stable and m[1].hold_p2p_mm > 3.0
    # P steady state: the probe sits f / K_h past the surface the simulation reports
    assert m[0].steady_state_error_mm == pytest.approx(run.f[0, -1] / 800.0 * 1e3, rel=0.01)


def test_the_stale_sampling_phase_is_the_full_loops_middle_tick() -> None:
    # the client sends its state every half simulation period, so the state the simulation
    # reads is at most N/2 servo ticks old (the other end of the sampling phase: the servo's and
    # the simulation's clocks are not synchronised): the lifted loop at sampling tick N - 1 -
    # N/2 = 24 of 50. K_h = 700 N/m on 1000 N/m at 20 Hz is stable at the last tick (0.78) and
    # rings at that one (1.19), K_h = 500 N/m is stable at both
    k_h = np.array([500.0, 700.0])
    rho = spectral_radius(hand=DEFAULT_HAND, k_o=1000.0, k_h=k_h, rate_ratio=50,
                          sample_ticks=[24, 49])  # fmt: skip
    assert rho[0].max() < 1.0 and rho[1, 1] < 1.0 < rho[1, 0]
    cells = [
        Cell(Rendering("local-p", "coupling", k_h=float(k)), 1000.0, 20.0, 0.0, DEFAULT_HAND,
             PRESS, stale_sample=stale)
        for k in k_h
        for stale in (False, True)
    ]  # fmt: skip
    m = cell_metrics(simulate(cells), cells)
    assert [c.stable for c in m] == [True, True, True, False]
    assert m[3].hold_p2p_mm > 2.0  # a ringing the hand feels (stable: below 0.5 mm)


def test_delayed_direct_rendering_is_active_and_penetrates_on_impact() -> None:
    # the paper's footnote 4: a delayed rendering lets the user in too far, and gives energy
    hand = Hand(0.3, 5.0, 300.0)
    cells = [
        Cell(DIRECT, 1000.0, 20.0, 100.0, hand, IMPACT),
        Cell(P500, 1000.0, 20.0, 0.0, hand, IMPACT),
        Cell(DIRECT, 1000.0, 20.0, 100.0, hand, TAP),
    ]
    m = cell_metrics(simulate(cells), cells)
    assert m[0].peak_penetration_mm > 2.0 * m[1].peak_penetration_mm
    assert m[2].energy_out_mj > 0.0
    assert not m[0].stable


def test_every_scheme_has_a_rendering_and_a_stated_tuning() -> None:
    dev = DeviceModel()
    for s in SCHEMES:
        assert scheme_tuning(s, dev)
        if s.startswith("local"):
            with pytest.raises(ValueError, match="design"):
                rendering_for(s, sim_rate_hz=20.0, device=dev)
        else:
            r = rendering_for(s, sim_rate_hz=20.0, device=dev)
            assert r.scheme == s
    vc = rendering_for("virtual-coupling", sim_rate_hz=20.0, device=dev)
    assert (vc.k_h, vc.b_h) == (dev.max_stiffness_n_per_m, dev.max_damping_n_s_per_m)
    with pytest.raises(ValueError, match="unknown scheme"):
        rendering_for("teleport", sim_rate_hz=20.0)


@pytest.mark.parametrize(
    ("delay_ms", "rate", "ticks"),
    [(0.0, 20.0, 0), (10.0, 20.0, 0), (50.0, 20.0, 2), (100.0, 20.0, 4), (200.0, 20.0, 8),
     (10.0, 100.0, 2), (50.0, 10.0, 1)],
)  # fmt: skip
def test_design_delay_ticks_is_what_the_client_measures(
    delay_ms: float, rate: float, ticks: int
) -> None:
    # a round trip of twice the delay plus half a period of state age, in whole periods, minus the
    # one the loop always has: e.g. 20 Hz, 50 ms each way: 100 + 25 ms -> 3 periods -> 2 extra
    assert design_delay_ticks(delay_ms * 1e-3, rate) == ticks
    s = ClientSession("A", device=DeviceInfo(max_stiffness_n_per_m=1000.0))
    s.receive(
        encode(Welcome(user_id="u", name="A", role="user", sim_rate_hz=rate, object=OBJ)), 0.0
    )
    for _ in range(10):
        s.rtt_s.append(2.0 * delay_ms * 1e-3)
    assert s.delay_ticks() == ticks


def test_bad_input_is_refused() -> None:
    with pytest.raises(ValueError, match="at least one"):
        simulate([])
    with pytest.raises(ValueError, match="whole"):
        simulate([Cell(P500, 1000.0, 30.0, 0.0, None, PRESS)])
    with pytest.raises(ValueError, match="delay"):
        simulate([Cell(P500, 1000.0, 20.0, 0.5, None, PRESS)])
    with pytest.raises(ValueError, match="k_o"):
        simulate([Cell(P500, math.nan, 20.0, 0.0, None, PRESS)])
    with pytest.raises(ValueError, match="position-source"):
        felt_stiffness_ratio(
            simulate([Cell(P500, 1000.0, 20.0, 0.0, DEFAULT_HAND, PRESS)]),
            [Cell(P500, 1000.0, 20.0, 0.0, DEFAULT_HAND, PRESS)],
        )
    with pytest.raises(ValueError):
        design_delay_ticks(-1.0, 20.0)
