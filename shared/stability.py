"""Stability of the simulation loop through a slow, delayed deformable-object simulation.

Implements sections 2-5 of Barbagli, Prattichizzo, Salisbury (IJRR 2005):

- :func:`lift` — the lifted local model (A~, B~, C~, D~) of eq. (3)-(5);
- :func:`slow_rate_model` — the SISO slow-rate local model L_h of Fig. 6,
  ``L_h = [A_L^N, sum_{i<N} A_L^i B_L, C_L, D_L]``;
- :func:`object_state_space` — the object admittance D(z): elastic (eq. 6) or visco-elastic (eq. 9);
- :func:`closed_loop_matrix` / :func:`analyze` — the closed simulation loop
  ``z^-(1+delay) * L_h(z) * D(z)`` in negative feedback: poles, spectral radius, verdict;
- :func:`eq8_stable`, :func:`eq10_stable`, :func:`eq15_stable`, :func:`eq16_stable` — the paper's
  closed-form (Jury) conditions;
- :func:`select_gains` — Step 2 of section 6: K_h and I inside the stability region (Fig. 8) with a
  margin on K_o, capped by the device's maximum stiffness.

Every :class:`StateSpace` carries its sample time ``dt`` [s]: T for the servo-rate local model,
N*T for the lifted and slow-rate models and the object; connecting two models on different
timebases is refused (:func:`common_timebase`). The rates themselves, and N, come from
:class:`shared.rates.Rates` (:func:`rate_ratio` and :func:`dividing_rates` are re-exported here).

Units: stiffness [N/m], I [N/(m*s)], damping b [N*s/m], B_o = b / (N*T) [N/m], periods [s].
The delay counts *extra* whole simulation ticks on top of the one tick the simulation itself takes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from haptic_collab.shared.checks import nonneg as _nonneg
from haptic_collab.shared.checks import positive as _positive
from haptic_collab.shared.checks import whole as _whole
from haptic_collab.shared.rates import PERIOD_RTOL, Rates
from haptic_collab.shared.rates import dividing_rates as dividing_rates
from haptic_collab.shared.rates import rate_ratio as rate_ratio
from haptic_collab.shared.types import FloatArray

#: Poles with magnitude below 1 - STABILITY_TOL count as stable (guards marginal round-off).
STABILITY_TOL = 1e-9


@dataclass(frozen=True)
class StateSpace:
    """Discrete-time state-space quadruple ``x(k+1) = A x + B u``, ``y = C x + D u``, sampled
    every ``dt`` seconds.

    Shapes: A (n, n), B (n, m), C (p, n), D (p, m); n may be 0 (a static gain).

    ``dt`` [s] is the sample time: T for a servo-rate model (:func:`local_model_state_space`),
    N*T for a lifted or slow-rate one (:func:`lift`, :func:`slow_rate_model`) and for the object
    (:func:`object_state_space`). ``None`` means unspecified (a static gain valid at any rate) and
    is compatible with every timebase; functions that connect two models refuse two different
    sample times (:func:`common_timebase`), as python-control does.
    """

    A: FloatArray
    B: FloatArray
    C: FloatArray
    D: FloatArray
    dt: float | None

    def __post_init__(self) -> None:
        if self.dt is not None and not (math.isfinite(self.dt) and self.dt > 0.0):
            raise ValueError(
                f"sample time dt must be a finite number > 0 s or None, got {self.dt!r}"
            )

    @property
    def n_states(self) -> int:
        """Number of states n."""
        return int(self.A.shape[0])


def _ss(a: object, b: object, c: object, d: object, dt: float | None) -> StateSpace:
    A = np.atleast_2d(np.asarray(a, dtype=float))
    D = np.atleast_2d(np.asarray(d, dtype=float))
    n = 0 if A.size == 0 else A.shape[0]
    A = A.reshape(n, n)
    B = np.asarray(b, dtype=float).reshape(n, D.shape[1])
    C = np.asarray(c, dtype=float).reshape(D.shape[0], n)
    return StateSpace(A, B, C, D, None if dt is None else float(dt))


def _describe_dt(dt: float | None) -> str:
    return "dt unspecified" if dt is None else f"dt = {dt:g} s ({1.0 / dt:g} Hz)"


def common_timebase(
    first: StateSpace, second: StateSpace, names: tuple[str, str] = ("first", "second")
) -> float | None:
    """The sample time [s] two models share, for connecting them (python-control's rule).

    ``None`` (unspecified) is compatible with any sample time; two given sample times must agree
    within a relative :data:`shared.rates.PERIOD_RTOL` (they may be computed as ``N * T`` on one
    side and ``1 / sim_rate`` on the other).

    Parameters
    ----------
    first, second : StateSpace
    names : (str, str)
        What the two models are, for the message.

    Returns
    -------
    float or None
        The common sample time (the first given one), None if neither has one.

    Raises
    ------
    ValueError
        Different sample times, e.g. a servo-rate model wired to a slow-rate one; the message
        names both models and their sample times.
    """
    a, b = first.dt, second.dt
    if a is None:
        return b
    if b is None:
        return a
    if abs(a - b) > PERIOD_RTOL * max(a, b):
        raise ValueError(
            f"cannot connect models on different timebases: {names[0]} has {_describe_dt(a)}, "
            f"{names[1]} has {_describe_dt(b)}"
        )
    return a


def local_model_state_space(k_h: float, i_gain: float, servo_period_s: float) -> StateSpace:
    """State-space realization at the servo period T of the local model L(z), eq. (12).

    ``L(z) = K_h + T*I/(z-1)``: A_L = 1, B_L = 1, C_L = T*I, D_L = K_h. With ``i_gain == 0`` the
    proportional model ``L(z) = K_h`` has no state (A_L is 0x0), so no spurious pole at z = 1.
    Either way its sample time ``dt`` is T = ``servo_period_s`` [s].

    Raises
    ------
    ValueError
        k_h <= 0, i_gain < 0, a non-positive period, or non-finite values.
    """
    _positive("k_h", k_h)
    _nonneg("i_gain", i_gain)
    _positive("servo period", servo_period_s)
    if i_gain == 0.0:
        return _ss(np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), [[k_h]], servo_period_s)
    return _ss([[1.0]], [[1.0]], [[servo_period_s * i_gain]], [[k_h]], servo_period_s)


def lift(model: StateSpace, n: int) -> StateSpace:
    """Lifted local model (A~, B~, C~, D~) of eq. (3)-(5), N inputs and N outputs per slow tick.

    ``A~ = A^N``, ``B~ = [A^(N-1) B, ..., A B, B]``, ``C~ = [C; C A; ...; C A^(N-1)]`` and D~ lower
    block-triangular with D on the diagonal and ``C A^(i-j-1) B`` below it. SISO models only.
    The lifted model is sampled every ``N * dt`` (unspecified stays unspecified).

    Raises
    ------
    ValueError
        If ``n < 1`` or the model is not SISO.
    """
    if n < 1:
        raise ValueError(f"lifting factor N must be >= 1, got {n}")
    if model.B.shape[1] != 1 or model.C.shape[0] != 1:
        raise ValueError("lift() takes a SISO local model")
    A, B, C, D = model.A, model.B, model.C, model.D
    ns = model.n_states
    powers = [np.eye(ns)]
    for _ in range(n):
        powers.append(powers[-1] @ A)
    At = powers[n]
    Bt = np.hstack([powers[n - 1 - j] @ B for j in range(n)]) if ns else np.zeros((0, n))
    Ct = np.vstack([C @ powers[i] for i in range(n)]) if ns else np.zeros((n, 0))
    Dt = np.zeros((n, n))
    for i in range(n):
        Dt[i, i] = D[0, 0]
        for j in range(i):
            Dt[i, j] = (C @ powers[i - j - 1] @ B)[0, 0] if ns else 0.0
    return StateSpace(At, Bt, Ct, Dt, None if model.dt is None else model.dt * n)


def slow_rate_model(model: StateSpace, n: int, sample_tick: int = 0) -> StateSpace:
    """The SISO slow-rate local model L_h of Fig. 6 (section 2.2).

    With an input held over the N fast ticks (zero-order hold, eq. 1) and the decimator keeping
    lifted output ``j = sample_tick`` (the paper's S_N keeps j = 0):
    ``L_h = [A^N, sum_{i<N} A^i B, C A^j, D + sum_{i<j} C A^i B]``.
    For the PI model and j = 0 this is ``L_h(z) = K_h + N*T*I/(z-1)`` (eq. 13); sampling later in
    the block adds ``j*T*I`` to the proportional part. A networked simulation that takes "the last
    force returned to the haptic device" (Step 3) samples at an arbitrary j, so gains must hold for
    every j (see :func:`select_gains`). Sampled every ``N * dt`` like :func:`lift`.

    Raises
    ------
    ValueError
        ``sample_tick`` outside [0, N).
    """
    if not 0 <= sample_tick < n:
        raise ValueError(f"sample_tick must be in [0, {n}), got {sample_tick}")
    lifted = lift(model, n)
    return StateSpace(
        lifted.A,
        lifted.B.sum(axis=1, keepdims=True),
        lifted.C[sample_tick : sample_tick + 1],
        lifted.D[sample_tick : sample_tick + 1].sum(axis=1, keepdims=True),
        lifted.dt,
    )


def object_state_space(
    k_o: float, b_o: float = 0.0, sim_period_s: float | None = None
) -> StateSpace:
    """Object admittance D(z) at the slow rate, force [N] in, position [m] out.

    Elastic, eq. (6): ``D(z) = 1/K_o``. Visco-elastic, eq. (9):
    ``D(z) = (K_o + B_o (z-1)/z)^-1 = z / ((K_o+B_o) z - B_o)``, realised with
    ``a = B_o/(K_o+B_o)``: A = a, B = 1, C = a/(K_o+B_o), D = 1/(K_o+B_o).

    Parameters
    ----------
    k_o : float
        K_o [N/m], > 0.
    b_o : float
        B_o = b / (N*T) [N/m], >= 0.
    sim_period_s : float, optional
        The simulation period N*T [s], the model's sample time ``dt`` (None: unspecified, then it
        connects to a model of any sample time).

    Raises
    ------
    ValueError
        k_o <= 0, b_o < 0, or a period that is not a finite number > 0.
    """
    _positive("k_o", k_o)
    _nonneg("b_o", b_o)
    if sim_period_s is not None:
        _positive("simulation period", sim_period_s)
    if b_o == 0.0:
        return _ss(
            np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), [[1.0 / k_o]], sim_period_s
        )
    s = k_o + b_o
    a = b_o / s
    return _ss([[a]], [[1.0]], [[a / s]], [[1.0 / s]], sim_period_s)


def closed_loop_matrix(l_h: StateSpace, obj: StateSpace, delay_ticks: int = 0) -> FloatArray:
    """State matrix of the slow-rate simulation loop of Fig. 6 with extra transport delay.

    The loop is ``x_o = z^-(1+delay) D(z) F``, ``F = L_h(z) (x_h - x_o)``; with x_h = 0 its
    state ``[lambda_L, xi_D, d_1 .. d_(1+delay)]`` evolves as ``s(k+1) = A_cl s(k)``. The delay line
    carries the object position, so the loop has no algebraic feedthrough.

    Both models must run at the simulation rate: ``l_h`` from :func:`slow_rate_model`, not the
    servo-rate :func:`local_model_state_space` (:func:`common_timebase`).

    Returns
    -------
    (n, n) float array, n = states(L_h) + states(D) + 1 + delay.

    Raises
    ------
    ValueError
        If ``delay_ticks < 0``, or the two models have different sample times ``dt``.
    """
    common_timebase(l_h, obj, ("the local model L_h", "the object D(z)"))
    if delay_ticks < 0:
        raise ValueError(f"delay_ticks must be >= 0, got {delay_ticks}")
    nl, no, nd = l_h.n_states, obj.n_states, 1 + delay_ticks
    n = nl + no + nd
    Acl = np.zeros((n, n))
    il, io, idl = slice(0, nl), slice(nl, nl + no), nl + no
    last = n - 1
    Ch, Dh = l_h.C[0], l_h.D[0, 0]
    # local model: lambda' = A_h lambda + B_h u, u = -d_last; F = C_h lambda - D_h d_last
    Acl[il, il] = l_h.A
    Acl[il, last] += -l_h.B[:, 0]
    # object: xi' = A_o xi + B_o F
    Acl[io, io] = obj.A
    Acl[io, il] += np.outer(obj.B[:, 0], Ch)
    Acl[io, last] += -obj.B[:, 0] * Dh
    # first delay register takes the object output p = C_o xi + D_o F
    Do = obj.D[0, 0]
    Acl[idl, io] = obj.C[0]
    Acl[idl, il] += Do * Ch
    Acl[idl, last] += -Do * Dh
    for j in range(1, nd):
        Acl[idl + j, idl + j - 1] = 1.0
    return Acl


def eq8_stable(k_h: float, k_o: float) -> bool:
    """Eq. (8): proportional local model on an elastic object is stable iff K_h < K_o."""
    return k_h < k_o


def eq10_stable(k_h: float, k_o: float, b_o: float) -> bool:
    """Eq. (10): proportional local model, visco-elastic object: K_h < K_o + 2 B_o."""
    return k_h < k_o + 2.0 * b_o


def eq15_stable(k_h: float, k_o: float, nti: float) -> bool:
    """Eq. (15): PI local model, elastic object, with ``nti = I*N*T`` [N/m] (I > 0).

    ``|INT - K_h| < K_o`` and ``INT - 2 K_h > -2 K_o``.
    """
    return nti > 0.0 and abs(nti - k_h) < k_o and nti - 2.0 * k_h > -2.0 * k_o


def eq16_stable(k_h: float, k_o: float, nti: float, b_o: float) -> bool:
    """Eq. (16): PI local model, visco-elastic object (I > 0).

    ``|INT - K_h + B_o| < K_o + B_o`` and ``INT - 2 K_h > -2 K_o - 4 B_o``.
    """
    return (
        nti > 0.0 and abs(nti - k_h + b_o) < k_o + b_o and nti - 2.0 * k_h > -2.0 * k_o - 4.0 * b_o
    )


@dataclass(frozen=True)
class LoopAnalysis:
    """Verdict on the slow-rate simulation loop.

    Attributes
    ----------
    stable : bool
        All poles strictly inside the unit circle.
    spectral_radius : float
        Largest pole magnitude.
    poles : (n,) complex array
        Closed-loop poles at the simulation rate.
    analytic_stable : bool or None
        Verdict of eq. 8, 10, 15 or 16 (None when a delay makes them inapplicable).
    condition : str
        Which condition was used, in words.
    rate_ratio : int
        N.
    b_o : float
        B_o = b / (N*T) [N/m].
    nti : float
        I*N*T [N/m].
    """

    stable: bool
    spectral_radius: float
    poles: NDArray[np.complex128]
    analytic_stable: bool | None
    condition: str
    rate_ratio: int
    b_o: float
    nti: float

    def to_json(self) -> dict[str, object]:
        """The ``haptic stability --json`` object."""
        return {
            "stable": self.stable,
            "spectral_radius": self.spectral_radius,
            "poles": [[float(p.real), float(p.imag)] for p in self.poles],
            "analytic_stable": self.analytic_stable,
            "condition": self.condition,
            "rate_ratio": self.rate_ratio,
            "b_o": self.b_o,
            "nti": self.nti,
        }


def analyze(
    k_o: float,
    k_h: float,
    *,
    i_gain: float = 0.0,
    damping: float = 0.0,
    servo_rate_hz: float = 1000.0,
    sim_rate_hz: float = 20.0,
    delay_ticks: int = 0,
    sample_tick: int = 0,
) -> LoopAnalysis:
    """Analyse the simulation loop numerically via lifting, and by the closed forms when they apply.

    Parameters
    ----------
    k_o : float
        Object local stiffness K_o [N/m], > 0.
    k_h : float
        Local model stiffness K_h [N/m], > 0.
    i_gain : float
        Integral weight I [N/(m*s)], >= 0 (0: proportional local model).
    damping : float
        Object damping b [N*s/m], >= 0; B_o = b / (N*T) (eq. 9).
    servo_rate_hz, sim_rate_hz : float
        1/T and 1/(N*T); the servo rate must be a whole multiple of the simulation rate.
    delay_ticks : int
        Extra whole simulation ticks of transport delay (network, computation), >= 0.
    sample_tick : int
        Servo tick within the block whose force the simulation samples (0: the paper's decimator;
        the closed forms assume 0 and are reported only then).

    Raises
    ------
    ValueError
        On any out-of-range, non-finite or inconsistent input.
    """
    rates = Rates(servo_rate_hz, sim_rate_hz)
    n = rates.ratio
    _positive("k_o", k_o)
    _positive("k_h", k_h)
    _nonneg("i_gain", i_gain)
    _nonneg("damping", damping)
    _whole("delay_ticks", delay_ticks, 0)
    delay_ticks = int(delay_ticks)
    period = rates.servo_period_s
    b_o = damping * sim_rate_hz
    nti = i_gain * n * period
    l_h = slow_rate_model(local_model_state_space(k_h, i_gain, period), n, sample_tick)
    acl = closed_loop_matrix(l_h, object_state_space(k_o, b_o, rates.sim_period_s), delay_ticks)
    poles = np.linalg.eigvals(acl) if acl.size else np.zeros(0, dtype=complex)
    rho = float(np.max(np.abs(poles))) if poles.size else 0.0
    analytic: bool | None
    if sample_tick and i_gain > 0.0:
        analytic = None
        cond = f"numeric: force sampled at servo tick {sample_tick} of {n}, {delay_ticks} tick(s) of delay"
    elif delay_ticks:
        analytic, cond = None, f"numeric: spectral radius with {delay_ticks} tick(s) of delay"
    elif i_gain == 0.0 and b_o == 0.0:
        analytic, cond = eq8_stable(k_h, k_o), "eq. 8: K_h < K_o"
    elif i_gain == 0.0:
        analytic, cond = eq10_stable(k_h, k_o, b_o), "eq. 10: K_h < K_o + 2 B_o"
    elif b_o == 0.0:
        analytic = eq15_stable(k_h, k_o, nti)
        cond = "eq. 15: |INT - K_h| < K_o and INT - 2 K_h > -2 K_o"
    else:
        analytic = eq16_stable(k_h, k_o, nti, b_o)
        cond = "eq. 16: |INT - K_h + B_o| < K_o + B_o and INT - 2 K_h > -2 K_o - 4 B_o"
    return LoopAnalysis(
        stable=rho < 1.0 - STABILITY_TOL,
        spectral_radius=rho,
        poles=poles.astype(np.complex128),
        analytic_stable=analytic,
        condition=cond,
        rate_ratio=n,
        b_o=b_o,
        nti=nti,
    )


def spectral_radius_grid(
    k_o: float | FloatArray,
    k_h: FloatArray,
    nti: FloatArray,
    b_o: float = 0.0,
    delay_ticks: int = 0,
) -> FloatArray:
    """Spectral radius of the PI/P loop for arrays of (K_h, INT) at once (broadcast shapes).

    Uses the characteristic polynomial of the Fig. 6 loop,
    ``z^d (z-1) ((K_o+B_o) z - B_o) + K_h (z-1) + INT = 0``, whose roots equal the poles of
    :func:`closed_loop_matrix` (for INT = 0 the common factor (z-1) is removed: P model).
    Vectorised over companion matrices; used for Fig. 8 and gain selection.
    """
    k_h_a, nti_a, k_o_a = np.broadcast_arrays(
        np.asarray(k_h, float), np.asarray(nti, float), np.asarray(k_o, float)
    )
    shape = k_h_a.shape
    kh, ni, ko = k_h_a.ravel(), nti_a.ravel(), k_o_a.ravel()
    d = int(delay_ticks)
    deg = d + 2
    # coefficients, highest power first: z^d * [(Ko+Bo) z^2 - (Ko+2Bo) z + Bo] + Kh z - Kh + INT
    coeffs = np.zeros((kh.size, deg + 1))
    coeffs[:, 0] = ko + b_o
    coeffs[:, 1] = -(ko + 2.0 * b_o)
    coeffs[:, 2] = b_o
    coeffs[:, deg - 1] += kh
    coeffs[:, deg] += ni - kh
    rho = np.empty(kh.size)
    p_only = ni == 0.0
    if np.any(~p_only):
        rho[~p_only] = _companion_radius(coeffs[~p_only])
    if np.any(p_only):
        # P model: z^d ((Ko+Bo) z - Bo) + Kh
        pc = np.zeros((int(p_only.sum()), d + 2))
        pc[:, 0] = (ko + b_o)[p_only]
        pc[:, 1] = -b_o
        pc[:, d + 1] += kh[p_only]
        rho[p_only] = _companion_radius(pc)
    return rho.reshape(shape)


def _companion_radius(coeffs: FloatArray) -> FloatArray:
    """Largest root magnitude of each row's polynomial (highest power first, leading != 0)."""
    m, deg = coeffs.shape[0], coeffs.shape[1] - 1
    if deg == 0:
        return np.zeros(m)
    monic = coeffs[:, 1:] / coeffs[:, :1]
    comp = np.zeros((m, deg, deg))
    comp[:, 0, :] = -monic
    if deg > 1:
        idx = np.arange(deg - 1)
        comp[:, idx + 1, idx] = 1.0
    return np.max(np.abs(np.linalg.eigvals(comp)), axis=1)


@dataclass(frozen=True)
class GainChoice:
    """Local model gains chosen by :func:`select_gains`.

    Attributes
    ----------
    k_h : float
        K_h [N/m].
    i_gain : float
        I [N/(m*s)] (0 for a proportional local model).
    spectral_radius : float
        Slow-loop spectral radius at the reported K_o (worst force-sampling phase).
    worst_spectral_radius : float
        The larger of the spectral radii at the reported K_o and at the design value
        (1 - margin) K_o. For ``pi`` it is below 1: stable for any object stiffness from K_o' up.
        For ``p`` it is 1 by construction (K_h = K_o' sits on eq. 8's boundary at K_o').
    stable : bool
        The loop is stable at the reported K_o.
    """

    k_h: float
    i_gain: float
    spectral_radius: float
    worst_spectral_radius: float
    stable: bool


def select_gains(
    k_o: float,
    *,
    rate_ratio: int,
    servo_period_s: float,
    b_o: float = 0.0,
    delay_ticks: int = 0,
    margin: float = 0.3,
    k_h_max: float = math.inf,
    mode: Literal["p", "pi"] = "pi",
    grid: int = 48,
) -> GainChoice:
    """Step 2 of section 6: pick K_h (and I) inside the stability region with a margin.

    Following the paper's advice ("K_h and I can always be picked based on values of K_o lower
    than those returned by a deformable object simulator in order to have a certain stability
    margin"), the gains are designed for ``K_o' = (1 - margin) K_o``:

    - ``p``: ``K_h = min(k_h_max, K_o')`` — as close to K_o as the margin allows (eq. 8 and 11);
      with pure delay the P loop keeps ``|z|^(1+d) = K_h/K_o`` so this stays stable.
    - ``pi``: K_h <= min(k_h_max, K_o') and INT in (0, 2 K_o'] minimising the worst spectral
      radius at K_o' and K_o *and over the force-sampling phase*: the simulation may sample the
      force at any servo tick j of the block (Step 3 over a network), which turns K_h into
      ``K_h + (j/N) INT`` (:func:`slow_rate_model`). Phases 0, 1/4, 1/2, 3/4 and (N-1)/N are
      checked; without delay the region of eq. 15/16 is convex, so the two ends already cover every
      phase. Searched on a ``grid x grid`` grid plus a local refinement (Fig. 8).

    Parameters
    ----------
    k_o : float
        Reported (coupling-aware) object stiffness K_o_eff [N/m], > 0.
    rate_ratio : int
        N, servo ticks per simulation tick, >= 1.
    servo_period_s : float
        T [s].
    b_o : float
        B_o [N/m] (eq. 9), >= 0.
    delay_ticks : int
        Extra whole simulation ticks of delay, >= 0.
    margin : float
        Fraction in [0, 1) by which K_o may be overestimated.
    k_h_max : float
        The device's maximum stable stiffness [N/m] at its servo rate.
    mode : {"p", "pi"}
        Proportional or proportional-integral local model.

    Raises
    ------
    ValueError
        Out-of-range inputs.
    """
    _positive("k_o", k_o)
    _nonneg("b_o", b_o)
    _positive("servo period", servo_period_s)
    if rate_ratio < 1:
        raise ValueError(f"rate_ratio must be >= 1, got {rate_ratio}")
    if not (0.0 <= margin < 1.0):
        raise ValueError(f"margin must be in [0, 1), got {margin!r}")
    if not (k_h_max > 0.0):
        raise ValueError(f"k_h_max must be > 0, got {k_h_max!r}")
    if delay_ticks < 0:
        raise ValueError(f"delay_ticks must be >= 0, got {delay_ticks}")
    if mode not in ("p", "pi"):
        raise ValueError(f"mode must be 'p' or 'pi', got {mode!r}")
    k_design = (1.0 - margin) * k_o
    kh_cap = min(k_h_max, k_design if margin > 0.0 else 0.999 * k_o)
    nt = rate_ratio * servo_period_s
    last = (rate_ratio - 1) / rate_ratio
    phases = sorted({0.0, min(0.25, last), min(0.5, last), min(0.75, last), last})

    def worst(kh: FloatArray, nti: FloatArray) -> FloatArray:
        out = np.zeros(np.broadcast(kh, nti).shape)
        for alpha in phases:
            for k in (k_design, k_o):
                out = np.maximum(
                    out, spectral_radius_grid(k, kh + alpha * nti, nti, b_o, delay_ticks)
                )
        return out

    if mode == "p":
        kh = np.array([kh_cap])
        nti = np.array([0.0])
    else:
        kh_axis = np.linspace(kh_cap / grid, kh_cap, grid)
        nti_axis = np.linspace(2.0 * k_design / grid, 2.0 * k_design, grid)
        KH, NI = np.meshgrid(kh_axis, nti_axis, indexing="ij")
        w = worst(KH, NI)
        i, j = np.unravel_index(int(np.argmin(w)), w.shape)
        # local refinement around the best cell
        dkh, dni = kh_axis[1] - kh_axis[0], nti_axis[1] - nti_axis[0]
        kh_f = np.clip(np.linspace(KH[i, j] - dkh, KH[i, j] + dkh, 21), kh_cap * 1e-3, kh_cap)
        ni_f = np.clip(np.linspace(NI[i, j] - dni, NI[i, j] + dni, 21), 1e-9, 2.0 * k_design)
        KH2, NI2 = np.meshgrid(kh_f, ni_f, indexing="ij")
        w2 = worst(KH2, NI2)
        i2, j2 = np.unravel_index(int(np.argmin(w2)), w2.shape)
        kh = np.array([KH2[i2, j2]])
        nti = np.array([NI2[i2, j2]])
    rho_reported = float(
        max(spectral_radius_grid(k_o, kh + a * nti, nti, b_o, delay_ticks)[0] for a in phases)
    )
    rho_worst = float(worst(kh, nti)[0])
    return GainChoice(
        k_h=float(kh[0]),
        i_gain=float(nti[0] / nt),
        spectral_radius=rho_reported,
        worst_spectral_radius=rho_worst,
        stable=rho_reported < 1.0 - STABILITY_TOL,
    )
