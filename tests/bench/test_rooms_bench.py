"""``haptic bench rooms``' reading of the lateness histogram (:func:`haptic_collab.bench.rooms._p99_ms`):
the window's p99 from two cumulative ``/metrics`` readings, interpolated within its bucket."""

from __future__ import annotations

import math

import pytest

from haptic_collab.bench.rooms import _p99_ms

BOUNDS = (0.001, 0.005, 0.01, math.inf)


def cumulative(counts: list[int]) -> list[tuple[float, float]]:
    out, running = [], 0
    for le, n in zip(BOUNDS, counts, strict=True):
        running += n
        out.append((le, float(running)))
    return out


def test_the_p99_of_the_window_is_interpolated_in_its_bucket() -> None:
    before = cumulative([50, 0, 0, 0])  # what came before the window does not count
    # the window: 90 ticks under 1 ms, 10 between 5 and 10 ms -> the 99th of 100 is in (5, 10]
    after = cumulative([140, 0, 10, 0])
    assert _p99_ms(before, after) == pytest.approx(5.0 + 5.0 * (99 - 90) / 10)


def test_no_tick_in_the_window_has_no_p99_and_the_open_bucket_answers_its_lower_bound() -> None:
    same = cumulative([5, 5, 0, 0])
    assert _p99_ms(same, same) is None
    assert _p99_ms(cumulative([0, 0, 0, 0]), cumulative([0, 0, 0, 10])) == pytest.approx(10.0)
