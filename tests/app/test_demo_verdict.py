"""The demo's verdict on each user's whole hold, on synthetic recordings and summaries.

What a user of ``haptic demo`` notices: a hold whose rendered gains flip between a fallback and a
design (70 / 210 N/m: the force on a still hand jumps 1 N, 3 N, 1 N, 3 N) is not called steady;
a user that never got a model is said to have felt nothing, not ``0.00 nan NO``, and the demo
exits non-zero; a run on a machine too loaded to judge says so instead of calling a user
unstable, with its own exit status.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from haptic_collab import demo as haptic_demo
from haptic_collab.client.recorder import COLUMNS, CSV_HEADER, format_rows
from haptic_collab.demo_report import (
    EXIT_CODES,
    GAIN_TRANSFER_S,
    STIFFNESS_JND,
    Timeline,
    build_report,
    coupling_report,
    delay_rise_in_hold,
    felt_stiffness,
    felt_stiffness_step,
    hold_window,
    in_gain_transfer,
    judge_user,
    link_lost_in_hold,
    machine_load,
    print_summary,
    rest_plane_k_h,
    run_verdict,
    run_verdict_line,
    script_start_s,
    timeline,
)

RATE = 1000.0
DURATION = 20.0
TL = timeline(DURATION)
K_O = 280.0  # the object's stiffness at A's contact [N/m]
TOP = np.array([0.0, 0.0, 0.1])  # A presses the top: outward +z
SIDE = np.array([-0.1, 0.0, 0.0])  # B rests on the side: outward -x


def user(
    name: str,
    k_h: Any = 210.0,
    own_gain: Any = None,
    force_n: Any = None,
    probe_wobble_m: Any = 0.0,
    tl: Timeline = TL,
) -> dict[str, np.ndarray]:
    """A user's telemetry over the whole run, every recorder column (SI units).

    A approaches, presses 10 mm into the top and holds until its release; B rests 1.5 mm into
    the side from 1 s on. ``k_h`` and ``own_gain`` (default 1/K_h: a design with C_h K_h = 1)
    are numbers or functions of time; ``force_n`` overrides the force on the hand;
    ``probe_wobble_m`` is added to the probe's depth (a function of time or a number).
    """
    t = np.arange(0.0, DURATION, 1.0 / RATE)
    cols = {c: np.zeros_like(t) for c in COLUMNS}
    cols["tick"] = np.arange(t.size, dtype=float)
    cols["t_s"] = t

    def at(v: Any) -> np.ndarray:
        return np.asarray(v(t) if callable(v) else np.full_like(t, float(v)), float)

    if name == "A":
        anchor, normal = TOP, np.array([0.0, 0.0, 1.0])
        press = np.clip((t - tl.contact_s) / tl.press_s, 0.0, 1.0)
        release = np.clip((t - tl.hold_end_s) / tl.release_s, 0.0, 1.0)
        depth = 0.010 * press * (1.0 - release) - 0.02 * (t < tl.contact_s)
    else:
        anchor, normal = SIDE, np.array([-1.0, 0.0, 0.0])
        depth = np.where(t >= 1.0, 0.0015, -0.02)
    depth = depth + at(probe_wobble_m)
    kh = at(k_h)
    own = 1.0 / kh if own_gain is None else at(own_gain)
    contact = depth > 0.0
    force = np.where(contact, K_O * depth, 0.0) if force_n is None else at(force_n)
    probe = anchor[None, :] - np.outer(depth, normal)
    for i, ax in enumerate("xyz"):
        cols[f"probe_{ax}_m"] = probe[:, i]
        cols[f"proxy_{ax}_m"] = anchor[i] + np.zeros_like(t)
        cols[f"force_{ax}_n"] = force * normal[i]
    cols["force_n"] = force
    cols["penetration_m"] = depth
    cols["k_h_n_per_m"] = kh
    cols["own_gain_m_per_n"] = own
    cols["own_offset_m"] = own * force
    cols["in_contact"] = contact.astype(float)
    cols["force_scale"] = np.ones_like(t)
    cols["period_s"] = np.full_like(t, 1.0 / RATE)
    return cols


def summary(name: str, **over: Any) -> dict[str, Any]:
    """A client's summary (``haptic client --summary``) with the fields the verdict reads."""
    out: dict[str, Any] = {
        "name": name,
        "patches": 390,
        "fallback_patches": 40,
        "gain_designs": 4,
        "rtt_ms_p50": 2.0,
        "rtt_ms_samples": [2.0] * 10,
        "gain_changes": [{"tick": 30, "k_h": 210.0, "k_o_eff": K_O}],
        "servo_rate_hz": 999.9,
        "servo_rate_hz_set": 1000.0,
        "period_us_p99": 1001.0,
        "clock_origin_s": 100.0,
    }
    out.update(over)
    return out


