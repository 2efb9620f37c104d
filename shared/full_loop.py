"""The full haptic loop: hand + device, local model, slow delayed simulation (DESIGN section 6b).

The paper (sections 2-5) proves the *simulation loop* stable with the probe treated as a position
source. A user holds the device, so hand and device close a second loop at the servo rate through
the local model, and the simulation-rate proxy jumps excite it. This module models the complete
N-periodic system exactly and judges it by the spectral radius of its monodromy matrix (the
state-transition matrix over one simulation period).

One-dimensional, along the contact normal, linearised in contact (the threshold theta and the
unilateral contact are affine offsets or switches and do not change the linear verdict; the
time-domain passivity layer is the safety net for those, :mod:`shared.passivity`). Coordinates are
depths along the inward normal [m]: ``x`` the probe, ``p`` the proxy (surface) the servo renders
against, ``e = x - p`` the penetration.

Blocks, servo tick n (period T), simulation tick k (period N*T):

hand + device
    ``m x'' = -b x' - k x - f``: total moving mass m [kg], damping b [N*s/m], stiffness k [N/m]
    toward a still target (its offset does not change stability); the force f [N] the local model
    writes pushes the probe out and is held over the tick (zero-order hold, discretised exactly).
    ``hand=None`` is the paper's rigid probe (a position source, x = 0).
local model (servo rate, eq. 12 plus an optional probe damper)
    ``f(n) = K_h e(n) + s(n) + B_h u(n)``, ``s(n+1) = s(n) + T I e(n)``, with the probe velocity
    ``u(n) = (1 - a) u(n-1) + a (x(n) - x(n-1)) / T`` low-pass filtered (``a = T / (T + tau)``,
    tau = :data:`DAMPER_FILTER_S`: one encoder count would otherwise be a force step of
    B_h * count / T). The damper acts on the probe only, never on the proxy's jumps.
decimation (Step 3 of section 6)
    the simulation takes the force of servo tick ``j`` (``sample_tick``) of each block.
object (simulation rate), eq. 6 / eq. 9
    ``x_o(k+1) = (F(k) + B_o x_o(k)) / (K_o + B_o)``: K_o and B_o are what the server reports
    of the object at a contact, and all the local model knows of it (the protocol carries no
    more); eq. 9 lumps whatever holds a push beyond one tick (mass, relaxation) into the damper.
delay
    ``D`` whole extra simulation ticks (network, computation) before ``x_o`` reaches the servo.
proxy hold
    ``zoh``: the proxy jumps to the new surface at the block boundary (eq. 1); ``foh``: it moves
    linearly from the previous surface to the new one over the block, reaching it at the last tick
    (``p(i) = p_old + (p_new - p_old) (i + 1) / N``), one simulation period of smoothing.
own-force compensation (optional; not in the paper)
    the proxy the servo renders against is the reported surface moved out by ``C_h F_s``, where
    ``F_s`` is the force the simulation applied from this user when it computed that surface and
    C_h [m/N] the compensation gain: with ``C_h = 1 / K_o`` the proxy is where the surface would
    be without the user's own push (the object's rest surface for a single user), so a P local
    model with ``K_h = K_o`` renders K_o itself and the simulation loop carries only the model's
    error. Other users' pushes still move the proxy. ``C_h = 0`` is the paper's local model.

With ``hand=None``, ``b_h = 0`` and ``zoh`` the monodromy matrix has the same non-zero eigenvalues
as :func:`shared.stability.closed_loop_matrix` (the paper's Fig. 6 loop): tested to 1e-9.

Everything is vectorised over a batch of hands and gains (numpy broadcasting): the gain design
(:mod:`shared.gains.design`) evaluates thousands of candidates at once.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal, ParamSpec

import numpy as np
from scipy.linalg import expm

from haptic_collab.shared.checks import (
    NonNegFinite,
    PositiveFinite,
    nonneg,
    params_dataclass,
    positive,
)
from haptic_collab.shared.checks import whole as _whole
from haptic_collab.shared.rates import Rates
from haptic_collab.shared.types import FloatArray

ProxyHold = Literal["zoh", "foh"]

_P = ParamSpec("_P")

#: Spectral radii below 1 - STABILITY_TOL count as stable (guards marginal round-off).
STABILITY_TOL = 1e-9

#: Time constant [s] of the first-order filter on the probe velocity of the damper B_h (the
#: servo uses the same): 5 ms, a 32 Hz corner, well above the hand's 1-10 Hz motion.
DAMPER_FILTER_S = 0.005


@params_dataclass(frozen=True, slots=True)
class Hand:
    """Combined hand and device as the probe feels them, SI units (DESIGN section 6b).

    Parameters
    ----------
    mass_kg : float
        Total moving mass m [kg] (hand + device handle), > 0.
    damping_n_s_per_m : float
        Total damping b [N*s/m] (hand + device friction), >= 0.
    stiffness_n_per_m : float
        Hand stiffness k [N/m] toward where the user wants to be, >= 0.

    Raises
    ------
    pydantic.ValidationError
        (a ValueError naming the field) Non-finite, non-numeric or out-of-range values.
    """

    mass_kg: PositiveFinite
    damping_n_s_per_m: NonNegFinite
    stiffness_n_per_m: NonNegFinite

    def as_dict(self) -> dict[str, float]:
        """``{"mass_kg", "stiffness_n_per_m", "damping_n_s_per_m"}``."""
        return {
            "mass_kg": self.mass_kg,
            "stiffness_n_per_m": self.stiffness_n_per_m,
            "damping_n_s_per_m": self.damping_n_s_per_m,
        }


#: The project's simulated user (client.devices.sim: 0.45 kg hand, 300 N/m, 5 N*s/m) on the
#: simulated Phantom Desktop (0.045 kg, 0.5 N*s/m), as the probe feels them.
DEFAULT_HAND = Hand(mass_kg=0.495, damping_n_s_per_m=5.5, stiffness_n_per_m=300.0)


@params_dataclass(frozen=True, slots=True)
class HandBox:
    """A box of plausible combined hand + device parameters (README "The hand box" for sources).

    Gains are accepted only if the full loop is stable for every hand the box yields
    (:meth:`hands`): its 8 corners, the centres of its faces, its centre and the ``extra`` hands.

    Parameters
    ----------
    mass_kg, damping_n_s_per_m, stiffness_n_per_m : (lo, hi)
        Ranges [kg], [N*s/m], [N/m]; lo <= hi, lo > 0 for the mass.
    extra : tuple of Hand
        Hands checked besides the box's points (the simulated hand by default).

    Raises
    ------
    pydantic.ValidationError
        (a ValueError naming the field) A range that is not a tuple of two finite numbers >= 0
        (> 0 for the mass) with lo <= hi.
    """

    mass_kg: tuple[PositiveFinite, PositiveFinite] = (0.1, 0.6)
    damping_n_s_per_m: tuple[NonNegFinite, NonNegFinite] = (2.0, 10.0)
    stiffness_n_per_m: tuple[NonNegFinite, NonNegFinite] = (20.0, 1000.0)
    extra: tuple[Hand, ...] = (DEFAULT_HAND,)

    def __post_init__(self) -> None:
        for name in ("mass_kg", "damping_n_s_per_m", "stiffness_n_per_m"):
            lo, hi = getattr(self, name)
            if not lo <= hi:
                raise ValueError(f"hand box {name} must have lo <= hi, got ({lo!r}, {hi!r})")

    def hands(self) -> list[Hand]:
        """A lattice over the box, then ``extra``: 5 masses x 3 dampings x 5 stiffnesses.

        Stability is not monotone in the hand's mass or stiffness (a lightly damped hand has its
        worst mass between the corners), so the corners alone are not enough; tests re-check
        designs on an independent 4 x 4 x 4 lattice.
        """
        out: list[Hand] = []
        for mi in np.linspace(*self.mass_kg, 5):
            for bi in np.linspace(*self.damping_n_s_per_m, 3):
                for ki in np.linspace(*self.stiffness_n_per_m, 5):
                    h = Hand(float(mi), float(bi), float(ki))
                    if h not in out:
                        out.append(h)
        for h in self.extra:
            if h not in out:
                out.append(h)
        return out

    def corners(self) -> list[Hand]:
        """The 8 corners of the box."""
        return [
            Hand(mi, bi, ki)
            for mi in self.mass_kg
            for bi in self.damping_n_s_per_m
            for ki in self.stiffness_n_per_m
        ]

    def screen_hands(self) -> list[Hand]:
        """The 8 corners, the centre and ``extra``, without repeats.

        Fewer than :meth:`hands`: the gain design's quick screen before the full check, and each
        user's hands in :func:`shared.coupled_loop.verify_coupled`.
        """
        centre = Hand(
            0.5 * sum(self.mass_kg),
            0.5 * sum(self.damping_n_s_per_m),
            0.5 * sum(self.stiffness_n_per_m),
        )
        return list(dict.fromkeys([*self.corners(), centre, *self.extra]))

    def as_dict(self) -> dict[str, list[float]]:
        """``{"mass_kg": [lo, hi], "stiffness_n_per_m": [lo, hi], "damping_n_s_per_m": [lo, hi]}``."""
        return {
            "mass_kg": list(self.mass_kg),
            "stiffness_n_per_m": list(self.stiffness_n_per_m),
            "damping_n_s_per_m": list(self.damping_n_s_per_m),
        }


#: The hand box every gain design is checked against (README, "The hand box").
DEFAULT_HAND_BOX = HandBox()


def object_coefficients(
    k_o: FloatArray | float, b_o: FloatArray | float
) -> tuple[FloatArray, FloatArray]:
    """The object's step (eq. 9, module docstring "object"), broadcast over arrays: for K_o
    [N/m] and B_o [N/m] (negative counts as 0), ``inv = 1 / (K_o + B_o)`` and the coefficient
    ``c_x = B_o`` of ``x_o(k)`` in ``x_o(k+1) = inv (F + c_x x_o(k))``."""
    ko, bo = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (k_o, b_o)))
    damper = np.maximum(bo, 0.0)
    return 1.0 / (damper + ko), damper


def object_impedance(
    freq_hz: FloatArray | float,
    k_o: FloatArray | float,
    b_o: FloatArray | float,
    sim_period_s: FloatArray | float,
) -> FloatArray:
    """The stepped object's dynamic stiffness dF/dx [N/m] (complex) at ``freq_hz`` [Hz], what a
    transparent rendering is felt as, broadcast over arrays: eq. 9's ``K_o + B_o (1 - z^-1)`` at
    ``z = e^{j w h}``, h the simulation period [s] (B_o negative counts as 0)."""
    _, c_x = object_coefficients(k_o, b_o)
    zi = np.exp(-2j * np.pi * np.asarray(freq_hz, dtype=float) * np.asarray(sim_period_s))
    return np.asarray(k_o) + c_x * (1.0 - zi)


def _hand_zoh(
    m: FloatArray, b: FloatArray, k: FloatArray, period_s: float
) -> tuple[FloatArray, FloatArray]:
    """Exact ZOH discretisation of ``m x'' = -b x' - k x - f``: Phi (B, 2, 2), Gamma (B, 2).

    One matrix exponential per distinct hand (a batch repeats few hands many times).
    """
    hands, inverse = np.unique(np.stack([m, b, k], axis=1), axis=0, return_inverse=True)
    mu, bu, ku = hands[:, 0], hands[:, 1], hands[:, 2]
    aug = np.zeros((hands.shape[0], 3, 3))
    aug[:, 0, 1] = 1.0
    aug[:, 1, 0] = -ku / mu
    aug[:, 1, 1] = -bu / mu
    aug[:, 1, 2] = -1.0 / mu
    e = expm(aug * period_s)[inverse.reshape(-1)]
    return e[:, :2, :2], e[:, :2, 2]


def batch_arrays(*values: float | FloatArray) -> list[FloatArray]:
    """``values`` as contiguous float arrays broadcast to one batch shape, each at least (1,).

    A scalar stands for every batch element.

    Raises
    ------
    ValueError
        Shapes that do not broadcast.
    """
    arrays = [np.atleast_1d(np.asarray(v, dtype=float)) for v in values]
    return [np.ascontiguousarray(a) for a in np.broadcast_arrays(*arrays)]


def _fast_system(
    hand: tuple[FloatArray, FloatArray, FloatArray] | None,
    k_h: FloatArray,
    i_gain: FloatArray,
    b_h: FloatArray,
    period_s: float,
    integral: bool,
    damper_filter_s: float = DAMPER_FILTER_S,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Servo-rate closed hand + local model with the proxy as input.

    Returns A (B, n, n), Bp (B, n), C (B, n), D (B,) with ``xi' = A xi + Bp p``, ``f = C xi + D p``.
    State: [x, v, (s), x_prev, u_prev] with a hand; [(s)] for a rigid probe.
    """
    nb = k_h.shape[0]
    T = period_s
    if hand is None:
        n = 1 if integral else 0
        A = np.ones((nb, n, n))
        Bp = np.zeros((nb, n))
        C = np.zeros((nb, n))
        if integral:
            Bp[:, 0] = -T * i_gain
            C[:, 0] = 1.0
        return A, Bp, C, -k_h
    m, b, k = hand
    phi, gam = _hand_zoh(m, b, k, T)
    a = T / (T + damper_filter_s)
    n = 5 if integral else 4
    ix, ip, iu = 0, n - 2, n - 1
    C = np.zeros((nb, n))
    C[:, ix] = k_h + b_h * a / T
    C[:, ip] = -b_h * a / T
    C[:, iu] = b_h * (1.0 - a)
    if integral:
        C[:, 2] = 1.0
    D = -k_h
    A = np.zeros((nb, n, n))
    A[:, :2, :2] = phi
    A[:, ip, ix] = 1.0
    A[:, iu, ix] = a / T
    A[:, iu, ip] = -a / T
    A[:, iu, iu] = 1.0 - a
    Bu = np.zeros((nb, n))
    Bu[:, :2] = gam
    Bp = Bu * D[:, None]
    if integral:
        A[:, 2, 2] = 1.0
        A[:, 2, ix] += T * i_gain
        Bp[:, 2] = -T * i_gain
    A = A + Bu[:, :, None] * C[:, None, :]
    return A, Bp, C, D


