"""Fig. 7, 8 and 9 of Barbagli, Prattichizzo & Salisbury (IJRR 2005): the data, from the project code.

This module owns the computation only: it simulates, measures and judges, and returns each
figure's data (the JSON object and the arrays the plot draws). It draws nothing and writes no
file; :mod:`haptic_collab.research.plots` draws the figures from this data and writes the PNG and JSON
files (``haptic reproduce``).

Every number and curve is computed by the project's own code, nothing is typed in:

- the time responses (Fig. 7 and 9) run :func:`haptic_collab.research.multirate.simulate` with a
  :class:`shared.local_model.LocalModel` -- the same local model the client's servo thread runs --
  and are measured with :func:`haptic_collab.research.multirate.step_metrics`;
- the stability verdicts come from :func:`shared.stability.analyze` (lifting, section 2 and the
  slow-rate loop of Fig. 6), :func:`shared.stability.spectral_radius_grid` and
  :func:`shared.stability.eq15_stable` (the Jury conditions of eq. 15).

The paper's experiment is reproduced: servo loop at 1 kHz (T = 1 ms), deformable-object simulation
at 20 Hz (N = 50), elastic object (eq. 6), no extra delay.

The JSON objects are in SI units (m, s, N, N/m, N/(m*s)) unless a key says otherwise (``_mm``).

Usage::

    from haptic_collab.research.reproduce import figure_data, json_text
    data = figure_data("fig7")          # Fig7Data: .result (the JSON object), .traces
    text = json_text(data.result)       # the text of fig7.json
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from haptic_collab.research.multirate import StepMetrics, Trace, simulate, step_metrics
from haptic_collab.shared.local_model import LocalModel, LocalModelParams, ThresholdParams
from haptic_collab.shared.stability import STABILITY_TOL, analyze, eq15_stable, spectral_radius_grid
from haptic_collab.shared.types import FloatArray

BoolArray = NDArray[np.bool_]
#: One figure this module computes.
FigureId = Literal["fig7", "fig8", "fig9"]
#: A figure or ``"all"`` of them.
FigureName = Literal["fig7", "fig8", "fig9", "all"]

#: The figures this module computes, in order.
FIGURES: tuple[FigureId, ...] = ("fig7", "fig8", "fig9")
#: Servo rate 1/T [Hz] of the paper's experiment.
SERVO_RATE_HZ = 1000.0
#: Deformable-object simulation rate 1/(N*T) [Hz] of the paper's experiment.
SIM_RATE_HZ = 20.0
#: Servo period T [s].
SERVO_PERIOD_S = 1.0 / SERVO_RATE_HZ
#: Rate ratio N.
RATE_RATIO = round(SERVO_RATE_HZ / SIM_RATE_HZ)

# Fig. 7: (case, K_o [N/m], K_h [N/m]) from the caption.
_FIG7_CASES: tuple[tuple[str, float, float], ...] = (
    ("a", 900.0, 100.0),
    ("b", 200.0, 190.0),
    ("c", 200.0, 220.0),
)
_FIG7_STEP_T_S = 0.5
_FIG7_STEP_M = 0.060
_FIG7_RUN_S = 8.0

# Fig. 8 grid (normalised by K_o) and the absolute slices of the "stability volume".
_FIG8_K_O = 300.0
_FIG8_D = 0.025
_FIG8_KH_MAX = 3.25
_FIG8_NTI_MAX = 4.25
_FIG8_SLICES_K_O: tuple[float, ...] = (200.0, 500.0, 1000.0)

# Fig. 9 (caption and section 5): K_o = 0.3 N/mm, K_h = 0.1 N/mm, 4 mm offset (eq. 17).
_FIG9_K_O = 300.0
_FIG9_K_H = 100.0
_FIG9_I_GAIN = 3000.0  # N/(m*s): 0.003 N/mm per ms, see _I_GAIN_REASON
_FIG9_I_LITERAL = 3.0  # N/(m*s): 0.003 N mm^-1 s^-1 read literally
_FIG9_THETA_M = 0.004
_FIG9_START_M = -0.010
_FIG9_DEPTH_M = 0.030
_FIG9_STEP_T_S = 0.5
_FIG9_RUN_S = 5.0


@dataclass(frozen=True)
class Fig7Data:
    """Fig. 7: step responses of the proportional local model on a spring.

    Attributes
    ----------
    result : dict
        The JSON object of ``fig7.json`` (SI units); ``result["cases"]`` is keyed by case
        ``"a"``, ``"b"``, ``"c"`` in the caption's order.
    traces : dict of str to haptic_collab.research.multirate.Trace
        The simulated run of each case, same keys; one row per servo tick, ``run_s`` / T rows.
    """

    result: dict[str, Any]
    traces: dict[str, Trace]


@dataclass(frozen=True)
class Fig8Data:
    """Fig. 8: stability region of the PI local model, numeric and eq. 15.

    Attributes
    ----------
    result : dict
        The JSON object of ``fig8.json`` (SI units).
    kh_over_ko : (n_kh,) float
        Grid axis K_h / K_o [-], from 0.
    nti_over_ko : (n_nti,) float
        Grid axis I N T / K_o [-], from one grid step (> 0).
    spectral_radius : (n_kh, n_nti) float
        Spectral radius [-] of the Fig. 6 slow-rate loop at K_o = ``result["k_o"]`` [N/m].
    stable : (n_kh, n_nti) bool
        Numeric verdict: ``spectral_radius < 1 - STABILITY_TOL``.
    slices_spectral_radius : dict of float to (n_kh, n_nti) float
        Spectral radius [-] for each slice K_o [N/m] of the "stability volume" (200, 500,
        1000 N/m), on the same grid in absolute units: K_h = ``kh_over_ko * K_o``,
        I N T = ``nti_over_ko * K_o``.
    fig9_gains : (float, float)
        (K_h / K_o, I N T / K_o) of the Fig. 9 gains [-], a point of the plane.
    """

    result: dict[str, Any]
    kh_over_ko: FloatArray
    nti_over_ko: FloatArray
    spectral_radius: FloatArray
    stable: BoolArray
    slices_spectral_radius: dict[float, FloatArray]
    fig9_gains: tuple[float, float]


@dataclass(frozen=True)
class Fig9Data:
    """Fig. 9: proportional vs proportional-integral local model with a 4 mm offset.

    Attributes
    ----------
    result : dict
        The JSON object of ``fig9.json`` (SI units unless a key ends in ``_mm``).
    traces : dict of str to haptic_collab.research.multirate.Trace
        The simulated run, keyed ``"pi"`` (I = ``result["i_gain"]``) and ``"p_only"`` (I = 0),
        like ``result["pi"]`` and ``result["p_only"]``; one row per servo tick.
    """

    result: dict[str, Any]
    traces: dict[str, Trace]


FigureData = Fig7Data | Fig8Data | Fig9Data


def _probe_step(before_m: float, after_m: float, t_step_s: float, run_s: float) -> NDArray[Any]:
    """Probe depth x_h [m] per servo tick: ``before_m`` until ``t_step_s`` [s], then ``after_m``."""
    n_ticks = round(run_s / SERVO_PERIOD_S)
    i_step = round(t_step_s / SERVO_PERIOD_S)
    xh = np.full(n_ticks, float(before_m))
    xh[i_step:] = after_m
    return xh


def _none_if(value: float | None, cond: bool) -> float | None:
    return None if cond or value is None else float(value)


def _t(value: float | None) -> float | None:
    """A time [s] rounded to 1 ns (settling times are whole servo ticks; drops 0.0999999...)."""
    return None if value is None else round(float(value), 9)


def _metrics_json(m: StepMetrics) -> dict[str, Any]:
    """Step-response figures of merit, SI units, None where they do not exist."""
    return {
        "settled": m.settled,
        "settling_time_s": m.settling_time_s,
        "steady_state_ratio": m.steady_state_ratio,
        "steady_state_error_m": m.steady_state_error_m,
        "overshoot": m.overshoot,
    }


# --------------------------------------------------------------------------------------------
# Fig. 7
# --------------------------------------------------------------------------------------------


def fig7_data() -> Fig7Data:
    """Fig. 7: step response of the proportional local model on a linear spring (section 3-4).

    Runs the bilateral (linear) coupling ``LocalModelParams(k_h, unilateral=False)`` -- the model
    of section 3 whose slow-rate loop is eq. (7) and whose stability condition is eq. (8),
    K_h < K_o -- for the three (K_o, K_h) pairs of the caption, with x_h stepping from 0 to 60 mm
    at t = 0.5 s. The verdict of the simulated response (settles within 2 %) must equal the
    verdict of :func:`shared.stability.analyze` (spectral radius and eq. 8).

    Returns
    -------
    Fig7Data
        The JSON object and the three simulated runs (8 s each, 8000 servo ticks).

    Raises
    ------
    AssertionError
        If a simulated response and the stability analysis disagree (they never should).
    """
    cases: dict[str, dict[str, Any]] = {}
    traces: dict[str, Trace] = {}
    for name, k_o, k_h in _FIG7_CASES:
        xh = _probe_step(0.0, _FIG7_STEP_M, _FIG7_STEP_T_S, _FIG7_RUN_S)
        model = LocalModel(
            LocalModelParams(k_h=k_h, servo_period_s=SERVO_PERIOD_S, unilateral=False)
        )
        tr = simulate(model, xh, k_o=k_o, n_ticks=xh.size, sim_rate_hz=SIM_RATE_HZ)
        m = step_metrics(tr, t_step_s=_FIG7_STEP_T_S)
        a = analyze(k_o, k_h, servo_rate_hz=SERVO_RATE_HZ, sim_rate_hz=SIM_RATE_HZ)
        if not (m.settled == a.stable == bool(a.analytic_stable)):
            raise AssertionError(
                f"fig7 case {name}: simulation settled={m.settled}, numeric stable={a.stable}, "
                f"eq. 8 stable={a.analytic_stable} disagree"
            )
        unstable = not a.stable
        cases[name] = {
            "k_o": k_o,
            "k_h": k_h,
            "stable": a.stable,
            "settling_time_s": _t(_none_if(m.settling_time_s, unstable)),
            "steady_state_ratio": _none_if(m.steady_state_ratio, unstable),
            "eq11_ratio": k_h / (k_h + k_o),
            "overshoot": _none_if(m.overshoot, unstable),
            "final_proxy_m": _none_if(m.final_proxy_m, unstable),
            "max_abs_proxy_m": float(np.max(np.abs(tr.proxy_m))),
            "spectral_radius": a.spectral_radius,
            "slow_pole": -k_h / k_o,
            "condition": a.condition,
            "analytic_stable": a.analytic_stable,
        }
        traces[name] = tr

    result: dict[str, Any] = {
        "figure": "fig7",
        "model": (
            "proportional local model L(z) = K_h, linear bilateral coupling "
            "(LocalModelParams(unilateral=False)) as analysed in section 3, eq. (7)-(8), (11); "
            "elastic object D(z) = 1/K_o (eq. 6)"
        ),
        "servo_period_s": SERVO_PERIOD_S,
        "n": RATE_RATIO,
        "probe": {"t_step_s": _FIG7_STEP_T_S, "x_before_m": 0.0, "x_after_m": _FIG7_STEP_M},
        "run_s": _FIG7_RUN_S,
        "settling_band": 0.02,
        "cases": cases,
    }
    return Fig7Data(result=result, traces=traces)


# --------------------------------------------------------------------------------------------
# Fig. 8
# --------------------------------------------------------------------------------------------


def fig8_data() -> Fig8Data:
    """Fig. 8: stability region of the PI local model in the (K_h/K_o, I N T/K_o) plane (eq. 15).

    The numeric verdict is the spectral radius of the Fig. 6 slow-rate loop
    (:func:`shared.stability.spectral_radius_grid`) below ``1 - STABILITY_TOL``; it is compared
    point by point with the closed form :func:`shared.stability.eq15_stable`. Points that lie
    exactly on a boundary of eq. 15 (where the spectral radius is 1 up to round-off) are counted
    separately. Slices of the "stability volume" for several K_o in absolute units show that the
    region scales with K_o (section 5).

    Returns
    -------
    Fig8Data
        The JSON object and the grids: K_h/K_o from 0 to 3.25 and I N T/K_o from 0.025 to 4.25,
        step 0.025 (131 x 170 points), at K_o = 300 N/m and for the slices.
    """
    k_o = _FIG8_K_O
    kh_r = np.round(np.arange(0.0, _FIG8_KH_MAX + _FIG8_D / 2, _FIG8_D), 10)
    nti_r = np.round(np.arange(_FIG8_D, _FIG8_NTI_MAX + _FIG8_D / 2, _FIG8_D), 10)
    KH, NI = np.meshgrid(kh_r, nti_r, indexing="ij")
    rho = spectral_radius_grid(k_o, KH * k_o, NI * k_o)
    numeric = rho < 1.0 - STABILITY_TOL
    closed = np.array(
        [[eq15_stable(kh * k_o, k_o, ni * k_o) for ni in nti_r] for kh in kh_r], dtype=bool
    )
    # distance (in units of K_o) to the nearest boundary line of eq. 15
    dist = np.minimum.reduce(
        [np.abs(np.abs(NI - KH) - 1.0), np.abs(NI - 2.0 * KH + 2.0) / math.sqrt(5.0), NI]
    )
    on_boundary = dist < 1e-9
    agree = numeric == closed
    fraction = float(np.mean(agree))
    off_boundary_agree = bool(np.all(agree | on_boundary))
    i_min = np.unravel_index(int(np.argmin(rho)), rho.shape)

    slices: dict[str, Any] = {}
    slices_rho: dict[float, FloatArray] = {}
    for ko in _FIG8_SLICES_K_O:
        r = spectral_radius_grid(ko, KH * ko, NI * ko)
        slices_rho[ko] = r
        slices[f"{ko:g}"] = {
            "k_o": ko,
            "stable_fraction": float(np.mean(r < 1.0 - STABILITY_TOL)),
            "vertices_k_h_nti": [[0.0, 0.0], [ko, 0.0], [3.0 * ko, 4.0 * ko], [0.0, ko]],
        }

    result: dict[str, Any] = {
        "figure": "fig8",
        "model": (
            "PI local model L(z) = K_h + T I/(z-1) (eq. 12) on an elastic object; slow-rate loop "
            "of Fig. 6, eq. (13)-(14); closed form eq. (15)"
        ),
        "k_o": k_o,
        "n": RATE_RATIO,
        "servo_period_s": SERVO_PERIOD_S,
        "kh_over_ko": kh_r.tolist(),
        "nti_over_ko": nti_r.tolist(),
        "stable": numeric.tolist(),
        "agreement_fraction": fraction,
        "n_points": int(numeric.size),
        "n_disagree": int(np.sum(~agree)),
        "n_on_boundary": int(np.sum(on_boundary)),
        "agrees_with_eq15": off_boundary_agree,
        "spectral_radius_min": float(rho[i_min]),
        "spectral_radius_min_at": {
            "kh_over_ko": float(kh_r[i_min[0]]),
            "nti_over_ko": float(nti_r[i_min[1]]),
        },
        "stable_fraction": float(np.mean(numeric)),
        "region_vertices_normalised": [[0.0, 0.0], [1.0, 0.0], [3.0, 4.0], [0.0, 1.0]],
        "slices": slices,
    }
    fig9_gains = (_FIG9_K_H / _FIG9_K_O, _FIG9_I_GAIN * RATE_RATIO * SERVO_PERIOD_S / _FIG9_K_O)
    return Fig8Data(
        result=result,
        kh_over_ko=kh_r,
        nti_over_ko=nti_r,
        spectral_radius=rho,
        stable=numeric,
        slices_spectral_radius=slices_rho,
        fig9_gains=fig9_gains,
    )


# --------------------------------------------------------------------------------------------
# Fig. 9
# --------------------------------------------------------------------------------------------

_I_GAIN_REASON = (
    "The paper prints I = 0.003 N mm^-1 s^-1. Read literally that is 3 N/(m*s): I*N*T = 0.15 N/m, "
    "about 1/2000 of K_o = 300 N/m; analyze() then gives a slow pole at z = {lit_pole:.5f} per "
    "simulation tick (time constant {lit_tau:.0f} s), an integral that needs minutes to act, "
    "not the fast settling of Fig. 9 (our 5 s run with that gain ends at {lit_final_mm:.1f} mm "
    "instead of 26 mm). Read as 0.003 N/mm per millisecond (the servo period T) it is "
    "I = 3000 N/(m*s), I*N*T = {nti:.0f} N/m, well inside eq. 15's region (0 < INT < "
    "K_h + K_o = {nti_max:.0f} N/m here) with spectral radius {rho:.3f} (poles "
    "{poles}), close to the fastest-settling point INT = K_h + K_o/9 = {nti_best:.1f} N/m "
    "(double pole at z = 1/3). We use I = 3000 N/(m*s)."
)


def _fig9_run(i_gain: float, unilateral: bool = True) -> tuple[Trace, StepMetrics]:
    """Run the Fig. 9 experiment with integral gain ``i_gain`` [N/(m*s)] (0: P only)."""
    xh = _probe_step(_FIG9_START_M, _FIG9_DEPTH_M, _FIG9_STEP_T_S, _FIG9_RUN_S)
    params = LocalModelParams(
        k_h=_FIG9_K_H,
        i_gain=i_gain,
        servo_period_s=SERVO_PERIOD_S,
        threshold=ThresholdParams(mode="fixed", theta_m=_FIG9_THETA_M),
        unilateral=unilateral,
    )
    tr = simulate(LocalModel(params), xh, k_o=_FIG9_K_O, n_ticks=xh.size, sim_rate_hz=SIM_RATE_HZ)
    return tr, step_metrics(tr, t_step_s=_FIG9_STEP_T_S)


def _fig9_case(tr: Trace, m: StepMetrics, i_gain: float) -> dict[str, Any]:
    a = analyze(
        _FIG9_K_O, _FIG9_K_H, i_gain=i_gain, servo_rate_hz=SERVO_RATE_HZ, sim_rate_hz=SIM_RATE_HZ
    )
    if not (m.settled and a.stable and bool(a.analytic_stable)):
        raise AssertionError(
            f"fig9 I={i_gain}: settled={m.settled}, stable={a.stable}, analytic={a.analytic_stable}"
        )
    err = m.steady_state_error_m
    after = tr.t_s >= _FIG9_STEP_T_S
    return {
        "i_gain": i_gain,
        "nti": a.nti,
        "steady_state_error_mm": None if err is None else err * 1e3,
        "settling_time_s": _t(m.settling_time_s),
        "overshoot": m.overshoot,
        "final_proxy_mm": m.final_proxy_m * 1e3,
        "final_probe_mm": float(tr.probe_m[-1]) * 1e3,
        "final_force_n": float(tr.force_n[-1]),
        "min_penetration_after_step_mm": float(np.min(tr.probe_m[after] - tr.proxy_m[after])) * 1e3,
        "spectral_radius": a.spectral_radius,
        "poles": [[float(p.real), float(p.imag)] for p in a.poles],
        "condition": a.condition,
        "analytic_stable": a.analytic_stable,
        "metrics_si": _metrics_json(m),
    }


def fig9_data() -> Fig9Data:
    """Fig. 9: proportional vs proportional-integral local model with a 4 mm offset (section 5).

    K_o = 300 N/m, K_h = 100 N/m, I = 3000 N/(m*s) (see ``i_gain_reason``), fixed integration
    threshold theta = 4 mm (eq. 17). The unilateral local model (a contact only pushes) is used.
    The probe starts 10 mm outside the object and steps to 30 mm depth at t = 0.5 s. Expected: the
    PI model settles with the proxy 4 mm (theta) from the probe, the P model with the eq. 11
    error K_o/(K_h+K_o) * x_h = 22.5 mm.

    Returns
    -------
    Fig9Data
        The JSON object and the PI and P runs (5 s each, 5000 servo ticks).

    Raises
    ------
    AssertionError
        If a simulated response and the stability analysis disagree (they never should).
    """
    tr_pi, m_pi = _fig9_run(_FIG9_I_GAIN)
    tr_p, m_p = _fig9_run(0.0)
    pi = _fig9_case(tr_pi, m_pi, _FIG9_I_GAIN)
    p_only = _fig9_case(tr_p, m_p, 0.0)

    # the literal reading of the printed gain, for the record
    a_lit = analyze(
        _FIG9_K_O,
        _FIG9_K_H,
        i_gain=_FIG9_I_LITERAL,
        servo_rate_hz=SERVO_RATE_HZ,
        sim_rate_hz=SIM_RATE_HZ,
    )
    lit_pole = float(np.max(np.real(a_lit.poles)))
    lit_tau = -(RATE_RATIO * SERVO_PERIOD_S) / math.log(lit_pole)
    tr_lit, _ = _fig9_run(_FIG9_I_LITERAL)
    lit_final_mm = float(tr_lit.proxy_m[-1]) * 1e3
    nti_best = _FIG9_K_H + _FIG9_K_O / 9.0
    a_best = analyze(
        _FIG9_K_O,
        _FIG9_K_H,
        i_gain=nti_best / (RATE_RATIO * SERVO_PERIOD_S),
        servo_rate_hz=SERVO_RATE_HZ,
        sim_rate_hz=SIM_RATE_HZ,
    )
    poles_txt = ", ".join(f"{re:.3f}{im:+.3f}j" for re, im in pi["poles"])
    reason = _I_GAIN_REASON.format(
        lit_pole=lit_pole,
        lit_tau=lit_tau,
        lit_final_mm=lit_final_mm,
        nti=pi["nti"],
        nti_max=_FIG9_K_H + _FIG9_K_O,
        rho=pi["spectral_radius"],
        poles=poles_txt,
        nti_best=nti_best,
    )

    result: dict[str, Any] = {
        "figure": "fig9",
        "model": (
            "unilateral local model (a contact only pushes), L(z) = K_h + T I/(z-1) (eq. 12), "
            "integrator fed with e - theta, fixed threshold theta (eq. 17); elastic object (eq. 6)"
        ),
        "k_o": _FIG9_K_O,
        "k_h": _FIG9_K_H,
        "i_gain": _FIG9_I_GAIN,
        "i_gain_reason": reason,
        "theta_m": _FIG9_THETA_M,
        "nti": pi["nti"],
        "servo_period_s": SERVO_PERIOD_S,
        "n": RATE_RATIO,
        "probe": {
            "t_step_s": _FIG9_STEP_T_S,
            "x_before_m": _FIG9_START_M,
            "x_after_m": _FIG9_DEPTH_M,
        },
        "run_s": _FIG9_RUN_S,
        "settling_band": 0.02,
        "eq11_p_error_mm": _FIG9_K_O / (_FIG9_K_H + _FIG9_K_O) * _FIG9_DEPTH_M * 1e3,
        "pi": pi,
        "p_only": p_only,
        "literal_reading": {
            "i_gain": _FIG9_I_LITERAL,
            "nti": a_lit.nti,
            "spectral_radius": a_lit.spectral_radius,
            "slow_pole": lit_pole,
            "time_constant_s": lit_tau,
            "proxy_at_end_mm": lit_final_mm,
        },
        "fastest_settling": {"nti": nti_best, "spectral_radius": a_best.spectral_radius},
    }
    return Fig9Data(result=result, traces={"pi": tr_pi, "p_only": tr_p})


# --------------------------------------------------------------------------------------------
# all figures
# --------------------------------------------------------------------------------------------


def figure_names(figure: FigureName) -> list[FigureId]:
    """The figures ``figure`` stands for: ``["fig7", "fig8", "fig9"]`` for ``"all"``.

    Raises
    ------
    ValueError
        Unknown figure name.
    """
    if figure == "all":
        return list(FIGURES)
    if figure in FIGURES:
        return [figure]
    raise ValueError(f"figure must be one of fig7, fig8, fig9, all; got {figure!r}")


def figure_data(name: FigureId) -> FigureData:
    """Compute one figure's data: :func:`fig7_data`, :func:`fig8_data` or :func:`fig9_data`.

    Parameters
    ----------
    name : {"fig7", "fig8", "fig9"}
        - ``fig7``: step responses of the proportional local model on a spring (section 3-4,
          eq. 7, 8, 11), cases (a) K_o = 900, K_h = 100; (b) K_o = 200, K_h = 190;
          (c) K_o = 200, K_h = 220 N/m, with the linear bilateral coupling of section 3;
        - ``fig8``: stability region of the PI local model in the (K_h/K_o, I N T/K_o) plane,
          numeric spectral radius vs the Jury conditions of eq. 15, plus slices of the stability
          volume for K_o = 200, 500, 1000 N/m;
        - ``fig9``: P vs PI local model (K_o = 300, K_h = 100 N/m, I = 3000 N/(m*s), eq. 17
          threshold 4 mm), unilateral contact.

    Returns
    -------
    Fig7Data, Fig8Data or Fig9Data
        ``.result`` is the figure's JSON object (SI units: m, s, N, N/m, N/(m*s)).

    Raises
    ------
    ValueError
        Unknown figure name (``"all"`` included: see :func:`figure_names`).
    AssertionError
        If a simulated response and the stability analysis disagree (they never should).
    """
    if name == "fig7":
        return fig7_data()
    if name == "fig8":
        return fig8_data()
    if name == "fig9":
        return fig9_data()
    raise ValueError(f"figure must be one of fig7, fig8, fig9; got {name!r}")


def json_text(result: dict[str, Any]) -> str:
    """The text of ``<fig>.json`` for a figure's JSON object ``result``, ending in a newline.

    Fig. 8 is written on one line (its grid verdicts would take one line per boolean with an
    indent), the others with an indent of 2.

    Raises
    ------
    ValueError
        A NaN or infinite number in ``result`` (JSON has none).
    """
    indent = None if result.get("figure") == "fig8" else 2
    return json.dumps(result, indent=indent, allow_nan=False) + "\n"