def a_hold() -> list[tuple[float, float]]:
    return hold_window("A", TL, user("A"), None)


def flipping(t: np.ndarray) -> np.ndarray:
    """Fallback 70 N/m and a designed 210 N/m, each for 0.4 s, in the first half of A's hold;
    the designed gains alone in its last seconds (which the demo used to judge alone)."""
    hold0 = TL.contact_s + TL.press_s
    flips = (t >= hold0) & (t < hold0 + 4.0) & (np.floor((t - hold0) / 0.4) % 2 == 0)
    return np.where(flips, 70.0, 210.0)


def test_gains_flipping_between_a_fallback_and_a_design_are_a_felt_stiffness_step() -> None:
    """The issue's hold: the fallback renders 70 N/m without own-force compensation, the design
    210 N/m with C_h = 1/K_h; the hand holds still. A still hand feels K_o through the design and
    1/(1/70 + 1/K_o) = 56 N/m through the fallback: a step of x5, far beyond the JND."""
    cols = user("A", k_h=flipping, own_gain=lambda t: np.where(flipping(t) < 100.0, 0.0, 1 / 210))
    judged = judge_user(cols, summary("A"), a_hold(), load=[])
    felt = judged["felt_stiffness"]
    fallback_felt = 1.0 / (1.0 / 70.0 + 1.0 / K_O)
    assert felt["low_n_per_m"] == pytest.approx(fallback_felt, rel=1e-6)
    assert felt["high_n_per_m"] == pytest.approx(K_O, rel=1e-6)
    assert felt["ratio"] == pytest.approx(K_O / fallback_felt, rel=1e-6)
    assert felt["step_n_per_m"] == pytest.approx(K_O - fallback_felt, rel=1e-6)
    assert felt["jnd"] == pytest.approx(0.10)  # shared.gains.verified_plane's ln(1.1), as a share
    assert judged["hold_oscillation_mm"] < 0.01  # the probe never moved
    assert judged["verdict"] == "unstable"
    (reason,) = judged["verdict_reasons"]
    assert "felt stiffness stepped x5.00 (56 <-> 280 N/m" in reason
    # the last second of the hold, all the demo used to judge, is steady: judged alone it passes
    last = [(TL.hold_end_s - 1.0, TL.hold_end_s)]
    assert judge_user(cols, summary("A"), last, load=[])["verdict"] == "stable"


def test_designs_with_own_force_compensation_feel_the_same_whatever_their_k_h() -> None:
    """Both gains compensated (C_h K_h = 1, as every P design on the balloon): the hand feels the
    object's own K_o through either, so the same flips are no step and the hold is stable."""
    judged = judge_user(user("A", k_h=flipping), summary("A"), a_hold(), load=[])
    assert judged["felt_stiffness"]["ratio"] == pytest.approx(1.0)
    assert judged["verdict"] == "stable" and judged["verdict_reasons"] == []


def test_a_felt_step_within_the_jnd_is_steady() -> None:
    """A felt stiffness 5 % off for a second is within the stiffness JND (10 %); 40 % is not."""
    hold0 = TL.contact_s + TL.press_s

    def softer(c: float):  # coupling compliance c/K_o for one second mid-hold
        return lambda t: np.where((t >= hold0 + 2.0) & (t < hold0 + 3.0), c / K_O, 0.0)

    inside = user("A", k_h=1e9, own_gain=lambda t: -softer(0.05)(t))  # K_h ~ inf: c = -C_h
    outside = user("A", k_h=1e9, own_gain=lambda t: -softer(0.4)(t))
    j_in = judge_user(inside, summary("A"), a_hold(), load=[])
    j_out = judge_user(outside, summary("A"), a_hold(), load=[])
    assert j_in["felt_stiffness"]["ratio"] == pytest.approx(1.05, rel=1e-3)
    assert j_in["felt_stiffness"]["ratio"] < 1.0 + STIFFNESS_JND
    assert j_in["verdict"] == "stable"
    assert j_out["felt_stiffness"]["ratio"] == pytest.approx(1.4, rel=1e-3)
    assert j_out["verdict"] == "unstable"


