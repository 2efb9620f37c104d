"""Time-domain passivity observer/controller at the device port (Hannaford and Ryu 2002).

The handle is a kinematic position source (a hand that moves as it likes), so the energy the
environment delivers to the user is computed here independently of the controller, from the forces
it returned and the true displacements: sum f_a(n-1) . (x(n) - x(n-1)).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest

from haptic_collab.shared.passivity import PassivityController, PassivityParams

T = 1e-3
U = (0.6, 0.0, 0.8)  # unit direction of motion: the controller works in 3-D
Vec = tuple[float, float, float]


def _along(s: float) -> Vec:
    return (s * U[0], s * U[1], s * U[2])


def _dot(a: Vec, b: Vec) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _sine(amplitude_m: float, freq_hz: float, n_ticks: int) -> list[float]:
    return [amplitude_m * math.sin(2.0 * math.pi * freq_hz * n * T) for n in range(n_ticks + 1)]


class Run:
    """Outcome of driving a controller with a scripted handle."""

    def __init__(self) -> None:
        self.delivered_j = 0.0  # net energy the device gave the user (ground truth)
        self.max_delivered_j = 0.0
        self.min_observed_j = math.inf
        self.desired: list[Vec] = []
        self.applied: list[Vec] = []
        self.alphas: list[float] = []


def drive(
    pc: PassivityController, s: list[float], force: Callable[[int, list[float]], float]
) -> Run:
    """Move the handle along U through positions s [m]; force(n, s) is the desired force along U."""
    run = Run()
    prev: Vec = (0.0, 0.0, 0.0)
    for n in range(len(s)):
        ds = s[n] - s[n - 1] if n > 0 else 0.0
        run.delivered_j += _dot(prev, _along(ds))
        run.max_delivered_j = max(run.max_delivered_j, run.delivered_j)
        v = _along(ds / T)
        f = _along(force(n, s))
        out = pc.step(*f, *v)
        run.min_observed_j = min(run.min_observed_j, pc.observed_energy_j)
        run.desired.append(f)
        run.applied.append(out)
        run.alphas.append(pc.alpha_n_s_per_m)
        prev = out
    return run


def _pc(**kw: object) -> PassivityController:
    kw.setdefault("max_damping_n_s_per_m", 50.0)
    return PassivityController(PassivityParams(**kw))  # type: ignore[arg-type]


def test_passive_wall_is_left_alone():
    """A sampled spring with Colgate's damping b >= K T / 2 is passive: the PC never touches it."""
    k, b = 2000.0, 2000.0 * T  # b = K T, twice the minimum
    s = _sine(0.001, 4.0, 750)  # three whole cycles at 4 Hz
    pc = _pc(energy_bias_j=0.0)
    run = drive(pc, s, lambda n, s: -k * s[n] - b * (s[n] - s[n - 1]) / T if n else 0.0)
    assert run.min_observed_j >= -1e-12
    assert pc.observed_energy_j == pytest.approx(-run.delivered_j, abs=1e-12)
    assert pc.dissipated_energy_j == 0.0
    assert pc.active_energy_j == 0.0
    assert max(run.alphas) == 0.0
    assert run.applied == run.desired


def test_observer_is_exact_for_the_zero_order_hold():
    """An undamped sampled spring leaks K/2 sum dx^2 to the user: the observer sees exactly that."""
    k = 2000.0
    s = _sine(0.001, 4.0, 500)
    pc = _pc(enabled=False)
    drive(pc, s, lambda n, s: -k * s[n])
    leak = 0.5 * k * sum((s[n] - s[n - 1]) ** 2 for n in range(1, len(s)))
    assert leak > 0.0
    assert pc.observed_energy_j == pytest.approx(0.5 * k * s[-1] ** 2 - leak, rel=1e-9, abs=1e-15)


def _delayed_spring(k: float, delay_ticks: int) -> Callable[[int, list[float]], float]:
    return lambda n, s: -k * s[max(n - delay_ticks, 0)]


def test_delayed_spring_is_made_passive():
    """A spring felt 5 ticks late pumps energy into a 4 Hz, 1 mm hand motion; the PC stops it."""
    s = _sine(0.001, 4.0, 2000)  # 2 s
    env = _delayed_spring(2000.0, 5)
    free = drive(_pc(enabled=False), s, env)
    assert free.delivered_j > 1e-3  # several mJ: a growing buzz on a real device

    bias = 1e-5
    # When E reaches -bias while the spring gives back what it stored, the PC must cancel the
    # spring's force: alpha ~ |f| / |v| ~ 60 N s/m here. With that much damping available the
    # user never receives more than the bias, at any moment.
    pc = _pc(energy_bias_j=bias, max_damping_n_s_per_m=200.0)
    run = drive(pc, s, env)
    assert run.delivered_j <= bias + 1e-6
    assert run.max_delivered_j <= bias + 1e-6  # at no moment, not just at the end
    assert pc.observed_energy_j == pytest.approx(-run.delivered_j, abs=1e-12)
    assert pc.dissipated_energy_j > 1e-3
    assert pc.active_energy_j > 1e-3

    # A device limited to 50 N s/m lets a transient deficit through, and repays it.
    pc = _pc(energy_bias_j=bias, max_damping_n_s_per_m=50.0)
    run = drive(pc, s, env)
    assert max(run.alphas) == 50.0
    assert run.delivered_j <= bias + 1e-6
    assert run.max_delivered_j <= bias + 2e-5


def test_negative_damper_is_made_passive():
    b = 3.0  # N s/m of negative damping: pushes the hand along its motion
    s = _sine(0.002, 2.0, 2000)
    env = lambda n, s: b * (s[n] - s[n - 1]) / T if n else 0.0  # noqa: E731
    free = drive(_pc(enabled=False), s, env)
    assert free.delivered_j > 1e-3
    pc = _pc(energy_bias_j=0.0)
    run = drive(pc, s, env)
    assert run.max_delivered_j <= 1e-6
    assert pc.dissipated_energy_j > 1e-3