def monodromy(
    *,
    hand: Hand | Sequence[Hand] | None,
    k_o: float | FloatArray,
    k_h: float | FloatArray,
    i_gain: float | FloatArray = 0.0,
    b_h: float | FloatArray = 0.0,
    b_o: float | FloatArray = 0.0,
    servo_period_s: float = 1e-3,
    rate_ratio: int = 50,
    delay_ticks: int = 0,
    sample_ticks: Sequence[int] | None = None,
    proxy_hold: ProxyHold = "zoh",
    integral: bool | None = None,
    own_gain: float | FloatArray = 0.0,
) -> FloatArray:
    """Monodromy matrices of the full loop over one simulation period (module docstring).

    Parameters
    ----------
    hand : Hand, sequence of Hand, or None
        The combined hand + device (None: rigid probe, the paper's position source). A sequence is
        one hand per batch element.
    k_o, k_h, i_gain, b_h, b_o : float or (B,) array
        K_o [N/m], K_h [N/m], I [N/(m*s)], probe damper B_h [N*s/m], B_o [N/m]; broadcast to the
        batch size B.
    servo_period_s : float
        T [s].
    rate_ratio : int
        N, servo ticks per simulation tick, >= 1.
    delay_ticks : int
        Extra whole simulation ticks of delay D, >= 0.
    sample_ticks : sequence of int, optional
        Servo ticks j in [0, N) at which the simulation samples the force (default: all N).
    proxy_hold : {"zoh", "foh"}
    integral : bool, optional
        Model the integral state (default: any ``i_gain > 0``). Without it I is ignored.
    own_gain : float or (B,) array
        Own-force compensation C_h [m/N] (module docstring), >= 0; 0: the paper's local model.

    Returns
    -------
    (B, J, n, n) float array
        One monodromy matrix per batch element and sampling tick; the state is
        [fast states, proxy, (previous proxy), object, delay line] (:func:`slow_layout`).

    Raises
    ------
    ValueError
        Out-of-range rate ratio, delay, sampling ticks or hold.
    """
    if rate_ratio < 1:
        raise ValueError(f"rate_ratio must be >= 1, got {rate_ratio}")
    if delay_ticks < 0:
        raise ValueError(f"delay_ticks must be >= 0, got {delay_ticks}")
    if proxy_hold not in ("zoh", "foh"):
        raise ValueError(f"proxy_hold must be 'zoh' or 'foh', got {proxy_hold!r}")
    N, T = int(rate_ratio), float(servo_period_s)
    js = list(range(N)) if sample_ticks is None else [int(j) for j in sample_ticks]
    if not js or any(not 0 <= j < N for j in js):
        raise ValueError(f"sample ticks must be in [0, {N}), got {sample_ticks!r}")
    hands: list[Hand] | None
    if hand is None:
        hands = None
    elif isinstance(hand, Hand):
        hands = [hand]
    else:
        hands = list(hand)
    hand_params: list[FloatArray] = []
    if hands is not None:
        hand_params = [
            np.array([h.mass_kg for h in hands]),
            np.array([h.damping_n_s_per_m for h in hands]),
            np.array([h.stiffness_n_per_m for h in hands]),
        ]
    arrays = batch_arrays(k_o, k_h, i_gain, b_h, b_o, own_gain, *hand_params)
    ko, kh, ig, bh, bo, og = arrays[:6]
    if integral is None:
        integral = bool(np.any(ig > 0.0))
    hand_arr = None if hands is None else (arrays[6], arrays[7], arrays[8])
    A, Bp, C, Dp = _fast_system(hand_arr, kh, ig, bh, T, integral)
    nb, nf = A.shape[0], A.shape[1]
    foh = proxy_hold == "foh"
    # proxy inputs over the block: p(i) = w_old(i) p_old + w_new(i) p
    if foh:
        w_new = (np.arange(N) + 1.0) / N
    else:
        w_new = np.ones(N)
    w_old = 1.0 - w_new
    # propagate xi(i) = Phi_i xi0 + G_old_i p_old + G_new_i p, recording F at the sampled ticks
    Phi = np.broadcast_to(np.eye(nf), (nb, nf, nf)).copy()
    Gn = np.zeros((nb, nf))
    Go = np.zeros((nb, nf))
    want = {j: idx for idx, j in enumerate(js)}
    F_xi = np.zeros((nb, len(js), nf))
    F_new = np.zeros((nb, len(js)))
    F_old = np.zeros((nb, len(js)))
    for i in range(N):
        idx = want.get(i)
        if idx is not None:
            F_xi[:, idx] = np.einsum("bn,bnm->bm", C, Phi)
            F_new[:, idx] = np.einsum("bn,bn->b", C, Gn) + Dp * w_new[i]
            F_old[:, idx] = np.einsum("bn,bn->b", C, Go) + Dp * w_old[i]
        Phi = A @ Phi
        Gn = np.einsum("bnm,bm->bn", A, Gn) + Bp * w_new[i]
        Go = np.einsum("bnm,bm->bn", A, Go) + Bp * w_old[i]
    # slow state: [xi (nf), p, (p_old), x_obj, q_1..q_D]
    D = int(delay_ticks)
    lay = slow_layout(nf, foh, D)
    i_p, i_po, i_obj, i_q, n = lay.proxy, lay.proxy_old, lay.obj, lay.delay, lay.n
    M = np.zeros((nb, len(js), n, n))
    M[:, :, :nf, :nf] = Phi[:, None]
    M[:, :, :nf, i_p] = Gn[:, None]
    if i_po is not None:
        M[:, :, :nf, i_po] = Go[:, None]
        M[:, :, i_po, i_p] = 1.0
    # object: x_obj' = inv (F + c_x x_obj) (eq. 9: c_x = B_o, inv = 1 / (K_o + B_o)),
    # F = F_xi xi + F_new p + F_old p_old
    inv, c_x = object_coefficients(ko, bo)
    obj_row = np.zeros((nb, len(js), n))
    obj_row[:, :, :nf] = F_xi * inv[:, None, None]
    obj_row[:, :, i_p] = F_new * inv[:, None]
    if i_po is not None:
        obj_row[:, :, i_po] = F_old * inv[:, None]
    obj_row[:, :, i_obj] = (c_x * inv)[:, None]
    M[:, :, i_obj, :] = obj_row
    # the proxy delivered: the new surface moved out by C_h times the force sampled
    proxy_row = obj_row.copy()
    proxy_row[:, :, :nf] -= F_xi * og[:, None, None]
    proxy_row[:, :, i_p] -= F_new * og[:, None]
    if i_po is not None:
        proxy_row[:, :, i_po] -= F_old * og[:, None]
    if D == 0:
        M[:, :, i_p, :] = proxy_row
    else:
        M[:, :, i_p, i_q] = 1.0
        for r in range(D - 1):
            M[:, :, i_q + r, i_q + r + 1] = 1.0
        M[:, :, i_q + D - 1, :] = proxy_row
    return M