def test_the_whole_hold_is_judged_for_shake_not_for_creep() -> None:
    hold0 = TL.contact_s + TL.press_s
    early = lambda t: np.where(  # noqa: E731  a 6 Hz, 1.6 mm shake in the hold's first seconds
        (t >= hold0 + 1.0) & (t < hold0 + 2.5), 0.0008 * np.sin(2 * np.pi * 6.0 * t), 0.0
    )
    shaky = judge_user(user("A", probe_wobble_m=early), summary("A"), a_hold(), load=[])
    assert shaky["verdict"] == "unstable"
    assert 1.4 < shaky["hold_oscillation_mm"] < 2.0  # 1.6 mm; each window's trend moves it a little
    assert hold0 + 0.5 <= shaky["hold_oscillation_at_s"] < hold0 + 2.5
    assert "the probe shook" in shaky["verdict_reasons"][0]
    # the probe sinking 4 mm in 1.5 s (the device held at its continuous force limit) is a creep
    creep = lambda t: 0.004 * np.clip((t - hold0 - 4.0) / 1.5, 0.0, 1.0)  # noqa: E731
    steady = judge_user(user("A", probe_wobble_m=creep), summary("A"), a_hold(), load=[])
    assert steady["hold_oscillation_mm"] < 1.0 and steady["verdict"] == "stable"


def test_a_user_that_never_got_a_model_is_never_rendered_and_fails_the_run(capsys) -> None:
    """The issue's heaviest load: no patch, no force, the probe 47 mm inside the object. The
    demo printed `0.00 nan NO` and exited 0."""
    none = user("A", k_h=0.0, own_gain=0.0, force_n=0.0, probe_wobble_m=0.037)
    none["in_contact"] = np.zeros_like(none["t_s"])
    judged = judge_user(none, summary("A", patches=0, gain_changes=[]), a_hold(), load=[])
    assert judged["verdict"] == "never rendered"
    assert judged["verdict_reasons"] == ["no local model arrived (0 patches): it rendered no force"]
    assert judged["hold_oscillation_mm"] is None and judged["felt_stiffness"] is None
    stable_b = {"verdict": "stable"}
    verdict = run_verdict({"A": judged, "B": stable_b})
    assert verdict == {
        "verdict": "never rendered",
        "exit_code": 1,
        "users": {"A": "never rendered", "B": "stable"},
    }
    # on a loaded machine too: the load is named, and the user still felt nothing
    loaded = judge_user(none, summary("A", patches=0), a_hold(), load=["the server overran 40%"])
    assert loaded["verdict"] == "never rendered"
    assert loaded["verdict_reasons"][1] == "the machine was loaded: the server overran 40%"
    # a model, but the probe never met the surface during the hold: the user felt nothing either
    away = user("A", probe_wobble_m=-0.05)
    assert judge_user(away, summary("A"), a_hold(), load=[])["verdict_reasons"] == [
        "it never touched the object during its hold"
    ]


