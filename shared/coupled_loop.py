"""Several users on one object: every user's full loop, coupled through the object's compliance.

Each user's full loop (:mod:`shared.full_loop`, DESIGN section 6b) is the hand + device plant, the
local model L(z) of eq. 12 with the filtered probe damper, the decimator (Step 3 of the paper's
section 6: the simulation takes the force of servo tick ``j`` of the user's block), the object,
``D`` ticks of delay and the proxy hold (eq. 1, or a first-order hold). With M users on one object
the object block is a matrix: the contacts' normal compliance ``C`` (M x M, [m/N], symmetric
positive definite, DESIGN section 5, ``C_ij = beta_i^T K^-1 beta_j``) maps the M sampled forces to
the M surface displacements, eq. 6 and eq. 9 written for M contacts:

    ``x_o(k+1) = (C^-1 + B_o)^-1 (F(k) + B_o x_o(k)) = (I + C B_o)^-1 C (F(k) + B_o x_o(k))``

with ``B_o = diag(b_o)`` [N/m] (0: the elastic object ``x_o(k+1) = C F(k)``). User u's proxy is its
own surface displacement ``x_o,u``, held after ``D`` ticks. The users' servo loops are not
synchronised, so every user has its own sampling tick ``j_u`` (its own phase between its patch
arriving and the simulation taking its force); each block is the user's own N servo ticks.
The coupled monodromy matrix (the state-transition matrix over one simulation period) is
assembled from the per-user lifted blocks of :func:`shared.full_loop.monodromy` (evaluated with
``K_o = 1`` so that its object row is exactly the sampled-force row); with one user and
``C = 1 / K_o`` it reproduces :func:`shared.full_loop.spectral_radius` (tested to 1e-9).

Modal decomposition (why K_o_eff alone is not enough). If every user has the same hand, local
model, hold and sampling tick, and ``B_o = b I``, write ``C = V diag(lambda) V^T`` (V orthonormal).
All user blocks are identical linear maps and the only cross-user term is C, so the coordinates
``V^T`` (applied to every state of the M users alike) split the coupled loop into M single-user
full loops with object stiffness ``1 / lambda_i``: the coupled spectral radius is the largest
single-user spectral radius over the *modal stiffnesses* ``1 / lambda_i(C)``. With
``S = K^1/2 C K^1/2`` (``K = diag(K_o,i)``, ``K_o,i = 1 / C_ii``, unit diagonal) they range over

- ``K_o_eff = K_o / lambda_max(S)``: the common mode, all users pressing together on a softer
  object; what the server reports today (:func:`server.contact_stiffness.effective_stiffness`).
  The paper's P argument (eq. 8 for each mode: ``rho(C diag K_h) < 1``) needs only this one.
- ``K_o_stiff = K_o / lambda_min(S)``: the differential mode, one user pressing, another pushed
  back; at coupling c -> 1 the object transmits the push rigidly (``K_o_stiff -> inf``).

For the product's parametrisation ``C = (1/K_o) ((1 - c) I + c 1 1^T)``:
``K_o_eff = K_o / (1 + (M-1) c)``, ``K_o_stiff = K_o / (1 - c)``. With a rigid probe a stiffer
object only helps (eq. 8, eq. 15: the PI region of Fig. 8 scales up with K_o), but with the hand in
the loop the PI local model is *not* robust to a stiffer object: against a rigid proxy the hand +
PI loop is roughly ``m s^3 + (b + B_h) s^2 + (k + K_h) s + I`` (continuous time, no delay, no
damper filter), unstable for a heavy, lightly damped hand once ``I > (b + B_h)(k + K_h) / m``. An
integral chosen for the soft K_o_eff breaks that (docs/coupled-users.md: coupled spectral radius
up to 1.10 with the Phantom's limits). So each user's gains must be designed over the whole modal
range ``[(1 - margin) K_o_eff, K_o_stiff]`` (:func:`shared.gains.coupled_design.design_coupled`), then
verified on the coupled loop with *different* hands and sampling ticks per user, which the modal
argument does not cover (:func:`verify_coupled`). A proportional local model (I = 0) needs only
K_o_eff (measured, same document). :func:`stiff_ratio_class` and :func:`coupled_k_o_hi` are the
product's form of the rule for a gain table keyed on K_o_eff.

This module owns the coupled loop and its verification (:func:`coupled_monodromy`,
:func:`verify_coupled`); the compliance matrix and its modal stiffnesses are
:mod:`shared.coupled_compliance`, the per-user design over the modal range
:mod:`shared.gains.coupled_design`.

Units SI throughout; depths along each contact's inward normal [m]; forces [N].
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from haptic_collab.shared.checks import NonNegFinite, PositiveFinite, params_dataclass
from haptic_collab.shared.checks import whole as _whole
from haptic_collab.shared.coupled_compliance import check_compliance
from haptic_collab.shared.full_loop import (
    DEFAULT_HAND_BOX,
    STABILITY_TOL,
    Hand,
    HandBox,
    ProxyHold,
    monodromy,
    spectral_radius_function,
)
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.policy import MIN_DECAY_RATE_PER_S
from haptic_collab.shared.rates import Rates
from haptic_collab.shared.stability_margin import mode_radii
from haptic_collab.shared.types import FloatArray, IndexArray

#: Batch size of coupled monodromy matrices per eigenvalue call (bounds memory: 4096 x 30 x 30).
_CHUNK = 4096


# --------------------------------------------------------------------------------------------
# the coupled lifted loop


@params_dataclass(frozen=True, slots=True)
class UserGains:
    """One user's local model (eq. 12 plus the probe damper), SI units.

    Attributes
    ----------
    k_h : float
        K_h [N/m], > 0.
    i_gain : float
        I [N/(m*s)], >= 0 (0: proportional local model).
    b_h : float
        Probe damper B_h [N*s/m], >= 0.
    proxy_hold : {"zoh", "foh"}
    own_gain : float
        Own-force compensation C_h [m/N], >= 0 (:mod:`shared.full_loop`): the user's proxy is its
        surface displacement less C_h times its own sampled force.

    Raises
    ------
    pydantic.ValidationError
        (a ValueError naming the field) Non-finite, non-numeric or out-of-range values.
    """

    k_h: PositiveFinite
    i_gain: NonNegFinite = 0.0
    b_h: NonNegFinite = 0.0
    proxy_hold: ProxyHold = "zoh"
    own_gain: NonNegFinite = 0.0

    @classmethod
    def from_design(cls, design: GainDesign) -> UserGains:
        """The gains of a :class:`shared.gains.design.GainDesign`."""
        return cls(design.k_h, design.i_gain, design.b_h, design.proxy_hold, design.own_gain)


@dataclass(frozen=True)
class _Blocks:
    """One user's lifted servo-rate pieces for H hands and J sampling ticks (no object)."""

    phi: FloatArray  # (H, nf, nf) fast state over the block
    g_new: FloatArray  # (H, nf) ... from the proxy
    g_old: FloatArray  # (H, nf) ... from the previous proxy (foh)
    f_xi: FloatArray  # (H, J, nf) sampled force from the fast state
    f_new: FloatArray  # (H, J) ... from the proxy
    f_old: FloatArray  # (H, J) ... from the previous proxy (foh)
    foh: bool
    own_gain: float = 0.0  # C_h [m/N]: the proxy less C_h times the user's own sampled force

    @property
    def nf(self) -> int:
        return int(self.phi.shape[1])


