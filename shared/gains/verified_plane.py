"""The verified plane: the object's own plane, checked for a K_o known to within a few percent.

The product's designs hold on objects from 15 % softer than the K_o reported to 25 % stiffer
(:class:`shared.gains.key.GainKey`), and pay for it with a damper or a K_h away from K_o, felt over
the band. Where the own-response check (:mod:`shared.gains.own_response`) has seen the object yield to
this user's force as a spring of the K_o reported does, the client may render instead the plane
at the rest surface with the object's stiffness: K_h = K_o and C_h = 1 / K_o (own-force
compensation, ``F = K_h (x - x_o) + F_s``; :mod:`shared.gains.design`), which is model-mediated
teleoperation's plane (Mitra and Niemeyer 2008) and is felt as the object itself at every
frequency. It is rendered only as verified here: the lightest probe damper of
:data:`PLANE_DAMPERS` (and the proxy hold) with which the plane passes the design's own acceptance
test (:func:`shared.gains.interim.verify_gains`: every hand of the box, every sampling tick,
oscillations decaying at 1/s) on the objects it is rendered for: scaled to the K_o reported
(K_h = K_o, C_h = 1 / K_o), on objects :data:`VERIFIED_RANGE` either side of that K_o, where the
own-response check holds the object, at the cell's grid point, middle and top (the top also up to
that much above the cell's top where K_h stops at the device's: those K_o render the top's
gains; :func:`_scale_range`). Checked instead as one design across the cell (every scale on
objects up to 5 % above the cell's top), the grid point's plane met objects 15 % stiffer than its
C_h, which the own-response check never lets it render on, and needed a damper felt up to 1.23
times the object at 8 Hz (100 N/m, 10 Hz, 200 ms each way) where none is needed.

Just above the device's stiffness (up to :data:`CAPPED_PLANE_MAX` times it) the plane is
*capped*: K_h stops at the device's limit K_max. Its C_h is one of :data:`CAPPED_COMPENSATION`'s
steps from the compliance of the cell's grid point g towards the device's,
``C_h = (1 - c) / g + c / K_max``. A spring of K is felt statically as
``K_max / (1 + K_max / K - K_max C_h)``: with c = 0 (C_h = 1 / g) the plane stays at the rest
surface on an object of g and is felt as the device's stiffness (static-local's plane, with the
other users' pushes); with c = 1 (C_h = 1 / K_max, as the designs' C_h K_h = 1) the surface is
moved out by more than the object yields, and the object's own stiffness K is felt whatever it is:
``F = K_max (x - x_s) + F_s``, the simulation's force with the device's stiffness about it
(force-jacobian's rendering, Cavusoglu and Tendick 2000). The simulation loop's static gain is then
``1 - K_max / K`` (up to 0.2 in these cells), which the delay and the hand can make ring. The
check decides: of every step, damper and proxy hold, the one felt closest to the object across the
cell (the measure :func:`felt_closer` ranks by) that passes the check (one set
of gains: on objects from 5 % below g to 5 % above the cell's top) is the plane, and it must be
felt closer than the design across its cell (:func:`felt_closer`). Measured with the fidelity
benchmark (2026-11-26, the spring 20 % stiffer than the 1000 N/m reported, 1200 N/m, against c = 0
alone): felt 0.04-0.08 off where it was 0.15-0.18 at 20-100 Hz without delay and at 100 Hz with
10 ms, within the JND of the best scheme in 4 more conditions, none lost, stable with every hand
of the box as before.

Measured with the fidelity benchmark's grid (2026-11-26, 1 kHz servo, its simulated device:
1000 N/m, 10 N*s/m): on the spring from 100 to 1000 N/m at 10-100 Hz and 0-200 ms such a plane
passes in all 60 conditions: at 100 N/m without a damper in all 20, at 300 N/m with at most
0.5 N*s/m (felt at most 0.026 (ln) off over 0.5-8 Hz across the cell), at 1000 N/m with
0.25-3.5 N*s/m (at most 0.096 off across the cell, where K_h stops at the device's); the
product's own designs are felt up to 0.51 off there. :data:`PLANE_DAMPERS` reach half the
device's damping: on 1000 N/m 5 N*s/m is felt as ``|1 + j 2 pi 8 Hz B / K_o|`` = 1.03 at 8 Hz,
and where a damper is felt more (a softer cell) :func:`felt_closer` keeps the design.
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import replace
from typing import Literal

import numpy as np

from haptic_collab.shared.felt_stiffness import felt_responses
from haptic_collab.shared.full_loop import HandBox, object_impedance
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.interim import verify_gains
from haptic_collab.shared.gains.key import GainKey
from haptic_collab.shared.gains.policy import (
    AHEAD_SOFTER,
    AHEAD_STIFFER,
    CAPPED_COMPENSATION,
    CAPPED_PLANE_MAX,
    FELT_BAND_HZ,
    MIN_DECAY_RATE_PER_S,
    PLANE_DAMPERS,
    VERIFIED_RANGE,
)

_HOLDS: tuple[Literal["zoh", "foh"], ...] = ("zoh", "foh")


def _band_response(
    key: GainKey,
    k_o: float,
    *,
    k_h: float,
    b_h: float,
    proxy_hold: Literal["zoh", "foh"],
    own_gain: float,
    i_gain: float = 0.0,
) -> np.ndarray:
    """Felt responses dF/dx [N/m] over :data:`shared.gains.policy.FELT_BAND_HZ` of these gains
    on an object of ``k_o`` [N/m] under ``key`` (its rates, delay and B_o), shape (F,)."""
    return felt_responses(
        FELT_BAND_HZ,
        k_o=k_o,
        k_h=k_h,
        i_gain=i_gain,
        b_h=b_h,
        b_o=key.b_o,
        servo_period_s=key.rates.servo_period_s,
        rate_ratio=key.rates.ratio,
        delay_ticks=key.delay_ticks,
        proxy_hold=proxy_hold,
        own_gain=own_gain,
    )[:, 0]


def _own(key: GainKey, k_o: float) -> np.ndarray:
    """The object's own dynamic stiffness [N/m] over the band under ``key``
    (:func:`shared.full_loop.object_impedance`: K_o itself on the undamped objects planes apply
    to), shape (F,)."""
    return object_impedance(np.asarray(FELT_BAND_HZ), k_o, key.b_o, 1.0 / key.sim_rate_hz)


def _band_error(q: np.ndarray, own: np.ndarray) -> float:
    """The largest ``|ln |q / own||`` over the band of felt responses ``q`` [N/m] against the
    object's own ``own`` [N/m] (:func:`_own`)."""
    return float(np.max(np.abs(np.log(np.abs(q) / np.abs(own)))))


