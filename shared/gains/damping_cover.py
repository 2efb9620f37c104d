"""How much object damping B_o a design made for B_o = 0 holds for: its coverage.

The shipped gain tables (:mod:`shared.gains.table_file`) hold designs for objects without damping
(B_o = 0: the balloon, any mesh). The FEM solid reports B_o > 0 (the paper's eq. 9: the object's
damping over the simulation period [N/m]; docs/fem.md), so its keys miss the tables. A design for
less object damping is the safe side of the paper's bound (eq. 10: ``K_h < K_o + 2 B_o``) but
not, on the full loop with the hand and a delay, a proof: own-force compensation expects the
object to answer as a spring, and a damped object answers a step push first as ``K_o + B_o``.
So every shipped design is checked again, offline, on the loop with object damping ``b_o`` on
the lattice :data:`shared.gains.policy.B_O_COVER_LATTICE` (whole N/m, as the key quantizes B_o):
the design's own acceptance test (:func:`shared.gains.interim.verify_gains`: every hand of the
hand box, every sampling tick, the decay margin), over the K_o range the key with that ``b_o``
has (:func:`shared.gains.table.cell_k_o_range`: up to ``max((1 + stiffer_by) top, top + b_o)``),
at the design's own gains and scaled to the middle and top of its range, as
:func:`shared.gains.design.design_gains` checked it. :func:`covered_b_o` is the largest lattice
``b_o`` up to which every lattice point passed; :func:`shared.gains.choose.table_design` renders
the design for a key of B_o up to it.

Pure (no I/O, no clock); the checks are slow (about 0.1-0.4 s each), run offline
(``haptic gains-table --cover``). :func:`cover_code_hash` hashes this module and what it runs,
so a shipped coverage is fresh only for the check code and lattice that made it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

from haptic_collab.shared.full_loop import HandBox
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.interim import verify_gains
from haptic_collab.shared.gains.key import GainKey
from haptic_collab.shared.gains.policy import B_O_COVER_LATTICE
from haptic_collab.shared.gains.table import cell_k_o_range


def damped_check(
    key: GainKey,
    cell: int,
    design: GainDesign,
    b_o: float,
    grid_ratio: float,
    hand_box: HandBox,
) -> tuple[bool, float]:
    """Does ``design`` (of ``cell`` of ``key``) pass its acceptance test with object damping
    ``b_o`` [N/m]?

    The full loop (:func:`shared.gains.interim.verify_gains`) with ``key``'s rates and delay and
    B_o = ``b_o``, for every hand of ``hand_box`` and every sampling tick, with the decay margin
    of :mod:`shared.stability_margin`, over K_o' from the design's own softest end to the top of
    the range a key with this ``b_o`` has (:func:`shared.gains.table.cell_k_o_range`), at the
    design's gains and at them scaled (:meth:`GainDesign.at`) to the geometric middle and the top
    of their scale (``design.scale_max``), each from its own softest end: what
    :func:`shared.gains.design.design_gains` checked at B_o = 0.

    Parameters
    ----------
    key : GainKey
        The design's key (its ``b_o`` is replaced by ``b_o``).
    cell : int
        The K_o grid cell (g_i = ``grid_ratio**cell`` [N/m]).
    design : GainDesign
        The cell's design, as stored (not scaled to a K_o).
    b_o : float
        Object damping [N/m] (eq. 9), finite and >= 0.
    grid_ratio : float
        The table's grid ratio, > 1.
    hand_box : HandBox
        The hands the design holds for.

    Returns
    -------
    (bool, float)
        Passed, and the worst spectral radius seen (of the first failing scale when it fails).

    Raises
    ------
    ValueError
        A ``b_o`` that is not finite and >= 0, or gains out of range (as
        :func:`shared.gains.interim.verify_gains`).
    """
    if not (math.isfinite(b_o) and b_o >= 0.0):
        raise ValueError(f"b_o must be finite and >= 0 N/m, got {b_o!r}")
    damped = replace(key, b_o=float(b_o))
    hi = cell_k_o_range(damped, cell, grid_ratio)[1]
    s_top = max(1.0, design.scale_max)
    worst = 0.0
    for s in dict.fromkeys((1.0, math.sqrt(s_top), s_top)):
        g = design.at(design.k_o * s) if s > 1.0 else design
        ok, rho = verify_gains(
            damped,
            cell,
            grid_ratio,
            hand_box,
            k_h=g.k_h,
            i_gain=g.i_gain,
            b_h=g.b_h,
            proxy_hold=g.proxy_hold,
            own_gain=g.own_gain,
            k_o_range=(g.k_o_range[0], max(hi, g.k_o)),
        )
        worst = max(worst, rho)
        if not ok:
            return False, worst
    return True, worst


def covered_b_o(
    key: GainKey,
    cell: int,
    design: GainDesign,
    grid_ratio: float,
    hand_box: HandBox,
    lattice: Sequence[float] = B_O_COVER_LATTICE,
) -> float:
    """The largest ``b_o`` [N/m] of ``lattice`` (ascending) up to which ``design`` passed
    :func:`damped_check` at every lattice point; 0 when it fails at the first. Stops at the
    first failure: a design is never rendered above a lattice point where it failed.

    Raises
    ------
    ValueError
        ``lattice`` not strictly ascending and > 0, or as :func:`damped_check`.
    """
    pts = [float(b) for b in lattice]
    if not pts or pts[0] <= 0.0 or any(b <= a for a, b in zip(pts, pts[1:], strict=False)):
        raise ValueError(f"lattice must be ascending and > 0 N/m, got {tuple(lattice)!r}")
    covered = 0.0
    for b in pts:
        if not damped_check(key, cell, design, b, grid_ratio, hand_box)[0]:
            break
        covered = b
    return covered


def valid_cover(value: object) -> float:
    """A coverage read from a file [N/m]: a finite number >= 0 (a bool is not one).

    Raises
    ------
    ValueError
        Anything else (NaN, negative, infinite, not a number): a corrupted coverage would render
        a design on objects it was never checked on.
    """
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"b_o_covered must be a number of N/m, got {value!r}")
    v = float(value)
    if not (math.isfinite(v) and v >= 0.0):
        raise ValueError(f"b_o_covered must be finite and >= 0 N/m, got {value!r}")
    return v
