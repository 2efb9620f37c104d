"""The servo loop: forces felt, safety ramps, patch hand-over and deadline scheduling.

Time is an input everywhere except one short real-thread test.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import replace

import numpy as np
import pytest

from haptic_collab.client.devices.base import HapticError, Vec3
from haptic_collab.client.scheduler import DeadlineLoop
from haptic_collab.client.servo import ServoConfig, ServoCore
from haptic_collab.client.servo_thread import ServoThread
from haptic_collab.shared.local_model import LocalModelParams
from haptic_collab.shared.local_model_update import LocalModelUpdate
from haptic_collab.shared.primitives import make_plane, make_sphere
from tests.support.helpers import FakeDevice, lab_limits, max_step

T = 1e-3
RAMP_S = 0.05
STEP = T / RAMP_S  # safety-gain change per tick


def make_core(dev: FakeDevice, link_timeout_s: float = 0.25) -> ServoCore:
    return ServoCore(dev, ServoConfig(ramp_s=RAMP_S, link_timeout_s=link_timeout_s))


def mag(v: Vec3) -> float:
    return math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)


def run(core: ServoCore, t0: float, n: int, notify_every: int | None = None) -> float:
    """Tick n times from tick-time t0; optionally notify the link every few ticks."""
    t = t0
    for k in range(n):
        t = t0 + k * T
        if notify_every is not None and k % notify_every == 0:
            core.notify_link(t)
        core.tick(t)
    return t0 + n * T


PLANE = make_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0))


def pressing_core(ticks: int = 100, notify_every: int = 10) -> tuple[FakeDevice, ServoCore, float]:
    """A handle 5 mm into PLANE at K_h = 300 N/m (1.5 N at full gain), forces on, the default
    0.25 s link timeout, ticked ``ticks`` times from t = 0 with the link notified every
    ``notify_every`` ticks; with the tick time that comes next."""
    dev = FakeDevice((0.0, 0.0, -0.005))
    core = make_core(dev)
    core.enable_forces()
    core.set_patch(PLANE, 300.0, 0.0)
    t = run(core, 0.0, ticks, notify_every=notify_every)
    return dev, core, t


def test_no_force_before_first_patch_nor_before_enable() -> None:
    dev = FakeDevice((0.0, 0.0, -0.005))  # where a surface would be pushing hard
    core = make_core(dev)
    core.enable_forces()
    run(core, 0.0, 200, notify_every=10)
    assert all(w == (0.0, 0.0, 0.0) for w in dev.writes)
    assert core.latest() is not None and math.isnan(core.latest().penetration_m)  # type: ignore[union-attr]

    # a patch but forces never enabled: still nothing
    dev2 = FakeDevice((0.0, 0.0, -0.005))
    core2 = make_core(dev2)
    core2.set_patch(PLANE, 200.0, 0.0)
    run(core2, 0.0, 200, notify_every=10)
    assert all(w == (0.0, 0.0, 0.0) for w in dev2.writes)
    assert not dev2.enabled


@pytest.mark.parametrize(
    "normal", [(0.0, 0.0, 1.0), (0.6, 0.0, 0.8), (0.0, -1.0, 0.0)], ids=["z", "tilted", "-y"]
)
def test_plane_5mm_inside_gives_k_h_times_5mm_outward(normal: Vec3) -> None:
    anchor = (0.01, 0.02, 0.03)
    plane = make_plane(anchor, normal)
    probe = tuple(a - 0.005 * n for a, n in zip(anchor, plane.normal, strict=True))
    dev = FakeDevice(probe)  # type: ignore[arg-type]
    core = make_core(dev)
    core.enable_forces()
    core.set_patch(plane, 300.0, 0.0)
    run(core, 0.0, int(RAMP_S / T) + 20, notify_every=10)
    f = dev.displayed
    expected = 300.0 * 0.005  # 1.5 N
    assert mag(f) == pytest.approx(expected, rel=1e-9)
    for fi, ni in zip(f, plane.normal, strict=True):
        assert fi == pytest.approx(expected * ni, abs=1e-12)
    snap = core.latest()
    assert snap is not None and snap.in_contact and snap.penetration_m == pytest.approx(0.005)


def test_forces_ramp_up_on_first_patch_without_a_jump() -> None:
    dev, _, _ = pressing_core()
    mags = [mag(w) for w in dev.writes]
    full = 1.5
    assert max_step(mags) <= STEP * full + 1e-12
    assert mags[-1] == pytest.approx(full)


def test_force_above_device_max_is_clamped_and_counted() -> None:
    dev = FakeDevice((0.0, 0.0, -0.02), max_force_n=7.9)  # 1000 N/m * 20 mm = 20 N asked
    core = make_core(dev)
    core.enable_forces()
    core.set_patch(PLANE, 1000.0, 0.0)
    run(core, 0.0, 200, notify_every=10)
    assert max(mag(w) for w in dev.writes) == pytest.approx(7.9)
    assert dev.displayed[2] == pytest.approx(7.9)
    st = core.status()
    assert st.counts[HapticError.FORCE_LIMIT] == 1  # one episode, not one per tick
    assert st.last_event is not None and st.last_event.kind is HapticError.FORCE_LIMIT


def test_stiffness_above_device_max_is_clamped() -> None:
    dev = FakeDevice((0.0, 0.0, -0.001))
    core = make_core(dev)
    core.enable_forces()
    patch = core.set_patch(PLANE, 5000.0, 0.0)
    run(core, 0.0, 100, notify_every=10)
    assert patch.k_h == dev.limits.max_stiffness_n_per_m
    assert dev.displayed[2] == pytest.approx(1000.0 * 0.001)
    assert core.status().stiffness_clamps == 1


@pytest.mark.parametrize("bad", [(0.0, 0.0), (math.nan, 0.0), (100.0, -1.0), (100.0, math.inf)])
def test_bad_gains_are_refused_in_the_callers_thread(bad: tuple[float, float]) -> None:
    core = make_core(FakeDevice())
    with pytest.raises(ValueError):
        core.set_patch(PLANE, *bad)
    with pytest.raises(TypeError):
        core.set_patch("plane", 100.0, 0.0)  # type: ignore[arg-type]


def test_link_silence_ramps_force_to_zero_linearly_then_back_on_new_patch() -> None:
    dev, core, t = pressing_core(500, notify_every=50)  # link alive for 0.5 s, 0.25 s timeout
    last_notify = 0.45
    full = 1.5
    assert dev.displayed[2] == pytest.approx(full)
    n0 = len(dev.writes)
    t = run(core, t, 600)  # silence
    mags = [mag(w) for w in dev.writes[n0 - 1 :]]
    steps = [b - a for a, b in zip(mags, mags[1:], strict=False)]
    assert max_step(mags) <= STEP * full + 1e-12  # never a jump
    assert all(s <= 1e-12 for s in steps)  # monotone down
    times = [0.5 + k * T for k in range(600)]
    zero_at = next(tt for tt, m in zip(times, mags[1:], strict=True) if m == 0.0)
    assert zero_at <= last_notify + 0.25 + RAMP_S + 2 * T
    assert zero_at > last_notify + 0.25  # nothing changed before the timeout
    st = core.status()
    assert st.counts[HapticError.LINK_LOST] == 1 and not st.link_alive and not st.has_patch

    # a pong alone does not bring forces back: the old patch is stale
    core.notify_link(t)
    t = run(core, t + T, 20)
    assert dev.displayed == (0.0, 0.0, 0.0)
    # a new patch does, smoothly
    n1 = len(dev.writes)
    core.set_patch(PLANE, 300.0, 0.0)
    run(core, t, 200, notify_every=20)
    mags = [mag(w) for w in dev.writes[n1 - 1 :]]
    assert max(b - a for a, b in zip(mags, mags[1:], strict=False)) <= STEP * full + 1e-12
    assert mags[-1] == pytest.approx(full)


def test_device_fault_ramps_force_to_zero() -> None:
    dev, core, t = pressing_core()
    dev.fault = "USB read failed"
    n0 = len(dev.writes)
    run(core, t, 100, notify_every=10)
    mags = [mag(w) for w in dev.writes[n0 - 1 :]]
    assert max(a - b for a, b in zip(mags, mags[1:], strict=False)) <= STEP * 1.5 + 1e-12
    assert mags[int(RAMP_S / T) + 1] == 0.0 and mags[-1] == 0.0
    st = core.status()
    assert st.counts[HapticError.DEVICE_FAULT] == 1
    assert st.device_fault == "USB read failed"
    assert st.last_event is not None and "USB read failed" in st.last_event.detail


def test_non_finite_position_ramps_force_down_and_keeps_the_velocity_limit_working() -> None:
    dev, core, t = pressing_core()
    dev.position = (math.nan, 0.0, -0.005)  # one bad sample, then a stuck NaN
    n0 = len(dev.writes)
    t = run(core, t, 100, notify_every=10)
    forces = [mag(w) for w in dev.writes[n0 - 1 :]]
    assert all(math.isfinite(f) for f in forces)
    assert max(a - b for a, b in zip(forces, forces[1:], strict=False)) <= STEP * 1.5 + 1e-12
    assert forces[-1] == 0.0
    assert core.status().counts[HapticError.DEVICE_FAULT] == 1
    dev.position = (0.0, 0.0, -0.005)  # good samples again: forces return
    t = run(core, t, 200, notify_every=10)
    assert mag(dev.displayed) == pytest.approx(1.5)
    for k in range(50):  # and a fast probe still trips the velocity limit
        dev.position = (0.002 * k, 0.0, -0.005)
        core.notify_link(t)
        core.tick(t)
        t += T
    assert core.status().counts[HapticError.VELOCITY_LIMIT] == 1


def test_fast_probe_ramps_force_down_and_back() -> None:
    dev = FakeDevice((0.0, 0.0, 0.4995))  # 0.5 mm inside a 0.5 m sphere
    core = make_core(dev)
    core.enable_forces()
    core.set_patch(make_sphere((0.0, 0.0, 0.0), 0.5), 300.0, 0.0)
    t = run(core, 0.0, 100, notify_every=10)
    before = mag(dev.displayed)
    assert before > 0
    # the probe whips sideways at 2 m/s (limit 0.5 m/s), staying at the same depth
    for k in range(100):
        a = 2.0 * k * T / 0.4995
        dev.position = (0.4995 * math.sin(a), 0.0, 0.4995 * math.cos(a))
        core.notify_link(t)
        core.tick(t)
        t += T
    assert mag(dev.displayed) == 0.0
    assert core.status().counts[HapticError.VELOCITY_LIMIT] == 1
    run(core, t, 200, notify_every=10)  # held still: forces come back
    assert mag(dev.displayed) == pytest.approx(before)


def test_new_patch_changes_gains_without_a_force_jump_from_the_integral() -> None:
    params = LocalModelParams(k_h=200.0, i_gain=2000.0, servo_period_s=T)
    dev = FakeDevice((0.0, 0.0, -0.005))
    core = ServoCore(dev, ServoConfig(ramp_s=RAMP_S), local_model=params)
    core.enable_forces()
    core.set_patch(PLANE, 200.0, 2000.0)
    t = run(core, 0.0, 500, notify_every=10)
    integral = core.local_model.integral_n
    assert integral > 1.0  # the integral carries a force the user feels
    before = dev.displayed[2]
    increment = T * 2000.0 * 0.005  # what one tick adds to the integral

    core.set_patch(PLANE, 200.0, 500.0)  # new I, same K_h
    core.notify_link(t)
    core.tick(t)
    assert abs(dev.displayed[2] - before) <= increment + 1e-12
    assert core.local_model.integral_n >= integral

    core.set_patch(PLANE, 300.0, 500.0)  # new K_h: only the proportional part changes
    before = dev.displayed[2]
    core.tick(t + T)
    assert dev.displayed[2] - before == pytest.approx(100.0 * 0.005, abs=T * 500.0 * 0.005 + 1e-12)


def test_new_gains_mid_press_reach_the_hand_as_a_ramp_not_a_step() -> None:
    """Through the servo: stiffness and probe damper change, the displayed force moves smoothly."""
    params = LocalModelParams(k_h=50.0, servo_period_s=T, gain_transfer_s=0.2)
    dev = FakeDevice((0.0, 0.0, -0.006))
    core = ServoCore(dev, ServoConfig(ramp_s=RAMP_S), local_model=params)
    core.enable_forces()
    core.set_patch(PLANE, 50.0, 0.0, b_h=10.0)
    t = run(core, 0.0, 200, notify_every=10)
    assert dev.displayed[2] == pytest.approx(50.0 * 0.006)
    core.set_patch(PLANE, 150.0, 0.0, b_h=5.0)
    n0 = len(dev.writes)
    run(core, t, 400, notify_every=10)
    forces = [w[2] for w in dev.writes[n0:]]  # forces are on: each is the one displayed
    assert max_step([50.0 * 0.006, *forces]) <= 100.0 * 0.006 / 200 * 1.0001  # 0.6 N over 0.2 s
    assert forces[-1] == pytest.approx(150.0 * 0.006)


def test_a_long_hard_press_comes_down_to_the_continuous_force_without_a_step() -> None:
    """Peak force for moments only: the limit falls to the continuous force, at 1 N/s."""
    dev = FakeDevice((0.0, 0.0, -0.01))  # 10 mm in at 500 N/m: the local model asks 5 N
    dev.limits = replace(dev.limits, max_continuous_force_n=1.75, thermal_time_constant_s=1.0)
    core = make_core(dev)
    core.enable_forces()
    core.set_patch(PLANE, 500.0, 0.0)
    run(core, 0.0, 6000, notify_every=10)
    f = np.array([w[2] for w in dev.writes])  # forces are on: each is the one displayed
    on = int(np.argmax(f >= 5.0 - 1e-9))  # after the safety ramp
    t_peak = -1.0 * math.log(1.0 - (1.75 / 5.0) ** 2)  # the model's budget from cold: 0.13 s
    first_lowered = int(np.argmax(f[on:] < 5.0 - 1e-9))
    assert first_lowered * T == pytest.approx(t_peak, abs=0.02)
    assert np.diff(f[on:]).min() >= -T * 1.0001  # 1 N/s, never a step
    assert f[-1] == pytest.approx(1.75)
    ev = core.status().last_event
    assert ev is not None and "motors warm" in ev.detail


def test_stop_ramps_down_then_disables_the_device() -> None:
    dev, core, t = pressing_core()
    assert dev.enabled
    core.request_stop()
    n0 = len(dev.writes)
    stopped_after = None
    for k in range(200):
        core.notify_link(t)
        if core.tick(t):
            stopped_after = k
            break
        t += T
    assert stopped_after is not None and stopped_after <= int(RAMP_S / T) + 1
    mags = [mag(w) for w in dev.writes[n0 - 1 :]]
    assert max(a - b for a, b in zip(mags, mags[1:], strict=False)) <= STEP * 1.5 + 1e-12
    assert dev.writes[-1] == (0.0, 0.0, 0.0) and not dev.enabled
    assert core.status().stopped


def test_local_model_period_must_match_the_servo_rate() -> None:
    with pytest.raises(ValueError, match="period"):
        ServoCore(
            FakeDevice(),
            ServoConfig(servo_rate_hz=1000.0),
            local_model=LocalModelParams(k_h=100.0, servo_period_s=2e-3),
        )


class FakeClock:
    """Time that advances only when slept on, plus 1 us per reading (so spinning ends)."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        self.t += 1e-6
        return self.t

    def sleep(self, d: float) -> None:
        self.t += max(d, 0.0)


