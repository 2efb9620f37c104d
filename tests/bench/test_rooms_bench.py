"""``haptic bench rooms``: its reading of the lateness histogram (the window's p99 from two
cumulative ``/metrics`` readings, interpolated within its bucket), the patch rates in the window
and the summary's count of rooms at 99 %, and (slow) the whole bench, small."""

from __future__ import annotations

import json
import math

import pytest

from haptic_collab.bench.rooms import _p99_ms, _quantile_ms, _rates, _summary, main

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


def test_each_users_patch_rate_counts_only_its_patches_inside_the_window() -> None:
    recs = [
        {"room": "default", "patches": [0.5, 1.0, 1.5, 2.0, 3.0]},  # 1.0, 1.5, 2.0 inside
        {"room": "b1", "patches": [1.2]},
    ]
    assert _rates(recs, 1.0, 2.5, ["default", "b1", "b2"]) == {
        "default": [2.0],
        "b1": [round(1 / 1.5, 2)],
        "b2": [],  # a room nobody was in has no rate
    }


def _run(shares: dict[str, float]) -> dict:
    rooms = {
        name: {
            "patch_share_min": share,
            "tick_ms_p50": 1.0,
            "tick_ms_p99": 2.0,
            "lateness_ms_p99": 3.0,
        }
        for name, share in shares.items()
    }
    return {"rooms": rooms, "machine": {"cpu_busy": 0.5}, "errors": []}


def test_the_summary_counts_the_rooms_whose_slowest_user_had_99_percent() -> None:
    one = _run({"default": 1.0, "b1": 0.975})  # b1's slowest user: 19.5 Hz of 20
    many = _run({"default": 0.99, "b1": 1.0})
    summary = _summary(
        [{"one_process": one, "room_processes": many}], ["default", "b1"], 20.0, None
    )
    assert summary["one_process"]["rooms_at_99pct"] == [1]
    assert summary["one_process"]["patch_share_min"] == 0.975
    assert summary["room_processes"]["rooms_at_99pct"] == [2]


def test_the_median_of_the_window_is_interpolated_in_its_bucket() -> None:
    # the window: 40 ticks under 1 ms, 60 in (1, 5] ms -> the 50th of 100 is the 10th of 60
    after = cumulative([40, 60, 0, 0])
    assert _quantile_ms(cumulative([0, 0, 0, 0]), after, 0.5) == pytest.approx(
        1.0 + 4.0 * (50 - 40) / 60
    )


def test_the_priority_comparison_sums_up_each_mode_and_their_lateness_ratio() -> None:
    def run(lateness_p50: float, lateness_p99: float, rates: list[float]) -> dict:
        room = {
            "patch_share_min": min(rates) / 20.0,
            "patch_rate_hz": rates,
            "tick_ms_p50": 3.0,
            "tick_ms_p99": 4.0,
            "lateness_ms_p50": lateness_p50,
            "lateness_ms_p99": lateness_p99,
            "overruns": 0,
        }
        return {"rooms": {"default": room}, "machine": {"cpu_busy": 1.0}, "errors": []}

    runs = [
        {
            "tick_priority_off": run(4.0, 20.0, [19.0, 10.0]),
            "tick_priority_realtime": run(0.5, 2.0, [20.0, 20.0]),
        },
        {
            "tick_priority_off": run(6.0, 40.0, [20.0, 12.0]),
            "tick_priority_realtime": run(1.0, 4.0, [20.0, 19.8]),
        },
    ]
    summary = _summary(runs, ["default"], 20.0, None)
    off, rt = summary["tick_priority_off"], summary["tick_priority_realtime"]
    assert off["fem_lateness_ms_p99_median"] == 30.0 and rt["fem_lateness_ms_p99_median"] == 3.0
    assert summary["fem_lateness_ms_p99_median_ratio_off_over_realtime"] == 10.0
    assert summary["fem_lateness_ms_p50_median_ratio_off_over_realtime"] == 6.67
    # B's patches: every user of every run counts, the slowest decides the minimum
    assert off["patch_share_min"] == 0.5 and rt["patch_share_min"] == 0.99
    assert off["fem_patch_share_median"] == pytest.approx(0.775)
    assert "balloon_lateness_p99_ratio_one_over_processes" not in summary


