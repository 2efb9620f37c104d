"""Interim gains: verified gains to render in a K_o grid cell while its design runs.

A design (:func:`shared.gains.table.design_cell`) takes tens of milliseconds to seconds; until it
is done a contact renders interim gains checked in a fraction of a second. This module owns the
policy that picks them (:func:`interim_design`: gains already known, then the generic rungs of
:data:`INTERIM_OWN_FORCE` and :data:`INTERIM_LADDER`, then a proportional design) and the check
each must pass first (:func:`verify_gains`): the design's own acceptance test, with the margin of
:mod:`shared.stability_margin`, over the cell's range of K_o.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import Literal

import numpy as np

from haptic_collab.shared.felt_stiffness import felt_stiffness
from haptic_collab.shared.full_loop import HandBox, monodromy
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.key import GainKey
from haptic_collab.shared.gains.policy import (
    INTERIM_LADDER,
    INTERIM_OWN_FORCE,
    INTERIM_OWN_FORCE_FOH,
    MIN_DECAY_RATE_PER_S,
)
from haptic_collab.shared.gains.table import cell_k_o_range, design_cell
from haptic_collab.shared.stability_margin import group_mode_radii, k_o_points


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
    probe_ticks: int = 2,
    k_o_range: tuple[float, float] | None = None,
) -> tuple[bool, float]:
    """Do these gains pass the design's acceptance test for grid cell ``cell`` of ``key``?

    The test :func:`shared.gains.design.design_gains` applies to its chosen gains: the full loop
    (:func:`shared.full_loop.monodromy`) for every hand of ``hand_box.hands()``, every sampling
    tick j in [0, N) and K_o' in {lo, sqrt(lo hi), hi}, ``(lo, hi) = ((1 - margin) g_i,
    g_(i+1))`` (the range :func:`shared.gains.table.design_cell` covers) has spectral radius below
    1 and every oscillating mode (faster than
    :data:`shared.gains.policy.CREEP_FREQUENCY_HZ`) below ``exp(-MIN_DECAY_RATE_PER_S N T)``.
    Stops at the first failing batch.

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
    probe_ticks : int
        Sampling ticks of the first pass: every case is checked first at this many ticks spread
        over the period, then at the others. A candidate that fails usually fails at most
        ticks, and one tick's spectrum costs as much as another's, so most failures cost a
        fraction of the whole check; the verdict and, when it passes, the worst spectral radius
        are the same as checking every tick at once.
    own_gain : float
        Own-force compensation C_h [m/N] >= 0 (:mod:`shared.full_loop`).
    k_o_scale : float
        s in [1, grid_ratio]: the gains are a design scaled to a reported K_o = s g_i
        (:meth:`GainDesign.at`), checked as the design checks its scales: K_o' from
        ``(1 - margin) s g_i`` up to the top of the cell's range.
    k_o_range : (float, float), optional
        ``(lo, hi)`` [N/m], 0 < lo <= hi: check K_o' over this range instead of the cell's (the
        verified plane, scaled to each K_o reported, is checked at each scale over the few
        percent the own-response check holds the object to:
        :func:`shared.gains.verified_plane.checked_plane`). ``k_o_scale`` is then unused.

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
    if k_o_range is None:
        lo, hi = cell_k_o_range(key, cell, grid_ratio)
        k_os = k_o_points(k_o_scale * lo, max(hi, k_o_scale * grid_ratio**cell))
    else:
        lo, hi = k_o_range
        if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo <= hi):
            raise ValueError(f"k_o_range must be 0 < lo <= hi N/m, got {k_o_range!r}")
        k_os = k_o_points(lo, hi)
    # the stiffest K_o' first, and a first batch of ``probe`` cases: a failing candidate (most
    # interim candidates fail) is usually refused there, at a fraction of the whole check's cost
    k_os = sorted(k_os, reverse=True)
    box = hand_box.hands()
    hands = [h for _ in k_os for h in box]
    ko = np.repeat(np.asarray(k_os, float), len(box))
    rho_limit = math.exp(-MIN_DECAY_RATE_PER_S * n * T)
    worst = 0.0
    stride = max(1, n // max(1, probe_ticks))
    for ticks in (list(range(0, n, stride)), [j for j in range(n) if j % stride]):
        if not ticks:
            continue
        # as many matrices per batch as ``chunk`` cases of every tick
        per = max(chunk, chunk * n // len(ticks))
        bounds = [0, *range(min(probe, per), len(hands), per), len(hands)]
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
                sample_ticks=ticks,
                proxy_hold=proxy_hold,
                integral=i_gain > 0.0,
            )
            Mf = M.reshape(-1, *M.shape[-2:])
            marg, rad = group_mode_radii(Mf, rho_limit, n, T, np.zeros(len(Mf), np.intp), 1)
            worst = max(worst, float(rad[0]))
            margin_r = float(marg[0])
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
    (:func:`shared.gains.table.design_cell` with ``mode="p"``, seconds). A module-level function
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