def verified_key(key: GainKey) -> GainKey:
    """``key`` with the verified plane's range (:data:`VERIFIED_RANGE` either way)."""
    return replace(key, margin=VERIFIED_RANGE, stiffer_by=VERIFIED_RANGE)


def plane_applies(key: GainKey) -> bool:
    """Whether a contact of ``key`` may render a verified plane: own-force compensation allowed,
    uncoupled (``stiff_ratio`` 1) and no object damping reported (B_o = 0). Eq. 9's damper
    does not say how a viscoelastic object answers a press over more than one tick, and the K_o
    and B_o a patch carries are all the client knows of the object."""
    return key.own_force and key.stiff_ratio == 1.0 and key.b_o == 0.0


def ahead_cells(key: GainKey, cell: int, grid_ratio: float) -> tuple[int, ...]:
    """The gain-table cells whose verified planes a client checks ahead around ``cell`` (the
    cell of the K_o reported), nearest first and, at the same distance, the stiffer first: from
    :data:`AHEAD_SOFTER` to :data:`AHEAD_STIFFER` times the cell's grid point, none above
    :data:`CAPPED_PLANE_MAX` times ``key.k_h_max`` (no plane there), none below cell 0, and none
    if the key allows no plane (:func:`plane_applies`).

    A plane's check (:func:`checked_plane`) does not depend on the press, so a client may run it
    before a contact reaches the cell: a press into a stiffening object then finds each cell's
    plane checked, where a check started on arrival (0.3-1 s idle) would leave it rendering the
    fallback and hunting between cells (docs/fidelity.md, "not covered").

    Raises
    ------
    ValueError
        A grid ratio not above 1, or a negative cell.
    """
    if not (math.isfinite(grid_ratio) and grid_ratio > 1.0):
        raise ValueError(f"grid_ratio must be > 1, got {grid_ratio!r}")
    if cell < 0:
        raise ValueError(f"cell must be >= 0, got {cell!r}")
    if not plane_applies(key):
        return ()
    step = math.log(grid_ratio)
    lo = max(0, cell + math.floor(math.log(AHEAD_SOFTER) / step + 1e-9))
    hi = cell + math.floor(math.log(AHEAD_STIFFER) / step + 1e-9)
    top = math.floor(math.log(CAPPED_PLANE_MAX * key.k_h_max) / step + 1e-9)
    hi = min(hi, top)
    return tuple(sorted(range(lo, hi + 1), key=lambda c: (abs(c - cell), c < cell)))