@dataclass(frozen=True)
class SlowLayout:
    """Where each slow state is in :func:`monodromy`'s matrices (None: absent); ``n`` states."""

    proxy: int
    proxy_old: int | None
    obj: int
    delay: int
    n: int


def slow_layout(nf: int, foh: bool, delay_ticks: int) -> SlowLayout:
    """The slow state's layout after ``nf`` fast states (:func:`monodromy`): the proxy, the
    previous proxy (``foh``), the object's depth and ``delay_ticks`` delay-line states, in that
    order."""
    i = nf + (2 if foh else 1)
    return SlowLayout(nf, nf + 1 if foh else None, i, i + 1, i + 1 + int(delay_ticks))


def spectral_radius_function(
    build: Callable[_P, FloatArray], *, name: str, doc: str
) -> Callable[_P, FloatArray]:
    """The function ``max |eigenvalue|`` of the matrices ``build`` returns, with its parameters.

    ``build`` returns monodromy matrices (..., n, n); the new function, named ``name`` with
    docstring ``doc``, returns their spectral radii, shape (...) (zeros for 0 x 0 matrices).
    It raises what ``build`` raises.
    """

    @functools.wraps(build)
    def radius(*args: _P.args, **kwargs: _P.kwargs) -> FloatArray:
        M = build(*args, **kwargs)
        if M.shape[-1] == 0:
            return np.zeros(M.shape[:-2])
        return np.max(np.abs(np.linalg.eigvals(M)), axis=-1)

    radius.__name__ = radius.__qualname__ = name
    radius.__doc__ = doc
    return radius