def test_a_loaded_machine_could_not_judge_and_says_why() -> None:
    """The issue's load ~7: fallback gains for 194 of 194 patches, no design done; the demo said
    `stable yes`. And a loaded hold that shook is not called unstable."""
    starved = summary("A", patches=194, fallback_patches=194, gain_designs=0)
    reasons = machine_load(starved, missed_in_hold_per_s=0.4, overrun_share=0.0, injected_rtt_ms=0)
    assert reasons == ["no gain design finished (fallback gains for 194 of 194 patches)"]
    judged = judge_user(user("A"), starved, a_hold(), load=reasons)
    assert judged["verdict"] == "could not judge"
    assert judged["verdict_reasons"] == [
        "machine too loaded: no gain design finished (fallback gains for 194 of 194 patches); "
        "measured anyway: a steady hold"
    ]
    # the server overran a quarter of its ticks, the servo missed 120 deadlines a second, the
    # round trip took 400 ms through a 100 ms link: each is a reason; the shake is still measured
    slow = summary("A", rtt_ms_p50=400.0)
    reasons = machine_load(
        slow, missed_in_hold_per_s=120.0, overrun_share=0.25, injected_rtt_ms=240
    )
    assert reasons == [
        "the server overran 25% of its ticks",
        "the servo missed 120 deadlines per second",
        "the round trip took 400 ms (median; 240 ms injected)",
    ]
    hold0 = TL.contact_s + TL.press_s
    shake = lambda t: np.where(t > hold0 + 1.0, 0.001 * np.sin(2 * np.pi * 8.0 * t), 0.0)  # noqa: E731
    judged = judge_user(user("A", probe_wobble_m=shake), slow, a_hold(), load=reasons)
    assert judged["verdict"] == "could not judge"
    assert "measured anyway: the probe shook" in judged["verdict_reasons"][0]
    verdict = run_verdict({"A": judged, "B": {"verdict": "stable"}})
    assert verdict["exit_code"] == 3 and verdict["verdict"] == "could not judge"
    # an unstable or unrendered user outranks one that could not be judged
    assert run_verdict({"A": judged, "B": {"verdict": "unstable"}})["exit_code"] == 1
    # a quiet machine gives no reason
    assert machine_load(summary("A"), 1.0, 0.01, 0.0) == []


def write_run(work: Path, a: dict, b: dict, a_sum: dict, b_sum: dict) -> None:
    """A demo's folder as its clients leave it: telemetry CSV and summary JSON per user."""
    work.mkdir(parents=True, exist_ok=True)
    for name, cols, summ in (("A", a, a_sum), ("B", b, b_sum)):
        rows = np.stack([cols[c] for c in COLUMNS], axis=1)
        (work / f"{name}.csv").write_text(CSV_HEADER + format_rows(rows))
        (work / f"{name}.json").write_text(json.dumps(summ))


class Settings:
    sim_rate_hz = 20.0
    stiffness_scale = 1.0
    latency_ms = 0.0
    jitter_ms = 0.0
    loss = 0.0
    duration_s = DURATION


def overrun_samples(share_in_hold: float) -> list[dict[str, float]]:
    """The server's status polled every 0.5 s on the clients' clock (origin 100 s): 20 ticks a
    second, ``share_in_hold`` of them overrun from A's contact on."""
    out, over = [], 0.0
    for k, t in enumerate(np.arange(0.0, DURATION + 0.5, 0.5)):
        if t > TL.contact_s:
            over += 10 * share_in_hold
        out.append({"t_clock_s": 100.0 + t, "tick": 10 * k, "overruns": round(over)})
    return out


def test_the_report_carries_the_verdict_and_the_console_ends_with_it(tmp_path, capsys) -> None:
    work = tmp_path / "run"
    a = user("A", k_h=flipping, own_gain=lambda t: np.where(flipping(t) < 100.0, 0.0, 1 / 210))
    write_run(work, a, user("B"), summary("A"), summary("B", gain_changes=[{"k_o_eff": 270.0}]))
    status = {"tick": 400, "overruns": 0, "tick_ms_p50": 3.0, "tick_ms_p99": 6.0}
    report = build_report(work, TL, status, Settings(), overrun_samples(0.0))
    json.dumps(report)  # JSON-able, as --report writes it
    assert report["verdict"] == {
        "verdict": "unstable",
        "exit_code": 1,
        "users": {"A": "unstable", "B": "stable"},
    }
    ua, ub = report["users"]["A"], report["users"]["B"]
    assert ua["stable"] is False and ub["stable"] is True
    assert ua["felt_stiffness"]["ratio"] == pytest.approx(5.0, rel=1e-3)
    assert ua["hold_window_s"] == [[TL.contact_s + TL.press_s + 0.5, TL.hold_end_s]]
    assert ua["server_overrun_share_in_hold"] == 0.0 and ua["machine_load"] == []
    # B is judged while A is still: before A touches, during A's hold, after A's release
    assert [w[1] for w in ub["hold_window_s"]][:2] == [TL.contact_s, TL.hold_end_s]
    print_summary(report)
    lines = capsys.readouterr().out.strip().splitlines()
    assert "nan" not in "\n".join(lines)
    assert lines[-2].startswith("A: UNSTABLE: the felt stiffness stepped x5.00")
    assert lines[-1].startswith("B: stable: over its ")
    assert run_verdict_line(report) == (
        "verdict: unstable (A unstable, B stable; B did not feel A's press; "
        "exit status 1: a user unstable or never rendered)"
    )


