"""The full haptic loop against an object's slow modes: rendered gains checked on the solid itself.

The gain design (:mod:`shared.gains.design`) checks a local model on :mod:`shared.full_loop`'s
loop, whose object is what the server reports of a contact and nothing more: eq. 9,
``x_o(k+1) = (F(k) + B_o x_o(k)) / (K_o + B_o)``. A FEM solid is more: its lowest modes (the
liver ball rocks at 1.6-2.4 Hz) keep moving for many simulation ticks, and a hand resting on it
through the local model can keep them going (docs/palpation.md; docs/fem.md, "The solid's slow
modes"). This module closes the same loop, block for block, over the contact's own modal
dynamics instead:

object (simulation rate), the contact's modes (:class:`ContactModes`)
    ``z(k+1) = A z(k) + b F(k)``, ``x_o(k+1) = c . z(k+1) + d F(k)``: every mode's displacement and
    velocity stepped exactly for the force held over the period, and the static residual of the
    rest in ``d``, as :meth:`server.objects.fem.FemSolid.step` moves the contact
    (:meth:`server.objects.fem.FemSolid.contact_modes` gives them).

Everything else (the hand and device, the local model at the servo rate, its probe damper, the
decimation, the delay, the proxy hold, own-force compensation) is :func:`shared.full_loop.monodromy`'s,
read from its own matrices: the servo-rate block over one simulation period is taken from
``monodromy`` for a unit object and re-closed here (:func:`modal_monodromy`), so both checks
share one model of everything but the object. Not part of the design code
(:func:`shared.gains.table_file.design_code_hash`): a diagnosis of rendered gains, as
``tools/modal_loop_check.py`` runs it.

Judged as the design judges: the monodromy matrix's eigenvalues over every sampling tick and
hand, oscillating modes by their decay and creep only for growth (:func:`decay_rates`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from haptic_collab.shared.full_loop import Hand, ProxyHold, _hand_zoh, monodromy, slow_layout
from haptic_collab.shared.gains.policy import MIN_DECAY_RATE_PER_S
from haptic_collab.shared.stability_margin import mode_radii
from haptic_collab.shared.types import FloatArray

#: Frequencies from 0 to the simulation rate's Nyquist that :meth:`ContactModes.dynamic_peaks`
#: evaluates each mode at (besides its own).
PEAK_GRID = 32


@dataclass(frozen=True)
class ContactModes:
    """A contact's response to a push held over each simulation period (SI units).

    ``z(k+1) = a z(k) + b F(k)``; the contact's depth (along the inward normal, what
    :mod:`shared.full_loop` calls ``x_o``) ``x(k+1) = c . z(k+1) + d F(k)``.

    Attributes
    ----------
    a : (2M, 2M) float
        The modes' state transition over one period (block diagonal: each mode's displacement
        and velocity).
    b : (2M,) float
        Their input from the push F [N].
    c : (2M,) float
        The depth's output row [m per state unit].
    d : float
        The static residual [m/N]: the compliance of the modes not stepped and of each stepped
        mode's static part removed.
    """

    a: FloatArray
    b: FloatArray
    c: FloatArray
    d: float

    def __post_init__(self) -> None:
        n = len(self.b)
        if self.a.shape != (n, n) or self.c.shape != (n,):
            raise ValueError(f"modal shapes differ: a {self.a.shape}, b ({n},), c {self.c.shape}")
        if not (np.all(np.isfinite(self.a)) and np.all(np.isfinite(self.b))):
            raise ValueError("modal matrices hold a non-finite value")
        if not (math.isfinite(self.d) and self.c_static > 0.0):
            raise ValueError(f"the static compliance must be finite and > 0, got {self.c_static}")

    @property
    def mode_count(self) -> int:
        """How many modes are stepped."""
        return len(self.b) // 2

    @property
    def c_static(self) -> float:
        """The static compliance 1/K_o [m/N]: ``d`` and every mode's static share."""
        return self.d + float(self.static_shares().sum())

    def _blocks(self) -> tuple[FloatArray, ...]:
        """Each mode's 2x2 block of ``a`` (a00, a01, a10, a11), its ``b`` (b0, b1) and ``c`` (c0,
        c1): ten arrays of shape (M,)."""
        i = 2 * np.arange(self.mode_count)
        a = self.a
        return (
            a[i, i], a[i, i + 1], a[i + 1, i], a[i + 1, i + 1],
            self.b[i], self.b[i + 1], self.c[i], self.c[i + 1],
        )  # fmt: skip

    def static_shares(self) -> FloatArray:
        """Each mode's share of the static compliance [m/N]: its depth under a 1 N push held
        until it settles, ``c_i (I - A_i)^-1 b_i``; with ``d`` they add up to ``c_static``."""
        a00, a01, a10, a11, b0, b1, c0, c1 = self._blocks()
        det = (1.0 - a00) * (1.0 - a11) - a01 * a10
        return np.asarray(
            (c0 * ((1.0 - a11) * b0 + a01 * b1) + c1 * (a10 * b0 + (1.0 - a00) * b1)) / det
        )

    def dynamic_peaks(self) -> FloatArray:
        """Each mode's largest dynamic response [m/N]: ``max |G_i(e^jw) - G_i(1)|`` over the
        frequencies up to the simulation rate's Nyquist (a grid of :data:`PEAK_GRID` and the
        mode's own frequency), ``G_i`` its transfer from the push held over a period to the
        depth at the period's end (``c_i (z I - A_i)^-1 b_i z``) and ``G_i(1)`` its static share.

        What treating the mode as static (:meth:`reduced`: its share moved into ``d``) changes in
        the depth's response, at most: the H-infinity norm of the mode's dynamic part, the measure
        modal truncation ranks modes by (Gawronski 2004, *Advanced Structural Dynamics and
        Active Control of Structures*, ch. 5), and whose sum over the modes dropped bounds the
        reduced model's error at every frequency. A lightly damped mode peaks at its own
        frequency, an overdamped one at the Nyquist frequency; both are on the grid.
        """
        a00, a01, a10, a11, b0, b1, c0, c1 = (x[:, None] for x in self._blocks())
        half = 0.5 * (a00 + a11)
        own = np.abs(np.angle(half + np.sqrt(half**2 - (a00 * a11 - a01 * a10) + 0j)))
        grid = np.broadcast_to(np.linspace(0.0, math.pi, PEAK_GRID), (self.mode_count, PEAK_GRID))
        z = np.exp(1j * np.concatenate([grid, own], axis=1))
        det = (z - a00) * (z - a11) - a01 * a10  # adj(zI - A) b over det: (zI - A)^-1 b
        g = (c0 * ((z - a11) * b0 + a01 * b1) + c1 * (a10 * b0 + (z - a00) * b1)) / det * z
        return np.asarray(np.abs(g - self.static_shares()[:, None]).max(axis=1))

    def reduced(self, count: int) -> ContactModes:
        """The ``count`` modes of largest dynamic response (:meth:`dynamic_peaks`), the others'
        static shares moved into ``d`` (treated as static, as the solid treats the modes that
        settle within a period): the same static compliance, a loop of fewer states. On the liver
        ball's side and top (159 modes), with 0-2 ticks of delay, 6 modes so ranked gave the
        loop's slowest decay over the box within 0.015/s of 40 modes', and never more than
        0.001/s faster; ranked by static share instead, 12 were up to 0.019/s faster
        (docs/fem.md, "The solid's slow modes")."""
        if count >= self.mode_count:
            return self
        shares = self.static_shares()
        keep = np.sort(np.argsort(-self.dynamic_peaks(), kind="stable")[: max(int(count), 0)])
        sel = np.ravel([[2 * i, 2 * i + 1] for i in keep]).astype(int)
        folded = float(shares.sum() - shares[keep].sum())
        return ContactModes(
            a=self.a[np.ix_(sel, sel)],
            b=self.b[sel],
            c=self.c[sel],
            d=self.d + folded,
        )

    def step_response(self, ticks: int) -> FloatArray:
        """The depth [m] at the end of each of ``ticks`` periods under a 1 N push from rest."""
        z = np.zeros(len(self.b))
        out = np.empty(ticks)
        for k in range(ticks):
            z = self.a @ z + self.b
            out[k] = self.c @ z + self.d
        return out


