"""The rules that pick which gain key a contact renders and what renders while its gains are
checked, and their tuning constants, in one place (the design's own constants, which the shipped
gain tables depend on, stay with the design: :mod:`shared.gain_key`, :mod:`shared.gain_design`).

The loop delay's hold.

A design holds for one loop delay in whole simulation ticks (:class:`shared.gain_key.GainKey`).
Gains designed for fewer ticks than the loop has were unstable in every case tried (spectral
radius up to 1.18, tests/client/test_first_contact.py), so a rise of the measured delay must
change the key at once. A fall need not, and must not during a contact: every change of key
is a change of the gains rendered, and on a busy machine the round trip wavers by several ticks
(RTT p50 94 ms, p99 404 ms beside a loaded 2-core demo: 2 to 8 ticks at 20 Hz); letting the key
follow it down and up again within one steady hold gave the user a rendered stiffness that
alternated between a designed cell and the fallback, 70 and 210 N/m, every few seconds.

:class:`DelayHold` is that rule, for the client (:class:`client.session.ClientSession`) and the
server's gain advisor (:class:`server.gains.GainAdvisor`) alike: the delay designed for rises at
once to the one measured, and falls only out of contact, once the lower delay has been measured
for :data:`DELAY_FALL_S`. Pure: times are passed in.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from haptic_collab.shared.gain_key import loop_delay_ticks

#: Round trips over which the loop delay is measured (pings every 0.5 s: 10 s).
RTT_WINDOW = 20

#: Percentile of those round trips the delay is measured at: conservative under steady jitter,
#: yet one stall does not raise it.
RTT_PERCENTILE = 90.0

#: A lower loop delay is designed for only after it has been measured for this long [s], and
#: only out of contact (:class:`DelayHold`).
DELAY_FALL_S = 5.0

#: K_h / K_o_eff of the unverified fallback a contact renders while the check for its new
#: coupling class or larger delay runs (:class:`client.session.ClientSession`): a proportional
#: model, no own-force compensation, the device's whole damper, zero-order hold. Measured with
#: the hand in the loop (every hand of the box, every sampling tick, the Phantom Desktop's
#: 10 N*s/m): spectral radius at most 0.988 at K_h / K_o of 0.1, 0.15 and 0.25, K_o 30, 100,
#: 300, 600, 1000, 2000 and 4000 N/m and 0, 1, 2, 4 and 8 ticks of delay (K_h capped at the
#: device's 1 kN/m), where half K_o_eff, used before, reached 1.10 at 300 N/m and 1.40 at
#: 1000 N/m (tests/client/test_first_contact.py checks part of that grid). It is felt about a
#: fifth as stiff as the object; a compensated fallback (C_h = 1/K_h, felt as the object in a
#: held press) is not stable without its own check: at K_h / K_o of 0.1 and 0.25 it passed the
#: design's test in 5 of 75 cases at 20 Hz (K_o 30-3000 N/m, 0-8 ticks, coupling classes 1-4),
#: spectral radius up to 1.42 with a tick or more of delay (2026-11-27). A grid, not a proof;
#: not established for a device without a damper.
FALLBACK_K_RATIO = 0.25

#: Distance [m] the proxy may slide along the surface before the own-response check starts over
#: (:meth:`client.session.ClientSession._object_as_reported`): on a 5 cm radius, 0.5 mm of slide
#: deepens the measured surface by 2.5 um, under a hundredth of what a 0.3 N spread shows on
#: 1000 N/m.
OWN_RESPONSE_SLIDE_M = 0.5e-3

#: Cells of the gain table below a lone contact's own that its coupled class is checked for ahead
#: of need (:func:`client.link.likely_next`): a second user's press lowered K_o_eff by 12 % in the
#: demo, two cells of 10 %.
COUPLED_CELLS_BELOW = 2


def measured_delay_ticks(rtts_s: Sequence[float], state_age_s: float, sim_rate_hz: float) -> int:
    """The loop delay [whole simulation ticks] of the last :data:`RTT_WINDOW` round trips
    ``rtts_s`` [s] (oldest first) at their :data:`RTT_PERCENTILE`; 0 without any
    (:func:`shared.gain_key.loop_delay_ticks`).

    Raises
    ------
    ValueError
        As :func:`shared.gain_key.loop_delay_ticks`.
    """
    if not rtts_s:
        return 0
    # numpy.percentile's linear method in plain floats (the server runs this for every user
    # every tick: 40 us with numpy's machinery for 20 values)
    xs = sorted(float(v) for v in rtts_s[-RTT_WINDOW:])
    pos = (RTT_PERCENTILE / 100.0) * (len(xs) - 1)
    lo = math.floor(pos)
    hi = min(lo + 1, len(xs) - 1)
    t = pos - lo
    a, b = xs[lo], xs[hi]
    rtt = b - (b - a) * (1.0 - t) if t >= 0.5 else a + (b - a) * t
    return loop_delay_ticks(rtt, state_age_s, sim_rate_hz)


@dataclass
class DelayHold:
    """The loop delay a contact's gains are designed for (module docstring).

    Attributes
    ----------
    held : int or None
        The delay [ticks] designed for now (None before the first :meth:`update`).
    lower_since_s : float or None
        Since when [s] a lower delay has been measured out of contact (None: not now).
    """

    held: int | None = None
    lower_since_s: float | None = None

    def update(self, measured: int, now_s: float, in_contact: bool) -> int:
        """The delay [ticks] to design for, given the one ``measured`` now (at ``now_s`` [s]) and
        whether the user is ``in_contact`` with the object.

        Rises at once; falls to ``measured`` only after it has been lower for
        :data:`DELAY_FALL_S` without contact (a contact restarts the wait).

        Raises
        ------
        ValueError
            A negative ``measured`` or a time that is not finite.
        """
        if measured < 0:
            raise ValueError(f"measured delay must be >= 0 ticks, got {measured!r}")
        if not math.isfinite(now_s):
            raise ValueError(f"now_s must be finite, got {now_s!r}")
        held = self.held
        if held is None or measured > held:
            self.held, self.lower_since_s = measured, None
        elif measured == held or in_contact:
            self.lower_since_s = None
        elif self.lower_since_s is None:
            self.lower_since_s = now_s
        elif now_s - self.lower_since_s >= DELAY_FALL_S:
            self.held, self.lower_since_s = measured, None
        assert self.held is not None
        return self.held

    def reset(self) -> None:
        """Forget the delay held (a new session: its round trips are measured afresh)."""
        self.held, self.lower_since_s = None, None
