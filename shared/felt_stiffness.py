"""Felt stiffness: the force a user feels per unit of probe motion through the full loop.

The transparency measure of local-model gains (:mod:`shared.gains.design`): |dF/dx| at the probe,
probe as a position source, compared with the object's own stiffness K_o.

Felt stiffness is computed exactly on the lifted (N-periodic) loop: for a probe motion
``x(n) = Re(X e^{j w n T})`` the steady state of the lifted loop at ``z = e^{j w N T}`` gives the
servo-rate force over one block, whose component at w (the fundamental) over X is the felt
stiffness. For a P local model on an elastic object at low frequency it tends to
``K_h K_o / (K_h + K_o)``; for PI to K_o. :data:`FELT_BAND_HZ` is the band of hand motion a
design with own-force compensation is judged over.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from haptic_collab.shared.full_loop import (
    DAMPER_FILTER_S,
    ProxyHold,
    batch_arrays,
    monodromy,
    object_coefficients,
    object_impedance,
    slow_layout,
)
from haptic_collab.shared.types import FloatArray


def object_stiffness(
    freqs_hz: Sequence[float],
    *,
    k_o: float | FloatArray,
    b_o: float | FloatArray = 0.0,
    sim_period_s: float,
) -> FloatArray:
    """The paper's object's own dynamic stiffness dF/dx [N/m] (complex) at each of ``freqs_hz``,
    shape (F, B): the inverse of eq. 9's ``D(z) = (K_o + B_o (z - 1) / z)^-1`` at ``z = e^{j w
    N T}`` (``N T = sim_period_s``), ``K_o + B_o (1 - e^{-j w N T})``. What a transparent
    rendering of the object the simulation reports is felt as: ``K_o`` at DC and for an elastic
    object (B_o = 0), stiffer and leading towards the simulation's Nyquist rate for a damped or
    massive one (the one-tick stiffness ``K_o + B_o`` of a step push from rest,
    ``server.objects.fem.FemSolid.contact_damping``).

    Raises
    ------
    ValueError
        A non-positive ``sim_period_s`` or frequency.
    """
    if not (math.isfinite(sim_period_s) and sim_period_s > 0.0):
        raise ValueError(f"sim_period_s must be > 0, got {sim_period_s!r}")
    if not all(math.isfinite(f) and f > 0.0 for f in freqs_hz):
        raise ValueError(f"frequencies must be > 0 Hz, got {freqs_hz!r}")
    ko, bo = batch_arrays(k_o, b_o)
    f = np.asarray(freqs_hz, dtype=float)[:, None]
    return object_impedance(f, ko[None, :], bo[None, :], sim_period_s)


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
    lay = slow_layout(nf, foh, delay_ticks)
    i_p, i_obj = lay.proxy, lay.obj
    inv, _ = object_coefficients(ko, bo)
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
