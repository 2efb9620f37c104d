"""The servo's first-order proxy hold, probe damper and passivity layer, as the hand feels them.

ServoCore is driven tick by tick with injected time and a device whose handle follows a script.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest

from haptic_collab.client.servo import ServoCore
from haptic_collab.shared.primitives import make_plane, make_sphere
from tests.support.helpers import (
    SERVO_PERIOD_S,
    SERVO_RAMP_S,
    ScriptedDevice,
    max_step,
    plane_at,
    run,
    scripted_core,
)

T = SERVO_PERIOD_S
RAMP_S = SERVO_RAMP_S
RAMP_TICKS = round(RAMP_S / T)
SETTLE = RAMP_TICKS + 10  # ticks after which the safety gain is 1
K_H = 300.0
ENCODER_M = 23e-6  # one Phantom Desktop encoder count

PLANE = make_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0))  # outward +z: depth is -z


def settled_core() -> tuple[ScriptedDevice, ServoCore]:
    """A handle 5 mm into PLANE, at rest, felt through K_H with the safety gain up to 1."""
    dev = ScriptedDevice(lambda n: -0.005)
    core = scripted_core(dev)
    core.set_patch(PLANE, K_H, 0.0)
    run(core, SETTLE)
    return dev, core


# ------------------------------------------------------------------------------- proxy hold
HOLD = 50


@pytest.mark.parametrize("hold_ticks", [HOLD, 7])
def test_foh_slides_the_force_linearly_to_the_new_surface(hold_ticks: int) -> None:
    dev, core = settled_core()
    assert dev.fz[-1] == pytest.approx(K_H * 0.005)  # 1.5 N
    core.set_patch(plane_at(0.002), K_H, 0.0, proxy_hold="foh", hold_ticks=hold_ticks)
    n0 = len(dev.fz)
    run(core, hold_ticks + 20)
    after = dev.fz[n0:]
    jump = K_H * 0.002  # 0.6 N in all
    for i, f in enumerate(after):
        expected = K_H * 0.005 + jump * min(1.0, (i + 1) / hold_ticks)
        assert f == pytest.approx(expected, abs=1e-9), i
    assert max_step(dev.fz[n0 - 1 :]) <= jump / hold_ticks + 1e-9
    assert after[-1] == pytest.approx(K_H * 0.007)


def test_zoh_steps_to_the_new_surface_at_once() -> None:
    dev, core = settled_core()
    core.set_patch(plane_at(0.002), K_H, 0.0, proxy_hold="zoh", hold_ticks=HOLD)
    n0 = len(dev.fz)
    run(core, 5)
    assert dev.fz[n0] - dev.fz[n0 - 1] == pytest.approx(K_H * 0.002)
    assert dev.fz[n0:] == pytest.approx([K_H * 0.007] * 5)


def test_foh_then_the_next_patch_slides_from_where_the_last_one_ended() -> None:
    """Patches every simulation period (the hold's length): the force is a continuous ramp."""
    dev, core = settled_core()
    n0 = len(dev.fz)
    for k in range(1, 4):  # the surface moves out 1 mm per period
        core.set_patch(plane_at(0.001 * k), K_H, 0.0, proxy_hold="foh", hold_ticks=HOLD)
        run(core, HOLD)
    forces = dev.fz[n0 - 1 :]
    steps = [b - a for a, b in zip(forces, forces[1:], strict=False)]
    assert steps == pytest.approx([K_H * 0.001 / HOLD] * len(steps), abs=1e-9)
    assert forces[-1] == pytest.approx(K_H * 0.008)


@pytest.mark.parametrize("after_ticks", [1, 20, 49])
def test_foh_patch_arriving_mid_slide_slides_on_from_where_the_proxy_is(after_ticks: int) -> None:
    """Network jitter: the next patch comes before the slide to the last one is over. The proxy
    must go on from where it is (the blend reached), never jump back to the last target: no force
    step larger than the new slide's per-tick increment, and the new surface reached N ticks on."""
    dev, core = settled_core()
    core.set_patch(plane_at(0.002), K_H, 0.0, proxy_hold="foh", hold_ticks=HOLD)
    run(core, after_ticks)
    reached = 0.002 * after_ticks / HOLD  # where the first slide has got to [m]
    f_before = dev.fz[-1]
    assert f_before == pytest.approx(K_H * (0.005 + reached), abs=1e-9)
    core.set_patch(plane_at(0.004), K_H, 0.0, proxy_hold="foh", hold_ticks=HOLD)
    n0 = len(dev.fz)
    run(core, HOLD + 10)
    after = dev.fz[n0:]
    per_tick = K_H * (0.004 - reached) / HOLD  # the new slide's increment [N]
    for i, f in enumerate(after):
        expected = K_H * (0.005 + reached + (0.004 - reached) * min(1.0, (i + 1) / HOLD))
        assert f == pytest.approx(expected, abs=1e-9), i
    # (jumping back to the last target first would be a step of K_H * (2 mm - reached))
    assert max_step(dev.fz[n0 - 1 :]) <= per_tick + 1e-9
    assert after[-1] == pytest.approx(K_H * 0.009)


def test_foh_patches_every_few_ticks_keep_the_force_continuous() -> None:
    """Patches bunched by jitter (every 7 ticks instead of 50) onto a sphere growing 1 mm each:
    each new slide starts at the blend, so the force moves in small steps only."""
    center = (0.0, 0.0, -0.1)
    dev = ScriptedDevice(lambda n: -0.005)  # 5 mm inside a 100 mm sphere
    core = scripted_core(dev)
    core.set_patch(make_sphere(center, 0.1), K_H, 0.0)
    run(core, SETTLE)
    n0 = len(dev.fz)
    for k in range(1, 6):
        core.set_patch(make_sphere(center, 0.1 + 0.001 * k), K_H, 0.0, proxy_hold="foh",
                       hold_ticks=HOLD)  # fmt: skip
        run(core, 7)
    run(core, 2 * HOLD)
    forces = dev.fz[n0 - 1 :]
    # the largest slide covers at most 5 mm over HOLD ticks
    assert max_step(forces) <= K_H * 0.005 / HOLD + 1e-9
    assert forces[-1] == pytest.approx(K_H * 0.010, abs=1e-9)


def test_zoh_patch_mid_foh_slide_steps_at_once() -> None:
    """A zero-order-hold patch replaces the surface at once, even mid-slide (that is zoh)."""
    dev, core = settled_core()
    core.set_patch(plane_at(0.002), K_H, 0.0, proxy_hold="foh", hold_ticks=HOLD)
    run(core, 20)
    core.set_patch(plane_at(0.004), K_H, 0.0, proxy_hold="zoh", hold_ticks=HOLD)
    n0 = len(dev.fz)
    run(core, 5)
    assert dev.fz[n0:] == pytest.approx([K_H * 0.009] * 5)


# ----------------------------------------------------------------------------------- damper
V = 0.02  # m/s, a slow push
B_H = 10.0


def _moving(start_depth_m: float, depth_rate_m_s: float) -> Callable[[int], float]:
    """Depth start_depth until the gain has ramped, then changing at depth_rate [m/s]."""
    return lambda n: -(start_depth_m + depth_rate_m_s * T * max(0, n - SETTLE))


def _extra_force(depth_rate: float, b_h: float, *, start: float, ticks: int = 120) -> list[float]:
    """Rendered force minus K_h * depth, from 60 ticks (12 filter time constants) into the motion."""
    dev = ScriptedDevice(_moving(start, depth_rate))
    core = scripted_core(dev)
    patch = core.set_patch(PLANE, K_H, 0.0, b_h=b_h)
    run(core, SETTLE + ticks)
    assert patch.b_h <= dev.limits.max_damping_n_s_per_m
    return [f - K_H * -z for f, z in zip(dev.fz, dev.z, strict=True)][SETTLE + 60 :]


def test_damper_adds_b_h_times_speed_when_pressing_in() -> None:
    extra = _extra_force(+V, B_H, start=0.002)
    assert extra == pytest.approx([B_H * V] * len(extra), abs=1e-4)  # 0.2 N


def test_damper_subtracts_b_h_times_speed_when_backing_out() -> None:
    extra = _extra_force(-V, B_H, start=0.008)
    assert extra == pytest.approx([-B_H * V] * len(extra), abs=1e-4)


def test_without_a_damper_the_force_is_the_spring_alone_at_any_speed() -> None:
    extra = _extra_force(+V, 0.0, start=0.002)
    assert extra == pytest.approx([0.0] * len(extra), abs=1e-9)


@pytest.mark.parametrize("depth_rate", [+V, -V, 0.1])
def test_damper_gives_nothing_out_of_contact(depth_rate: float) -> None:
    dev = ScriptedDevice(_moving(-0.010, depth_rate))  # 10 mm outside, moving
    core = scripted_core(dev)
    core.set_patch(PLANE, K_H, 0.0, b_h=B_H)
    run(core, SETTLE + 80)  # at 0.1 m/s it stays 2 mm outside
    assert all(z > 0.0 for z in dev.z)
    assert all(w == (0.0, 0.0, 0.0) for w in dev.writes)


def test_damper_never_pulls_the_probe_into_the_surface() -> None:
    """Backing out at 0.1 m/s from 3 mm: K_h e - B_h v < 0 near the surface; the force stops at 0."""
    dev = ScriptedDevice(_moving(0.003, -0.1))
    core = scripted_core(dev)
    core.set_patch(PLANE, K_H, 0.0, b_h=B_H)
    run(core, SETTLE + 60)
    assert min(dev.fz) >= 0.0
    # the clamp is engaged: ticks still in contact (spring alone would push) but no force
    clamped = [
        i for i, (z, f) in enumerate(zip(dev.z, dev.fz, strict=True)) if z < 0.0 and f == 0.0
    ]
    assert any(i > SETTLE for i in clamped)


def test_one_count_encoder_dither_at_rest_does_not_buzz() -> None:
    """B_h * count / T = 0.23 N per tick from the raw backward difference; the filter keeps the
    force steps of a probe dithering by one count far below that."""
    dev = ScriptedDevice(lambda n: -0.005 + (ENCODER_M if n % 2 else 0.0))
    core = scripted_core(dev)
    core.set_patch(PLANE, K_H, 0.0, b_h=B_H)
    run(core, SETTLE + 200)
    forces = dev.fz[SETTLE:]
    assert max_step(forces) < 0.1
    assert B_H * ENCODER_M / T > 0.1  # what the unfiltered damper would do
    # and the damper does not bias the force at rest
    mean = sum(forces) / len(forces)
    assert mean == pytest.approx(K_H * (0.005 - ENCODER_M / 2), abs=0.01)


def test_damper_above_the_device_maximum_is_clamped() -> None:
    extra = _extra_force(+V, 50.0, start=0.002)  # asks 50 N*s/m, the device allows 10
    assert extra == pytest.approx([10.0 * V] * len(extra), abs=1e-4)
    core = scripted_core(ScriptedDevice())
    assert core.set_patch(PLANE, K_H, 0.0, b_h=50.0).b_h == 10.0
    assert core.set_patch(PLANE, K_H, 0.0, b_h=3.0).b_h == 3.0


def test_a_device_without_virtual_damping_gets_no_damper() -> None:
    dev = ScriptedDevice(_moving(0.002, V), max_damping_n_s_per_m=0.0)
    core = scripted_core(dev)
    assert core.set_patch(PLANE, K_H, 0.0, b_h=B_H).b_h == 0.0
    run(core, SETTLE + 100)
    extra = [f - K_H * -z for f, z in zip(dev.fz, dev.z, strict=True)][SETTLE:]
    assert extra == pytest.approx([0.0] * len(extra), abs=1e-9)


@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf])
def test_bad_damper_or_hold_is_refused(bad: float) -> None:
    core = scripted_core(ScriptedDevice())
    with pytest.raises(ValueError):
        core.set_patch(PLANE, K_H, 0.0, b_h=bad)
    with pytest.raises(ValueError):
        core.set_patch(PLANE, K_H, 0.0, proxy_hold="soh")
    with pytest.raises(ValueError):
        core.set_patch(PLANE, K_H, 0.0, proxy_hold="foh", hold_ticks=0)