spectral_radius = spectral_radius_function(
    monodromy,
    name="spectral_radius",
    doc="""Spectral radius of the full loop per batch element and sampling tick, shape (B, J).

    Same parameters as :func:`monodromy`. A value below 1 means every mode of hand, device, local
    model and object decays from one simulation period to the next.
    """,
)


@dataclass(frozen=True)
class FullLoopAnalysis:
    """Verdict on the full loop for one hand, gains and object (worst sampling tick).

    Attributes
    ----------
    stable : bool
        Spectral radius below 1 at every sampling tick.
    spectral_radius : float
        Largest over the sampling ticks.
    worst_sample_tick : int
        The sampling tick j at which it occurs.
    """

    stable: bool
    spectral_radius: float
    worst_sample_tick: int

    def to_json(self) -> dict[str, object]:
        """``{"stable", "spectral_radius", "worst_sample_tick"}``."""
        return {
            "stable": self.stable,
            "spectral_radius": self.spectral_radius,
            "worst_sample_tick": self.worst_sample_tick,
        }


def analyze_full_loop(
    hand: Hand | None,
    *,
    k_o: float,
    k_h: float,
    i_gain: float = 0.0,
    b_h: float = 0.0,
    damping: float = 0.0,
    servo_rate_hz: float = 1000.0,
    sim_rate_hz: float = 20.0,
    delay_ticks: int = 0,
    sample_tick: int | None = None,
    proxy_hold: ProxyHold = "zoh",
    own_gain: float = 0.0,
) -> FullLoopAnalysis:
    """The full-loop verdict for one case, in the units of :func:`shared.stability.analyze`.

    Parameters
    ----------
    hand : Hand or None
        Combined hand + device (None: rigid probe).
    k_o, k_h, i_gain, b_h : float
        K_o [N/m] > 0, K_h [N/m] > 0, I [N/(m*s)] >= 0, probe damper B_h [N*s/m] >= 0.
    damping : float
        Object damping b [N*s/m]; B_o = b / (N*T) (eq. 9).
    servo_rate_hz, sim_rate_hz : float
        The servo rate must be a whole multiple of the simulation rate.
    delay_ticks : int
        Extra whole simulation ticks of delay.
    sample_tick : int, optional
        One sampling tick; default: the worst over all N.
    proxy_hold : {"zoh", "foh"}
    own_gain : float
        Own-force compensation C_h [m/N] >= 0 (module docstring).

    Raises
    ------
    ValueError
        Out-of-range or inconsistent input.
    """
    rates = Rates(servo_rate_hz, sim_rate_hz)
    n = rates.ratio
    for name, v in (("k_o", k_o), ("k_h", k_h)):
        positive(name, v)
    for name, v in (("i_gain", i_gain), ("b_h", b_h), ("damping", damping), ("own_gain", own_gain)):
        nonneg(name, v)
    _whole("delay_ticks", delay_ticks, 0)
    js = list(range(n)) if sample_tick is None else [int(sample_tick)]
    rho = spectral_radius(
        hand=hand,
        k_o=k_o,
        k_h=k_h,
        i_gain=i_gain,
        b_h=b_h,
        b_o=damping * sim_rate_hz,
        servo_period_s=rates.servo_period_s,
        rate_ratio=n,
        delay_ticks=int(delay_ticks),
        sample_ticks=js,
        proxy_hold=proxy_hold,
        own_gain=own_gain,
    )[0]
    w = int(np.argmax(rho))
    r = float(rho[w])
    return FullLoopAnalysis(
        stable=r < 1.0 - STABILITY_TOL, spectral_radius=r, worst_sample_tick=js[w]
    )
