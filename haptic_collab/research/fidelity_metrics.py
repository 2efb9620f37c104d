"""What a user would notice in each cell of the fidelity benchmark: stability, penetration,
energy, force ripple, and the felt dynamic stiffness over the object's own.

:func:`cell_metrics` takes the benchmark's metrics (:class:`CellMetrics`) from a
:func:`haptic_collab.research.fidelity_1d.simulate` run (or a 3-D cell's record in the same
shape); :func:`felt_response` fits the felt impedance of position-source cells on a sine
trajectory, :func:`felt_stiffness_ratio` its magnitude.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from haptic_collab.research.fidelity_cases import Cell, Run
from haptic_collab.shared.types import FloatArray

#: Probe peak-to-peak [m] during the hold below which a cell counts as stable (docs/fidelity.md).
STABLE_HOLD_P2P_M = 0.5e-3


@dataclass(frozen=True, slots=True)
class CellMetrics:
    """What a user would notice in one cell (docs/fidelity.md), SI-derived units as named.

    Attributes
    ----------
    stable : bool
        Bounded (no runaway) and ``hold_p2p_mm`` below :data:`STABLE_HOLD_P2P_M`.
    hold_p2p_mm : float
        Probe peak to peak [mm] over the trajectory's hold window.
    peak_penetration_mm : float
        Largest ``x - x_s(f)`` [mm], ``x_s(f)`` the depth at which the relaxed object holds the
        force ``f`` (:meth:`ObjectModel.static_depth_m`; ``f / K_o`` for the design model): how
        far the probe went past the surface of the object pushing back with the force the user
        actually feels (0 for an ideal rendering; for a coupling it includes the steady-state
        error).
    steady_state_error_mm : float
        Mean of ``x - x_s(f)`` [mm] over the last half of the hold window (the probe-proxy gap of
        a P coupling, f / K_h; eq. 17's theta for PI).
    energy_out_mj : float
        Energy the device port gave the user over the trajectory's energy window [mJ]
        (``sum -f (x(n+1) - x(n))``); > 0 is active.
    force_ripple_n : float
        Force peak to peak [N] over the hold window.
    """

    stable: bool
    hold_p2p_mm: float
    peak_penetration_mm: float
    steady_state_error_mm: float
    energy_out_mj: float
    force_ripple_n: float

    def to_json(self) -> dict[str, object]:
        """The cell's metric fields of ``haptic bench fidelity --json``."""
        return {
            "stable": self.stable,
            "hold_p2p_mm": self.hold_p2p_mm,
            "peak_penetration_mm": self.peak_penetration_mm,
            "steady_state_error_mm": self.steady_state_error_mm,
            "energy_out_mj": self.energy_out_mj,
            "force_ripple_n": self.force_ripple_n,
        }


def _window(t: FloatArray, w: tuple[float, float]) -> NDArray[np.bool_]:
    return (t >= w[0] - 1e-9) & (t < w[1] - 1e-9)


def cell_metrics(run: Run, cells: Sequence[Cell]) -> list[CellMetrics]:
    """The :class:`CellMetrics` of every cell of a :func:`simulate` run, in order."""
    out: list[CellMetrics] = []
    for i, c in enumerate(cells):
        tr = c.trajectory
        n_i = round(tr.duration_s / (run.t[1] - run.t[0])) if run.t.size > 1 else 1
        t = run.t[:n_i]
        x = run.x[i, :n_i]
        f = run.f[i, :n_i]
        hold = _window(t, tr.hold_window_s)
        half = _window(t, (0.5 * (tr.hold_window_s[0] + tr.hold_window_s[1]), tr.hold_window_s[1]))
        pen = x - c.obj.static_depth_m(c.k_o, f)
        hold_p2p = float(np.ptp(x[hold]))
        ew = _window(t, tr.energy_window_s)
        dx = np.diff(x, append=x[-1])
        energy = float(np.sum(-f[ew] * dx[ew]))
        finite = bool(np.isfinite(x).all() and np.isfinite(f).all())
        stable = finite and not bool(run.runaway[i]) and hold_p2p < STABLE_HOLD_P2P_M
        out.append(
            CellMetrics(
                stable=stable,
                hold_p2p_mm=hold_p2p * 1e3,
                peak_penetration_mm=float(np.max(pen)) * 1e3,
                steady_state_error_mm=float(np.mean(pen[half])) * 1e3,
                energy_out_mj=energy * 1e3,
                force_ripple_n=float(np.ptp(f[hold])),
            )
        )
    return out


#: Felt-stiffness fits over the two halves of the window that differ by more than this fraction
#: are not a steady response (the loop has not settled, or it is growing): no number is reported.
FELT_FIT_TOLERANCE = 0.05

#: Largest distortion of the force over the window (:func:`force_distortion`: the RMS of what the
#: fit leaves over the RMS of the fundamental) at which its fundamental is read as a stiffness.
#: Above 1 the force has more power off the probe's frequency than at it: the hand feels a
#: chatter, and the ratio of the fundamentals says nothing of it (an uncapped passivity
#: controller switching its damping between the force clamp and zero at 3000 N/m, 200 ms each
#: way, read 2.3 times the object at 0.5 Hz and 0.6 times at 1 Hz with distortions of 1.4 and
#: 4.9). The linear renderings stay far below it: in ``haptic bench fidelity --quick`` every
#: read response over the ranked band was at most 0.26 for the local models and 0.63 for any
#: peer (docs/fidelity.md).
FELT_DISTORTION_MAX = 1.0


def _fit(t: FloatArray, y: FloatArray, w: float) -> tuple[complex, float]:
    """The fundamental of ``y`` at ``w`` [rad/s] (offset and drift removed) and the RMS of what
    the fit leaves."""
    f1, rest = _fits(t, y[None, :], w)
    return complex(f1[0]), float(rest[0])


def _fits(t: FloatArray, y: FloatArray, w: float) -> tuple[NDArray[np.complex128], FloatArray]:
    """:func:`_fit` of every row of ``y`` (G, n) sampled at the same ``t`` (n,): one least-squares
    solve for all of them; the fundamentals and the RMS of what each fit leaves, (G,) each."""
    A = np.stack([np.ones_like(t), t - t[0], np.cos(w * t), np.sin(w * t)], axis=1)
    c = np.linalg.lstsq(A, y.T, rcond=None)[0]  # (4, G)
    rest = np.sqrt(np.mean((y.T - A @ c) ** 2, axis=0))
    return c[2] - 1j * c[3], rest


def _distortion(f1: complex, rest: float, f: FloatArray) -> float:
    """The RMS ``rest`` [N] a fit left over the RMS of its fundamental ``f1`` [N] of force ``f``."""
    fund = abs(f1) / math.sqrt(2.0)
    # below rounding of the force, no fundamental
    return rest / fund if fund > 1e-12 * max(1.0, float(np.max(np.abs(f)))) else math.inf


def force_distortion(t: FloatArray, f: FloatArray, freq_hz: float) -> float:
    """How far the force ``f`` [N] sampled at ``t`` [s] is from a sine at ``freq_hz`` [Hz] on an
    offset and a drift: the RMS of the rest over the RMS of that sine (0 for a linear response,
    ``inf`` when it has no fundamental). A multirate staircase adds a little; a force switching
    between two levels adds more than its fundamental (:data:`FELT_DISTORTION_MAX`)."""
    return _distortion(*_fit(t, f, 2.0 * math.pi * freq_hz), f)


def felt_response(run: Run, cells: Sequence[Cell]) -> list[complex | None]:
    """Felt dynamic stiffness over the object's own, ``(dF/dx) / Z_o`` (complex: magnitude and
    phase at the probe frequency), of position-source cells (:func:`felt_trajectory`), in
    order; ``Z_o`` is :meth:`ObjectModel.impedance` at that frequency and depth (K_o for the
    design model), so 1 is an ideal rendering of the object. :func:`felt_stiffness_ratio` is its
    magnitude, its real part the elastic share (a lagging force is partly felt as damping, or,
    lagging by a long delay, as an active push).

    Least-squares fit of ``a + b t + c cos(w t) + d sin(w t)`` to the probe position and to the
    force over the trajectory's hold window (whole cycles of the probe and of every simulation
    rate of the grid; the multirate ripple is not at w and drops out); the ratio of the
    fundamentals over Z_o, as :func:`shared.felt_stiffness.felt_stiffness` computes it exactly for
    the linear loop. None when the cell ran away, the fits over the two halves of the window
    differ by more than :data:`FELT_FIT_TOLERANCE` (not a steady response), the force still
    ripples by more than that fraction of the response's peak to peak while the probe is held
    still before the oscillation (a limit cycle), or the force over the window is distorted beyond
    :data:`FELT_DISTORTION_MAX` (:func:`force_distortion`: a chatter, not a stiffness).

    Raises
    ------
    ValueError
        A cell that is not a position source oscillating at a frequency.
    """
    dt = run.t[1] - run.t[0]
    # cells on the same probe (frequency, windows, length) are fitted together
    groups: dict[tuple[int, float, tuple[float, float], float], list[int]] = defaultdict(list)
    for i, c in enumerate(cells):
        tr = c.trajectory
        if c.hand is not None or tr.sine_hz <= 0.0:
            raise ValueError("felt stiffness needs a position-source cell on a sine trajectory")
        n_i = round(tr.duration_s / dt)
        groups[(n_i, tr.sine_hz, tr.hold_window_s, tr.sine_start_s)].append(i)
    out: list[complex | None] = [None] * len(cells)
    for (n_i, hz, (a, b), start), idx in groups.items():
        t = run.t[:n_i]
        w = 2.0 * math.pi * hz
        x, f = run.x[idx, :n_i], run.f[idx, :n_i]
        z_obj = np.array(
            [cells[i].obj.impedance(cells[i].k_o, hz, cells[i].trajectory.y1_m) for i in idx]
        )
        mid = 0.5 * (a + b)
        ratios = []
        for lo, hi in ((a, b), (a, mid), (mid, b)):
            m = _window(t, (lo, hi))
            x1 = _fits(t[m], x[:, m], w)[0]
            f1, rest = _fits(t[m], f[:, m], w)
            with np.errstate(divide="ignore", invalid="ignore"):
                q = np.where(np.abs(x1) > 0.0, f1 / x1 / z_obj, complex(math.nan))
            if lo == a and hi == b:
                resp = q
                linear = [
                    _distortion(complex(f1[j]), float(rest[j]), f[j, m]) <= FELT_DISTORTION_MAX
                    for j in range(len(idx))
                ]
            ratios.append(np.abs(q))
        whole, h1, h2 = ratios
        steady = (
            np.isfinite(whole)
            & np.isfinite(h1)
            & np.isfinite(h2)
            & (np.abs(h1 - h2) <= FELT_FIT_TOLERANCE * np.maximum(np.abs(whole), 1e-9))
        )
        # a still probe must feel a still force: a limit cycle (the unilateral contact bounds an
        # unstable loop) is periodic too, but it is there before the probe moves
        still = _window(t, (start - 0.5, start))
        ripple = np.ptp(f[:, still], axis=1)
        amp = np.array([cells[i].trajectory.sine_amplitude_m for i in idx])
        quiet = ripple <= FELT_FIT_TOLERANCE * 2.0 * whole * np.abs(z_obj) * amp
        for j, i in enumerate(idx):
            if steady[j] and quiet[j] and linear[j] and not run.runaway[i]:
                out[i] = complex(resp[j])
    return out


def felt_stiffness_ratio(run: Run, cells: Sequence[Cell]) -> list[float | None]:
    """Felt stiffness |dF/dx| / K_o of position-source cells, in order (:func:`felt_response`)."""
    return [None if q is None else abs(q) for q in felt_response(run, cells)]