def _user_blocks(
    gains: UserGains,
    hands: Sequence[Hand | None],
    ticks: Sequence[int],
    *,
    servo_period_s: float,
    rate_ratio: int,
) -> _Blocks:
    """Blocks of :func:`shared.full_loop.monodromy` at ``K_o = 1``: its object row is the force."""
    foh = gains.proxy_hold == "foh"
    rigid = [h is None for h in hands]
    if any(rigid) and not all(rigid):
        raise ValueError("a user's hands must be all None (rigid probe) or all Hand")
    uniq = sorted(set(int(j) for j in ticks))
    M = monodromy(
        hand=None if rigid[0] else [h for h in hands if h is not None],
        k_o=1.0,
        k_h=np.full(len(hands), gains.k_h),
        i_gain=gains.i_gain,
        b_h=gains.b_h,
        b_o=0.0,
        servo_period_s=servo_period_s,
        rate_ratio=rate_ratio,
        delay_ticks=0,
        sample_ticks=uniq,
        proxy_hold=gains.proxy_hold,
        integral=gains.i_gain > 0.0,
    )
    sel = [uniq.index(int(j)) for j in ticks]
    M = M[:, sel]
    n = M.shape[-1]
    nf = n - 2 - (1 if foh else 0)
    i_p, i_obj = nf, n - 1
    g_new = M[:, 0, :nf, i_p]
    f_new = M[:, :, i_obj, i_p]
    return _Blocks(
        phi=M[:, 0, :nf, :nf],
        g_new=g_new,
        g_old=M[:, 0, :nf, nf + 1] if foh else np.zeros_like(g_new),
        f_xi=M[:, :, i_obj, :nf],
        f_new=f_new,
        f_old=M[:, :, i_obj, nf + 1] if foh else np.zeros_like(f_new),
        foh=foh,
        own_gain=float(gains.own_gain),
    )


