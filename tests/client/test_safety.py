"""The safety supervisor alone: when forces may be on, how the gain ramps, how large a force gets.

No device, no thread, no clock: each test feeds the tick's inputs and reads the gain and events.
"""

from __future__ import annotations

import math

import pytest

from haptic_collab.client.devices.base import DeviceLimits, HapticError
from haptic_collab.client.safety import SafetySupervisor
from haptic_collab.client.servo import ServoConfig

T = 1e-3
RAMP_S = 0.05
STEP = T / RAMP_S  # gain change per tick
RAMP_TICKS = round(RAMP_S / T)
VMAX = 0.5  # [m/s]
FMAX = 7.9  # [N]


def limits(**kw: float) -> DeviceLimits:
    args: dict = dict(
        max_force_n=FMAX,
        max_stiffness_n_per_m=1000.0,
        max_velocity_m_s=VMAX,
        damping_n_s_per_m=0.5,
        workspace_min_m=(-1.0, -1.0, -1.0),
        workspace_max_m=(1.0, 1.0, 1.0),
    )
    args.update(kw)
    return DeviceLimits(**args)


def supervisor(lim: DeviceLimits | None = None, **cfg: object) -> SafetySupervisor:
    config = ServoConfig(ramp_s=RAMP_S, **cfg)  # type: ignore[arg-type]
    return SafetySupervisor(lim if lim is not None else limits(), config)


def ready(**cfg: object) -> SafetySupervisor:
    """Enabled, with a patch just handed over at t = 0."""
    sup = supervisor(None, **cfg)
    sup.enable()
    sup.patch_arrived(0.0)
    return sup


class Ticker:
    """Drives a supervisor tick by tick; records the gain of each tick."""

    def __init__(self, sup: SafetySupervisor) -> None:
        self.sup = sup
        self.n = 0
        self.scales: list[float] = []

    @property
    def t(self) -> float:
        return self.n * T

    def run(
        self,
        ticks: int,
        *,
        link: bool = True,
        pressed: bool = False,
        fault: str | None = None,
        position_ok: bool = True,
        speed_m_s: float = 0.0,
    ) -> float:
        for _ in range(ticks):
            if link:
                self.sup.notify_link(self.t)
            s = self.sup.update(self.t, pressed, fault, position_ok, speed_m_s * speed_m_s)
            self.scales.append(s)
            self.n += 1
        return self.scales[-1]


def assert_linear(scales: list[float], step: float) -> None:
    """Consecutive gains differ by exactly ``step`` (signed) until the end stop."""
    for a, b in zip(scales, scales[1:], strict=False):
        end = 1.0 if step > 0 else 0.0
        assert b == pytest.approx(min(a + step, 1.0) if step > 0 else max(a + step, 0.0))
        if b == end:
            break


def test_forces_stay_off_until_enabled_and_a_patch_arrived() -> None:
    sup = supervisor()
    tk = Ticker(sup)
    assert tk.run(100) == 0.0 and not sup.want  # neither
    sup.enable()
    assert tk.run(100) == 0.0 and not sup.want  # enabled, no patch
    sup.patch_arrived(tk.t)
    assert tk.run(1) == pytest.approx(STEP) and sup.want and sup.ramping
    assert tk.run(RAMP_TICKS) == 1.0 and not sup.ramping


def test_link_timeout_ramps_down_linearly_and_back_only_with_a_new_patch() -> None:
    sup = ready(link_timeout_s=0.1)
    tk = Ticker(sup)
    assert tk.run(RAMP_TICKS + 5) == 1.0
    silent_from = tk.t
    # silence: full force until the timeout, then a linear ramp to zero, one LINK_LOST
    tk.scales.clear()
    tk.run(100 + RAMP_TICKS + 20, link=False)
    first_off = next(i for i, s in enumerate(tk.scales) if s < 1.0)
    assert first_off * T == pytest.approx(0.1, abs=1.5 * T)  # the last pong was 1 tick before
    assert_linear(tk.scales[first_off - 1 :], -STEP)
    assert tk.scales[-1] == 0.0
    assert sup.counts[HapticError.LINK_LOST] == 1 and sup.need_patch and not sup.link_ok
    assert sup.last_event is not None and sup.last_event.kind is HapticError.LINK_LOST
    assert sup.last_event.t_s == pytest.approx(silent_from + first_off * T)
    # a pong alone does not bring forces back: the old patch is stale
    assert tk.run(50) == 0.0 and sup.link_ok
    # a new patch does, ramping up linearly
    sup.patch_arrived(tk.t)
    tk.scales.clear()
    tk.run(RAMP_TICKS + 5)
    assert tk.scales[0] == pytest.approx(STEP)
    assert_linear(tk.scales, STEP)
    assert tk.scales[-1] == 1.0
    assert sup.counts[HapticError.LINK_LOST] == 1


