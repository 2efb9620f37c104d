"""``haptic demo --scenario palpation``: A's sweep over a hidden lump, what the report says of it,
and the whole scenario run end to end once the server takes inclusions (docs/palpation.md)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from haptic_collab.client.devices.trajectories import Sweep
from haptic_collab.demo import SWEEP_DEPTH_M, DemoOptions, palpation_setup, palpation_timeline
from haptic_collab.demo_report import STIFFNESS_JND, palpation_lines, palpation_report

HALF = math.radians(40.0)


def _sweep(**kw) -> Sweep:
    start = (-math.sin(HALF), 0.0, math.cos(HALF))
    end = (math.sin(HALF), 0.0, math.cos(HALF))
    return Sweep(centre=(0.0, 0.0, 0.0), radius_m=0.1, start=start, end=end, **kw)


def test_the_sweep_slides_at_one_depth_over_the_top_and_back():
    s = _sweep(depth_m=0.01, sweep_s=4.0)
    t0, t1 = s.slide_s
    ts = np.linspace(t0, t1, 401)
    points = np.array([s(t) for t in ts])
    # the hand target stays 10 mm inside the sphere the whole slide, out to the end and back
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), 0.09, atol=1e-12)
    assert points[:, 0].max() == pytest.approx(0.09 * math.sin(HALF))
    assert points[0, 0] == pytest.approx(-0.09 * math.sin(HALF))
    assert points[-1, 0] == pytest.approx(-0.09 * math.sin(HALF))
    # outside the surface before the approach and after the withdrawal
    assert np.linalg.norm(s(0.0)) == pytest.approx(0.13)
    assert np.linalg.norm(s(s.duration_s)) == pytest.approx(0.13)
    with pytest.raises(ValueError, match="opposite"):
        Sweep((0, 0, 0), 0.1, (0, 0, 1), (0, 0, -1))


def _write(work: Path, name: str, cols: dict[str, np.ndarray], origin: float) -> None:
    keys = list(cols)
    data = np.stack([cols[k] for k in keys], axis=1)
    np.savetxt(work / f"{name}.csv", data, delimiter=",", header=",".join(keys), comments="")
    (work / f"{name}.json").write_text(json.dumps({"clock_origin_s": origin}))


def test_the_report_says_how_much_a_force_rose_over_the_lump_and_whether_b_felt_it(tmp_path):
    """A's telemetry along a sweep with 0.30 N over the lump and 0.25 N elsewhere at the same
    depth under the surface: the report finds +20 %, felt; B's force swings 0.05 N on 0.2 N: B
    felt it."""
    s = _sweep(delay_s=4.0, sweep_s=4.0)
    t = np.arange(0.0, s.duration_s, 1e-3)
    hand = np.array([s(x) for x in t])
    ang = np.arctan2(hand[:, 0], hand[:, 2])
    over = np.abs(ang - math.radians(20.0)) < math.radians(6.0)
    contact = np.linalg.norm(hand, axis=1) < 0.1
    force = np.where(contact, np.where(over, 0.30, 0.25), 0.0)
    a = {"t_s": t, "probe_x_m": hand[:, 0], "probe_y_m": hand[:, 1], "probe_z_m": hand[:, 2],
         "force_n": force, "penetration_m": np.where(contact, 0.004, 0.0),
         "in_contact": contact.astype(float)}  # fmt: skip
    t0, t1 = s.slide_s
    sliding = (t >= t0) & (t <= t1)
    b_force = 0.2 + np.where(sliding, 0.05 * np.sin(2 * math.pi * (t - t0) / (t1 - t0)) ** 2, 0.0)
    b = {"t_s": t - 0.5, "force_n": b_force, "in_contact": np.ones_like(t)}
    _write(tmp_path, "A", a, 10.0)
    _write(tmp_path, "B", b, 10.5)  # B's clock starts 0.5 s after A's
    lump = (math.sin(math.radians(20.0)), 0.0, math.cos(math.radians(20.0)))
    twin = (-lump[0], 0.0, lump[2])
    p = palpation_report(tmp_path, s, lump, twin)
    assert p["a_over"]["force_n"] == pytest.approx(0.30)
    assert p["a_beside"]["force_n"] == pytest.approx(0.25)
    assert p["rise"] == pytest.approx(0.20) and p["felt"] is True
    assert p["b_rest_force_n"] == pytest.approx(0.2)
    assert p["b_force_range_in_sweep_n"] == pytest.approx(0.05, abs=0.005)
    assert p["b_felt_sweep"] is True
    assert "+20 %" in palpation_lines(p)[0] and "felt it" in palpation_lines(p)[0]
    # the same force everywhere: no rise, not felt
    a["force_n"] = np.where(contact, 0.25, 0.0)
    _write(tmp_path, "A", a, 10.0)
    flat = palpation_report(tmp_path, s, lump, twin)
    assert abs(flat["rise"]) < 1e-9 and flat["felt"] is False
    # the same force, but the probe sinks 12 mm beside the lump and 10 mm over it: the same depth
    # takes 20 % more force over the lump, which is what A feels there
    beside = np.abs(ang + math.radians(20.0)) < math.radians(6.0)
    deeper = np.where(beside, 0.088 / 0.09, 1.0)[:, None]
    a.update(probe_x_m=hand[:, 0] * deeper[:, 0], probe_z_m=hand[:, 2] * deeper[:, 0])
    _write(tmp_path, "A", a, 10.0)
    stiff = palpation_report(tmp_path, s, lump, twin)
    assert stiff["a_over"]["indentation_mm"] == pytest.approx(10.0, abs=1e-6)
    assert stiff["a_beside"]["indentation_mm"] == pytest.approx(12.0, abs=1e-6)
    assert stiff["rise"] == pytest.approx(0.20) and stiff["felt"] is True
    assert stiff["force_rise_at_hand_depth"] == pytest.approx(0.0, abs=1e-9)


def test_the_scenario_writes_a_lump_its_twin_and_a_sweep_over_them(tmp_path):
    tl, sweep_s = palpation_timeline(20.0)
    assert tl.hold_end_s + tl.release_s <= 20.0  # A is done within the run
    opts = DemoOptions(scenario="palpation", object="fem")
    tl2, sweep, flags, (over, beside) = palpation_setup(tmp_path, opts)
    assert tl2 == tl
    assert flags[1::2] == [str(tmp_path / "lump.stl"), "liver*10", str(tmp_path / "twin.stl"),
                           "liver"]  # fmt: skip
    rows = np.loadtxt(tmp_path / "sweep.csv", delimiter=",", skiprows=1)
    slide = (rows[:, 0] >= sweep.slide_s[0]) & (rows[:, 0] <= sweep.slide_s[1])
    dirs = rows[slide, 1:] / np.linalg.norm(rows[slide, 1:], axis=1, keepdims=True)
    # the slide passes straight over the lump and over its twin, 10 mm deep
    assert np.max(dirs @ np.array(over)) > math.cos(math.radians(0.5))
    assert np.max(dirs @ np.array(beside)) > math.cos(math.radians(0.5))
    np.testing.assert_allclose(np.linalg.norm(rows[slide, 1:], axis=1), 0.1 - SWEEP_DEPTH_M,
                               atol=1e-5)  # fmt: skip


@pytest.mark.slow
@pytest.mark.alone  # its verdict needs a quiet machine: run after the others
def test_the_palpation_demo_a_feels_the_lump_b_feels_the_sweep_and_both_stay_stable(tmp_path):
    report = tmp_path / "report.json"
    done = subprocess.run(
        [sys.executable, "-m", "haptic_collab.cli", "demo", "--scenario", "palpation",
         "--headless", "--port", "0", "--report", str(report),
         "--workdir", str(tmp_path / "work")],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert report.is_file(), done.stdout[-3000:] + done.stderr[-3000:]
    run = json.loads(report.read_text())
    if run["verdict"]["exit_code"] == 3:  # rendered with fallback gains through a stalled link
        pytest.skip(f"the machine was too loaded to judge the run: {run['server']}")
    assert run["verdict"]["exit_code"] == 0, run["verdict"]
    p = run["palpation"]
    # A slid over the lump and over its twin, and B felt A's sweep through the organ
    assert p["a_over"]["samples"] > 100 and p["a_beside"]["samples"] > 100, p
    assert p["b_felt_sweep"], p
    # A felt the lump: the same depth under the surface takes more force over it, by more than a
    # stiffness JND (the static solid: +20.5 %). The demo's default 30 s run felt +21.6 to
    # +23.3 % in 9 of 9 runs, quiet or beside two spinning processes (docs/palpation.md)
    assert p["felt"] and p["rise"] > STIFFNESS_JND, (
        f"rise {p['rise']}, over {p['a_over']}, beside {p['a_beside']}, A's delay "
        f"{run['users']['A']['delay_ticks_last']} ticks, server {run['server']}"
    )