def test_missed_deadlines_are_counted_and_skipped_not_piled_up() -> None:
    clock = FakeClock()
    loop = DeadlineLoop(1e-3, clock=clock, sleep=clock.sleep, spin_s=3e-4, late_tolerance=0.5)
    ticks: list[float] = []

    def tick(now: float) -> bool:
        ticks.append(now)
        if len(ticks) == 11:
            clock.t += 3.4e-3  # one tick takes 3.4 ms
        return False

    loop.run(tick, max_ticks=30)
    assert loop.overruns == 2  # deadlines 11 and 12 missed; 13 (0.4 ms late) runs at once
    start = ticks[0]
    idx = [round((t - start) / 1e-3) for t in ticks]
    assert idx[:11] == list(range(11))
    assert idx[11:] == list(range(13, 32))  # skipped, then back on the integer grid
    for t, k in zip(ticks[12:], idx[12:], strict=True):
        assert abs(t - (start + k * 1e-3)) < 5e-5  # on its deadline, no drift
    gaps = [b - a for a, b in zip(ticks, ticks[1:], strict=False)]
    assert min(gaps) > 0.5e-3  # no burst of catch-up ticks


def test_overruns_show_in_the_servo_status() -> None:
    clock = FakeClock()

    class SlowOnce(FakeDevice):
        calls = 0

        def read(self, t_s: float) -> Vec3:
            SlowOnce.calls += 1
            if SlowOnce.calls == 5:
                clock.t += 5.2e-3  # deadlines 5, 6, 7, 8 pass
            return self.position

    dev = SlowOnce((0.0, 0.0, 0.01))
    core = make_core(dev)
    th = ServoThread(core, clock=clock, sleep=clock.sleep, switch_interval_s=None)
    assert th.run(max_ticks=20) == 20
    st = core.status()
    assert st.counts[HapticError.SERVO_OVERRUN] == 4
    assert st.last_event is not None and st.last_event.kind is HapticError.SERVO_OVERRUN


