"""Felt stiffness |dF/dx| at the probe (shared.felt_stiffness), checked against closed forms: springs
in series for a P local model, the object itself for PI, a damper felt as viscosity."""

from __future__ import annotations

import math

import numpy as np
import pytest

from haptic_collab.shared.felt_stiffness import felt_stiffness, object_stiffness
from haptic_collab.shared.full_loop import DAMPER_FILTER_S, ProxyHold


# ----------------------------------------------------------------------------- felt stiffness
@pytest.mark.parametrize("hold", ["zoh", "foh"])
@pytest.mark.parametrize(("n", "delay"), [(50, 0), (50, 3), (10, 0)])
@pytest.mark.parametrize(("k_o", "k_h"), [(1000.0, 300.0), (300.0, 200.0), (50.0, 40.0)])
def test_p_coupling_feels_like_springs_in_series_at_low_frequency(
    k_o: float, k_h: float, n: int, delay: int, hold: ProxyHold
) -> None:
    felt = felt_stiffness(0.05, k_o=k_o, k_h=k_h, rate_ratio=n, delay_ticks=delay, proxy_hold=hold)
    assert felt.shape == (1,)
    assert felt[0] == pytest.approx(k_h * k_o / (k_h + k_o), rel=5e-3)


@pytest.mark.parametrize("hold", ["zoh", "foh"])
@pytest.mark.parametrize("delay", [0, 2])
@pytest.mark.parametrize(
    ("k_o", "k_h", "i_gain"), [(1000.0, 300.0, 7000.0), (300.0, 100.0, 3000.0)]
)
def test_pi_coupling_feels_the_object_itself_at_low_frequency(
    k_o: float, k_h: float, i_gain: float, delay: int, hold: ProxyHold
) -> None:
    felt = felt_stiffness(
        0.05, k_o=k_o, k_h=k_h, i_gain=i_gain, rate_ratio=50, delay_ticks=delay, proxy_hold=hold
    )
    assert felt[0] == pytest.approx(k_o, rel=0.02)
    # while P with the same K_h feels much softer: the integral is what brings K_o back
    p_only = felt_stiffness(0.05, k_o=k_o, k_h=k_h, rate_ratio=50, delay_ticks=delay)
    assert p_only[0] < 0.8 * k_o


@pytest.mark.parametrize("freq_hz", [0.05, 1.0])
@pytest.mark.parametrize("k_o", [100.0, 1000.0, 5000.0])
def test_simulation_at_servo_rate_with_k_h_near_k_o(k_o: float, freq_hz: float) -> None:
    k_h = 0.99 * k_o
    felt = felt_stiffness(freq_hz, k_o=k_o, k_h=k_h, rate_ratio=1)
    assert felt[0] == pytest.approx(k_h * k_o / (k_h + k_o), rel=5e-3)  # about K_o / 2


def test_felt_stiffness_is_vectorised_over_gains() -> None:
    k_h = np.array([100.0, 300.0, 600.0])
    felt = felt_stiffness(0.05, k_o=1000.0, k_h=k_h)
    assert felt == pytest.approx(k_h * 1000.0 / (k_h + 1000.0), rel=5e-3)
    assert np.all(np.diff(felt) > 0)  # stiffer coupling, stiffer feel


@pytest.mark.parametrize(("k_o", "k_h"), [(1000.0, 300.0), (5000.0, 10.0)])
@pytest.mark.parametrize("b_h", [2.0, 10.0])
def test_probe_damper_is_felt_as_viscosity_not_stiffness(
    k_o: float, k_h: float, b_h: float
) -> None:
    """Quasi-statically F = (K_h + j w B_h) x - K_h p with p = F / K_o, so the damper adds
    j w B_h K_o / (K_h + K_o) (-> j w B_h when K_h << K_o) and leaves the real part alone."""
    f = 0.05
    w = 2.0 * math.pi * f
    with_damper = felt_stiffness(f, k_o=k_o, k_h=k_h, b_h=b_h, complex_response=True)[0]
    without = felt_stiffness(f, k_o=k_o, k_h=k_h, complex_response=True)[0]
    assert (with_damper - without).imag == pytest.approx(b_h * w * k_o / (k_h + k_o), rel=0.01)
    assert with_damper.real == pytest.approx(without.real, rel=1e-3)
    if k_h < 0.01 * k_o:
        assert (with_damper - without).imag == pytest.approx(b_h * w, rel=0.01)


@pytest.mark.parametrize("freq_hz", [0.0, -1.0, 500.0, 2000.0])
def test_felt_stiffness_refuses_frequencies_outside_the_servo_band(freq_hz: float) -> None:
    with pytest.raises(ValueError):
        felt_stiffness(freq_hz, k_o=1000.0, k_h=300.0)