def _assemble(
    blocks: Sequence[_Blocks],
    hand_idx: IndexArray,
    tick_idx: IndexArray,
    compliance: FloatArray,
    b_o: FloatArray,
    delays: Sequence[int],
) -> FloatArray:
    """Coupled monodromy matrices (K, n, n) for hand/tick indices (K, M), compliance (K, M, M),
    user u's proxy ``delays[u]`` ticks late.

    State: per user u in turn ``[fast states, proxy, (previous proxy), object, delay line]``, the
    layout of :func:`shared.full_loop.monodromy`.
    """
    m = len(blocks)
    nb = hand_idx.shape[0]
    sizes = [b.nf + 2 + (1 if b.foh else 0) + int(d) for b, d in zip(blocks, delays, strict=True)]
    offs = [0, *itertools.accumulate(sizes)]
    n = offs[-1]
    Mx = np.zeros((nb, n, n))
    # object, eq. 9 for M contacts: x_o' = A F + Bm x_o, A = (I + C B_o)^-1 C, Bm = A B_o
    A = np.linalg.solve(np.eye(m)[None] + compliance * b_o[None, None, :], compliance)
    Bm = A * b_o[None, None, :]
    frows = np.zeros((m, nb, n))  # each user's sampled force over the whole state
    i_obj = []
    for u, bl in enumerate(blocks):
        o, nf = offs[u], bl.nf
        h, j = hand_idx[:, u], tick_idx[:, u]
        i_p = o + nf
        Mx[:, o:i_p, o:i_p] = bl.phi[h]
        Mx[:, o:i_p, i_p] = bl.g_new[h]
        frows[u, :, o:i_p] = bl.f_xi[h, j]
        frows[u, :, i_p] = bl.f_new[h, j]
        if bl.foh:
            Mx[:, o:i_p, i_p + 1] = bl.g_old[h]
            Mx[:, i_p + 1, i_p] = 1.0
            frows[u, :, i_p + 1] = bl.f_old[h, j]
        i_obj.append(i_p + (2 if bl.foh else 1))
    obj_rows = np.einsum("buv,vbn->bun", A, frows)
    obj_rows[:, :, np.array(i_obj)] += Bm
    for u, bl in enumerate(blocks):
        i_p, io = offs[u] + bl.nf, i_obj[u]
        Mx[:, io, :] = obj_rows[:, u]
        # the proxy delivered: the surface less C_h times the user's own sampled force
        proxy_row = obj_rows[:, u] - bl.own_gain * frows[u] if bl.own_gain else obj_rows[:, u]
        D = int(delays[u])
        if D == 0:
            Mx[:, i_p, :] = proxy_row
        else:
            Mx[:, i_p, io + 1] = 1.0
            for r in range(D - 1):
                Mx[:, io + 1 + r, io + 2 + r] = 1.0
            Mx[:, io + D, :] = proxy_row
    return Mx