def _plane(
    key: GainKey,
    g: float,
    grid_ratio: float,
    hand_box: HandBox,
    *,
    k_h: float,
    b_h: float,
    hold: Literal["zoh", "foh"],
    top: float,
    worst: float,
    own_gain: float,
) -> GainDesign:
    """The plane of the cell of grid point ``g`` [N/m] with these gains, as a design (its worst
    spectral radius ``worst``; ``top`` its ``scale_max``; ``own_gain`` its C_h [m/N] at g)."""
    rates = key.rates
    n, T = rates.ratio, rates.servo_period_s
    q = _band_response(key, g, k_h=k_h, b_h=b_h, proxy_hold=hold, own_gain=own_gain)
    q1, q8 = q[FELT_BAND_HZ.index(1.0)], q[FELT_BAND_HZ.index(8.0)]
    return GainDesign(
        k_h=k_h,
        i_gain=0.0,
        b_h=b_h,
        proxy_hold=hold,
        worst_spectral_radius=worst,
        rho_limit=math.exp(-MIN_DECAY_RATE_PER_S * n * T),
        felt_stiffness_ratio_1hz=float(abs(q1)) / g,
        felt_stiffness_ratio_8hz=float(abs(q8)) / g,
        k_o=g,
        k_o_range=((1.0 - VERIFIED_RANGE) * g, (1.0 + VERIFIED_RANGE) * g * grid_ratio),
        rate_ratio=n,
        delay_ticks=key.delay_ticks,
        mode="p",
        hand_box=hand_box,
        own_gain=own_gain,
        scale_max=top,
    )


def _scale_range(s: float, top: float, g: float, grid_ratio: float) -> tuple[float, float]:
    """The objects [N/m] the plane scaled by ``s`` (K_h = s g, C_h = 1 / (s g)) is checked on:
    :data:`VERIFIED_RANGE` either side of s g, the stiffness the own-response check has held
    the object to; at the last scale ``top``, up to that much above the cell's top (``grid_ratio``
    g), the rest of the cell rendering the gains of ``top`` (K_h stopped at the device's; the
    capped plane's one set of gains, ``top`` 1)."""
    hi = grid_ratio * g if s >= top else s * g
    return (1.0 - VERIFIED_RANGE) * s * g, (1.0 + VERIFIED_RANGE) * hi