def test_a_crashing_device_leaves_no_force_on() -> None:
    class Crashing(FakeDevice):
        def read(self, t_s: float) -> Vec3:
            if t_s > 100.05:
                raise RuntimeError("driver bug")
            return self.position

    clock = FakeClock()
    dev = Crashing((0.0, 0.0, -0.005))
    core = make_core(dev, link_timeout_s=math.inf)
    core.enable_forces()
    core.set_patch(PLANE, 300.0, 0.0)
    th = ServoThread(core, clock=clock, sleep=clock.sleep, switch_interval_s=None)
    th.run(max_ticks=1000)
    assert dev.writes[-1] == (0.0, 0.0, 0.0) and not dev.enabled
    assert "driver bug" in (core.status().error or "")


def test_real_thread_runs_and_stops_cleanly() -> None:
    switch_before = sys.getswitchinterval()
    dev = FakeDevice((0.0, 0.0, -0.004))
    core = make_core(dev)
    th = ServoThread(core)
    core.enable_forces()
    th.start()
    th.set_patch(LocalModelUpdate(PLANE, 250.0, 0.0))
    t_end = time.monotonic() + 0.3
    while time.monotonic() < t_end:
        th.notify_link()
        time.sleep(0.02)
    snap = th.latest()
    assert th.running
    assert snap is not None and snap.tick > 0 and snap.servo_rate_hz > 0
    assert snap.in_contact and snap.k_h == 250.0
    assert th.stop()
    assert not th.running
    assert core.status().stopped
    assert dev.writes[-1] == (0.0, 0.0, 0.0) and not dev.enabled
    assert sys.getswitchinterval() == switch_before  # the interpreter is left as it was


