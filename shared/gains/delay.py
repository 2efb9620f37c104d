"""The loop delay a contact's gains are designed for: measured from the round trips, held
through a contact.

A design holds for one loop delay in whole simulation ticks (:class:`shared.gains.key.GainKey`).
Gains designed for fewer ticks than the loop has were unstable in every case tried (spectral
radius up to 1.18, tests/client/test_first_contact.py), so a rise of the measured delay must
change the key at once. A fall need not, and must not during a contact: every change of key
is a change of the gains rendered, and on a busy machine the round trip wavers by several ticks
(2 to 8 ticks at 20 Hz beside a loaded 2-core demo; docs/results/gain-policy-load.json); letting
the key follow it down and up again within one steady hold changed the stiffness a user felt
every few seconds.

:class:`DelayHold` is that rule, for the client (:class:`client.session.ClientSession`) and the
server's gain advisor (:class:`server.gains.GainAdvisor`) alike: the delay designed for rises at
once to the one measured, and falls only out of contact, once the lower delay has been measured
for :data:`shared.gains.policy.DELAY_FALL_S`. Pure: times are passed in.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from haptic_collab.shared.gains.key import loop_delay_ticks
from haptic_collab.shared.gains.policy import DELAY_FALL_S, RTT_PERCENTILE, RTT_WINDOW


def measured_delay_ticks(rtts_s: Sequence[float], state_age_s: float, sim_rate_hz: float) -> int:
    """The loop delay [whole simulation ticks] of the last :data:`RTT_WINDOW` round trips
    ``rtts_s`` [s] (oldest first) at their :data:`RTT_PERCENTILE`; 0 without any
    (:func:`shared.gains.key.loop_delay_ticks`).

    Raises
    ------
    ValueError
        As :func:`shared.gains.key.loop_delay_ticks`.
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