def modal_monodromy(
    *,
    hand: Hand | Sequence[Hand] | None,
    modes: ContactModes,
    k_h: float,
    i_gain: float = 0.0,
    b_h: float = 0.0,
    own_gain: float = 0.0,
    servo_period_s: float = 1e-3,
    rate_ratio: int = 50,
    delay_ticks: int = 0,
    sample_ticks: Sequence[int] | None = None,
    proxy_hold: ProxyHold = "zoh",
) -> FloatArray:
    """Monodromy matrices of the full loop over one simulation period, the object ``modes``.

    Parameters as :func:`shared.full_loop.monodromy` (one set of gains; hands batched), with the
    object's :class:`ContactModes` for K_o and B_o.

    Returns
    -------
    (H, J, n, n) float array
        Per hand and sampling tick; the state is [fast states, proxy, (previous proxy), the
        object's modal states, delay line].

    Raises
    ------
    ValueError
        As :func:`shared.full_loop.monodromy`.
    """
    # the servo-rate block from monodromy itself, for a unit object without damping and without
    # compensation: its object row is then the sampled force's row F = F_xi xi + F_new p + F_old p_old
    unit = monodromy(
        hand=hand, k_o=1.0, k_h=k_h, i_gain=i_gain, b_h=b_h, b_o=0.0,
        servo_period_s=servo_period_s, rate_ratio=rate_ratio, delay_ticks=0,
        sample_ticks=sample_ticks, proxy_hold=proxy_hold, own_gain=0.0,
    )  # fmt: skip
    foh = proxy_hold == "foh"
    nb, nj, n0, _ = unit.shape
    nf = n0 - (3 if foh else 2)  # the fast states: [xi, p, (p_old), x_obj]
    lay0 = slow_layout(nf, foh, 0)
    force = unit[:, :, lay0.obj, :].copy()  # (nb, nj, n0): F as a row over the unit's states
    force[:, :, lay0.obj] = 0.0  # the unit object's own term (B_o = 0: none)
    nm = len(modes.b)
    D = int(delay_ticks)
    i_z = nf + (2 if foh else 1)  # the modal states replace x_obj
    i_q = i_z + nm
    n = i_q + D
    M = np.zeros((nb, nj, n, n))
    keep = slice(0, lay0.obj)  # fast states, proxy and previous proxy: as in the unit loop
    M[:, :, keep, keep] = unit[:, :, keep, keep]
    f_row = np.zeros((nb, nj, n))
    f_row[:, :, keep] = force[:, :, keep]
    # z' = A z + b F
    M[:, :, i_z:i_q, :] = modes.b[None, None, :, None] * f_row[:, :, None, :]
    M[:, :, i_z:i_q, i_z:i_q] += modes.a
    # the depth reported: c . z' + d F; the proxy delivered: that, moved out by C_h F
    proxy_row = np.einsum("m,bjmn->bjn", modes.c, M[:, :, i_z:i_q, :])
    proxy_row += (modes.d - float(own_gain)) * f_row
    i_p = lay0.proxy
    if D == 0:
        M[:, :, i_p, :] = proxy_row
    else:
        M[:, :, i_p, :] = 0.0
        M[:, :, i_p, i_q] = 1.0
        for r in range(D - 1):
            M[:, :, i_q + r, i_q + r + 1] = 1.0
        M[:, :, i_q + D - 1, :] = proxy_row
    return M