def checked_plane(
    key: GainKey,
    cell: int,
    grid_ratio: float,
    hand_box: HandBox,
    design: GainDesign | None = None,
) -> GainDesign | None:
    """The plane of grid cell ``cell`` (g = grid_ratio**cell [N/m]) with the lightest damper
    that passes the check (module docstring), as a design scaled across the cell
    (``scale_max = grid_ratio``: K_h = K_o, C_h = 1 / K_o for every K_o reported in the cell;
    within the cell holding the device's stiffness ``key.k_h_max``, K_h stops there). In a cell
    whose grid point is stiffer than the device, the capped plane: K_h = ``key.k_h_max``, C_h a
    step of :data:`CAPPED_COMPENSATION`, the one felt closest to the object across the cell
    that passes (:func:`felt_closer`'s measure), not scaled (``scale_max`` 1), up to
    :data:`CAPPED_PLANE_MAX` times the device's stiffness. None if none passes, above that, or if the key does not allow it
    (:func:`plane_applies`). It does not depend on ``key.mode`` (a plane has no integral).
    :func:`verified_plane` adds the comparison with the cell's design.

    With ``design``, the search stops (None) as soon as no rung left to try would be felt
    closer than it (:func:`felt_closer`: cheap, where a check takes 0.1-10 s). The result is
    then the plane found without ``design``, or None where that plane (if any) would be
    refused by :func:`felt_closer`: :func:`verified_plane`'s answer is the same either way.

    Raises
    ------
    ValueError
        A grid ratio not above 1, or as :func:`shared.gains.interim.verify_gains`.
    """
    if not (math.isfinite(grid_ratio) and grid_ratio > 1.0):
        raise ValueError(f"grid_ratio must be > 1, got {grid_ratio!r}")
    if not plane_applies(key):
        return None
    g = grid_ratio**cell
    # K_h follows K_o across the cell up to the device's stiffness; above it, K_h is the
    # device's (the capped plane: one set of gains)
    capped = g > key.k_h_max
    if g > CAPPED_PLANE_MAX * key.k_h_max:
        return None
    top = 1.0 if capped else min(grid_ratio, key.k_h_max / g)
    k_h = min(g, key.k_h_max)
    vkey = verified_key(key)
    scales = tuple(dict.fromkeys((1.0, math.sqrt(top), top)))
    # without a damper to give (a device without one) only the undamped rung
    fracs = itertools.takewhile(lambda f: f == 0.0 or f * key.b_h_max > 0.0, PLANE_DAMPERS)
    c_hs = [(1.0 - c) / g + c / k_h for c in CAPPED_COMPENSATION] if capped else [1.0 / g]
    params = [(frac * key.b_h_max, hold, c_h) for frac in fracs for hold in _HOLDS for c_h in c_hs]

    @functools.cache
    def rung(j: int) -> GainDesign:
        """The plane of rung ``params[j]``, made when first needed (a felt response)."""
        b_h, hold, c_h = params[j]
        return _plane(
            key, g, grid_ratio, hand_box, k_h=k_h, b_h=b_h, hold=hold, top=top, worst=0.0,
            own_gain=c_h,
        )  # fmt: skip

    order = list(range(len(params)))  # the lightest damper first ...
    if capped:
        # ... and the capped plane felt closest to the object across its cell first (module
        # docstring)
        order.sort(key=lambda j: _cell_errors(rung(j), key, _cell_points(rung(j))))
    # the first rung at or after i that would be felt closer than the design (found lazily:
    # the first usually is, and the search then costs one comparison)
    closer_at = -1
    for i, j_i in enumerate(order):
        if design is not None and closer_at < i:
            closer_at = next(
                (j for j in range(i, len(order)) if felt_closer(rung(order[j]), key, design)),
                len(order),
            )
            if closer_at == len(order):
                return None  # whichever rung passed from here, the design is felt closer
        b_h, hold, c_h = params[j_i]
        worst = 0.0
        for s in scales:
            ok, rho = verify_gains(
                vkey,
                cell,
                grid_ratio,
                hand_box,
                k_h=s * k_h,
                i_gain=0.0,
                b_h=b_h,
                proxy_hold=hold,
                own_gain=c_h / s,
                k_o_range=_scale_range(s, top, g, grid_ratio),
            )
            worst = max(worst, rho)
            if not ok:
                break
        else:
            return replace(rung(j_i), worst_spectral_radius=worst)
    return None