def test_velocity_limit_has_hysteresis() -> None:
    sup = ready(velocity_resume_ratio=0.8, link_timeout_s=math.inf)
    tk = Ticker(sup)
    assert tk.run(RAMP_TICKS + 1) == 1.0
    assert tk.run(1, speed_m_s=0.99 * VMAX) == 1.0 and not sup.overspeed  # under the limit
    tk.run(1, speed_m_s=1.01 * VMAX)
    assert sup.overspeed and not sup.want
    assert sup.counts[HapticError.VELOCITY_LIMIT] == 1
    # between the resume speed and the limit: still withheld, ramping down, no new event
    tk.run(RAMP_TICKS + 5, speed_m_s=0.9 * VMAX)
    assert tk.scales[-1] == 0.0 and sup.overspeed
    assert sup.counts[HapticError.VELOCITY_LIMIT] == 1
    # below the resume speed: forces come back
    tk.run(1, speed_m_s=0.79 * VMAX)
    assert not sup.overspeed and sup.want and tk.scales[-1] == pytest.approx(STEP)
    # a second episode counts again
    tk.run(1, speed_m_s=2.0 * VMAX)
    assert sup.counts[HapticError.VELOCITY_LIMIT] == 2


def test_a_device_fault_ramps_to_zero_and_back_when_it_clears() -> None:
    sup = ready(link_timeout_s=math.inf)
    tk = Ticker(sup)
    assert tk.run(RAMP_TICKS + 1) == 1.0
    tk.scales.clear()
    tk.run(RAMP_TICKS + 10, fault="unplugged")
    assert tk.scales[0] == pytest.approx(1.0 - STEP)
    assert_linear(tk.scales, -STEP)
    assert tk.scales[-1] == 0.0
    assert sup.fault == "unplugged" and sup.counts[HapticError.DEVICE_FAULT] == 1  # once
    assert sup.last_event is not None and sup.last_event.detail == "unplugged"
    tk.scales.clear()
    tk.run(RAMP_TICKS + 1)
    assert sup.fault is None
    assert_linear(tk.scales, STEP)
    assert tk.scales[-1] == 1.0


def test_a_non_finite_position_is_a_device_fault() -> None:
    sup = ready(link_timeout_s=math.inf)
    tk = Ticker(sup)
    tk.run(RAMP_TICKS + 1)
    assert tk.run(1, position_ok=False) == pytest.approx(1.0 - STEP)
    assert sup.fault == "device reported a non-finite position" and not sup.want
    assert sup.counts[HapticError.DEVICE_FAULT] == 1


def test_the_button_engages_and_disengages_forces() -> None:
    sup = ready(link_timeout_s=math.inf, engage_with_button=True)
    tk = Ticker(sup)
    assert tk.run(100) == 0.0 and not sup.engaged  # enabled and patched, not engaged
    tk.run(30, pressed=True)  # held down: one toggle, not one per tick
    assert sup.engaged and tk.scales[-1] == pytest.approx(min(1.0, 30 * STEP))
    tk.run(RAMP_TICKS)
    assert tk.scales[-1] == 1.0 and sup.engaged
    tk.run(3, pressed=True)  # next press: disengage, ramping down
    assert not sup.engaged and tk.scales[-1] == pytest.approx(1.0 - 3 * STEP)
    tk.run(RAMP_TICKS)
    assert tk.scales[-1] == 0.0


def test_without_button_engagement_the_button_is_ignored() -> None:
    sup = ready(link_timeout_s=math.inf)
    tk = Ticker(sup)
    tk.run(RAMP_TICKS + 1, pressed=True)
    tk.run(5)
    tk.run(5, pressed=True)
    assert sup.engaged and tk.scales[-1] == 1.0


def test_disable_and_stop_ramp_to_zero() -> None:
    sup = ready(link_timeout_s=math.inf)
    tk = Ticker(sup)
    tk.run(RAMP_TICKS + 1)
    sup.disable()
    tk.scales.clear()
    tk.run(RAMP_TICKS + 1)
    assert_linear(tk.scales, -STEP)
    assert tk.scales[-1] == 0.0 and not sup.want
    sup.enable()
    assert tk.run(RAMP_TICKS + 1) == 1.0
    sup.request_stop()
    assert tk.run(RAMP_TICKS + 1) == 0.0 and sup.stopping and not sup.want
    sup.zero()
    assert sup.scale == 0.0


