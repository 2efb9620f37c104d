"""``haptic bench gains``' plane check timing: it times the checks a client's worker runs."""

from __future__ import annotations

from haptic_collab.bench.gains import PLANE_CHECK_K_OS, _session, plane_check_ms


def test_the_plane_checks_are_timed_for_every_cell_and_delay_asked() -> None:
    s = _session()
    key = s.gain_key(0.0, 0)
    times = plane_check_ms(s.gain_table, key, (1200.0,))
    # one time per delay (0, 2 and 4 ticks) of the capped cell above the device's stiffness
    assert len(times) == 3 and all(t >= 0.0 for t in times)
    # the default cells reach above the session's device (1000 N/m): the capped planes
    assert max(PLANE_CHECK_K_OS) > s.device.max_stiffness_n_per_m