def decay_rates(m: FloatArray, servo_period_s: float = 1e-3, rate_ratio: int = 50) -> FloatArray:
    """The slowest decay rate [1/s] of each batch element of monodromy matrices ``m``
    (..., J, n, n) over its J sampling ticks, judged as the design judges
    (:func:`shared.stability_margin.mode_radii`): oscillating modes by their decay, creep (slower
    than :data:`shared.gains.policy.CREEP_FREQUENCY_HZ`) only for growth, so a rate meets
    :data:`shared.gains.policy.MIN_DECAY_RATE_PER_S` exactly where the design's margin does
    (negative: the loop grows)."""
    period = servo_period_s * rate_ratio
    rho_limit = math.exp(-MIN_DECAY_RATE_PER_S * period)
    margin_radius, _ = mode_radii(m, rho_limit, rate_ratio, servo_period_s)
    worst = margin_radius.max(axis=-1)
    return np.array([decay_rate_per_s(float(r), period) for r in np.ravel(worst)]).reshape(
        worst.shape
    )


def modal_decay_rates(
    *,
    hands: Sequence[Hand],
    modes: ContactModes,
    servo_period_s: float = 1e-3,
    rate_ratio: int = 50,
    **loop: Any,
) -> FloatArray:
    """The loop's slowest decay rate [1/s] per hand on ``modes`` (:func:`decay_rates` of
    :func:`modal_monodromy` with ``loop``: its gains, delay and proxy hold)."""
    m = modal_monodromy(
        hand=list(hands), modes=modes, servo_period_s=servo_period_s, rate_ratio=rate_ratio,
        **loop,
    )  # fmt: skip
    return decay_rates(m, servo_period_s, rate_ratio)