def test_output_clamps_at_the_device_max_and_counts_once_per_episode() -> None:
    sup = ready(link_timeout_s=math.inf)
    tk = Ticker(sup)
    tk.run(RAMP_TICKS + 1)
    n = (0.6, 0.0, 0.8)
    fx, fy, fz, fo = sup.output(2.0, *n, 0.0, 0.0, 0.0, tk.t, True)
    assert (fx, fy, fz) == pytest.approx((1.2, 0.0, 1.6)) and fo == 2.0 and not sup.limited
    for _ in range(3):
        fx, fy, fz, fo = sup.output(100.0, *n, 0.0, 0.0, 0.0, tk.t, True)
    assert fo == FMAX and math.hypot(fx, fy, fz) == pytest.approx(FMAX) and sup.limited
    assert sup.counts[HapticError.FORCE_LIMIT] == 1
    sup.output(1.0, *n, 0.0, 0.0, 0.0, tk.t, True)
    sup.output(-100.0, *n, 0.0, 0.0, 0.0, tk.t, True)  # a pull is clamped too
    assert sup.counts[HapticError.FORCE_LIMIT] == 2
    # the safety gain scales the clamped force
    sup.disable()
    s = tk.run(10)
    assert sup.output(100.0, *n, 0.0, 0.0, 0.0, tk.t, True)[3] == pytest.approx(FMAX * s)


def _engaged_with_thermal_limit() -> tuple[SafetySupervisor, Ticker]:
    """A supervisor with forces on, for a device with a 2 N continuous force and tau = 1 s."""
    lim = limits(max_continuous_force_n=2.0, thermal_time_constant_s=1.0)
    sup = SafetySupervisor(lim, ServoConfig(ramp_s=RAMP_S, link_timeout_s=math.inf))
    sup.enable()
    sup.patch_arrived(0.0)
    tk = Ticker(sup)
    tk.run(RAMP_TICKS + 1)
    return sup, tk


def test_a_held_peak_force_falls_to_the_continuous_force() -> None:
    sup, tk = _engaged_with_thermal_limit()
    assert sup.thermal is not None
    out = []
    for _ in range(10_000):  # 10 s asking for 50 N
        tk.run(1)
        out.append(sup.output(50.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, tk.t, True)[2])
    assert out[0] == FMAX  # the peak first
    assert out[-1] == pytest.approx(2.0)  # then the continuous force
    assert all(b <= a + 1e-12 for a, b in zip(out, out[1:], strict=False))  # never steps up
    assert max(a - b for a, b in zip(out, out[1:], strict=False)) < 0.01  # nor down
    assert sup.counts[HapticError.FORCE_LIMIT] == 1  # one episode
    assert sup.last_event is not None and sup.last_event.detail.startswith("local model force")
    # a new episode while the motors are still warm says so
    sup.output(0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, tk.t, True)
    assert sup.output(50.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, tk.t, True)[2] < 2.1
    assert sup.counts[HapticError.FORCE_LIMIT] == 2
    assert "motors warm" in sup.last_event.detail


def test_forces_not_displayed_do_not_heat_the_motors() -> None:
    sup, tk = _engaged_with_thermal_limit()
    for _ in range(5000):
        sup.output(50.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, tk.t, False)
    assert sup.thermal is not None and sup.thermal.heat == 0.0
    assert sup.thermal.limit_n == FMAX


def test_the_passivity_controller_damps_an_active_port_and_is_off_without_damping() -> None:
    lim = limits(max_damping_n_s_per_m=10.0)
    on = SafetySupervisor(lim, ServoConfig(ramp_s=RAMP_S, link_timeout_s=math.inf, passivity=True))
    off = SafetySupervisor(limits(), ServoConfig(ramp_s=RAMP_S, passivity=True))  # no damping
    assert off.passivity is None and off.passivity_energies() is None
    assert on.passivity is not None
    on.enable()
    on.patch_arrived(0.0)
    tk = Ticker(on)
    tk.run(RAMP_TICKS + 1)
    # an active port: the force pushes along the motion and grows (energy flows to the user)
    d = 1e-5  # 10 mm/s outward along +z
    written = []
    for k in range(2000):
        fz = on.output(0.5 + 1e-3 * k, 0.0, 0.0, 1.0, 0.0, 0.0, d, tk.t, True)[2]
        written.append(fz)
    energies = on.passivity_energies()
    assert energies is not None and set(energies) == {"observed_j", "dissipated_j", "active_j"}
    assert energies["dissipated_j"] > 0.0
    assert written[-1] < 0.5 + 1e-3 * 1999  # the controller took force off
