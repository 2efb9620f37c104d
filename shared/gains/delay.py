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


def delay_rtt_s(rtts_s: Sequence[float]) -> float | None:
    """The round trip [s] the loop delay is measured from: the
    :data:`shared.gains.policy.RTT_PERCENTILE` of the last :data:`shared.gains.policy.RTT_WINDOW`
    round trips ``rtts_s`` [s] (oldest first); None without any. The client sends it in every
    ``state`` (``delay_rtt_ms``), so the server's advisor measures the delay the client does."""
    if not rtts_s:
        return None
    # numpy.percentile's linear method in plain floats (40 us with numpy's machinery for 20
    # values, for every user every tick)
    xs = sorted(float(v) for v in rtts_s[-RTT_WINDOW:])
    pos = (RTT_PERCENTILE / 100.0) * (len(xs) - 1)
    lo = math.floor(pos)
    hi = min(lo + 1, len(xs) - 1)
    t = pos - lo
    a, b = xs[lo], xs[hi]
    return b - (b - a) * (1.0 - t) if t >= 0.5 else a + (b - a) * t


def measured_delay_ticks(rtts_s: Sequence[float], state_age_s: float, sim_rate_hz: float) -> int:
    """The loop delay [whole simulation ticks] of the round trips ``rtts_s`` [s] (oldest first):
    :func:`shared.gains.key.loop_delay_ticks` of their :func:`delay_rtt_s`; 0 without any.

    Raises
    ------
    ValueError
        As :func:`shared.gains.key.loop_delay_ticks`.
    """
    rtt = delay_rtt_s(rtts_s)
    return 0 if rtt is None else loop_delay_ticks(rtt, state_age_s, sim_rate_hz)


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