def _check_common(
    compliance: ArrayLike,
    gains: Sequence[UserGains],
    b_o: ArrayLike,
    rate_ratio: int,
    delay_ticks: int | Sequence[int],
) -> tuple[FloatArray, FloatArray]:
    c = check_compliance(compliance)
    m = c.shape[0]
    if len(gains) != m:
        raise ValueError(f"{m} users in the compliance but {len(gains)} gains")
    bo = np.broadcast_to(np.asarray(b_o, dtype=float), (m,)).copy()
    if not (np.all(np.isfinite(bo)) and np.all(bo >= 0.0)):
        raise ValueError(f"b_o must be finite and >= 0, got {b_o!r}")
    _whole("rate_ratio", rate_ratio, 1)
    return c, bo


def _delays(delay_ticks: int | Sequence[int], m: int) -> tuple[int, ...]:
    """Each of ``m`` users' delay [ticks]: one whole number for all, or one per user."""
    if isinstance(delay_ticks, Sequence):
        if len(delay_ticks) != m:
            raise ValueError(f"{m} users but {len(delay_ticks)} delays")
        for d in delay_ticks:
            _whole("delay_ticks", d, 0)
        return tuple(int(d) for d in delay_ticks)
    _whole("delay_ticks", delay_ticks, 0)
    return (int(delay_ticks),) * m


def coupled_monodromy(
    *,
    compliance: ArrayLike,
    gains: Sequence[UserGains],
    hands: Sequence[Sequence[Hand | None]],
    sample_ticks: Sequence[Sequence[int]] | None = None,
    b_o: ArrayLike = 0.0,
    servo_period_s: float = 1e-3,
    rate_ratio: int = 50,
    delay_ticks: int | Sequence[int] = 0,
) -> FloatArray:
    """Monodromy matrices of M users' full loops coupled through the object (module docstring).

    Parameters
    ----------
    compliance : (M, M) float [m/N]
        The contacts' normal compliance C (symmetric PSD, positive diagonal).
    gains : sequence of M UserGains
        Each user's local model.
    hands : (B, M) nested sequence of Hand or None
        B hand combinations, one hand per user (None: that user's probe is rigid, a position
        source; a user must be rigid in all combinations or in none).
    sample_ticks : (J, M) nested sequence of int, optional
        J combinations of sampling ticks, one ``j_u`` in [0, N) per user (default: the N
        combinations with every user at the same tick).
    b_o : float or sequence of M floats
        Object damping per contact B_o [N/m] (eq. 9), >= 0: ``B_o = diag(b_o)``.
    servo_period_s : float
        T [s].
    rate_ratio : int
        N, servo ticks per simulation tick.
    delay_ticks : int or sequence of M ints
        D, extra whole simulation ticks of delay, >= 0: the same for every user, or one per user
        (user u's proxy is its contact's surface D_u ticks late: each user's whole round trip
        lumped on the way to its proxy, the single-user loop's convention).

    Returns
    -------
    (B, J, n, n) float array
        ``n = sum_u (n_fast,u + 2 + [foh] + D)``; state per user as in
        :func:`shared.full_loop.monodromy`.

    Raises
    ------
    ValueError
        Inconsistent shapes, a bad compliance, out-of-range ticks, delay or gains.
    """
    c, bo = _check_common(compliance, gains, b_o, rate_ratio, delay_ticks)
    m, N = c.shape[0], int(rate_ratio)
    delays = _delays(delay_ticks, m)
    combos = [tuple(h) for h in hands]
    if not combos or any(len(h) != m for h in combos):
        raise ValueError(f"hands must be a non-empty sequence of {m}-user combinations")
    tick_combos = (
        [(j,) * m for j in range(N)] if sample_ticks is None else [tuple(t) for t in sample_ticks]
    )
    if not tick_combos or any(len(t) != m for t in tick_combos):
        raise ValueError(f"sample_ticks must be a non-empty sequence of {m}-user combinations")
    if any(not 0 <= int(j) < N for t in tick_combos for j in t):
        raise ValueError(f"sample ticks must be in [0, {N})")
    blocks, h_idx, t_idx = [], [], []
    for u in range(m):
        hu = list(dict.fromkeys(h[u] for h in combos))
        tu = sorted({int(t[u]) for t in tick_combos})
        blocks.append(
            _user_blocks(gains[u], hu, tu, servo_period_s=float(servo_period_s), rate_ratio=N)
        )
        h_idx.append([hu.index(h[u]) for h in combos])
        t_idx.append([tu.index(int(t[u])) for t in tick_combos])
    B, J = len(combos), len(tick_combos)
    hi = np.repeat(np.array(h_idx, dtype=np.intp).T, J, axis=0)
    ti = np.tile(np.array(t_idx, dtype=np.intp).T, (B, 1))
    Mx = _assemble(blocks, hi, ti, np.broadcast_to(c, (B * J, m, m)), bo, delays)
    return Mx.reshape(B, J, *Mx.shape[1:])