def _cell_points(plane: GainDesign) -> tuple[float, float, float]:
    """The objects [N/m] a plane is compared on: its cell's grid point g, middle and top (g,
    sqrt(r) g and r g, r the grid ratio, read from the range the plane was checked over)."""
    g = plane.k_o
    r = plane.k_o_range[1] / ((1.0 + VERIFIED_RANGE) * g)
    return g, math.sqrt(r) * g, r * g


def _cell_errors(d: GainDesign, key: GainKey, k_os: tuple[float, ...]) -> tuple[float, float]:
    """The worst and the mean over objects ``k_os`` [N/m] of the largest ``|ln |q / k||`` over
    the band with which ``d`` renders on each (``d.at(k)``) under ``key``."""
    errs = []
    for k in k_os:
        a = d.at(k)
        q = _band_response(
            key, k, k_h=a.k_h, i_gain=a.i_gain, b_h=a.b_h, proxy_hold=a.proxy_hold,
            own_gain=a.own_gain,
        )  # fmt: skip
        errs.append(_band_error(q, _own(key, k)))
    return max(errs), sum(errs) / len(errs)


def felt_closer(plane: GainDesign, key: GainKey, design: GainDesign) -> bool:
    """Whether ``plane`` (:func:`checked_plane`) is felt closer to the object than ``design``
    across the plane's cell: on objects at its grid point g, its middle and its top (g, sqrt(r)
    g and r g, r the grid ratio, read from the range the plane was checked over), each rendering
    as it is there (``plane.at(k)``, ``design.at(k)``, clamped to the range each was checked
    over), the largest ``|ln |q / k||`` over :data:`shared.gains.policy.FELT_BAND_HZ` under
    ``key`` (its rates, delay and B_o), the measure the design ranks by; the worst of the three
    first, then their mean. A capped plane's gains are one set across its cell, right at one
    stiffness at most, so it must win across the cell, not at g alone."""
    k_os = _cell_points(plane)
    return _cell_errors(plane, key, k_os) < _cell_errors(design, key, k_os)


def felt_error_at(d: GainDesign, key: GainKey, k_o: float) -> float:
    """How far ``d``, rendering as it does for the K_o reported ``k_o`` [N/m] (``d.at(k_o)``),
    is felt from the object under ``key``: the largest ``|ln |q / own||`` over the band
    (:func:`felt_closer`'s measure). One felt response."""
    return _cell_errors(d, key, (k_o,))[0]


def verified_plane(
    key: GainKey,
    cell: int,
    grid_ratio: float,
    hand_box: HandBox,
    design: GainDesign | None = None,
) -> GainDesign | None:
    """:func:`checked_plane`, or None if it is felt no closer to the object than ``design``
    (:func:`felt_closer`; the cell's own design, as :func:`shared.gains.table.design_cell` made
    it, or the design of the cell of the K_o reported where the plane is of a stiffness the
    own-response check identified).

    Raises
    ------
    ValueError
        As :func:`checked_plane`.
    """
    return plane_against(checked_plane(key, cell, grid_ratio, hand_box, design), key, design)


def plane_against(
    plane: GainDesign | None, key: GainKey, design: GainDesign | None
) -> GainDesign | None:
    """A plane already checked (:func:`checked_plane`, without a design: the client checks one
    alone while the cell of the K_o reported has no design) held against ``design`` once it is
    made: ``plane`` if felt closer (:func:`felt_closer`) or if there is no design, else None.
    The same answer as :func:`verified_plane` with that design, without checking the plane again
    (a comparison of felt responses, where a check takes 0.1-10 s)."""
    if plane is None or (design is not None and not felt_closer(plane, key, design)):
        return None
    return plane