def test_a_run_whose_server_overran_during_the_hold_could_not_be_judged(tmp_path, capsys) -> None:
    work = tmp_path / "run"
    write_run(work, user("A"), user("B"), summary("A"), summary("B"))
    status = {"tick": 400, "overruns": 120}
    report = build_report(work, TL, status, Settings(), overrun_samples(0.3))
    assert report["verdict"]["verdict"] == "could not judge"
    assert report["verdict"]["exit_code"] == EXIT_CODES["could not judge"] == 3
    ua = report["users"]["A"]
    assert ua["server_overrun_share_in_hold"] == pytest.approx(0.3, abs=0.02)
    assert ua["machine_load"] == ["the server overran 30% of its ticks"]
    assert report["server"]["overrun_share_in_hold_measured"] == "during the hold"
    print_summary(report)
    out = capsys.readouterr().out.strip().splitlines()
    assert out[-2].startswith("A: COULD NOT JUDGE: machine too loaded: the server overran 30%")
    assert run_verdict_line(report).startswith("verdict: could not judge (A could not be judged, ")
    assert run_verdict_line(report).endswith(
        "exit status 3: the machine was too loaded to judge; run it again on a quieter machine)"
    )


def test_a_user_that_never_rendered_makes_haptic_demo_exit_non_zero(
    tmp_path, monkeypatch, capsys
) -> None:
    """End to end through the command line, the processes replaced by a finished run's folder:
    the report is written, the folder kept, and ``haptic demo`` exits 1."""
    from haptic_collab.cli import main

    none = user("B", k_h=0.0, own_gain=0.0, force_n=0.0)
    none["in_contact"] = np.zeros_like(none["t_s"])
    run = tmp_path / "run"
    write_run(run, user("A"), none, summary("A"), summary("B", patches=0, gain_changes=[]))
    report_path = tmp_path / "out" / "report.json"

    def finished_run(work: Path, port: int, opts: haptic_demo.DemoOptions) -> dict[str, Any]:
        report = build_report(run, TL, {"tick": 400, "overruns": 0}, opts, [])
        assert opts.report is not None
        opts.report.parent.mkdir(parents=True, exist_ok=True)
        opts.report.write_text(json.dumps(report))
        return report

    monkeypatch.setattr(haptic_demo, "_run_in", finished_run)
    work = tmp_path / "work"
    args = ["demo", "--headless", "--port", "0", "--workdir", str(work)]
    assert main([*args, "--report", str(report_path)]) == 1
    saved = json.loads(report_path.read_text())
    assert saved["users"]["B"]["verdict"] == "never rendered"
    assert saved["verdict"]["exit_code"] == 1
    # without --workdir the temporary folder is kept after such a run, and named
    temp = tmp_path / "tmp"
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    with pytest.raises(haptic_demo.DemoVerdictError) as err:
        haptic_demo.run_demo(haptic_demo.DemoOptions(port=0, report=report_path))
    assert err.value.exit_code == 1 and "B never rendered" in str(err.value)
    (kept,) = temp.iterdir()
    out = capsys.readouterr().out.splitlines()
    assert out[-5].startswith("verdict: never rendered (A stable, B never rendered; ")
    assert out[-1].startswith(f"logs:   {kept.resolve()} (server.log, A.log, B.log")


def fallback_changes(unchecked_tick: int) -> list[dict[str, Any]]:
    """A client's gain changes: designs at delay 0, then at ``unchecked_tick`` (server ticks,
    20 a second from the run's start) the delay measured rises to 2 ticks and the client renders
    the unchecked quarter-K_o fallback (59 N/m) until a check for it brings checked gains back
    two seconds later."""
    design = {"k_h": 146.2, "verified": True, "fallback": False, "k_o_eff": 237.1}
    return [
        {**design, "tick": 30, "delay_ticks": 0},
        {
            "tick": unchecked_tick,
            "k_h": 59.3,
            "verified": False,
            "fallback": True,
            "delay_ticks": 2,
            "k_o_eff": 237.1,
        },
        {**design, "tick": unchecked_tick + 40, "fallback": True, "delay_ticks": 2},
    ]