def test_disabled_passes_force_through_but_observes():
    s = _sine(0.001, 4.0, 1000)
    pc = _pc(enabled=False)
    run = drive(pc, s, _delayed_spring(2000.0, 5))
    assert run.applied == run.desired
    assert pc.observed_energy_j == pytest.approx(-run.delivered_j, abs=1e-12)
    assert pc.observed_energy_j < -1e-3
    assert pc.active_energy_j > 1e-3  # telemetry: what the user received
    assert pc.dissipated_energy_j == 0.0
    assert max(run.alphas) == 0.0


def test_force_and_damping_stay_within_device_limits():
    s = _sine(0.01, 4.0, 1000)
    pc = _pc(max_damping_n_s_per_m=5.0, max_force_n=2.0)
    run = drive(pc, s, lambda n, s: 200.0 * (s[n] - s[n - 1]) / T if n else 0.0)
    assert max(math.sqrt(_dot(f, f)) for f in run.applied) <= 2.0 + 1e-12
    assert max(run.alphas) == 5.0  # the limit binds: the wanted damping is larger
    assert all(0.0 <= a <= 5.0 for a in run.alphas)
    # The damper's force counts against the limit too: a force across the motion plus damping.
    pc = _pc(max_damping_n_s_per_m=5.0, max_force_n=2.0)
    pc.step(2.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    pc.step(0.0, 2.0, 0.0, 0.1, 0.0, 0.0)  # the last tick gave the user 0.2 mJ
    out = pc.step(0.0, 2.0, 0.0, 0.1, 0.0, 0.0)
    assert math.sqrt(_dot(out, out)) == pytest.approx(2.0)
    assert out[0] < 0.0
    # A desired force beyond the limit is clamped even when nothing is active.
    assert _pc(max_force_n=2.0).step(3.0, 0.0, 4.0, 0.0, 0.0, 0.0) == pytest.approx((1.2, 0.0, 1.6))


def test_zero_or_tiny_velocity_leaves_the_force_alone():
    pc = _pc(max_damping_n_s_per_m=1.0)
    drive(pc, _sine(0.001, 4.0, 300), _delayed_spring(2000.0, 20))
    assert pc.observed_energy_j < 0.0  # the PC could not repay everything (alpha limit)
    assert pc.step(1.0, -2.0, 0.5, 0.0, 0.0, 0.0) == (1.0, -2.0, 0.5)
    assert pc.alpha_n_s_per_m == 0.0
    out = pc.step(1.0, -2.0, 0.5, 1e-160, 0.0, 0.0)  # |v|^2 T underflows: no 0/0
    assert all(math.isfinite(c) for c in out)
    assert pc.alpha_n_s_per_m == 1.0  # the deficit asks for more: the limit applies


def test_release_forgets_energy_so_free_space_is_not_draggy():
    s = _sine(0.001, 4.0, 300)
    for reset_on_release in (True, False):
        pc = _pc(max_damping_n_s_per_m=1.0, reset_on_release=reset_on_release)
        drive(pc, s, _delayed_spring(2000.0, 20))
        assert pc.observed_energy_j < 0.0
        pc.step(0.0, 0.0, 0.0, 0.01, 0.0, 0.0)  # out of contact, hand moving
        out = pc.step(0.0, 0.0, 0.0, 0.01, 0.0, 0.0)
        if reset_on_release:
            assert out == (0.0, 0.0, 0.0)
            assert pc.observed_energy_j == 0.0
        else:
            assert out[0] < 0.0  # drag opposing the motion until the deficit is repaid
    pc.reset()
    assert pc.observed_energy_j == 0.0
    assert pc.alpha_n_s_per_m == 0.0
    assert pc.dissipated_energy_j > 0.0  # totals are telemetry and survive a reset


def test_non_finite_input_raises_and_keeps_state():
    pc = _pc()
    pc.step(1.0, 0.0, 0.0, 0.1, 0.0, 0.0)
    before = pc.observed_energy_j
    with pytest.raises(ValueError, match="finite"):
        pc.step(math.nan, 0.0, 0.0, 0.1, 0.0, 0.0)
    with pytest.raises(ValueError, match="finite"):
        pc.step(1.0, 0.0, 0.0, math.inf, 0.0, 0.0)
    assert pc.observed_energy_j == before


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"max_damping_n_s_per_m": 0.0}, "max_damping"),
        ({"max_damping_n_s_per_m": math.inf}, "max_damping"),
        ({"max_damping_n_s_per_m": math.nan}, "max_damping"),
        ({"max_damping_n_s_per_m": 1.0, "energy_bias_j": -1e-3}, "energy_bias"),
        ({"max_damping_n_s_per_m": 1.0, "energy_bias_j": math.inf}, "energy_bias"),
        ({"max_damping_n_s_per_m": 1.0, "servo_period_s": 0.0}, "servo_period"),
        ({"max_damping_n_s_per_m": 1.0, "servo_period_s": math.nan}, "servo_period"),
        ({"max_damping_n_s_per_m": 1.0, "max_force_n": 0.0}, "max_force"),
        ({"max_damping_n_s_per_m": 1.0, "max_force_n": math.nan}, "max_force"),
        ({"max_damping_n_s_per_m": 1.0, "enabled": 1}, "enabled"),
        ({"max_damping_n_s_per_m": 1.0, "reset_on_release": "yes"}, "reset_on_release"),
    ],
)
def test_bad_parameters_raise(kw, match):
    with pytest.raises(ValueError, match=match):
        PassivityParams(**kw)
