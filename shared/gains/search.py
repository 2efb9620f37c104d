"""The candidate search behind :func:`shared.gains.design.design_gains`.

:mod:`shared.gains.design` states what a design must satisfy and which one wins; this module owns
how the candidates are found: the candidate gains (:func:`candidate_groups`: the paper's local
model, proportional models with own-force compensation, the plane above the device's stiffness),
the transparency objective they are ranked by (the felt response over the band and in a held
press, in steps of :data:`DESIGN_TIE`, then on objects stiffer and softer than reported), and the
staged stability check a candidate passes before it is accepted (two hands at one sampling tick,
a few hands at three, then every hand of the box at every tick and every K_o', with the margin of
:mod:`shared.stability_margin`): :class:`GainSearch`. Candidate gains are arrays of one value per
candidate keyed ``k_h`` [N/m], ``i_gain`` [N/(m*s)], ``b_h`` [N*s/m] and ``own_gain`` [m/N].
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from haptic_collab.shared.felt_stiffness import felt_responses, felt_stiffness
from haptic_collab.shared.full_loop import (
    Hand,
    HandBox,
    ProxyHold,
    monodromy,
    object_impedance,
)
from haptic_collab.shared.gains.policy import (
    DESIGN_TIE,
    OWN_FORCE_RATIOS,
)
from haptic_collab.shared.stability_margin import group_mode_radii, k_o_points
from haptic_collab.shared.types import FloatArray, IndexArray

_G = TypeVar("_G", float, FloatArray)


def scaled_gains(k_h: _G, i_gain: _G, own_gain: _G, s: _G) -> tuple[_G, _G, _G]:
    """K_h, I and C_h of gains scaled to a K_o s times the one designed for (s >= 1): K_h and I
    times s, C_h over s (:meth:`shared.gains.design.GainDesign.at`; B_h and the hold stay).
    Floats or arrays (of one value per candidate)."""
    return k_h * s, i_gain * s, own_gain / s


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
    :data:`shared.gains.policy.CREEP_FREQUENCY_HZ`) counted as ``|lambda| * rho_limit``, so
    that ``margin_radius < rho_limit`` means "oscillations decay at the required rate and creep is
    stable".
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
    per = L * K  # cases per candidate
    out = np.zeros(g)
    marg = np.zeros(g)
    for a in range(0, g * per, chunk):
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
        # each case's candidate, and each matrix's (chunk, J)
        first = a // per
        cand_of = np.arange(a, a + M.shape[0]) // per - first
        n_c = int(cand_of[-1]) + 1
        marg_c, rad_c = group_mode_radii(
            M.reshape(-1, *M.shape[-2:]),
            rho_limit,
            rate_ratio,
            servo_period_s,
            np.repeat(cand_of, M.shape[1]),
            n_c,
        )
        out[first : first + n_c] = np.maximum(out[first : first + n_c], rad_c)
        marg[first : first + n_c] = np.maximum(marg[first : first + n_c], marg_c)
    return marg, out


def _felt_dc(cand: dict[str, FloatArray], k_o: float) -> FloatArray:
    """Felt stiffness in a held press over K_o per candidate: 1 with an integral, else
    ``K_h / (K_o + (1 - C_h K_o) K_h)`` (:mod:`shared.gains.design`), inf where that denominator
    is <= 0 (the static loop gain ``K_h (C_h K_o - 1) / K_o`` >= 1 runs away)."""
    denom = k_o + (1.0 - cand["own_gain"] * k_o) * cand["k_h"]
    static = cand["k_h"] / np.where(denom > 0.0, denom, 1.0)
    return np.where(cand["i_gain"] > 0.0, 1.0, np.where(denom > 0.0, static, np.inf))


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


def _at_scale(base: dict[str, FloatArray], s: FloatArray) -> dict[str, FloatArray]:
    """Every candidate's gains scaled by s (:meth:`shared.gains.design.GainDesign.at`)."""
    k_h, i_gain, own_gain = scaled_gains(base["k_h"], base["i_gain"], base["own_gain"], s)
    return {"k_h": k_h, "i_gain": i_gain, "b_h": base["b_h"], "own_gain": own_gain}


