"""``haptic bench gains``' plane check timing: it times the checks a client's worker runs."""

from __future__ import annotations

import pytest

from haptic_collab.bench.gains import _session, plane_check_ms


@pytest.mark.slow  # a benchmark's sweep of plane checks
def test_the_plane_checks_are_timed_for_every_cell_and_delay_asked() -> None:
    s = _session()
    key = s.gain_key(0.0, 0)
    # a soft cell and the capped cell above the device's 1000 N/m, each with 0, 2 and 4 ticks
    times = plane_check_ms(s.gain_table, key, (300.0, 1200.0))
    assert len(times) == 6 and all(t >= 0.0 for t in times)