def test_a_delay_risen_on_loopback_with_unchecked_fallback_gains_is_the_machine_s_load() -> None:
    """The 12 s demo beside a load of 10: B's measured delay rose from 0 to 1-3 ticks on a
    loopback link, and B rendered the unchecked fallback in A's hold: its felt stiffness stepped
    x5. That is the machine's load, not B's instability: the demo could not judge B."""
    # the status polled: tick k at k / 20 s on A's clock
    tick_times = (np.array([0.0, 400.0]), np.array([0.0, 20.0]))
    in_hold = fallback_changes(unchecked_tick=int(20 * (TL.contact_s + TL.press_s + 1.0)))
    hold = a_hold()
    assert delay_rise_in_hold(summary("B", gain_changes=in_hold), hold, tick_times) == (2, 59.3)
    # the same before the hold (back to checked gains by then) is not in it
    before = fallback_changes(unchecked_tick=20)
    assert delay_rise_in_hold(summary("B", gain_changes=before), hold, tick_times) is None
    # with the injected latency's delay from the start (2 ticks throughout) nothing rose
    steady = [{**g, "delay_ticks": 2} for g in in_hold]
    assert delay_rise_in_hold(summary("B", gain_changes=steady), hold, tick_times) is None
    reasons = machine_load(summary("B"), 0.5, 0.0, 0.0, delay_rise=(2, 59.3))
    assert reasons == [
        "its measured delay rose to 2 simulation ticks and it rendered unchecked fallback "
        "gains (59 N/m) in its hold"
    ]


def test_a_report_with_a_risen_delay_in_the_hold_could_not_judge(tmp_path) -> None:
    hold0 = TL.contact_s + TL.press_s
    unchecked = lambda t: (t >= hold0 + 1.0) & (t < hold0 + 3.0)  # noqa: E731
    a = user(
        "A",
        k_h=lambda t: np.where(unchecked(t), 59.3, 210.0),
        own_gain=lambda t: np.where(unchecked(t), 0.0, 1.0 / 210.0),
    )
    changes = fallback_changes(unchecked_tick=int(20 * (hold0 + 1.0)))
    work = tmp_path / "run"
    write_run(work, a, user("B"), summary("A", gain_changes=changes), summary("B"))
    report = build_report(work, TL, {"tick": 400, "overruns": 0}, Settings(), overrun_samples(0))
    ua = report["users"]["A"]
    assert ua["verdict"] == "could not judge"
    assert ua["felt_stiffness"]["ratio"] > 4.0  # measured and reported all the same
    assert "its measured delay rose to 2 simulation ticks" in ua["verdict_reasons"][0]
    assert "measured anyway: the felt stiffness stepped" in ua["verdict_reasons"][0]
    assert report["verdict"]["exit_code"] == 3


def test_forces_ramped_down_for_a_silent_link_are_the_machine_s_load_not_the_loop() -> None:
    # a stalled server: the servo ramps the forces to zero just before A's hold, the hand falls
    # 20 mm in and is pushed back when the link returns; the shake is the stall's
    hold = a_hold()
    h0 = hold[0][0]
    a = user("A", probe_wobble_m=lambda t: np.where((t > h0) & (t < h0 + 0.5), 0.008, 0.0))
    a["force_scale"] = np.where((a["t_s"] > h0 - 0.3) & (a["t_s"] < h0 + 0.2), 0.0, 1.0)
    lost = summary("A", servo={"counts": {"link_lost": 2, "velocity_limit": 0}})
    seconds = link_lost_in_hold(a, lost, hold)
    assert seconds == pytest.approx(0.5, abs=0.01)
    reasons = machine_load(lost, 0.4, 0.0, 0.0, None, seconds)
    assert reasons and "link fell silent" in reasons[0]
    assert judge_user(a, lost, hold, load=reasons)["verdict"] == "could not judge"
    # the same ramp in a run that also tripped the velocity limit excuses nothing: an
    # oscillating probe trips it, and that must stay "unstable"
    fast = summary("A", servo={"counts": {"link_lost": 2, "velocity_limit": 3}})
    assert link_lost_in_hold(a, fast, hold) == 0.0
    assert (
        judge_user(a, fast, hold, load=machine_load(fast, 0.4, 0.0, 0.0))["verdict"] == "unstable"
    )
    # no ramp: nothing to excuse
    assert link_lost_in_hold(user("A"), lost, hold) == 0.0