# ------------------------------------------------------------------------------- passivity
def test_passivity_status_reports_the_energy_of_a_press() -> None:
    """Pressing from 2 to 4 mm at 0.02 m/s into K_h = 300 N/m with B_h = 10 N*s/m: the user does
    K_h (e2^2 - e1^2) / 2 + B_h v (e2 - e1) = 1.8 + 0.4 mJ of work, all absorbed."""
    depth_rate, ticks = V, 100  # 2 mm
    dev = ScriptedDevice(_moving(0.002, depth_rate))
    core = scripted_core(dev, passivity=True)
    core.set_patch(PLANE, K_H, 0.0, b_h=B_H)
    run(core, SETTLE + ticks)
    pas = core.status().passivity
    assert pas is not None
    assert set(pas) == {"observed_j", "dissipated_j", "active_j"}
    assert all(math.isfinite(v) for v in pas.values())
    work = K_H * (0.004**2 - 0.002**2) / 2 + B_H * depth_rate * 0.002
    assert pas["observed_j"] == pytest.approx(work, rel=0.05)
    assert pas["dissipated_j"] == pytest.approx(0.0, abs=1e-9)  # a passive wall needs no help
    assert pas["active_j"] >= 0.0
    assert core.status().as_dict()["passivity"] == pas


def test_passivity_status_is_none_when_off_or_when_the_device_cannot_damp() -> None:
    core = scripted_core(ScriptedDevice())
    core.set_patch(PLANE, K_H, 0.0)
    run(core, 5)
    assert core.status().passivity is None
    assert core.status().as_dict()["passivity"] is None
    no_damping = scripted_core(ScriptedDevice(max_damping_n_s_per_m=0.0), passivity=True)
    assert no_damping.status().passivity is None
