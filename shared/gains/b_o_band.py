"""Interim gains checked over a band of object damping B_o: one check for the keys of every
whole B_o in the band.

A gain key holds the object damping B_o in whole N/m (:func:`shared.gains.key.make_gain_key`),
and the FEM solid's B_o changes along its surface (the liver sphere: 8 N/m at the top, 53 at the
side; docs/fem.md). A hand sliding over it at a tick or more of loop delay, where the shipped
tables do not reach, changed key every few ticks: 8, 10, 12, 16, 20, 25, 30 ... N/m across the
palpation demo's sweep. Each new key asked an interim check, and until it came back (2-5 ticks)
the choice (:mod:`shared.gains.choose`) rendered what covered the key, often a wider coupling
class's paper PI without own-force compensation, which is felt softer while the hand moves:
K_h stepped between 95 and 194 N/m every few ticks, and the lump A felt fell from +22 % to +5 %
(docs/gains.md, "Interim gains over a band of B_o").

So interim gains found for one key (:func:`shared.gains.interim.interim_design`) are checked
again, with the same acceptance test (:func:`shared.gains.interim.verify_gains`: every hand of
the hand box, every sampling tick, the decay margin), at both ends of the band of
:data:`shared.gains.policy.B_O_COVER_LATTICE` the key's B_o lies in; where both pass they are
kept for every whole B_o of the band. That is the rule the shipped tables' damping coverage
already stands on (:mod:`shared.gains.damping_cover`): checked at the lattice's points, a
design is rendered for the B_o between them.

The band check is a job of its own, after the key's own check and behind every interim check
(:meth:`server.gains.GainAdvisor.next_job`; the server's check worker takes one only when no
interim check waits, so a check asked meanwhile waits for two acceptance tests at most). Run in
the same job as the key's own check, it made each job three times longer, and beside two
spinning processes the niced worker was starved: the needed checks came back late and a hand
rendered the covering PI for up to 61 % of its slide (docs/gains.md, "Interim gains over a band
of B_o").

Pure: no I/O, threads or clocks; a check is 0.03-0.1 s of CPU (run in a worker).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from haptic_collab.shared.full_loop import HandBox
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.interim import verify_gains
from haptic_collab.shared.gains.key import GainKey
from haptic_collab.shared.gains.policy import B_O_COVER_LATTICE


@dataclass(frozen=True)
class BandedGains:
    """Interim gains and the band of B_o [N/m] they passed at both ends of.

    Attributes
    ----------
    design : GainDesign
        The interim gains, as found for their own key.
    band : (float, float) or None
        ``(lo, hi)`` [N/m]: the gains also passed with B_o = ``lo`` and ``hi``, so they hold for
        every whole B_o from ``lo`` to ``hi``; None: for their own key only.
    """

    design: GainDesign
    band: tuple[float, float] | None = None

    def keys(self, key: GainKey) -> list[GainKey]:
        """The keys the gains hold for: ``key`` and, with a band, ``key`` at every whole B_o of
        it."""
        if self.band is None:
            return [key]
        lo, hi = self.band
        return [replace(key, b_o=float(b)) for b in range(int(lo), int(hi) + 1)]


def b_o_band(b_o: float) -> tuple[float, float] | None:
    """The band ``(lo, hi)`` [N/m] of :data:`shared.gains.policy.B_O_COVER_LATTICE` with
    ``lo <= b_o < hi``; None for ``b_o`` below the lattice's first point (an undamped key) or at
    or beyond its last, or not finite."""
    if not math.isfinite(b_o):
        return None
    lattice = B_O_COVER_LATTICE
    for lo, hi in zip(lattice, lattice[1:], strict=False):
        if lo <= b_o < hi:
            return float(lo), float(hi)
    return None


def check_band(
    key: GainKey,
    cell: int,
    design: GainDesign,
    grid_ratio: float,
    hand_box: HandBox,
) -> BandedGains:
    """``design`` (interim gains found for ``cell`` of ``key``) checked at both ends of
    :func:`b_o_band` of ``key.b_o``, each with the key's rates and delay and that B_o over the
    K_o range a key with that B_o has (:func:`shared.gains.interim.verify_gains`).

    Returns
    -------
    BandedGains
        With the band where both ends pass (an end equal to ``key.b_o`` is the check already
        made); without one where either fails or ``key.b_o`` is outside the lattice.
    """
    band = b_o_band(key.b_o)
    if band is None:
        return BandedGains(design)
    for b_o in band:
        if b_o == key.b_o:
            continue
        ok, _ = verify_gains(
            replace(key, b_o=b_o),
            cell,
            grid_ratio,
            hand_box,
            k_h=design.k_h,
            i_gain=design.i_gain,
            b_h=design.b_h,
            proxy_hold=design.proxy_hold,
            own_gain=design.own_gain,
        )
        if not ok:
            return BandedGains(design)
    return BandedGains(design, band)