def test_a_user_left_alone_on_the_rest_plane_feels_its_k_h_not_a_step() -> None:
    # B's contact goes from a compensated design (felt as the object, 270 N/m) to the rest plane
    # with K_h = K_o when A leaves: the rest plane's force does not go through the simulation, so
    # B feels 270 N/m throughout; read as a coupling in series with the object it was 135 N/m,
    # a false x2 step that called B unstable
    k_o = 270.0
    b = user("B", k_h=lambda t: np.where(t < 12.0, 240.0, k_o))
    b["own_gain_m_per_n"] = np.where(b["t_s"] < 12.0, 1.0 / 240.0, 0.0)
    changes = [
        {"tick": 30, "k_h": 240.0, "own_gain": round(1 / 240.0, 6), "k_o_eff": k_o},
        {"tick": 240, "k_h": k_o, "own_gain": 0.0, "k_o_eff": k_o, "rest": True},
    ]
    rest = summary("B", gain_changes=changes)
    w = b["t_s"] > 10.0
    step = felt_stiffness_step(*felt_stiffness(b, w, k_o, rest_k_h=rest_plane_k_h(rest)))
    assert step is not None and step["ratio"] == pytest.approx(1.0, abs=1e-6)
    # without the summary's rest flag the same samples read as a coupling: the false step
    plain = felt_stiffness_step(*felt_stiffness(b, w, k_o))
    assert plain is not None and plain["ratio"] == pytest.approx(2.0, rel=1e-3)


def test_a_coupled_contact_is_judged_against_its_own_stiffness_not_the_common_mode() -> None:
    # the palpation demo's B: while A pressed the top, B's contact was coupled to A's (K_o_eff
    # 146.5, K_o_stiff 238: its own K_o, the harmonic mean, 181.3 N/m) and rendered compensated
    # designs, felt as the object; once A left, the rest plane of K_h 181.3 N/m. Judged against
    # the median K_o_eff (156 N/m) that read as a step of x1.16 and called B unstable
    own = 181.3
    b = user("B", k_h=lambda t: np.where(t < 16.0, 48.0, own))
    b["own_gain_m_per_n"] = np.where(b["t_s"] < 16.0, 1.0 / 48.0, 0.0)
    coupled = [
        {"tick": 40 + i, "k_h": 48.0, "own_gain": round(1 / 48.0, 6), "k_o": own,
         "k_o_eff": k_eff, "k_o_stiff": k_eff * own / (2.0 * k_eff - own)}
        for i, k_eff in enumerate((146.5, 150.0, 156.0, 160.0, 170.0))
    ]  # fmt: skip
    rest = {"tick": 320, "k_h": own, "own_gain": 0.0, "k_o": own, "k_o_eff": own, "rest": True}
    hold = [(10.0, 19.0)]
    judged = judge_user(b, summary("B", gain_changes=[*coupled, rest]), hold, load=[])
    assert judged["felt_stiffness"]["k_o_n_per_m"] == pytest.approx(own)
    assert judged["felt_stiffness"]["ratio"] == pytest.approx(1.0, abs=1e-6)
    assert judged["verdict"] == "stable"
    # a summary without ``k_o`` (written before it was recorded) is judged against the median
    # K_o_eff, 158 N/m here: the false step
    old = [{k: v for k, v in g.items() if k != "k_o"} for g in [*coupled, rest]]
    judged = judge_user(b, summary("B", gain_changes=old), hold, load=[])
    assert judged["felt_stiffness"]["ratio"] == pytest.approx(own / 158.0, rel=1e-3)
    assert judged["verdict"] == "unstable"
    # a quarter-K_o fallback without compensation is still a step against the contact's own K_o
    b["k_h_n_per_m"] = np.where(b["t_s"] < 13.0, own / 4.0, b["k_h_n_per_m"])
    b["own_gain_m_per_n"] = np.where(b["t_s"] < 13.0, 0.0, b["own_gain_m_per_n"])
    judged = judge_user(b, summary("B", gain_changes=[*coupled, rest]), hold, load=[])
    assert judged["felt_stiffness"]["ratio"] == pytest.approx(5.0, rel=1e-3)
    assert judged["verdict"] == "unstable"