class StylusDevice(FakeDevice):
    """A fake device with a stylus button the test presses and releases."""

    has_buttons = True

    def __init__(self, position: Vec3) -> None:
        super().__init__(position)
        self.held = 0

    def buttons(self) -> int:
        return self.held


def test_the_stylus_button_engages_and_disengages_forces_with_ramps() -> None:
    dev = StylusDevice((0.0, 0.0, -0.005))
    core = ServoCore(dev, ServoConfig(ramp_s=RAMP_S, engage_with_button=True))
    core.enable_forces()
    core.set_patch(PLANE, 300.0, 0.0)
    t = run(core, 0.0, 200, notify_every=10)
    assert all(w == (0.0, 0.0, 0.0) for w in dev.writes)  # no force before the first press
    assert not core.status().engaged
    dev.held = 1  # press and hold: engages once, holding does not toggle again
    t = run(core, t, 200, notify_every=10)
    dev.held = 0
    t = run(core, t, 100, notify_every=10)
    assert core.status().engaged and dev.displayed[2] == pytest.approx(1.5)
    mags = [mag(w) for w in dev.writes]
    assert max_step(mags) <= STEP * 1.5 + 1e-12
    dev.held = 1  # the next press disengages: a ramp down, not a jump
    n0 = len(dev.writes)
    run(core, t, 200, notify_every=10)
    mags = [mag(w) for w in dev.writes[n0 - 1 :]]
    assert not core.status().engaged and mags[-1] == 0.0
    assert max_step(mags) <= STEP * 1.5 + 1e-12