def test_the_summary_gives_per_room_each_runs_slowest_user() -> None:
    def run(rates: dict[str, list[float]]) -> dict:
        rooms = {
            name: {"patch_rate_hz": r, "patch_share_min": min(r, default=0) / 20.0 or None}
            for name, r in rates.items()
        }
        return {"rooms": rooms, "machine": {"cpu_busy": 0.5}, "errors": []}

    runs = [
        {"one_process": run({"default": [19.9, 12.5, 20.0], "b1": [20.0, 19.0]})},
        {"one_process": run({"default": [20.0, 20.0], "b1": []})},  # nobody's rate in b1
    ]
    summary = _summary(runs, ["default", "b1"], 20.0, None)
    assert summary["one_process"]["slowest_user_patch_rate_hz"] == {
        "default": [12.5, 20.0],
        "b1": [19.0, None],
    }


def test_haptic_bench_rooms_takes_its_duration_and_rooms_and_prints_the_slowest(
    monkeypatch, capsys
) -> None:
    """``haptic bench rooms --duration S --rooms N``: the window and the rooms reach the bench
    (a FEM room and N-1 balloon rooms), and the report names each room's slowest user."""
    import haptic_collab.bench.rooms as bench
    from haptic_collab.cli import main as haptic

    seen = []

    def fake_run(opts):
        seen.append(opts)
        rooms = ["default", *(f"b{i + 1}" for i in range(opts.balloon_rooms))]
        per = {r: {"patch_rate_hz": [20.0, 17.25], "patch_share_min": 0.8625} for r in rooms}
        runs = [{"one_process": {"rooms": per, "machine": {"cpu_busy": 0.5}, "errors": []}}]
        return {"runs": runs, "summary": _summary(runs, rooms, 20.0, None)}

    monkeypatch.setattr(bench, "run", fake_run)
    assert haptic(["bench", "rooms", "--duration", "3", "--rooms", "3"]) == 0
    (opts,) = seen
    assert opts.duration_s == 3.0 and opts.balloon_rooms == 2
    err = capsys.readouterr().err
    assert "slowest user's patch rate" in err
    for room in ("default", "b1", "b2"):
        assert any(line.split() == [room, "17.25"] for line in err.splitlines()), err
    assert haptic(["bench", "rooms"]) == 0  # the bench's own defaults: 20 s, 8 rooms
    assert (seen[1].duration_s, seen[1].balloon_rooms) == (20.0, 7)
    assert haptic(["bench", "rooms", "--rooms", "1"]) == 2
    assert "--rooms must be at least 2" in capsys.readouterr().err


@pytest.mark.slow
def test_the_bench_kills_a_room_process_and_its_users_get_their_seats_back(tmp_path) -> None:
    """The whole bench, small: two rooms, two users each, short windows, one run."""
    out = tmp_path / "rooms.json"
    argv = [
        "--balloon-rooms", "1", "--users", "2", "--workers", "2", "--warmup-s", "1",
        "--duration-s", "3", "--kill-window-s", "3", "--repeats", "1", "--no-starts",
        "--fem-subdivisions", "2", "--subdivisions", "2", "--json", str(out),
    ]  # fmt: skip
    main(argv)
    result = json.loads(out.read_text())
    (run,) = result["runs"]
    for mode in ("one_process", "room_processes"):
        assert run[mode]["joined"] == run[mode]["expected"] == 4
        for room in ("default", "b1"):
            assert all(rate > 0 for rate in run[mode]["rooms"][room]["patch_rate_hz"])
    kill = run["room_processes"]["kill"]
    assert kill["room"] == "b1" and kill["rejoin_s"] > 0
    assert all(rate > 0 for rate in kill["others_patch_rate_hz"]["default"])
    assert [v["errors"] for v in kill["victims"]] == [["room_restarting"]] * 2
    assert all(v["resumed"] and v["same_user_id"] for v in kill["victims"])