def test_the_objects_own_stiffness_is_the_inverse_of_eq_9() -> None:
    # D(z) = (K_o + B_o (z - 1) / z)^-1 at z = e^{j w N T}: the deformation per newton; its
    # inverse is what a transparent rendering is felt as. A spring (B_o = 0) is K_o at every
    # frequency; a damped one K_o at DC, K_o + 2 B_o at the simulation's Nyquist rate
    freqs = (0.5, 2.0, 8.0, 10.0)
    got = object_stiffness(freqs, k_o=300.0, b_o=[0.0, 200.0], sim_period_s=0.05)
    assert got.shape == (4, 2)
    for f, row in zip(freqs, got, strict=True):
        z = complex(math.cos(2 * math.pi * f * 0.05), math.sin(2 * math.pi * f * 0.05))
        d = 1.0 / (300.0 + 200.0 * (z - 1.0) / z)
        assert row[0] == pytest.approx(300.0)
        assert row[1] == pytest.approx(1.0 / d, rel=1e-12)
    assert got[-1, 1] == pytest.approx(700.0)
    assert abs(object_stiffness((1e-4,), k_o=300.0, b_o=200.0, sim_period_s=0.05)[0, 0]) == (
        pytest.approx(300.0, rel=1e-5)
    )
    for bad in ({"sim_period_s": 0.0}, {"sim_period_s": math.nan}):
        with pytest.raises(ValueError, match="sim_period_s"):
            object_stiffness((1.0,), k_o=300.0, **bad)
    with pytest.raises(ValueError, match="frequencies"):
        object_stiffness((0.0,), k_o=300.0, sim_period_s=0.05)


# ----------------------------------------------------------------- against the stepped loop
def _felt_by_stepping(
    k_o: float,
    k_h: float,
    b_h: float,
    own_gain: float,
    n: int,
    delay: int,
    b_o: float,
    freq_hz: float,
) -> complex:
    """The felt response dF/dx at ``freq_hz``, the probe a position source, by stepping the loop
    tick by tick (a P local model with the filtered probe damper, the simulation sampling the
    force at the last tick of each block, the object of eq. 9, a delay line, zero-order hold)
    and taking the force's fundamental over whole cycles once settled."""
    T = 1e-3
    a_u = T / (T + DAMPER_FILTER_S)
    w = 2.0 * math.pi * freq_hz
    cycle = round(1.0 / (freq_hz * T))
    ticks = n * math.ceil(6 * cycle / n) + cycle * 4
    x_o = 0.0
    line = [0.0] * delay
    p = 0.0
    u, x_last = 0.0, 0.0
    f_sample = 0.0
    fs, xs = [], []
    for i in range(ticks):
        if i > 0 and i % n == 0:
            x_o = (f_sample + b_o * x_o) / (k_o + b_o)
            line.append(x_o - own_gain * f_sample)
            p = line.pop(0)
        x = math.sin(w * i * T)
        u += a_u * ((x - x_last) / T - u)
        x_last = x
        f = k_h * (x - p) + b_h * u
        if i % n == n - 1:
            f_sample = f
        fs.append(f)
        xs.append(x)
    f_tail = np.array(fs[-cycle * 4 :])
    ph = np.exp(-1j * w * T * np.arange(ticks - cycle * 4, ticks))
    return complex(2.0 * np.mean(f_tail * ph) / (2.0 * np.mean(np.array(xs[-cycle * 4 :]) * ph)))


@pytest.mark.parametrize(
    ("k_o", "n", "delay", "b_o"),
    [(300.0, 20, 0, 300.0), (1000.0, 10, 1, 0.0), (100.0, 50, 0, 50.0)],
)
def test_the_felt_response_on_a_damped_object_is_the_stepped_loops(
    k_o: float, n: int, delay: int, b_o: float
) -> None:
    # the plane at the rest surface (K_h = K_o, C_h = 1 / K_o) renders eq. 9's object through
    # the simulation: felt as the stepped loop is, at the bottom and the top of the band
    for f in (1.0, 8.0):
        got = felt_stiffness(
            f, k_o=k_o, k_h=k_o, b_h=1.0, b_o=b_o, own_gain=1.0 / k_o, rate_ratio=n,
            delay_ticks=delay, complex_response=True,
        )[0]  # fmt: skip
        want = _felt_by_stepping(k_o, k_o, 1.0, 1.0 / k_o, n, delay, b_o, f)
        assert got == pytest.approx(want, rel=0.02)
