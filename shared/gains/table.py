"""The table of gain designs on a geometric grid of object stiffness K_o.

:class:`GainTable` caches designs (:func:`shared.gains.design.design_gains`) on a geometric grid of
K_o so that a client's network loop only looks gains up (the design itself runs off the loop, in a
thread or a worker process: :func:`design_cell`). This module owns the grid: the K_o range a cell
is checked over (:func:`cell_k_o_range`, widened for an object stiffer than reported and for a
coupled contact), the design of one cell, the lookup of a reported K_o, the fallback while a cell
is being designed, and the warm-up of a worker process (:func:`warm_up`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX, HandBox
from haptic_collab.shared.gains.design import GainDesign, design_gains, design_gains_modes
from haptic_collab.shared.gains.key import GainKey, Mode, coupled_k_o_hi
from haptic_collab.shared.gains.policy import K_O_GRID_RATIO


def stiffest_k_o(k_o: float, stiffer_by: float, b_o: float) -> float:
    """The stiffest object [N/m] a design for ``k_o`` [N/m] is checked on: ``(1 + stiffer_by)
    k_o`` (an object stiffer than reported), or its one-tick stiffness ``k_o + b_o`` where that
    is higher (an object with mass or relaxation: eq. 9's B_o [N/m], docs/gains.md)."""
    return max(k_o * (1.0 + stiffer_by), k_o + b_o)


def cell_k_o_range(key: GainKey, cell: int, grid_ratio: float) -> tuple[float, float]:
    """``[(1 - margin) g_i, k_o_hi]`` [N/m], the K_o range every design of a :class:`GainTable`
    cell is checked over (a compensated design may be checked further down, to ``g_i / (1 +
    stiffer_by)``, where that costs less than a JND: its ``k_o_range`` says so;
    :func:`shared.gains.design.softest_k_o`).

    ``g_i = grid_ratio**cell``; ``k_o_hi`` is the next grid point times ``1 + key.stiffer_by``,
    or its one-tick stiffness ``g_(i+1) + key.b_o`` where that is higher (an object with mass
    or relaxation: eq. 9's B_o, docs/gains.md), or for a coupled contact
    ``coupled_k_o_hi(g_(i+1), key.stiff_ratio)`` where that is higher (:mod:`shared.coupled_loop`).
    """
    g = grid_ratio**cell
    top = grid_ratio ** (cell + 1)
    # an object stiffer than reported; a coupled contact's modal range already reaches beyond
    # (the two are not stacked: a coupled press on the balloon then got the paper's PI, felt
    # 0.79 K_o at 1 Hz, instead of a compensated model). An object with mass or relaxation is
    # as stiff as K_o + B_o to a step push over its first simulation period, and a relaxing one
    # (a standard linear solid, a FEM solid's slow modes) stays near that for many periods where
    # eq. 9 lets it relax within one or two: checked only up to 1.25 K_o, a P design (300 N/m,
    # 100 Hz, 2 ticks, B_o 472 N/m) held the heavy loose hand in a 4.5 Hz, 0.75 mm ring on the
    # fidelity benchmark's viscoelastic object (docs/fidelity.md)
    hi = stiffest_k_o(top, key.stiffer_by, key.b_o)
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
        (``scale_max`` 1), but for the cell below's own-force compensation, which keeps its
        share of the K_o reported, ``C_h k_o``: a function of ``k_o`` without steps, so a press
        held where the K_o reported crosses a cell boundary is not pushed back and forth across
        it (with C_h stepping at the boundaries, a press into a strain-stiffening object held
        still at 1000 N/m, 20 Hz rang at 5 Hz; tests/research/test_fidelity_objects.py).
        """
        i = self.cell(k_o)
        cells = [c for (k, c) in self._cells if k == key]
        if not cells:
            return None
        below = [c for c in cells if c <= i]
        if below:
            c = max(below)
            d = replace(self._cells[(key, c)], scale_max=1.0)
            # own-force compensation keeps its share of the K_o reported (C_h K_o), not its C_h
            own = d.own_gain * self.grid_point(c) / k_o
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
            As :func:`shared.gains.design.design_gains`.
        """
        i = self.cell(k_o)
        d = design_cell(key, i, self.grid_ratio, self.hand_box)
        self.store(key, i, d)
        return d.at(k_o)

    def __len__(self) -> int:
        return len(self._cells)

    def cells(self) -> list[tuple[GainKey, int, GainDesign]]:
        """Every designed cell as ``(key, cell, design)``, in the order stored."""
        return [(k, c, d) for (k, c), d in self._cells.items()]

    def has(self, key: GainKey, cell: int) -> bool:
        """Whether ``cell`` of ``key`` is designed."""
        return (key, cell) in self._cells


def design_cell(key: GainKey, cell: int, grid_ratio: float, hand_box: HandBox) -> GainDesign:
    """Design grid cell ``cell`` of a :class:`GainTable`: K_o = ratio**cell, checked up to the next.

    A module-level function so that a worker process can run it (arguments and result pickle).

    Raises
    ------
    ValueError
        As :func:`shared.gains.design.design_gains`.
    """
    return design_cell_modes(key, cell, grid_ratio, hand_box, (key.mode,))[key.mode]


def design_cell_modes(
    key: GainKey,
    cell: int,
    grid_ratio: float,
    hand_box: HandBox,
    modes: Sequence[Mode] = ("p", "pi"),
) -> dict[Mode, GainDesign]:
    """:func:`design_cell` of ``key`` with each local model of ``modes`` (``key.mode``
    ignored), ``{mode: design}``, their common candidates searched once
    (:func:`shared.gains.design.design_gains_modes`): what the fidelity benchmark designs for the
    keys of both local models.

    Raises
    ------
    ValueError
        As :func:`shared.gains.design.design_gains_modes`.
    """
    g = grid_ratio**cell
    return design_gains_modes(
        g,
        modes=modes,
        b_o=key.b_o,
        servo_rate_hz=key.servo_rate_hz,
        sim_rate_hz=key.sim_rate_hz,
        delay_ticks=key.delay_ticks,
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