coupled_spectral_radius = spectral_radius_function(
    coupled_monodromy,
    name="coupled_spectral_radius",
    doc="""Spectral radius of the coupled loop per hand and tick combination, shape (B, J).

    Same parameters as :func:`coupled_monodromy`. Below 1: every mode of every user's hand,
    device and local model and of the object decays from one simulation period to the next.
    """,
)


# --------------------------------------------------------------------------------------------
# verification over hands, sampling ticks and the K_o margin


@dataclass(frozen=True)
class CoupledVerdict:
    """Worst case of the coupled loop over the checked combinations (:func:`verify_coupled`).

    Attributes
    ----------
    spectral_radius : float
        Largest spectral radius of the coupled monodromy.
    margin_radius : float
        Largest oscillating eigenvalue magnitude, creep eigenvalues (slower than
        :data:`shared.gains.policy.CREEP_FREQUENCY_HZ`) counted as ``|lambda| * rho_limit``: the
        quantity :func:`shared.gains.design.design_gains` holds below ``rho_limit``.
    rho_limit : float
        ``exp(-min_decay_rate * N * T)``, the single-user design's bound.
    meets_margin : bool
        ``margin_radius < rho_limit`` and ``spectral_radius < 1``: the same margin as one user.
    stable : bool
        ``spectral_radius < 1``.
    worst_hands : tuple of Hand
        One hand per user at the worst case.
    worst_sample_ticks : tuple of int
        One sampling tick per user at the worst case.
    worst_compliance_scale : float
        The compliance factor (1, or ``1 / (1 - margin)``) at the worst case.
    cases : int
        Coupled loops evaluated.
    """

    spectral_radius: float
    margin_radius: float
    rho_limit: float
    meets_margin: bool
    stable: bool
    worst_hands: tuple[Hand | None, ...]
    worst_sample_ticks: tuple[int, ...]
    worst_compliance_scale: float
    cases: int

    def to_json(self) -> dict[str, object]:
        """Plain JSON-able dict."""
        return {
            "spectral_radius": self.spectral_radius,
            "margin_radius": self.margin_radius,
            "rho_limit": self.rho_limit,
            "meets_margin": self.meets_margin,
            "stable": self.stable,
            "worst_hands": [None if h is None else h.as_dict() for h in self.worst_hands],
            "worst_sample_ticks": list(self.worst_sample_ticks),
            "worst_compliance_scale": self.worst_compliance_scale,
            "cases": self.cases,
        }


