"""One-dimensional multirate simulation of the loop of Fig. 2-4, with the client's own local model.

A servo loop at period T runs :class:`shared.local_model.LocalModel` (the very code the client's
servo thread runs) on the penetration ``e = x_h - x_o`` along the contact normal. The object runs at
N*T: every N servo ticks it samples the force of servo tick ``sample_tick`` of the previous block
(0 is the decimator S_N of section 2.2; a networked simulation taking the latest force, Step 3 of
section 6, samples a later tick), computes its new surface position, and
that position reaches the servo loop ``1 + delay_ticks`` simulation ticks after the force was
sampled, held constant in between (zero-order hold, eq. 1).

Coordinates: depth along the inward normal [m]. ``x_h`` is the probe depth, ``x_o`` the surface
(proxy) depth, both 0 at the undeformed surface; the force [N] pushes the object inward.

Object models at the slow rate (force sampled at tick k, position out at tick k+1):

- elastic, eq. (6): ``x_o(k+1) = F(k) / K_o``;
- visco-elastic, eq. (9): ``x_o(k+1) = (F(k) + B_o x_o(k)) / (K_o + B_o)``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from haptic_collab.shared.local_model import LocalModel
from haptic_collab.shared.rates import Rates
from haptic_collab.shared.types import FloatArray


@dataclass(frozen=True)
class Trace:
    """Time series of a 1-D multirate run, one row per servo tick.

    Attributes
    ----------
    t_s : (n,) float [s]
    probe_m : (n,) float [m]  probe depth x_h
    proxy_m : (n,) float [m]  surface depth x_o seen by the servo loop
    force_n : (n,) float [N]  local model force
    integral_n : (n,) float [N]  integral force of the local model
    sim_period_s : float [s]  N*T
    """

    t_s: FloatArray
    probe_m: FloatArray
    proxy_m: FloatArray
    force_n: FloatArray
    integral_n: FloatArray
    sim_period_s: float


def simulate(
    local_model: LocalModel,
    probe_m: Callable[[int], float] | FloatArray,
    *,
    k_o: float,
    n_ticks: int,
    damping: float = 0.0,
    sim_rate_hz: float = 20.0,
    delay_ticks: int = 0,
    sample_tick: int = 0,
) -> Trace:
    """Run the multirate loop for ``n_ticks`` servo ticks.

    Parameters
    ----------
    local_model : LocalModel
        The local model, stepped once per servo tick (its own ``servo_period_s`` sets T).
    probe_m : callable (servo tick -> depth [m]) or (n_ticks,) array
        The probe trajectory x_h.
    k_o : float
        Object stiffness [N/m].
    n_ticks : int
        Servo ticks to run.
    damping : float
        Object damping b [N*s/m]; B_o = b * sim_rate (eq. 9).
    sim_rate_hz : float
        Simulation rate [Hz]; the servo rate must be a whole multiple of it.
    delay_ticks : int
        Extra whole simulation ticks of delay before a new surface reaches the servo loop.
    sample_tick : int
        Servo tick of each block whose force the simulation samples (0: the paper's decimator,
        N-1: the last force before the next simulation step).

    Raises
    ------
    ValueError
        Inconsistent rates, non-positive stiffness, negative delay.
    """
    period = local_model.params.servo_period_s
    n = Rates(1.0 / period, sim_rate_hz).ratio
    if not k_o > 0.0:
        raise ValueError(f"k_o must be > 0, got {k_o!r}")
    if delay_ticks < 0:
        raise ValueError(f"delay_ticks must be >= 0, got {delay_ticks}")
    if not 0 <= sample_tick < n:
        raise ValueError(f"sample_tick must be in [0, {n}), got {sample_tick}")
    b_o = damping * sim_rate_hz
    if callable(probe_m):
        xh = np.array([probe_m(i) for i in range(n_ticks)], dtype=float)
    else:
        xh = np.asarray(probe_m, dtype=float)[:n_ticks]
    xo_out = np.empty(n_ticks)
    f_out = np.empty(n_ticks)
    s_out = np.empty(n_ticks)
    pipeline: deque[float] = deque([0.0] * delay_ticks)
    x_obj = 0.0  # the object's own surface position (simulation side)
    x_seen = 0.0  # the surface position the servo loop renders against
    f_sample = 0.0
    for i in range(n_ticks):
        if i % n == 0:
            if i > 0:
                x_obj = (f_sample + b_o * x_obj) / (k_o + b_o)
                pipeline.append(x_obj)
                x_seen = pipeline.popleft()
        f = local_model.step(xh[i] - x_seen)
        if i % n == sample_tick:
            f_sample = f
        xo_out[i] = x_seen
        f_out[i] = f
        s_out[i] = local_model.integral_n
    return Trace(
        t_s=np.arange(n_ticks, dtype=np.float64) * period,
        probe_m=xh,
        proxy_m=xo_out,
        force_n=f_out,
        integral_n=s_out,
        sim_period_s=n * period,
    )


@dataclass(frozen=True)
class StepMetrics:
    """Step-response figures of merit of a :class:`Trace`.

    Attributes
    ----------
    settled : bool
        The proxy stays within the band around its final value over the last quarter of the run
        and the run did not blow up.
    settling_time_s : float or None
        First time after which the proxy stays within ``band`` of its final value (None if it
        never settles).
    final_proxy_m : float
        Mean proxy depth over the last simulation tick [m].
    steady_state_ratio : float or None
        x_o / x_h at the end (None when not settled).
    steady_state_error_m : float or None
        x_h - x_o at the end (None when not settled).
    overshoot : float or None
        (max x_o - final) / final (None when not settled).
    """

    settled: bool
    settling_time_s: float | None
    final_proxy_m: float
    steady_state_ratio: float | None
    steady_state_error_m: float | None
    overshoot: float | None


def step_metrics(trace: Trace, *, t_step_s: float = 0.0, band: float = 0.02) -> StepMetrics:
    """Settling time (to within ``band`` of the final value), ratio and overshoot after a step.

    The step happens at ``t_step_s``; the final value is the mean over the last simulation tick.
    """
    per_block = max(1, round(trace.sim_period_s / (trace.t_s[1] - trace.t_s[0])))
    final = float(np.mean(trace.proxy_m[-per_block:]))
    after = trace.t_s >= t_step_s
    xo = trace.proxy_m[after]
    t = trace.t_s[after]
    xh_final = float(trace.probe_m[-1])
    scale = max(abs(final), 1e-12)
    outside = np.abs(xo - final) > band * scale
    finite = bool(np.all(np.isfinite(xo)))
    tail = outside[-max(1, len(outside) // 4) :]
    settled = finite and not bool(np.any(tail)) and abs(final) < 1e3
    if not settled:
        return StepMetrics(False, None, final, None, None, None)
    idx = np.nonzero(outside)[0]
    settle_t = 0.0 if idx.size == 0 else float(t[min(idx[-1] + 1, len(t) - 1)] - t_step_s)
    overshoot = float((np.max(xo) - final) / scale)
    return StepMetrics(
        settled=True,
        settling_time_s=settle_t,
        final_proxy_m=final,
        steady_state_ratio=final / xh_final if xh_final else None,
        steady_state_error_m=xh_final - final,
        overshoot=max(0.0, overshoot),
    )