def direct_decay_rates(
    *,
    hands: Sequence[Hand],
    modes: ContactModes,
    pad_stiffness_n_per_m: float,
    pad_damping_n_s_per_m: float,
    period_s: float,
) -> FloatArray:
    """The slowest decay rate [1/s] of each hand held on the object itself, no product between.

    The finger pad is a spring and damper from the probe to the contact, ``f = K (x - y) + B x'``
    (``x`` the probe's depth, ``y`` the contact's), its force solved each period with the
    object's one-period response as ``tools/landing_reference.py`` solves it, linearised in
    contact; no delay, no local model. ``modes`` must be stepped at ``period_s`` (a solid built
    with that simulation period, 1 ms for a servo-rate reference). What a hand does on the solid
    itself, for judging :func:`modal_decay_rates` (docs/fem.md, "The solid's slow modes").
    """
    k_pad, b_pad = float(pad_stiffness_n_per_m), float(pad_damping_n_s_per_m)
    phi, gam = _hand_zoh(
        np.array([h.mass_kg for h in hands]),
        np.array([h.damping_n_s_per_m for h in hands]),
        np.array([h.stiffness_n_per_m for h in hands]),
        period_s,
    )
    nz = len(modes.b)
    gain = 1.0 / (1.0 + k_pad * (float(modes.c @ modes.b) + modes.d))
    force = np.zeros(nz + 2)  # f over the state [z, x, x']
    force[:nz] = -k_pad * gain * (modes.c @ modes.a)  # the contact where it goes unpushed
    force[nz] = k_pad * gain
    force[nz + 1] = b_pad * gain
    out = np.empty(len(hands))
    for i in range(len(hands)):
        m = np.zeros((nz + 2, nz + 2))
        m[:nz, :nz] = modes.a
        m[:nz] += np.outer(modes.b, force)  # the push moves the object in
        m[nz:, nz:] = phi[i]
        m[nz:] += np.outer(gam[i], force)  # and the hand out
        radius = float(np.max(np.abs(np.linalg.eigvals(m))))
        out[i] = decay_rate_per_s(radius, period_s)
    return out


def decay_rate_per_s(radius: float, sim_period_s: float) -> float:
    """The decay rate [1/s] of the slowest mode of a loop whose monodromy over one simulation
    period ``sim_period_s`` [s] has spectral radius ``radius`` (negative: it grows)."""
    if radius <= 0.0:
        return math.inf
    return -math.log(radius) / sim_period_s