def verification_hands(box: HandBox = DEFAULT_HAND_BOX) -> list[Hand]:
    """The hands each user takes in :func:`verify_coupled`: box corners, centre, ``extra``."""
    return box.screen_hands()


def _permutation_symmetric(c: FloatArray, gains: Sequence[UserGains], b_o: FloatArray) -> bool:
    """Whether relabelling the users leaves the coupled loop unchanged (equal gains and object
    damping, equal diagonal, equal off-diagonal compliance)."""
    m = c.shape[0]
    if any(g != gains[0] for g in gains) or np.ptp(b_o) > 0.0:
        return False
    d = np.diag(c)
    off = c[~np.eye(m, dtype=bool)]
    tol = 1e-12 * float(np.max(np.abs(c)))
    return bool(np.ptp(d) <= tol and (off.size == 0 or np.ptp(off) <= tol))


def verify_coupled(
    compliance: ArrayLike,
    gains: Sequence[UserGains],
    *,
    b_o: ArrayLike = 0.0,
    servo_rate_hz: float = 1000.0,
    sim_rate_hz: float = 20.0,
    delay_ticks: int | Sequence[int] = 0,
    margin: float = 0.15,
    hands: Sequence[Hand | None] | None = None,
    sample_ticks: Sequence[int] | None = None,
    hand_combos: Sequence[Sequence[Hand | None]] | None = None,
    tick_combos: Sequence[Sequence[int]] | None = None,
    min_decay_rate_per_s: float = MIN_DECAY_RATE_PER_S,
) -> CoupledVerdict:
    """Worst coupled spectral radius over hands x sampling ticks x the K_o margin.

    Every user takes every hand of ``hands`` and every tick of ``sample_ticks`` independently
    (all combinations; when relabelling users leaves the loop unchanged -- equal gains and object
    damping, equal diagonal and off-diagonal compliance -- only one combination per multiset of
    (hand, tick) pairs, which is exact). The compliance is checked as given and scaled by
    ``1 / (1 - margin)`` (every K_o overestimated by ``margin``, as
    :func:`shared.gains.design.design_gains` checks).

    Parameters
    ----------
    compliance : (M, M) float [m/N]
    gains : sequence of M UserGains
    b_o : float or (M,) [N/m]
    servo_rate_hz, sim_rate_hz : float
        1/T and 1/(N*T) [Hz]; N must be whole.
    delay_ticks : int or sequence of M ints
        One delay for every user or one per user (:func:`coupled_monodromy`).
    margin : float
        In [0, 1).
    hands : sequence of Hand or None, optional
        Per-user hands (default :func:`verification_hands`: the 8 corners of the default box, its
        centre and the simulated user's hand).
    sample_ticks : sequence of int, optional
        Per-user sampling ticks (default ``{0, N/2, N-1}``: the worst cases sit at the ends).
    hand_combos, tick_combos : (B, M) and (J, M) nested sequences, optional
        Explicit combinations instead of the products above (then no symmetry reduction).
    min_decay_rate_per_s : float
        Decay-rate margin [1/s] (:data:`shared.gains.policy.MIN_DECAY_RATE_PER_S`).

    Raises
    ------
    ValueError
        As :func:`coupled_monodromy`; margin outside [0, 1); no hands or ticks.
    """
    rates = Rates(servo_rate_hz, sim_rate_hz)
    N, T = rates.ratio, rates.servo_period_s
    c, bo = _check_common(compliance, gains, b_o, N, delay_ticks)
    delays = _delays(delay_ticks, c.shape[0])
    if not (math.isfinite(margin) and 0.0 <= margin < 1.0):
        raise ValueError(f"margin must be in [0, 1), got {margin!r}")
    m = c.shape[0]
    hs: list[Hand | None] = [h for h in (verification_hands() if hands is None else hands)]
    if not hs:
        raise ValueError("hands must not be empty")
    ts = (
        sorted({0, N // 2, N - 1})
        if sample_ticks is None
        else sorted({int(j) for j in _ticks_ok(sample_ticks, N)})
    )
    # per-user (hand, tick) pairs
    if hand_combos is None and tick_combos is None:
        pairs = [(h, t) for h in range(len(hs)) for t in range(len(ts))]
        combos: list[tuple[int, ...]]
        if _permutation_symmetric(c, gains, bo) and len(set(delays)) == 1:
            combos = list(itertools.combinations_with_replacement(range(len(pairs)), m))
        else:
            combos = list(itertools.product(range(len(pairs)), repeat=m))
        idx = np.array(combos, dtype=np.intp).reshape(len(combos), m)
        pair_arr = np.array(pairs, dtype=np.intp)
        h_idx, t_idx = pair_arr[idx, 0], pair_arr[idx, 1]
        user_hands: list[list[Hand | None]] = [hs] * m
        user_ticks: list[list[int]] = [ts] * m
    else:
        hc = [tuple(h) for h in (hand_combos or [(h,) * m for h in hs])]
        tc = [tuple(int(j) for j in t) for t in (tick_combos or [(j,) * m for j in ts])]
        if any(len(h) != m for h in hc) or any(len(t) != m for t in tc):
            raise ValueError(f"hand_combos and tick_combos must hold {m}-user combinations")
        _ticks_ok([j for t in tc for j in t], N)
        user_hands = [list(dict.fromkeys(h[u] for h in hc)) for u in range(m)]
        user_ticks = [sorted({t[u] for t in tc}) for u in range(m)]
        hh = np.array([[user_hands[u].index(h[u]) for u in range(m)] for h in hc], dtype=np.intp)
        tt = np.array([[user_ticks[u].index(t[u]) for u in range(m)] for t in tc], dtype=np.intp)
        h_idx = np.repeat(hh, len(tc), axis=0)
        t_idx = np.tile(tt, (len(hc), 1))
    blocks = [
        _user_blocks(gains[u], user_hands[u], user_ticks[u], servo_period_s=T, rate_ratio=N)
        for u in range(m)
    ]
    rho_limit = math.exp(-min_decay_rate_per_s * N * T)
    scales = [1.0] if margin == 0.0 else [1.0, 1.0 / (1.0 - margin)]
    best = (-1.0, -1.0, 0, 1.0)  # margin radius, radius, combo, scale
    K = h_idx.shape[0]
    for s in scales:
        for a in range(0, K, _CHUNK):
            sl = slice(a, min(a + _CHUNK, K))
            k = sl.stop - sl.start
            Mx = _assemble(
                blocks, h_idx[sl], t_idx[sl], np.broadcast_to(c * s, (k, m, m)), bo, delays
            )
            marg, rad = mode_radii(Mx, rho_limit, N, T)
            w = int(np.argmax(marg))
            if marg[w] > best[0]:
                best = (float(marg[w]), max(best[1], float(rad.max())), a + w, s)
            else:
                best = (best[0], max(best[1], float(rad.max())), best[2], best[3])
    marg_r, rad_r, wc, ws = best
    return CoupledVerdict(
        spectral_radius=rad_r,
        margin_radius=marg_r,
        rho_limit=rho_limit,
        meets_margin=bool(marg_r < rho_limit and rad_r < 1.0 - STABILITY_TOL),
        stable=bool(rad_r < 1.0 - STABILITY_TOL),
        worst_hands=tuple(user_hands[u][int(h_idx[wc, u])] for u in range(m)),
        worst_sample_ticks=tuple(int(user_ticks[u][int(t_idx[wc, u])]) for u in range(m)),
        worst_compliance_scale=ws,
        cases=K * len(scales),
    )


def _ticks_ok(ticks: Sequence[int], rate_ratio: int) -> list[int]:
    """``ticks`` as ints, checked to lie in [0, N)."""
    out = [int(j) for j in ticks]
    if not out or any(not 0 <= j < rate_ratio for j in out):
        raise ValueError(f"sample ticks must be in [0, {rate_ratio}), got {list(ticks)!r}")
    return out