def test_a_script_that_started_late_is_judged_on_its_hold_not_its_arrival(tmp_path) -> None:
    """A's scripted hand starts at its servo's first tick, 2.5 s into A's clock on a loaded
    machine: the demo shifts its timeline there, so A's steady hold is called steady and not
    the press that arrived 2.5 s later than planned."""
    late = 2.5
    real = replace(TL, delay_s=TL.delay_s + late)
    a = user("A", tl=real)
    first = a["t_s"] >= late  # no telemetry before the servo's first tick
    a = {c: v[first] for c, v in a.items()}
    work = tmp_path / "run"
    write_run(work, a, user("B"), summary("A"), summary("B"))
    assert script_start_s(work / "A.csv") == pytest.approx(late, abs=1e-3)
    status = {"tick": 400, "overruns": 0, "tick_ms_p50": 3.0, "tick_ms_p99": 6.0}

    planned = build_report(work, TL, status, Settings(), overrun_samples(0.0))
    assert planned["users"]["A"]["stable"] is False  # the press itself, judged as a hold

    shifted = replace(TL, delay_s=TL.delay_s + script_start_s(work / "A.csv"))
    report = build_report(work, shifted, status, Settings(), overrun_samples(0.0))
    ua = report["users"]["A"]
    assert ua["stable"] is True
    (start, end), *_ = ua["hold_window_s"]
    assert real.contact_s + real.press_s <= start and end <= real.hold_end_s
    assert report["verdict"]["users"]["A"] == "stable"


def test_no_telemetry_means_no_shift(tmp_path) -> None:
    assert script_start_s(tmp_path / "missing.csv") == 0.0
    (tmp_path / "empty.csv").write_text(CSV_HEADER)
    assert script_start_s(tmp_path / "empty.csv") == 0.0


def test_the_surface_under_b_is_read_where_no_change_of_gains_is_carried_over() -> None:
    # B's gains change 0.05 s into A's hold (K_h 121 -> 48 N/m, compensated): the client carries
    # the change over in 0.25 s, the rendered proxy moving from the old offset C_h F to the new
    # one while the recorded offset steps at once. Read through that ramp, a surface that moved
    # 0.5 mm out looked as if it moved in, and "B feels A's press" was answered no
    from haptic_collab.client.app import GAIN_TRANSFER_S as client_transfer_s

    assert GAIN_TRANSFER_S == client_transfer_s
    hold0 = TL.contact_s + TL.press_s
    hold = (hold0, hold0 + 1.0)
    b = user("B")
    t = b["t_s"]
    change = hold0 + 0.05
    kh = np.where(t < change, 121.0, 48.0)
    f = np.where(t < TL.contact_s, 0.214, 0.367)  # B's force rises as A presses
    surface = -0.1 - np.where(t < TL.contact_s, 0.0, 0.0005)  # and the side bulges 0.5 mm out
    offset = f / kh  # C_h F, stepping at once at the change
    # the proxy ramps from the old offset to the new one over the transfer
    ramp = np.clip((t - change) / GAIN_TRANSFER_S, 0.0, 1.0)
    proxy_offset = np.where(
        t < change, offset, 0.367 / 121.0 + ramp * (0.367 / 48.0 - 0.367 / 121.0)
    )
    b.update(
        k_h_n_per_m=kh, own_gain_m_per_n=1.0 / kh, own_offset_m=offset, force_n=f,
        force_x_n=-f, proxy_x_m=surface - proxy_offset,
    )  # fmt: skip
    assert in_gain_transfer(b)[(t >= change) & (t < change + GAIN_TRANSFER_S - 0.01)].all()
    assert not in_gain_transfer(b)[(t > change + GAIN_TRANSFER_S + 0.01)].any()
    c = coupling_report(b, TL, hold, 1.0)
    assert c["b_surface_displacement_mm"] == pytest.approx(0.5, abs=0.01)
    assert c["b_feels_a"]