def candidate_groups(
    k_o: float,
    lo: float,
    hi: float,
    *,
    rate_ratio: int,
    servo_period_s: float,
    integral: bool,
    k_h_max: float,
    b_h_max: float,
    own_force: bool,
    scaled: bool,
    felt_at: Sequence[float],
) -> list[tuple[dict[str, FloatArray], bool]]:
    """The candidate gains of :func:`shared.gains.design.design_gains`, in groups ``(gains, with
    an integral)``.

    The paper's local model first (K_h below ``lo``, with an integral when ``integral``), then,
    with ``own_force``, proportional models with own-force compensation (C_h K_h in
    :data:`OWN_FORCE_RATIOS`) and, for K_o above ``k_h_max``, the plane at the rest surface
    (C_h = 1 / K_o). Each group maps ``k_h`` [N/m], ``i_gain`` [N/(m*s)], ``b_h`` [N*s/m] and
    ``own_gain`` [m/N] to arrays of one value per candidate, shape (G,).

    Parameters
    ----------
    k_o, lo, hi : float
        The reported K_o [N/m] and the range ``[lo, hi]`` of K_o' the design is checked over.
    rate_ratio, servo_period_s : int, float
        N and T [s].
    integral : bool
        Whether the paper's local model has an integral (``pi``).
    k_h_max, b_h_max : float
        The device's maximum stiffness [N/m] and virtual damping [N*s/m].
    own_force, scaled, felt_at
        As :func:`shared.gains.design.design_gains` (``felt_at``: its ``felt_k_os``, or
        ``[k_o]``).
    """
    N, T = rate_ratio, servo_period_s
    # the paper's local model (K_h below K_o, the simulation loop's bound) ...
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
    return groups


@dataclass(frozen=True)
class Candidate:
    """The candidate :meth:`GainSearch.best_in_group` found: its gains (SI units, as
    :class:`shared.gains.design.GainDesign`), the worst spectral radius of its full check, its felt
    stiffness over K_o at 1 and 8 Hz, its largest scale, and its ``rank`` among the groups' and
    holds' candidates (higher wins): the objective, the model-error robustness, the mean over
    ``felt_at`` and closeness to K_o at 8 Hz."""

    k_h: float
    i_gain: float
    b_h: float
    own_gain: float
    proxy_hold: ProxyHold
    worst_spectral_radius: float
    felt_stiffness_ratio_1hz: float
    felt_stiffness_ratio_8hz: float
    scale_max: float
    rank: tuple[float, float, float, float]