def test_without_button_engagement_buttons_are_ignored() -> None:
    dev = StylusDevice((0.0, 0.0, -0.005))
    core = make_core(dev)
    core.enable_forces()
    core.set_patch(PLANE, 300.0, 0.0)
    dev.held = 1
    run(core, 0.0, 200, notify_every=10)
    assert core.status().engaged and dev.displayed[2] == pytest.approx(1.5)


def test_the_object_is_pushed_by_the_coupling_not_by_the_passivity_controllers_damper() -> None:
    """The state a client sends carries the local model's force (Step 3). The passivity
    controller's damper acts on the hand alone: fed to the simulation it closed a second,
    delayed loop through the object, and three PI users on a soft object rang 8.7 mm
    (docs/stability.md)."""
    dev = FakeDevice((0.0, 0.0, -0.005))
    dev.limits = lab_limits(max_velocity_m_s=0.5, max_damping_n_s_per_m=10.0)
    core = ServoCore(dev, ServoConfig(ramp_s=RAMP_S, link_timeout_s=math.inf, passivity=True))
    core.enable_forces()
    core.set_patch(PLANE, 500.0, 0.0)
    t = run(core, 0.0, 200)
    # the surface jumps 4 mm out and the hand gives way under it: the port gives energy
    core.set_patch(make_plane((0.0, 0.0, 0.004), (0.0, 0.0, 1.0)), 500.0, 0.0)
    pushed: list[tuple[float, float]] = []
    for k in range(200):
        dev.position = (0.0, 0.0, -0.005 + 4e-3 * min(k / 100, 1.0))
        core.tick(t + k * T)
        snap = core.latest()
        assert snap is not None
        pushed.append((snap.force_n[2], dev.displayed[2]))
    pc = core.safety.passivity
    assert pc is not None and pc.dissipated_energy_j > 0.0  # the controller did act
    # the object was pushed with the coupling's force, K_h times the penetration...
    for k, (sent, _) in enumerate(pushed[:100]):
        depth = 0.004 + 0.005 - 4e-3 * min(k / 100, 1.0)
        assert sent == pytest.approx(500.0 * depth, rel=1e-9, abs=1e-12)
    # ...while the hand felt less: the damper's share stayed at the device port
    assert any(shown < sent - 0.05 for sent, shown in pushed)
