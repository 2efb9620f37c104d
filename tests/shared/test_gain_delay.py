"""The loop delay a contact's gains are designed for: held through a contact (shared.gains.delay)."""

from __future__ import annotations

import pytest

from haptic_collab.shared.gains.delay import DelayHold, measured_delay_ticks
from haptic_collab.shared.gains.policy import DELAY_FALL_S, RTT_WINDOW


def test_a_rise_is_designed_for_at_once_in_contact_or_not() -> None:
    for in_contact in (False, True):
        hold = DelayHold()
        assert hold.update(2, 0.0, in_contact) == 2
        assert hold.update(5, 0.05, in_contact) == 5


def test_in_contact_the_delay_never_falls_however_long_it_is_lower() -> None:
    hold = DelayHold()
    hold.update(6, 0.0, True)
    # a steady hold of a minute while the round trip wavers between 2 and 6 ticks
    seen = {hold.update(2 + (i % 5), 0.05 * i, True) for i in range(1200)}
    assert seen == {6}


def test_out_of_contact_it_falls_after_the_lower_delay_lasted_and_contact_restarts_the_wait() -> (
    None
):
    hold = DelayHold()
    hold.update(6, 0.0, False)
    t = 0.0
    while t < DELAY_FALL_S - 0.1:
        t += 0.05
        assert hold.update(3, t, False) == 6
    hold.update(3, t + 0.05, True)  # a touch: the wait starts over
    t += 0.1
    assert hold.update(3, t, False) == 6
    assert hold.update(3, t + DELAY_FALL_S - 0.05, False) == 6
    assert hold.update(3, t + DELAY_FALL_S, False) == 3


def test_bad_inputs_are_refused_and_reset_forgets() -> None:
    hold = DelayHold()
    with pytest.raises(ValueError):
        hold.update(-1, 0.0, False)
    with pytest.raises(ValueError):
        hold.update(1, float("nan"), False)
    hold.update(4, 0.0, False)
    hold.reset()
    assert hold.update(1, 0.0, False) == 1


def test_the_measured_delay_is_the_90th_percentile_of_the_recent_round_trips() -> None:
    assert measured_delay_ticks([], 0.025, 20.0) == 0
    # one 400 ms stall among 1 ms round trips: not counted
    assert measured_delay_ticks([0.001] * 19 + [0.4], 0.025, 20.0) == 0
    # 220 ms at 20 Hz with a 25 ms state age: ceil(0.245 * 20) - 1 = 4
    assert measured_delay_ticks([0.22] * RTT_WINDOW, 0.025, 20.0) == 4
    # only the last RTT_WINDOW count
    assert measured_delay_ticks([0.5] * 50 + [0.001] * RTT_WINDOW, 0.025, 20.0) == 0


def test_the_percentile_is_numpys_on_random_windows() -> None:
    import numpy as np

    from haptic_collab.shared.gains.key import loop_delay_ticks

    rng = np.random.default_rng(7)
    for n in (1, 2, 7, 19, 20, 35):
        for _ in range(300):
            rtts = list(rng.exponential(0.08, size=n))
            expected = loop_delay_ticks(float(np.percentile(rtts[-RTT_WINDOW:], 90)), 0.025, 20.0)
            assert measured_delay_ticks(rtts, 0.025, 20.0) == expected