class GainSearch:
    """One :func:`shared.gains.design.design_gains` problem: where its candidates are checked
    (hands, sampling ticks, K_o'), how they are judged (felt responses over the band, on the
    objects of ``felt_at`` and of the model error), and the staged search of one candidate group
    (:meth:`best_in_group`).

    Built once per call from its validated inputs; pure (no state changes after ``__init__``).
    """

    def __init__(
        self,
        k_o: float,
        lo: float,
        hi: float,
        *,
        b_o: float,
        rate_ratio: int,
        servo_period_s: float,
        delay_ticks: int,
        rho_limit: float,
        band: list[float],
        felt_at: list[float],
        model_error_k_os: list[float],
        own_force: bool,
        scaled: bool,
        hand_box: HandBox,
    ) -> None:
        N = rate_ratio
        self.k_o, self.lo, self.hi, self.b_o = k_o, lo, hi, b_o
        self.N, self.T, self.delay = N, servo_period_s, delay_ticks
        self.rho_limit, self.band, self.felt_at = rho_limit, band, felt_at
        self.model_error_k_os, self.own_force, self.scaled = model_error_k_os, own_force, scaled
        self.hand_box = hand_box
        self.k_os = k_o_points(lo, hi)
        self.screen_hands = hand_box.screen_hands()
        # the light, stiff, least damped hand and the heavy, soft, least damped one: the first
        # to ring
        self.pre_hands = list(
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
        self.pre_ticks = [N - 1]
        self.all_hands = hand_box.hands()
        self.screen_ticks = sorted({0, N // 2, N - 1})
        self.all_ticks = list(range(N))
        self.mid_ticks = sorted({int(j) for j in np.linspace(0, N - 1, 8)})
        self.rest_ticks = [j for j in self.all_ticks if j not in self.mid_ticks]
        # one tick in the middle of the period first, at every K_o': a candidate that passed the
        # screen's few hands and fails, mostly fails with another hand at most ticks
        self.probe_tick = [self.mid_ticks[len(self.mid_ticks) // 2]]
        self.mid_rest = [j for j in self.mid_ticks if j not in self.probe_tick]

    def _worst(
        self,
        cand: dict[str, FloatArray],
        hold: ProxyHold,
        hands: list[Hand],
        ticks: list[int],
        integral: bool,
        scale: float = 1.0,
        part: slice = slice(None),
    ) -> tuple[FloatArray, FloatArray]:
        """:func:`_worst_rho` of candidates ``cand`` scaled by ``scale`` (the K_o' they are
        checked over start at ``scale`` times ``lo``), over the K_o' of ``part``."""
        ks = (
            self.k_os
            if scale == 1.0
            else k_o_points(scale * self.lo, max(self.hi, scale * self.k_o))
        )
        if not ks[part]:
            # a range of one K_o' (no margin either way) has no points past the first: none fails
            g = cand["k_h"].shape[0]
            return np.zeros(g), np.zeros(g)
        return _worst_rho(
            cand,
            hold,
            hands,
            ks[part],
            b_o=self.b_o,
            servo_period_s=self.T,
            rate_ratio=self.N,
            delay_ticks=self.delay,
            sample_ticks=ticks,
            integral=integral,
            rho_limit=self.rho_limit,
        )

    def _served(
        self, k: float, base: dict[str, FloatArray], s_max: FloatArray
    ) -> dict[str, FloatArray]:
        """Every candidate's gains as rendered for a reported K_o = k (scaled when ``scaled``,
        each up to its ``s_max``)."""
        return _at_scale(base, np.minimum(max(k / self.k_o, 1.0), s_max)) if self.scaled else base

    def _own(self, k: float) -> FloatArray:
        """|the object's own dynamic stiffness| [N/m] at K_o = k over ``band``, (F, 1)
        (:func:`shared.full_loop.object_impedance`): eq. 9's ``|K_o + B_o (1 - e^{-j w N T})|``,
        K_o itself where B_o = 0. Real: the active share -Im of a response over it keeps its
        sign."""
        return np.abs(
            object_impedance(np.asarray(self.band)[:, None], k, self.b_o, self.N * self.T)
        )

    def _response(self, k: float, sc: dict[str, FloatArray], hold: ProxyHold) -> FloatArray:
        """Felt responses dF/dx (complex values, (F, G)) of gains ``sc`` on K_o = k at 1 Hz
        and, with ``own_force``, every frequency of ``band``
        (:data:`shared.gains.policy.FELT_BAND_HZ`), each over the magnitude of the object's own
        dynamic stiffness there with ``own_force`` (:meth:`_own`), else over K_o."""
        own = self._own(k) if self.own_force else np.full((len(self.band), 1), k)
        return (
            felt_responses(
                self.band,
                k_o=k,
                servo_period_s=self.T,
                rate_ratio=self.N,
                delay_ticks=self.delay,
                proxy_hold=hold,
                b_o=self.b_o,
                k_h=sc["k_h"],
                i_gain=sc["i_gain"],
                b_h=sc["b_h"],
                own_gain=sc["own_gain"],
            )
            / own
        )

    def _robustness(
        self, idx: IndexArray, base: dict[str, FloatArray], hold: ProxyHold
    ) -> FloatArray:
        """The worst error on the objects softer and stiffer than reported (the gains made
        for k_o rendering them), negated and rounded, for candidates ``idx``: computed only
        for the steps of the objective the search reaches."""
        if not self.model_error_k_os:
            return np.zeros(idx.size)
        sub = {k: v[idx] for k, v in base.items()}
        off = [
            np.maximum(_band_miss(self._response(k, sub, hold)), _log_miss(_felt_dc(sub, k)))
            for k in self.model_error_k_os
        ]
        return np.round(-np.max(off, axis=0), 3)

    def _passes(
        self,
        b: int,
        hold: ProxyHold,
        base: dict[str, FloatArray],
        with_i: bool,
        s_max: FloatArray,
    ) -> tuple[bool, float]:
        """Does candidate ``b`` pass the full check (every hand of the box, every sampling tick,
        every K_o' of its range), at its own gains and scaled to the middle and the top of its
        range (``s_max[b]``)? And the worst spectral radius seen."""
        one = {k: v[b : b + 1] for k, v in base.items()}
        s_top = float(s_max[b])
        rho = 0.0
        # the design's own gains, then scaled to the middle and the top of its range
        for s in dict.fromkeys((1.0, math.sqrt(s_top), s_top)):
            sc = _at_scale(one, np.full(1, s)) if s != 1.0 else one
            # most failures show at one tick, or at a few ticks and at the softest K_o' (a
            # compensated model with K_h above it): cheaper first. The verdict, and the worst
            # radius of a pass, are those of every tick at once
            for ticks, part in (
                [
                    (self.probe_tick, slice(None)),
                    (self.mid_rest, slice(0, 1)),
                    (self.mid_rest, slice(1, None)),
                    (self.rest_ticks, slice(None)),
                ]
                if len(self.all_ticks) > len(self.mid_ticks)
                else [(self.all_ticks, slice(None))]
            ):
                m_r, r_r = self._worst(sc, hold, self.all_hands, ticks, with_i, s, part)
                if not (m_r[0] < self.rho_limit and r_r[0] < 1.0 - 1e-9):
                    return False, float(r_r[0])
                rho = max(rho, float(r_r[0]))
        return True, rho

    def best_in_group(
        self,
        base: dict[str, FloatArray],
        with_i: bool,
        hold: ProxyHold,
        s_max: FloatArray,
        best_felt: float | None,
    ) -> Candidate | None:
        """The most transparent candidate of group ``base`` (with an integral: ``with_i``) with
        proxy hold ``hold`` that passes the full check; None if none does, or none can rank
        above ``best_felt`` (the objective, ``rank[0]``, of the best candidate so far).
        """
        k_o = self.k_o
        felt_dc = _felt_dc(base, k_o)
        resp_band = self._response(k_o, base, hold)
        resp1 = resp_band[self.band.index(1.0)]
        # objective, with own-force compensation: how far the felt response is from the
        # object's own (eq. 9: K_o where B_o = 0) over the band and from K_o in a held press
        # (DC), whichever is further (_band_miss, _log_miss);
        # across felt_at the worst counts, in steps of DESIGN_TIE (what a hand would not feel
        # apart); then the worst on the objects stiffer and softer than reported (model error);
        # then the mean over felt_at (a tie of the worst: K_h at the device's stiffness is the
        # top of a scaled K_h's range). Without it (the paper's models alone): the elastic part
        # of the felt stiffness at 1 Hz, capped at the object's own
        if self.own_force:
            errs = [np.maximum(_band_miss(resp_band), _log_miss(felt_dc))]
            for k in self.felt_at:
                if k != k_o:
                    sc = self._served(k, base, s_max)
                    errs.append(
                        np.maximum(
                            _band_miss(self._response(k, sc, hold)), _log_miss(_felt_dc(sc, k))
                        )
                    )
            worst_err = np.max(errs, axis=0)
            felt1 = -np.floor(np.where(np.isfinite(worst_err), worst_err, 1e9) / DESIGN_TIE)
            felt1 = np.where(np.isfinite(worst_err), felt1, -np.inf)
            felt_mean = np.round(1.0 - np.mean(errs, axis=0), 4)
        else:
            felt1 = np.round(np.minimum(resp1.real, 1.0), 3)
            felt_mean = np.zeros_like(felt1)
        robust = np.zeros_like(felt1)
        if best_felt is not None:
            felt1 = np.where(felt1 < best_felt - 1e-9, -np.inf, felt1)  # cannot win

        # the search goes step by step of the objective, the best first, when a step's order
        # depends on the model-error check (computed as the search reaches it)
        if self.model_error_k_os:
            steps = [np.flatnonzero(felt1 == v) for v in np.unique(felt1[np.isfinite(felt1)])[::-1]]
        else:
            steps = [np.flatnonzero(np.isfinite(felt1))]
        found = self._first_passing(steps, felt1, robust, felt_mean, base, with_i, hold, s_max)
        if found is None:
            return None
        i, rho_full = found
        own1 = float(self._own(k_o)[self.band.index(1.0), 0]) if self.own_force else k_o
        felt8 = float(
            felt_stiffness(
                8.0,
                k_o=k_o,
                k_h=base["k_h"][i],
                i_gain=base["i_gain"][i],
                b_h=base["b_h"][i],
                own_gain=base["own_gain"][i],
                b_o=self.b_o,
                servo_period_s=self.T,
                rate_ratio=self.N,
                delay_ticks=self.delay,
                proxy_hold=hold,
            )[0]
            / k_o
        )
        return Candidate(
            k_h=float(base["k_h"][i]),
            i_gain=float(base["i_gain"][i]),
            b_h=float(base["b_h"][i]),
            own_gain=float(base["own_gain"][i]),
            proxy_hold=hold,
            worst_spectral_radius=rho_full,
            felt_stiffness_ratio_1hz=float(abs(resp1[i]) * own1 / k_o),
            felt_stiffness_ratio_8hz=felt8,
            scale_max=float(s_max[i]),
            rank=(float(felt1[i]), float(robust[i]), float(felt_mean[i]), -abs(felt8 - 1.0)),
        )

    def _first_passing(
        self,
        steps: list[IndexArray],
        felt1: FloatArray,
        robust: FloatArray,
        felt_mean: FloatArray,
        base: dict[str, FloatArray],
        with_i: bool,
        hold: ProxyHold,
        s_max: FloatArray,
    ) -> tuple[int, float] | None:
        """The first candidate, in order of transparency, that passes the full check, and its
        worst spectral radius; fills ``robust`` for the steps it reaches.

        Screens in order of transparency (two hands at one tick, then few hands at three
        sampling ticks), then verifies fully; each stage only drops candidates a later one would.
        """
        for in_step in steps:
            robust[in_step] = self._robustness(in_step, base, hold)
            order = in_step[np.lexsort((-felt_mean[in_step], -robust[in_step], -felt1[in_step]))]
            for a in range(0, order.size, 64):
                idx = order[a : a + 64]
                sub = {k: v[idx] for k, v in base.items()}
                rho_p = self._worst(sub, hold, self.pre_hands, self.pre_ticks, with_i)[0]
                idx = idx[rho_p < self.rho_limit]
                if idx.size == 0:
                    continue
                sub = {k: v[idx] for k, v in base.items()}
                rho_s = self._worst(sub, hold, self.screen_hands, self.screen_ticks, with_i)[0]
                for b in idx[rho_s < self.rho_limit]:
                    ok_b, r_b = self._passes(int(b), hold, base, with_i, s_max)
                    if ok_b:
                        return int(b), r_b
        return None
