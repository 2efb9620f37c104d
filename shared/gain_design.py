"""Local model gains with the hand in the loop: the most transparent gains the full loop allows.

Step 2 of the paper's section 6 picks K_h and I inside the stability region of the *simulation
loop* (probe as a position source). This module picks them inside the stability region of the
*full loop* (:mod:`shared.full_loop`): the gains are accepted only if the loop is stable, with a
decay-rate margin, for

- every hand of the hand box (:class:`shared.full_loop.HandBox`),
- every servo tick j at which the simulation may sample the force (Step 3 over a network),
- every object stiffness K_o' in ``[(1 - margin) K_o, K_o]`` (the paper's advice to design for a
  lower K_o than reported) and, for the product's :class:`GainTable` designs, up to
  ``1 + stiffer_by`` times the top of the cell (:attr:`GainKey.stiffer_by`: an object stiffer
  than reported, docs/fidelity.md),

and among those the one with the best *transparency*: the felt stiffness |dF/dx| at the probe,
probe as a position source, relative to K_o. For the paper's models alone, at 1 Hz (then 8 Hz
to break ties); with own-force compensation (the product), its largest error |ln |q|| over the
band :data:`FELT_BAND_HZ` (0.5-8 Hz) and in a held press, compared in steps of
:data:`DESIGN_TIE` (half a stiffness JND), then the same on objects ``1 + stiffer_by`` times
softer and stiffer than reported. A
:class:`GainTable` design serves every K_o reported in its cell, scaled to it (K_h and I in
proportion, :meth:`GainDesign.at`; ``scaled``), so its transparency is judged at the cell's two
ends and middle, the worst of them counting, then their mean (``felt_k_os``), and each scale is
checked like the design.
Besides K_h (P) and K_h, I (PI), the design may use

- a probe damper B_h on the backward difference of the probe position, in contact only, up to the
  device's ``b_h_max``;
- a first-order-hold proxy (``foh``): the proxy moves linearly to each new surface over the next
  simulation period instead of jumping (``zoh``);
- own-force compensation C_h (:mod:`shared.full_loop`; not in the paper), for a proportional
  local model: the proxy is the reported surface moved out by C_h times the force F_s the
  simulation applied from this user, ``F = K_h (x - x_o) + C_h K_h F_s``. With C_h K_h = 1 the
  force is the last applied one corrected by the coupling, and a held press settles with the
  probe on the surface at ``F = K_o x``: the object's own stiffness, whatever K_h (the simulation
  loop's static gain is ``1 - K_h / K_o``) and whatever the error in the reported K_o. At K_h =
  K_o it is rendered at the servo rate and the simulation loop carries only the model's error,
  so K_h is no longer bounded by K_o; above the device's stiffness the stiffness comes through
  the (contracting) simulation loop. In general the felt stiffness at DC is ``K_h K_o / (K_o + (1
  - C_h K_o) K_h)``. Not with an integral (it would hold the probe at the compensated surface:
  infinitely stiff at DC). Used by the product
  (:attr:`GainKey.own_force`); a ``pi`` design may then be a compensated P model (I = 0) when
  that is closer to K_o over the band and at DC than any PI one;
- for K_o above the device's stiffness, the plane at the rest surface the simulation's model
  gives, C_h = 1 / K_o with K_h at (or just below) the device's stiffness: felt as K_h at every
  frequency of the band (model-mediated teleoperation: Mitra and Niemeyer 2008), where the
  paper's P model feels ``K_h K_o / (K_h + K_o)`` and its PI creeps toward K_o at 0.5 Hz but
  falls to 0.2-0.3 K_o at 4 Hz.

Felt stiffness is computed exactly on the lifted (N-periodic) loop: for a probe motion
``x(n) = Re(X e^{j w n T})`` the steady state of the lifted loop at ``z = e^{j w N T}`` gives the
servo-rate force over one block, whose component at w (the fundamental) over X is the felt
stiffness. For a P local model on an elastic object at low frequency it tends to
``K_h K_o / (K_h + K_o)``; for PI to K_o.

:class:`GainTable` caches designs on a geometric grid of K_o so that a client's network loop only
looks gains up (the design itself runs off the loop).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Literal, TypeVar

import numpy as np

from haptic_collab.shared.checks import positive as _positive
from haptic_collab.shared.checks import whole as _whole
from haptic_collab.shared.full_loop import (
    DAMPER_FILTER_S,
    DEFAULT_HAND_BOX,
    Hand,
    HandBox,
    ProxyHold,
    batch_arrays,
    monodromy,
)
from haptic_collab.shared.gain_key import (
    K_O_GRID_RATIO,
    GainKey,
    Mode,
    coupled_k_o_hi,
)
from haptic_collab.shared.rates import Rates
from haptic_collab.shared.types import FloatArray, IndexArray

_G = TypeVar("_G", float, FloatArray)

#: Slowest accepted decay of any *oscillating* mode of the full loop [1/s]: its eigenvalue over
#: one simulation period must have magnitude at most exp(-MIN_DECAY_RATE * N * T). 1/s: a
#: vibration falls to a third within a second; the box's least damped hand (0.6 kg, 2 N*s/m) alone
#: decays at 1.7/s.
MIN_DECAY_RATE_PER_S = 1.0

#: C_h K_h values the design tries with own-force compensation (module docstring). At 1 the
#: local model is ``F = K_h (x - x_o) + F_s``: in a held press the probe settles on the surface
#: with ``F = K_o x``, the object's own stiffness whatever K_h and whatever the error in K_o (the
#: simulation loop's static gain ``1 - K_h / K_o`` must stay inside (-1, 1)); for coupled users
#: the held press is the object's own physics, the others' pushes included. Ratios below 1 feel
#: softer in a held press; they won only at K_o above the device's stiffness, where the paper's PI
#: does as well, and made a contact's rendering change with its coupling class (a user resting
#: with 0.42 N felt 0.40 N while another pressed), so they are not tried. The one exception is
#: the plane above the device's stiffness (C_h = 1 / K_o with K_h capped below K_o,
#: :func:`design_gains`): there no ratio of 1 can be rendered.
OWN_FORCE_RATIOS: tuple[float, ...] = (1.0,)

#: Frequencies [Hz] the transparency of a design with own-force compensation is judged at: the
#: band of voluntary hand motion in which people judge stiffness by pressing (0.5-8 Hz; the
#: fidelity benchmark ranks over the same band, docs/fidelity.md). At 1 Hz alone a 10 N*s/m damper
#: at 1000 N/m passed as 1.00 K_o while a hand felt it as 1.12-1.22 K_o at 8 Hz.
FELT_BAND_HZ: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0, 8.0)

#: Step [ln of the felt stiffness ratio] in which a design's error on the design model is
#: compared (:func:`design_gains`): half the fidelity benchmark's tie, ln(1.1) (a stiffness JND of
#: 10 %, docs/fidelity.md). Within a step, the design more transparent on an object stiffer or
#: softer than reported (:attr:`GainKey.stiffer_by`) wins.
DESIGN_TIE = 0.5 * math.log(1.1)

#: Modes slower than this [Hz] are creep, not vibration (the integral slowly pushing a stiff hand
#: out): they need only be stable (|eigenvalue| < 1), not decay at MIN_DECAY_RATE_PER_S.
CREEP_FREQUENCY_HZ = 0.5


@dataclass(frozen=True)
class GainDesign:
    """Gains for one object stiffness, with their robustness and transparency (SI units).

    Attributes
    ----------
    k_h : float
        K_h [N/m].
    i_gain : float
        I [N/(m*s)] (0: proportional local model).
    b_h : float
        Probe damper B_h [N*s/m], in contact only.
    proxy_hold : {"zoh", "foh"}
    worst_spectral_radius : float
        Largest spectral radius of the full loop over the hand box, every sampling tick and the
        K_o range: below 1; every oscillating mode is below ``rho_limit``.
    rho_limit : float
        exp(-MIN_DECAY_RATE * N * T): the bound oscillating modes respect (slow creep of the
        integral, below :data:`CREEP_FREQUENCY_HZ`, need only be stable).
    felt_stiffness_ratio_1hz, felt_stiffness_ratio_8hz : float
        |dF/dx| / K_o at the probe (position source) at 1 Hz and 8 Hz.
    k_o : float
        K_o [N/m] designed for; the design holds for K_o' in ``k_o_range``.
    k_o_range : (float, float)
        Object stiffness interval [N/m] checked.
    rate_ratio, delay_ticks : int
    mode : {"p", "pi"}
    hand_box : HandBox
    design_ms : float
        Wall time the design took [ms], set by whoever ran it (:func:`haptic_collab.workers.timed`;
        this module reads no clock); 0 when not measured. Informative: ``haptic bench gains``
        measures properly.
    own_gain : float
        Own-force compensation C_h [m/N] (module docstring), >= 0; 0: the paper's local model.
    scale_max : float
        >= 1. Above 1 the gains scale with the reported K_o (:meth:`at`): K_h and I by s =
        K_o / ``k_o``, C_h by 1 / s, B_h unchanged, for s in [1, ``scale_max``], checked like the
        design itself at s = 1, its middle and top (:func:`design_gains`, ``scaled``). 1: the
        same gains for every K_o reported (the paper's models, interim and fallback gains,
        :func:`design_gains` without ``scaled``).
    """

    k_h: float
    i_gain: float
    b_h: float
    proxy_hold: ProxyHold
    worst_spectral_radius: float
    rho_limit: float
    felt_stiffness_ratio_1hz: float
    felt_stiffness_ratio_8hz: float
    k_o: float
    k_o_range: tuple[float, float]
    rate_ratio: int
    delay_ticks: int
    mode: Mode
    hand_box: HandBox = field(default=DEFAULT_HAND_BOX, repr=False)
    design_ms: float = 0.0
    own_gain: float = 0.0
    scale_max: float = 1.0

    def at(self, k_o: float) -> GainDesign:
        """The gains to render for a reported K_o [N/m] (``scale_max``), s clamped to
        [1, ``scale_max``]: K_h, I times s, C_h over s, B_h as designed; ``k_o`` times s and
        the lower end of ``k_o_range`` times s (what those gains were checked over), and
        ``scale_max`` over s, so ``d.at(k).at(k) == d.at(k)``. A design with ``scale_max == 1``
        is returned as is.

        Raises
        ------
        ValueError
            A K_o that is not finite and > 0.
        """
        _positive("k_o", k_o)
        if self.scale_max <= 1.0:
            return self
        s = min(max(k_o / self.k_o, 1.0), self.scale_max)
        if s <= 1.0 + 1e-12:  # (rounding: the design scaled to k_o is at k_o already)
            return self
        k_h, i_gain, own_gain = _scaled_gains(self.k_h, self.i_gain, self.own_gain, s)
        lo, hi = self.k_o_range
        return replace(
            self,
            k_h=k_h,
            i_gain=i_gain,
            own_gain=own_gain,
            k_o=self.k_o * s,
            k_o_range=(lo * s, hi),
            scale_max=self.scale_max / s,
        )

    def to_json(self) -> dict[str, object]:
        """The ``haptic gains --json`` object."""
        return {
            "k_h": self.k_h,
            "i_gain": self.i_gain,
            "b_h": self.b_h,
            "proxy_hold": self.proxy_hold,
            "worst_spectral_radius": self.worst_spectral_radius,
            "rho_limit": self.rho_limit,
            "hand_box": self.hand_box.as_dict(),
            "felt_stiffness_ratio_1hz": self.felt_stiffness_ratio_1hz,
            "felt_stiffness_ratio_8hz": self.felt_stiffness_ratio_8hz,
            "k_o": self.k_o,
            "k_o_range": list(self.k_o_range),
            "rate_ratio": self.rate_ratio,
            "delay_ticks": self.delay_ticks,
            "local_model": self.mode,
            "own_gain": self.own_gain,
            "scale_max": self.scale_max,
            "design_ms": self.design_ms,
        }


def felt_stiffness(
    freq_hz: float,
    *,
    k_o: float | FloatArray,
    k_h: float | FloatArray,
    i_gain: float | FloatArray = 0.0,
    b_h: float | FloatArray = 0.0,
    b_o: float | FloatArray = 0.0,
    servo_period_s: float = 1e-3,
    rate_ratio: int = 50,
    delay_ticks: int = 0,
    sample_tick: int | None = None,
    proxy_hold: ProxyHold = "zoh",
    complex_response: bool = False,
    own_gain: float | FloatArray = 0.0,
) -> FloatArray:
    """Felt stiffness |dF/dx| [N/m] at the probe, probe as a position source, shape (B,).

    Exact fundamental-harmonic response of the N-periodic loop (module docstring) to a probe motion
    at ``freq_hz``; the other parameters as in :func:`shared.full_loop.monodromy`. The simulation
    samples the force at ``sample_tick`` (default N - 1: the latest force, Step 3).

    Raises
    ------
    ValueError
        ``freq_hz`` not in (0, servo rate / 2), or as :func:`shared.full_loop.monodromy`.
    """
    f1 = felt_responses(
        (freq_hz,),
        k_o=k_o,
        k_h=k_h,
        i_gain=i_gain,
        b_h=b_h,
        b_o=b_o,
        servo_period_s=servo_period_s,
        rate_ratio=rate_ratio,
        delay_ticks=delay_ticks,
        sample_tick=sample_tick,
        proxy_hold=proxy_hold,
        own_gain=own_gain,
    )[0]
    return f1 if complex_response else np.abs(f1)


def felt_responses(
    freqs_hz: Sequence[float],
    *,
    k_o: float | FloatArray,
    k_h: float | FloatArray,
    i_gain: float | FloatArray = 0.0,
    b_h: float | FloatArray = 0.0,
    b_o: float | FloatArray = 0.0,
    servo_period_s: float = 1e-3,
    rate_ratio: int = 50,
    delay_ticks: int = 0,
    sample_tick: int | None = None,
    proxy_hold: ProxyHold = "zoh",
    own_gain: float | FloatArray = 0.0,
) -> FloatArray:
    """Felt responses dF/dx [N/m] (complex) at each of ``freqs_hz``, shape (F, B): the loop's
    monodromy computed once, then :func:`felt_stiffness` at each frequency.

    Raises
    ------
    ValueError
        A frequency not in (0, servo rate / 2), or as :func:`shared.full_loop.monodromy`.
    """
    N, T = int(rate_ratio), float(servo_period_s)
    for freq_hz in freqs_hz:
        if not (0.0 < freq_hz < 0.5 / T):
            raise ValueError(f"freq_hz must be in (0, {0.5 / T:g}), got {freq_hz!r}")
    j = N - 1 if sample_tick is None else int(sample_tick)
    ko, kh, ig, bh, bo, og = batch_arrays(k_o, k_h, i_gain, b_h, b_o, own_gain)
    integral = bool(np.any(ig > 0.0))
    M = monodromy(
        hand=None,
        own_gain=og,
        k_o=ko,
        k_h=kh,
        i_gain=ig,
        b_h=bh,
        b_o=bo,
        servo_period_s=T,
        rate_ratio=N,
        delay_ticks=delay_ticks,
        sample_ticks=[j],
        proxy_hold=proxy_hold,
        integral=integral,
    )[:, 0]
    nb, n = M.shape[0], M.shape[1]
    out = np.empty((len(freqs_hz), nb), dtype=complex)
    i_ticks = np.arange(N)
    a_f = T / (T + DAMPER_FILTER_S)
    ti = T * ig
    nf = 1 if integral else 0
    foh = proxy_hold == "foh"
    i_p, i_obj = nf, nf + (2 if foh else 1)
    inv = 1.0 / (ko + bo)
    row_new = i_p if delay_ticks == 0 else n - 1
    w_new = (i_ticks + 1.0) / N if foh else np.ones(N)
    for q, freq_hz in enumerate(freqs_hz):
        w = 2.0 * math.pi * freq_hz
        c = np.exp(1j * w * T * i_ticks)  # probe phasor at each tick of block 0
        z = np.exp(1j * w * N * T)
        # (B,) damper on the filtered backward difference of the probe (shared.full_loop)
        zi = np.exp(-1j * w * T)
        damp = bh * a_f * (1.0 - zi) / T / (1.0 - (1.0 - a_f) * zi)
        # probe contributions to the sampled force and to the next slow state
        csum = np.concatenate(([0.0], np.cumsum(c)))  # csum[i] = sum_{l<i} c_l
        fx = kh * c[j] + (ti * csum[j] if integral else 0.0) + damp * c[j]
        bx = np.zeros((nb, n), dtype=complex)
        if integral:
            bx[:, 0] = ti * csum[N]
        bx[:, i_obj] = fx * inv
        bx[:, row_new] = fx * (inv - og)
        Y = np.linalg.solve(z * np.eye(n)[None] - M, bx[:, :, None])[:, :, 0]
        p = Y[:, i_p]
        p_old = Y[:, nf + 1] if foh else p
        prox = np.outer(p_old, 1.0 - w_new) + np.outer(p, w_new)  # (B, N)
        e = c[None, :] - prox
        f = kh[:, None] * e + damp[:, None] * c[None, :]
        if integral:
            s0 = Y[:, 0]
            e_cum = np.concatenate((np.zeros((nb, 1)), np.cumsum(e, axis=1)[:, :-1]), axis=1)
            f = f + s0[:, None] + ti[:, None] * e_cum
        out[q] = (f * np.conj(c)[None, :]).mean(axis=1)
    return out


def mode_radii(
    M: FloatArray, rho_limit: float, rate_ratio: int, servo_period_s: float
) -> tuple[FloatArray, FloatArray]:
    """``(margin_radius, radius)`` of each monodromy matrix of ``M`` (..., n, n), each shape (...).

    ``radius`` is the spectral radius; ``margin_radius`` the largest eigenvalue magnitude with
    creep eigenvalues (slower than :data:`CREEP_FREQUENCY_HZ`: angle below
    ``2 pi CREEP_FREQUENCY_HZ N T`` per simulation period) counted as ``|lambda| * rho_limit``.
    """
    creep_angle = 2.0 * math.pi * CREEP_FREQUENCY_HZ * rate_ratio * servo_period_s
    ev = np.linalg.eigvals(M)
    mag = np.abs(ev)
    slow = np.abs(np.angle(ev)) < creep_angle
    return np.max(np.where(slow, mag * rho_limit, mag), axis=-1), np.max(mag, axis=-1)


def _worst_rho(
    cand: dict[str, FloatArray],
    hold: ProxyHold,
    hands: Sequence[Hand],
    k_os: Sequence[float],
    *,
    b_o: float,
    servo_period_s: float,
    rate_ratio: int,
    delay_ticks: int,
    sample_ticks: Sequence[int],
    integral: bool,
    rho_limit: float = 1.0,
    chunk: int = 4096,
) -> tuple[FloatArray, FloatArray]:
    """Worst full-loop spectral radius per candidate over hands x K_o' x sampling ticks, (G,).

    Returns ``(margin_radius, radius)``: ``radius`` the true spectral radius; ``margin_radius``
    the largest oscillating eigenvalue magnitude, with creep eigenvalues (slower than
    :data:`CREEP_FREQUENCY_HZ`) counted as ``|lambda| * rho_limit``, so that ``margin_radius <
    rho_limit`` means "oscillations decay at the required rate and creep is stable".
    """
    g = cand["k_h"].shape[0]
    L, K = len(hands), len(k_os)
    # batch order: candidate, hand, k_o
    kh = np.repeat(cand["k_h"], L * K)
    ig = np.repeat(cand["i_gain"], L * K)
    bh = np.repeat(cand["b_h"], L * K)
    og = np.repeat(cand["own_gain"], L * K) if "own_gain" in cand else np.zeros(g * L * K)
    hs = [h for h in hands for _ in range(K)] * g
    ko = np.tile(np.asarray(k_os, float), g * L)
    out = np.empty(g * L * K)
    marg = np.empty(g * L * K)
    for a in range(0, out.size, chunk):
        sl = slice(a, a + chunk)
        M = monodromy(
            hand=hs[sl],
            k_o=ko[sl],
            k_h=kh[sl],
            i_gain=ig[sl],
            b_h=bh[sl],
            own_gain=og[sl],
            b_o=b_o,
            servo_period_s=servo_period_s,
            rate_ratio=rate_ratio,
            delay_ticks=delay_ticks,
            sample_ticks=sample_ticks,
            proxy_hold=hold,
            integral=integral,
        )
        marg_j, rad_j = mode_radii(M, rho_limit, rate_ratio, servo_period_s)  # (chunk, J)
        out[sl] = np.max(rad_j, axis=-1)
        marg[sl] = np.max(marg_j, axis=-1)
    return marg.reshape(g, L * K).max(axis=1), out.reshape(g, L * K).max(axis=1)


def _felt_dc(cand: dict[str, FloatArray], k_o: float) -> FloatArray:
    """Felt stiffness in a held press over K_o per candidate: 1 with an integral, else
    ``K_h / (K_o + (1 - C_h K_o) K_h)`` (module docstring), inf where that denominator is <= 0
    (the static loop gain ``K_h (C_h K_o - 1) / K_o`` >= 1 runs away)."""
    denom = k_o + (1.0 - cand["own_gain"] * k_o) * cand["k_h"]
    static = cand["k_h"] / np.where(denom > 0.0, denom, 1.0)
    return np.where(cand["i_gain"] > 0.0, 1.0, np.where(denom > 0.0, static, np.inf))


def _scaled_gains(k_h: _G, i_gain: _G, own_gain: _G, s: _G) -> tuple[_G, _G, _G]:
    """K_h, I and C_h of gains scaled to a K_o s times the one designed for (s >= 1): K_h and I
    times s, C_h over s (:meth:`GainDesign.at`; B_h and the hold stay). Floats or arrays."""
    return k_h * s, i_gain * s, own_gain / s


def _log_miss(ratio: FloatArray) -> FloatArray:
    """|ln q| of felt stiffness ratios q > 0 (inf where q is not > 0 or not finite): a factor
    too soft and the same factor too stiff miss equally (Weber's law for stiffness)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.abs(np.log(ratio))
    return np.where(np.isfinite(out) & (ratio > 0.0), out, np.inf)


def _band_miss(resp: FloatArray) -> FloatArray:
    """How far felt responses (complex dF/dx / K_o, shape (F, G)) over a band of frequencies are
    from the object's own stiffness, per candidate (G,): the largest over the band of |ln |q||
    (:func:`_log_miss`; a damper's lead is felt as a stiffer object at the top of the band) and
    of the active share -Im q (a force lagging the probe gives energy to the user)."""
    return np.max(np.maximum(_log_miss(np.abs(resp)), -resp.imag), axis=0)


def design_gains(
    k_o: float,
    *,
    b_o: float = 0.0,
    servo_rate_hz: float = 1000.0,
    sim_rate_hz: float = 20.0,
    delay_ticks: int = 0,
    mode: Mode = "pi",
    margin: float = 0.15,
    k_o_hi: float | None = None,
    k_h_max: float = math.inf,
    b_h_max: float = 0.0,
    holds: Sequence[ProxyHold] = ("zoh", "foh"),
    hand_box: HandBox = DEFAULT_HAND_BOX,
    min_decay_rate_per_s: float = MIN_DECAY_RATE_PER_S,
    own_force: bool = False,
    felt_k_os: Sequence[float] | None = None,
    scaled: bool = False,
    stiffer_by: float = 0.0,
) -> GainDesign:
    """The most transparent gains stable over the hand box (module docstring).

    Parameters
    ----------
    k_o : float
        Reported (coupling-aware) object stiffness K_o_eff [N/m], > 0.
    b_o : float
        B_o [N/m] (eq. 9), >= 0.
    servo_rate_hz, sim_rate_hz : float
        1/T and 1/(N*T); N must be a whole number.
    delay_ticks : int
        Extra whole simulation ticks of delay, >= 0.
    mode : {"p", "pi"}
        Proportional or proportional-integral local model.
    margin : float
        Fraction in [0, 1) by which K_o may be overestimated: stability is checked down to
        ``(1 - margin) K_o``.
    k_o_hi : float, optional
        Upper end of the K_o range checked (default ``k_o``; :class:`GainTable` passes the next
        grid point so a design covers its whole cell).
    k_h_max : float
        The device's maximum stable stiffness [N/m].
    b_h_max : float
        The device's maximum virtual damping [N*s/m] (0: no probe damper).
    holds : sequence of {"zoh", "foh"}
        Proxy holds the design may use.
    hand_box : HandBox
        Hands the gains must be stable for.
    min_decay_rate_per_s : float
        Decay-rate margin [1/s] (:data:`MIN_DECAY_RATE_PER_S`).
    own_force : bool
        Also consider own-force compensation C_h = r / K_h, r in :data:`OWN_FORCE_RATIOS`
        (module docstring), proportional only, and, for K_o above ``k_h_max``, the plane at the
        rest surface (C_h = 1 / K_o, K_h up to ``k_h_max``: model-mediated teleoperation's
        plane). The objective is then the felt response closest to K_o itself over the band
        (compensation can overshoot and lag K_o): the largest over :data:`FELT_BAND_HZ` of
        |ln |q|| and the active share -Im q (:func:`_band_miss`) and the held press's |ln q|,
        in steps of :data:`DESIGN_TIE`; then the same on the objects of ``stiffer_by``; instead
        of the elastic part at 1 Hz capped at K_o.
    felt_k_os : sequence of float, optional
        Object stiffnesses [N/m] the transparency is also judged at, with ``own_force``: the
        worst of them and ``k_o`` counts, then their mean (default: ``k_o`` alone).
        :func:`design_cell` passes its cell's ends and middle, ``g_i``, ``sqrt(g_i g_(i+1))``
        and ``g_(i+1)``: every reported K_o in the cell gets the design, and with a delay the
        felt response depends on ``K_h / K_o`` (fixed gains fitted to ``g_i`` alone felt
        0.78-0.82 K_o at 1 Hz at the top of the 300 and 1000 N/m cells at 20 Hz with 8 ticks of
        delay; judged across the cell, 0.86-0.91; scaled, 1.005 across the 300 N/m cell and
        0.92-0.95 across the 1000 N/m one, where K_h reaches the device's 1000 N/m).
    stiffer_by : float
        With ``own_force``, >= 0: the transparency is also judged on objects ``1 + stiffer_by``
        times softer and stiffer than ``k_o`` (the gains made for ``k_o`` rendering them; a
        model error), the worst counting. Stability over the stiffer object is the caller's
        range (``k_o_hi``; :func:`cell_k_o_range` widens it by :attr:`GainKey.stiffer_by`).
    scaled : bool
        Compensated gains are rendered scaled to the reported K_o (:meth:`GainDesign.at`) over
        ``[k_o, max(felt_k_os)]``, as far as K_h stays within ``k_h_max``: transparency at each
        of ``felt_k_os`` is judged with the gains scaled to it, and a candidate is accepted only
        if it passes at the scales s = 1, the geometric middle and its top, each over K_o' in
        ``[(1 - margin) s k_o, k_o_hi]`` (the margin below the reported K_o, and up to the top of
        the range as for fixed gains, at least ``s k_o``). With own-force compensation the felt
        response then depends on K_h / K_o alone and K_h = K_o feels the object's own stiffness
        across the cell (fixed gains: within 10 % of it at 1 Hz with long delays; the 1-D
        benchmark's 100 and 300 N/m cells 0.97 K_o median).

    Returns
    -------
    GainDesign
        For ``pi``, a proportional design (``mode == "p"``, I = 0) when no integral is stable
        over the box (long delays without a probe damper).

    Raises
    ------
    ValueError
        Out-of-range input, or no candidate is stable over the box (then the box or the rates are
        beyond what any local model can render).
    """
    rates = Rates(servo_rate_hz, sim_rate_hz)
    N, T = rates.ratio, rates.servo_period_s
    if not (math.isfinite(k_o) and k_o > 0.0):
        raise ValueError(f"k_o must be a finite stiffness > 0 N/m, got {k_o!r}")
    if not (math.isfinite(b_o) and b_o >= 0.0):
        raise ValueError(f"b_o must be finite and >= 0, got {b_o!r}")
    if not 0.0 <= margin < 1.0:
        raise ValueError(f"margin must be in [0, 1), got {margin!r}")
    if not (math.isfinite(stiffer_by) and stiffer_by >= 0.0):
        raise ValueError(f"stiffer_by must be finite and >= 0, got {stiffer_by!r}")
    _whole("delay_ticks", delay_ticks, 0)
    if mode not in ("p", "pi"):
        raise ValueError(f"mode must be 'p' or 'pi', got {mode!r}")
    if not k_h_max > 0.0:
        raise ValueError(f"k_h_max must be > 0, got {k_h_max!r}")
    if not (math.isfinite(b_h_max) and b_h_max >= 0.0):
        raise ValueError(f"b_h_max must be finite and >= 0, got {b_h_max!r}")
    if not holds or any(h not in ("zoh", "foh") for h in holds):
        raise ValueError(f"holds must name 'zoh' and/or 'foh', got {holds!r}")
    hi = float(k_o if k_o_hi is None else max(k_o, k_o_hi))
    lo = (1.0 - margin) * k_o
    felt_at = [float(k_o)] if felt_k_os is None else [float(v) for v in felt_k_os]
    if not felt_at or not all(math.isfinite(v) and v > 0.0 for v in felt_at):
        raise ValueError(f"felt_k_os must be finite stiffnesses > 0 N/m, got {felt_k_os!r}")
    k_os = k_o_points(lo, hi)
    rho_limit = math.exp(-min_decay_rate_per_s * N * T)
    delay = int(delay_ticks)
    integral = mode == "pi"
    band = list(FELT_BAND_HZ) if own_force else [1.0]
    model_error_k_os = (
        [k_o / (1.0 + stiffer_by), k_o * (1.0 + stiffer_by)] if own_force and stiffer_by > 0 else []
    )

    # candidates: the paper's local model (K_h below K_o, the simulation loop's bound) ...
    kh_cap = min(k_h_max, 0.999 * lo)
    kh_axis = kh_cap * np.geomspace(0.03, 1.0, 28 if integral else 48)
    bh_axis = np.unique(np.linspace(0.0, b_h_max, 4)) if b_h_max > 0.0 else np.zeros(1)
    i_axis = lo * np.geomspace(0.02, 2.0, 16) / (N * T) if integral else np.zeros(1)
    KH, NI, BH = np.meshgrid(kh_axis, i_axis, bh_axis, indexing="ij")
    paper = {
        "k_h": KH.ravel(),
        "i_gain": NI.ravel(),
        "b_h": BH.ravel(),
        "own_gain": 0.0 * KH.ravel(),
    }
    groups: list[tuple[dict[str, FloatArray], bool]] = [(paper, integral)]
    if own_force:
        # ... and proportional ones with own-force compensation, K_h up to the device's
        # stiffness (or 2 K_o). No integral: against the compensated surface it would hold the
        # probe at a surface its own push does not move (at DC an infinitely stiff object)
        kh_top = min(k_h_max, 2.0 * hi)
        # the coarse axis, and a fine one where the most transparent K_h lies (near K_o)
        span = [float(k_o)] if scaled else felt_at
        near = np.append(np.geomspace(0.8 * min(span), 1.25 * max(span), 17), k_o)
        kh_axis_c = np.unique(
            np.concatenate((kh_top * np.geomspace(0.03, 1.0, 40), near[near <= kh_top]))
        )
        # light dampers too: with K_h = K_o the damper only lends the hand's slowest modes the
        # decay margin, and it is felt (as viscosity) in proportion to B_h / K_o
        bh_axis_c = np.unique(
            np.concatenate((bh_axis, b_h_max * np.array([0.025, 0.05, 0.1, 0.15, 0.2, 0.25, 0.5])))
        )
        KH, BH, AL = np.meshgrid(kh_axis_c, bh_axis_c, np.asarray(OWN_FORCE_RATIOS), indexing="ij")
        comp = {"k_h": KH.ravel(), "i_gain": 0.0 * KH.ravel(), "b_h": BH.ravel()}
        groups.append(({**comp, "own_gain": AL.ravel() / KH.ravel()}, False))
        if k_h_max < k_o:
            # ... and, for an object stiffer than the device, the plane at the rest surface the
            # simulation's own model gives (C_h = 1 / K_o: the surface less the object's own
            # deformation) with K_h up to the device's stiffness: model-mediated teleoperation's
            # plane (Mitra and Niemeyer 2008), felt as K_h at every frequency of the band where
            # the paper's models creep (PI) or feel K_h K_o / (K_h + K_o) (P)
            kh_plane = k_h_max * np.geomspace(0.5, 1.0, 6)
            kh_p, bh_p = (v.ravel() for v in np.meshgrid(kh_plane, bh_axis_c, indexing="ij"))
            plane = {"k_h": kh_p, "i_gain": 0.0 * kh_p, "b_h": bh_p}
            groups.append(({**plane, "own_gain": np.full(kh_p.size, 1.0 / k_o)}, False))
    screen_hands = hand_box.screen_hands()
    # the light, stiff, least damped hand and the heavy, soft, least damped one: the first to ring
    pre_hands = list(
        dict.fromkeys(
            [
                Hand(
                    min(hand_box.mass_kg),
                    min(hand_box.damping_n_s_per_m),
                    max(hand_box.stiffness_n_per_m),
                ),
                Hand(
                    max(hand_box.mass_kg),
                    min(hand_box.damping_n_s_per_m),
                    min(hand_box.stiffness_n_per_m),
                ),
            ]
        )
    )
    pre_ticks = [N - 1]
    all_hands = hand_box.hands()
    screen_ticks = sorted({0, N // 2, N - 1})
    all_ticks = list(range(N))
    mid_ticks = sorted({int(j) for j in np.linspace(0, N - 1, 8)})
    rest_ticks = [j for j in all_ticks if j not in mid_ticks]

    best: tuple[float, float, float, float, GainDesign] | None = None
    ALL = slice(None)

    def worst(
        cand: dict[str, FloatArray],
        hold: ProxyHold,
        hands: list[Hand],
        ticks: list[int],
        integral: bool,
        scale: float = 1.0,
        part: slice = slice(None),
    ) -> tuple[FloatArray, FloatArray]:
        ks = k_os if scale == 1.0 else k_o_points(scale * lo, max(hi, scale * k_o))
        return _worst_rho(
            cand,
            hold,
            hands,
            ks[part],
            b_o=b_o,
            servo_period_s=T,
            rate_ratio=N,
            delay_ticks=delay,
            sample_ticks=ticks,
            integral=integral,
            rho_limit=rho_limit,
        )

    # the largest scale of each candidate's gains (``scaled``): to the top of felt_at, K_h within
    # the device's stiffness; compensated candidates only. The paper's models keep one set of
    # gains per cell: they win only above the device's stiffness, where K_h is at or near its
    # limit, and checking them scaled dropped PI designs that felt 8 % stiffer (3000 N/m, 100 Hz,
    # 40 ticks: 0.42 against 0.46 K_o at 1 Hz)
    top = max(felt_at) / k_o if scaled else 1.0
    smax = [
        np.clip(k_h_max / base["k_h"], 1.0, max(top, 1.0)) if g > 0 else np.ones_like(base["k_h"])
        for g, (base, _) in enumerate(groups)
    ]

    def at_k(base: dict[str, FloatArray], s: FloatArray) -> dict[str, FloatArray]:
        """Every candidate's gains scaled by s (GainDesign.at)."""
        k_h, i_gain, own_gain = _scaled_gains(base["k_h"], base["i_gain"], base["own_gain"], s)
        return {"k_h": k_h, "i_gain": i_gain, "b_h": base["b_h"], "own_gain": own_gain}

    for (g, (base, with_i)), hold in itertools.product(enumerate(groups), holds):
        felt_dc = _felt_dc(base, k_o)

        def served(
            k: float, base: dict[str, FloatArray] = base, g: int = g
        ) -> dict[str, FloatArray]:
            """Every candidate's gains as rendered for a reported K_o = k (scaled when
            ``scaled``)."""
            return at_k(base, np.minimum(max(k / k_o, 1.0), smax[g])) if scaled else base

        def response(k: float, sc: dict[str, FloatArray], hold: ProxyHold = hold) -> FloatArray:
            """Felt responses dF/dx / K_o (complex values, (F, G)) of gains ``sc`` on K_o = k
            at 1 Hz and, with ``own_force``, every frequency of :data:`FELT_BAND_HZ`."""
            return (
                felt_responses(
                    band,
                    k_o=k,
                    servo_period_s=T,
                    rate_ratio=N,
                    delay_ticks=delay,
                    proxy_hold=hold,
                    b_o=b_o,
                    k_h=sc["k_h"],
                    i_gain=sc["i_gain"],
                    b_h=sc["b_h"],
                    own_gain=sc["own_gain"],
                )
                / k
            )

        resp_band = response(k_o, base)
        resp1 = resp_band[band.index(1.0)]
        # objective, with own-force compensation: how far the felt response is from K_o over
        # the band and in a held press (DC), whichever is further (_band_miss, _log_miss);
        # across felt_at the worst counts, in steps of DESIGN_TIE (what a hand would not feel
        # apart); then the worst on the objects stiffer and softer than reported (model error);
        # then the mean over felt_at (a tie of the worst: K_h at the device's stiffness is the
        # top of a scaled K_h's range). Without it (the paper's models alone): the elastic part
        # of the felt stiffness at 1 Hz, capped at the object's own
        if own_force:
            errs = [np.maximum(_band_miss(resp_band), _log_miss(felt_dc))]
            for k in felt_at:
                if k != k_o:
                    sc = served(k)
                    errs.append(np.maximum(_band_miss(response(k, sc)), _log_miss(_felt_dc(sc, k))))
            worst_err = np.max(errs, axis=0)
            felt1 = -np.floor(np.where(np.isfinite(worst_err), worst_err, 1e9) / DESIGN_TIE)
            felt1 = np.where(np.isfinite(worst_err), felt1, -np.inf)
            felt_mean = np.round(1.0 - np.mean(errs, axis=0), 4)
        else:
            felt1 = np.round(np.minimum(resp1.real, 1.0), 3)
            felt_mean = np.zeros_like(felt1)
        robust = np.zeros_like(felt1)
        if best is not None:
            felt1 = np.where(felt1 < best[0] - 1e-9, -np.inf, felt1)  # cannot win

        def robustness(idx: IndexArray, base: dict[str, FloatArray] = base) -> FloatArray:
            """The worst error on the objects softer and stiffer than reported (the gains made
            for k_o rendering them), negated and rounded, for candidates ``idx``: computed only
            for the steps of the objective the search reaches."""
            if not model_error_k_os:
                return np.zeros(idx.size)
            sub = {k: v[idx] for k, v in base.items()}
            off = [
                np.maximum(_band_miss(response(k, sub)), _log_miss(_felt_dc(sub, k)))
                for k in model_error_k_os
            ]
            return np.round(-np.max(off, axis=0), 3)

        # the search goes step by step of the objective, the best first, when a step's order
        # depends on the model-error check (computed as the search reaches it)
        if model_error_k_os:
            steps = [np.flatnonzero(felt1 == v) for v in np.unique(felt1[np.isfinite(felt1)])[::-1]]
        else:
            steps = [np.flatnonzero(np.isfinite(felt1))]
        found = None

        def passes(
            b: int,
            hold: ProxyHold = hold,
            base: dict[str, FloatArray] = base,
            with_i: bool = with_i,
            g: int = g,
        ) -> tuple[bool, float]:
            one = {k: v[b : b + 1] for k, v in base.items()}
            s_top = float(smax[g][b])
            rho = 0.0
            # the design's own gains, then scaled to the middle and the top of its range
            for s in dict.fromkeys((1.0, math.sqrt(s_top), s_top)):
                sc = at_k(one, np.full(1, s)) if s != 1.0 else one
                # most failures show at a few ticks and at the softest K_o' (a compensated model
                # with K_h above it): cheaper first
                for ticks, part in (
                    [(mid_ticks, slice(0, 1)), (mid_ticks, slice(1, None)), (rest_ticks, ALL)]
                    if len(all_ticks) > len(mid_ticks)
                    else [(all_ticks, ALL)]
                ):
                    m_r, r_r = worst(sc, hold, all_hands, ticks, with_i, s, part)
                    if not (m_r[0] < rho_limit and r_r[0] < 1.0 - 1e-9):
                        return False, float(r_r[0])
                    rho = max(rho, float(r_r[0]))
            return True, rho

        # screen in order of transparency (two hands at one tick, then few hands at three
        # sampling ticks), then verify fully; each stage only drops candidates a later one would
        for in_step in steps:
            robust[in_step] = robustness(in_step)
            order = in_step[np.lexsort((-felt_mean[in_step], -robust[in_step], -felt1[in_step]))]
            for a in range(0, order.size, 64):
                idx = order[a : a + 64]
                sub = {k: v[idx] for k, v in base.items()}
                rho_p = worst(sub, hold, pre_hands, pre_ticks, with_i)[0]
                idx = idx[rho_p < rho_limit]
                if idx.size == 0:
                    continue
                sub = {k: v[idx] for k, v in base.items()}
                rho_s = worst(sub, hold, screen_hands, screen_ticks, with_i)[0]
                for b in idx[rho_s < rho_limit]:
                    ok_b, r_b = passes(int(b))
                    if ok_b:
                        found = (int(b), r_b)
                        break
                if found is not None:
                    break
            if found is not None:
                break
        if found is None:
            continue
        i, rho_full = found
        felt8 = float(
            felt_stiffness(
                8.0,
                k_o=k_o,
                k_h=base["k_h"][i],
                i_gain=base["i_gain"][i],
                b_h=base["b_h"][i],
                own_gain=base["own_gain"][i],
                b_o=b_o,
                servo_period_s=T,
                rate_ratio=N,
                delay_ticks=delay,
                proxy_hold=hold,
            )[0]
            / k_o
        )
        d = GainDesign(
            k_h=float(base["k_h"][i]),
            i_gain=float(base["i_gain"][i]),
            b_h=float(base["b_h"][i]),
            proxy_hold=hold,
            worst_spectral_radius=rho_full,
            rho_limit=rho_limit,
            felt_stiffness_ratio_1hz=float(abs(resp1[i])),
            felt_stiffness_ratio_8hz=felt8,
            k_o=float(k_o),
            k_o_range=(lo, hi),
            rate_ratio=N,
            delay_ticks=delay,
            mode=mode,
            hand_box=hand_box,
            own_gain=float(base["own_gain"][i]),
            scale_max=float(smax[g][i]),
        )
        key = (
            float(felt1[i]),
            float(robust[i]),
            float(felt_mean[i]),
            -abs(d.felt_stiffness_ratio_8hz - 1.0),
        )
        if best is None or key > best[:4]:
            best = (*key, d)
    if best is None and integral:
        # no integral is stable here: render the best proportional local model instead
        return design_gains(
            k_o,
            b_o=b_o,
            servo_rate_hz=servo_rate_hz,
            sim_rate_hz=sim_rate_hz,
            delay_ticks=delay,
            mode="p",
            margin=margin,
            k_o_hi=k_o_hi,
            k_h_max=k_h_max,
            b_h_max=b_h_max,
            holds=holds,
            hand_box=hand_box,
            min_decay_rate_per_s=min_decay_rate_per_s,
            own_force=own_force,
            felt_k_os=felt_k_os,
            scaled=scaled,
            stiffer_by=stiffer_by,
        )
    if best is None:
        raise ValueError(
            f"no {mode} local model is stable over the hand box at K_o = {k_o:g} N/m, "
            f"{sim_rate_hz:g} Hz, {delay} tick(s) of delay"
        )
    return best[4]


#: Largest ratio between neighbouring K_o points a design is checked at (:func:`k_o_points`).
K_O_CHECK_RATIO = 4.0


def k_o_points(lo: float, hi: float) -> list[float]:
    """The K_o values [N/m] a design over ``[lo, hi]`` is checked at.

    ``lo``, the geometric middle and ``hi`` for a range up to :data:`K_O_CHECK_RATIO` wide; a
    geometric grid with a ratio of at most :data:`K_O_CHECK_RATIO` between neighbours beyond
    (a coupled contact's range reaches ``K_O_RIGID`` = 1e6 N/m: about 8 points from 150 N/m).
    """
    if hi <= lo:
        return [float(lo)]
    n = max(3, 1 + math.ceil(math.log(hi / lo) / math.log(K_O_CHECK_RATIO) - 1e-9))
    return [float(v) for v in np.geomspace(lo, hi, n)]


def cell_k_o_range(key: GainKey, cell: int, grid_ratio: float) -> tuple[float, float]:
    """``[(1 - margin) g_i, k_o_hi]`` [N/m], the K_o range a :class:`GainTable` cell is checked over.

    ``g_i = grid_ratio**cell``; ``k_o_hi`` is the next grid point times ``1 + key.stiffer_by``,
    or for a coupled contact ``coupled_k_o_hi(g_(i+1), key.stiff_ratio)`` where that is higher
    (:mod:`shared.coupled_loop`).
    """
    g = grid_ratio**cell
    top = grid_ratio ** (cell + 1)
    # an object stiffer than reported; a coupled contact's modal range already reaches beyond
    # (the two are not stacked: a coupled press on the balloon then got the paper's PI, felt
    # 0.79 K_o at 1 Hz, instead of a compensated model)
    hi = top * (1.0 + key.stiffer_by)
    if key.stiff_ratio != 1.0:
        hi = max(hi, coupled_k_o_hi(top, key.stiff_ratio))
    return (1.0 - key.margin) * g, hi


class GainTable:
    """Designs cached on a geometric grid of K_o; lookups cost a dict access and a scaling.

    A design for grid point g_i is checked over K_o' in ``[(1 - margin) g_i, g_(i+1)]``; a reported
    K_o with ``g_i <= K_o < g_(i+1)`` gets it scaled to K_o (:meth:`GainDesign.at`, compensated
    designs), checked over ``[(1 - margin) K_o, g_(i+1)]`` at the cell's grid point, middle and
    top, so it is stable with the full margin below the reported K_o. The paper's models (not
    scaled) lose at most one grid ratio (10 %) of stiffness. The table never designs by itself:
    :meth:`lookup` says which cell is missing and the caller runs :meth:`design` off its event
    loop (a thread), then :meth:`lookup` again. Pure: no threads, no clocks.

    Parameters
    ----------
    hand_box : HandBox
        The hands every design is checked against.
    grid_ratio : float
        Ratio between neighbouring K_o grid points, > 1.
    """

    def __init__(self, hand_box: HandBox = DEFAULT_HAND_BOX, grid_ratio: float = K_O_GRID_RATIO):
        if not grid_ratio > 1.0:
            raise ValueError(f"grid_ratio must be > 1, got {grid_ratio!r}")
        self.hand_box = hand_box
        self.grid_ratio = float(grid_ratio)
        self._cells: dict[tuple[GainKey, int], GainDesign] = {}
        self._log_r = math.log(self.grid_ratio)

    def cell(self, k_o: float) -> int:
        """Grid index i with ``g_i <= k_o < g_(i+1)``, ``g_i = ratio**i`` [N/m]."""
        if not (math.isfinite(k_o) and k_o > 0.0):
            raise ValueError(f"k_o must be a finite stiffness > 0 N/m, got {k_o!r}")
        return math.floor(math.log(k_o) / self._log_r + 1e-12)

    def grid_point(self, i: int) -> float:
        """g_i [N/m]."""
        return self.grid_ratio**i

    def lookup(self, key: GainKey, k_o: float) -> GainDesign | None:
        """The design covering ``k_o``, scaled to it (:meth:`GainDesign.at`), or None if its
        cell has not been designed yet."""
        d = self._cells.get((key, self.cell(k_o)))
        return None if d is None else d.at(k_o)

    def fallback(self, key: GainKey, k_o: float) -> GainDesign | None:
        """Gains to render while the cell covering ``k_o`` is being designed, or None.

        The nearest designed cell below (a design for a softer object: its K_h is lower than the
        missing cell's would be; more than two cells below, without its integral), else the
        nearest above with K_h, I and B_h scaled down by the ratio of the grid points (the same
        gains relative to K_o). Either keeps the local model no stiffer, relative to K_o, than a
        verified design. The design's own gains (at its grid point), never scaled to ``k_o``
        (``scale_max`` 1).
        """
        i = self.cell(k_o)
        cells = [c for (k, c) in self._cells if k == key]
        if not cells:
            return None
        below = [c for c in cells if c <= i]
        if below:
            c = max(below)
            d = replace(self._cells[(key, c)], scale_max=1.0)
            # own-force compensation keeps its share of K_o (C_h K_o), not its C_h
            own = d.own_gain * self.grid_point(c) / self.grid_point(i)
            if i - c > 2 and d.i_gain > 0.0:
                # an integral designed for a much softer object may not hold on this one (a
                # heavy, soft, lightly damped hand): render its P part until the design is done
                return replace(d, i_gain=0.0, own_gain=own)
            return replace(d, own_gain=own) if own != d.own_gain else d
        c = min(cells)
        d = replace(self._cells[(key, c)], scale_max=1.0)
        r = self.grid_point(i) / self.grid_point(c)
        return replace(
            d, k_h=d.k_h * r, i_gain=d.i_gain * r, b_h=d.b_h * r, own_gain=d.own_gain / r
        )

    def store(self, key: GainKey, cell: int, design: GainDesign) -> None:
        """Keep ``design`` (from :func:`design_cell`) for ``cell``."""
        self._cells[(key, cell)] = design

    def design(self, key: GainKey, k_o: float) -> GainDesign:
        """Design (slow: tens of ms to a second) and store the cell covering ``k_o``; the design
        scaled to ``k_o``, as :meth:`lookup` gives it.

        Raises
        ------
        ValueError
            As :func:`design_gains`.
        """
        i = self.cell(k_o)
        d = design_cell(key, i, self.grid_ratio, self.hand_box)
        self.store(key, i, d)
        return d.at(k_o)

    def __len__(self) -> int:
        return len(self._cells)


def design_cell(key: GainKey, cell: int, grid_ratio: float, hand_box: HandBox) -> GainDesign:
    """Design grid cell ``cell`` of a :class:`GainTable`: K_o = ratio**cell, checked up to the next.

    A module-level function so that a worker process can run it (arguments and result pickle).

    Raises
    ------
    ValueError
        As :func:`design_gains`.
    """
    g = grid_ratio**cell
    return design_gains(
        g,
        b_o=key.b_o,
        servo_rate_hz=key.servo_rate_hz,
        sim_rate_hz=key.sim_rate_hz,
        delay_ticks=key.delay_ticks,
        mode=key.mode,
        margin=key.margin,
        k_o_hi=cell_k_o_range(key, cell, grid_ratio)[1],
        k_h_max=key.k_h_max,
        b_h_max=key.b_h_max,
        hand_box=hand_box,
        own_force=key.own_force,
        felt_k_os=(g, g * math.sqrt(grid_ratio), g * grid_ratio),
        scaled=True,
        stiffer_by=key.stiffer_by,
    )


def warm_up() -> None:
    """Import and exercise the design code once (a worker process calls this before the first
    real design, so the first patch does not also pay for imports)."""
    design_gains(300.0, mode="p", sim_rate_hz=100.0, holds=("zoh",))


# --------------------------------------------------------------------------------------------
# interim gains: checked in a fraction of a second while a design runs


#: Generic interim gains tried when no known gains pass, in order: (K_h, I) as multiples of the
#: cell's lowest K_o, lo = (1 - margin) g_i [N/m], i.e. K_h = a lo [N/m] and I = b lo [N/(m*s)],
#: with the device's full damper B_h and a zero-order hold. The PI one only with a damper and a
#: PI key: with a 10 N*s/m damper at 1 kHz / 20 Hz it passed at K_o = 30 to 3000 N/m and 0 to 3
#: ticks of delay, and no integral passed without a damper; P with K_h = 0.1 lo passed everywhere
#: but at 3000 N/m with a delay, hence 0.05.
INTERIM_LADDER: tuple[tuple[float, float], ...] = ((0.2, 2.0), (0.2, 0.0), (0.1, 0.0), (0.05, 0.0))

#: Generic interim gains with own-force compensation, tried first where the key allows it: K_h =
#: a lo (at most the device's), C_h = 1 / K_h, the device's full damper, zero-order hold and, with
#: a damper, first-order hold. They feel the object's own stiffness in a held press (module
#: docstring), so a user whose contact becomes coupled to another's keeps feeling it while the
#: coupled design runs. For a coupled contact (class 2 and 4, 20 Hz, 0 and 2 ticks, 100-1000 N/m,
#: the Phantom Desktop's 10 N*s/m) the zero-order rungs passed in 1 of 12 cases, with first-order
#: ones 8; without a damper no compensated gains passed there, so the first-order rungs are not
#: tried; nor below :data:`INTERIM_OWN_FORCE_FOH` lo (a coupled contact's loop gain
#: 1 - K_h / K_o' nears 1 as K_h falls, and a failed check delays the interim gains).
INTERIM_OWN_FORCE: tuple[float, ...] = (1.0, 0.5, 0.25, 0.1, 0.05)
INTERIM_OWN_FORCE_FOH = 0.5


def verify_gains(
    key: GainKey,
    cell: int,
    grid_ratio: float,
    hand_box: HandBox,
    *,
    k_h: float,
    i_gain: float,
    b_h: float,
    proxy_hold: Literal["zoh", "foh"],
    chunk: int = 256,
    own_gain: float = 0.0,
    k_o_scale: float = 1.0,
    probe: int = 32,
) -> tuple[bool, float]:
    """Do these gains pass the design's acceptance test for grid cell ``cell`` of ``key``?

    The test :func:`shared.gain_design.design_gains` applies to its chosen gains: the full loop
    (:func:`shared.full_loop.monodromy`) for every hand of ``hand_box.hands()``, every sampling
    tick j in [0, N) and K_o' in {lo, sqrt(lo hi), hi}, ``(lo, hi) = ((1 - margin) g_i,
    g_(i+1))`` (the range :func:`shared.gain_design.design_cell` covers) has spectral radius below
    1 and every oscillating mode (faster than :data:`shared.gain_design.CREEP_FREQUENCY_HZ`) below
    ``exp(-MIN_DECAY_RATE_PER_S N T)``. Stops at the first failing chunk.

    Parameters
    ----------
    key : GainKey
        Rates, delay ticks, margin and object damping B_o [N/m] to check at.
    cell, grid_ratio : int, float
        The K_o grid cell (g_i = grid_ratio**cell [N/m]).
    hand_box : HandBox
    k_h, i_gain, b_h : float
        K_h [N/m] > 0, I [N/(m*s)] >= 0, B_h [N*s/m] >= 0.
    proxy_hold : {"zoh", "foh"}
    chunk : int
        Loop cases per batch.
    probe : int
        Cases in the first batch (the stiffest K_o' first): most candidates that fail, fail
        there.
    own_gain : float
        Own-force compensation C_h [m/N] >= 0 (:mod:`shared.full_loop`).
    k_o_scale : float
        s in [1, grid_ratio]: the gains are a design scaled to a reported K_o = s g_i
        (:meth:`GainDesign.at`), checked as the design checks its scales: K_o' from
        ``(1 - margin) s g_i`` up to the top of the cell's range.

    Returns
    -------
    (bool, float)
        Passed, and the worst spectral radius seen.

    Raises
    ------
    ValueError
        Out-of-range gains or rates (as :func:`shared.full_loop.monodromy`).
    """
    if not (math.isfinite(k_h) and k_h > 0.0):
        raise ValueError(f"k_h must be a finite stiffness > 0 N/m, got {k_h!r}")
    for name, v in (("i_gain", i_gain), ("b_h", b_h), ("own_gain", own_gain)):
        if not (math.isfinite(v) and v >= 0.0):
            raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
    if not (math.isfinite(k_o_scale) and 1.0 <= k_o_scale <= grid_ratio):
        raise ValueError(f"k_o_scale must be in [1, {grid_ratio:g}], got {k_o_scale!r}")
    rates = key.rates
    n, T = rates.ratio, rates.servo_period_s
    lo, hi = cell_k_o_range(key, cell, grid_ratio)
    k_os = k_o_points(k_o_scale * lo, max(hi, k_o_scale * grid_ratio**cell))
    # the stiffest K_o' first, and a first batch of ``probe`` cases: a failing candidate (most
    # interim candidates fail) is usually refused there, at a fraction of the whole check's cost
    k_os = sorted(k_os, reverse=True)
    box = hand_box.hands()
    hands = [h for _ in k_os for h in box]
    ko = np.repeat(np.asarray(k_os, float), len(box))
    rho_limit = math.exp(-MIN_DECAY_RATE_PER_S * n * T)
    worst = 0.0
    bounds = [0, *range(min(probe, chunk), len(hands), chunk), len(hands)]
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        M = monodromy(
            hand=hands[a:b],
            k_o=ko[a:b],
            k_h=k_h,
            i_gain=i_gain,
            b_h=b_h,
            own_gain=own_gain,
            b_o=key.b_o,
            servo_period_s=T,
            rate_ratio=n,
            delay_ticks=key.delay_ticks,
            proxy_hold=proxy_hold,
            integral=i_gain > 0.0,
        )
        marg, rad = mode_radii(M, rho_limit, n, T)
        worst = max(worst, float(rad.max()))
        margin_r = float(marg.max())
        if margin_r >= rho_limit or worst >= 1.0 - 1e-9:
            return False, worst
    return True, worst


def interim_design(
    key: GainKey,
    cell: int,
    grid_ratio: float,
    hand_box: HandBox,
    candidates: Sequence[GainDesign] = (),
    design_fallback: bool = True,
) -> GainDesign:
    """Verified gains to render in grid cell ``cell`` of ``key`` until its design is done.

    Tries, in order, ``candidates`` (gains already known, most transparent first), then the
    generic gains of :data:`INTERIM_OWN_FORCE` (when the key allows own-force compensation) and
    :data:`INTERIM_LADDER`; returns the first that passes
    :func:`verify_gains`. If none does and ``design_fallback``, a proportional design of the cell
    (:func:`shared.gain_design.design_cell` with ``mode="p"``, seconds). A module-level function
    so that a worker process can run it.

    Returns
    -------
    GainDesign
        For this key and cell (``k_o_range`` the cell's checked range); ``design_ms`` the time it
        took.

    Raises
    ------
    ValueError
        Nothing passed (and, with ``design_fallback``, not even a proportional design is stable
        over the box).
    """
    lo, hi = cell_k_o_range(key, cell, grid_ratio)
    rates = key.rates
    n = rates.ratio
    own_ok = key.own_force
    tries: list[tuple[float, float, float, Literal["zoh", "foh"], float]] = [
        (c.k_h, c.i_gain, c.b_h, c.proxy_hold, c.own_gain)
        for c in candidates
        if own_ok or c.own_gain == 0.0
    ]
    if own_ok:
        for a in INTERIM_OWN_FORCE:
            k = min(a * lo, key.k_h_max)
            tries.append((k, 0.0, key.b_h_max, "zoh", 1.0 / k))
            if key.b_h_max > 0.0 and a >= INTERIM_OWN_FORCE_FOH:
                tries.append((k, 0.0, key.b_h_max, "foh", 1.0 / k))
    tries += [
        (min(a * lo, key.k_h_max), b * lo, key.b_h_max, "zoh", 0.0)
        for a, b in INTERIM_LADDER
        if b == 0.0 or (key.mode == "pi" and key.b_h_max > 0.0)
    ]
    seen: set[tuple[float, float, float, str, float]] = set()
    for k_h, i_gain, b_h, hold, own in tries:
        if (k_h, i_gain, b_h, hold, own) in seen or k_h > key.k_h_max or b_h > key.b_h_max:
            continue
        seen.add((k_h, i_gain, b_h, hold, own))
        ok, rho = verify_gains(
            key,
            cell,
            grid_ratio,
            hand_box,
            k_h=k_h,
            i_gain=i_gain,
            b_h=b_h,
            proxy_hold=hold,
            own_gain=own,
        )
        if not ok:
            continue
        g = grid_ratio**cell
        felt = [
            float(
                felt_stiffness(
                    hz,
                    k_o=g,
                    k_h=k_h,
                    i_gain=i_gain,
                    b_h=b_h,
                    b_o=key.b_o,
                    servo_period_s=rates.servo_period_s,
                    rate_ratio=n,
                    delay_ticks=key.delay_ticks,
                    proxy_hold=hold,
                    own_gain=own,
                )[0]
                / g
            )
            for hz in (1.0, 8.0)
        ]
        return GainDesign(
            k_h=k_h,
            i_gain=i_gain,
            b_h=b_h,
            proxy_hold=hold,
            worst_spectral_radius=rho,
            rho_limit=math.exp(-MIN_DECAY_RATE_PER_S * n / key.servo_rate_hz),
            felt_stiffness_ratio_1hz=felt[0],
            felt_stiffness_ratio_8hz=felt[1],
            k_o=g,
            k_o_range=(lo, hi),
            rate_ratio=n,
            delay_ticks=key.delay_ticks,
            mode="pi" if i_gain > 0.0 else "p",
            hand_box=hand_box,
            own_gain=own,
        )
    if not design_fallback:
        raise ValueError(f"no known or proportional gains pass in cell {cell} of {key}")
    return design_cell(replace(key, mode="p"), cell, grid_ratio, hand_box)
