"""What ``haptic demo`` says on the console, as a newcomer reads it.

Right after the start: what to open and for how long. While it runs: the phase in words, as the
users' own telemetry has it (never "B resting, A waiting" while nobody has joined). At the end:
whether B felt A in plain sentences, a one-line verdict, the viewer it served and the paths of
the report, the plot and the logs. The processes are replaced by pure inputs (telemetry rows, a
report dict), so nothing here starts a server.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from haptic_collab.client.recorder import COLUMNS, CSV_HEADER
from haptic_collab.demo import _last_row, _Narrator, closing_lines, opening_lines
from haptic_collab.demo_report import coupling_lines, run_verdict_line, timeline

TL = timeline(20.0)


def row(t_s: float, force_n: float, in_contact: bool = True) -> dict[str, float]:
    """A user's latest telemetry row: every column 0 but these."""
    out = dict.fromkeys(COLUMNS, 0.0)
    out.update(t_s=t_s, force_n=force_n, in_contact=float(in_contact))
    return out


def test_the_start_says_what_to_open_now_and_for_how_long() -> None:
    lines = opening_lines(["http://127.0.0.1:8765/"], TL, 20.0, opened=False)
    assert lines[0].startswith("open http://127.0.0.1:8765/ now: the demo is live for about ")
    live_s = float(lines[0].split("about ")[1].split(" s")[0])
    assert 20.0 <= live_s <= 30.0  # the users' 20 s and their joining
    assert f"after {TL.delay_s:.0f} s A moves onto the top" in lines[-1]
    more = opening_lines(["http://127.0.0.1:1/", "http://10.0.0.2:1/"], TL, 20.0, opened=True)
    assert more[1:3] == ["  (or http://10.0.0.2:1/)", "  (opened in your browser)"]


def test_the_phase_says_waiting_to_join_until_both_users_have_joined() -> None:
    n = _Narrator(TL, 20.0)
    # the issue: "B resting, A waiting ... users 0" for 5-7 s
    assert n.phase(0, None, None) == (
        "joining",
        "waiting for A and B to join (their processes are starting)",
    )
    assert (
        n.phase(1, None, row(0.5, 0.0, False))[1] == "waiting for A and B to join (1 of 2 joined)"
    )
    which, words = n.phase(2, row(1.0, 0.0, False), row(2.0, 0.0, False))
    assert which.startswith("waiting") and words.startswith("B moves onto the side; A waits")
    _, words = n.phase(2, row(2.0, 0.0, False), row(3.0, 0.28))
    assert words.startswith("B rests on the side with 0.28 N; A waits above the top")
    assert "(A touches it in 3 s)" in words
    # A's phase is A's own clock, not the demo's: a late A is still waiting
    assert n.phase(2, row(TL.contact_s - 0.5, 0.0, False), row(9.0, 0.28))[0] == "approach"
    which, words = n.phase(2, row(TL.contact_s + 0.7, 1.2), row(9.7, 0.35))
    assert which == "press" and words == (
        "A presses into the top with 1.20 N: the dent grows and B's side bulges out; "
        "B feels 0.35 N (0.28 N at rest)"
    )
    assert n.phase(2, row(TL.hold_end_s - 1.0, 3.0), row(15.0, 0.49))[1] == (
        "A holds still, pressing with 3.00 N; B feels 0.49 N (0.28 N at rest)"
    )
    assert n.phase(2, row(TL.hold_end_s + 0.5, 1.0), row(16.0, 0.4))[0] == "release"
    # B's run ends before A's (B started first): one user left is not "waiting to join"
    which, words = n.phase(1, row(TL.hold_end_s + 3.0, 0.0, False), row(19.0, 0.29))
    assert which == "after" and "the run ends in" in words
    assert n.phase(1, row(19.8, 0.0, False), None)[0] == "ending"
    # B in contact with its force ramped down (a loaded machine), or off the side after resting
    assert "B touches the side, no force yet" in n.phase(2, row(1.0, 0.0, False), row(2, 0.0))[1]
    assert "B is off the side" in n.phase(2, row(1.0, 0.0, False), row(2, 0.0, False))[1]


def test_the_latest_row_of_a_telemetry_file_being_written(tmp_path: Path) -> None:
    path = tmp_path / "A.csv"
    assert _last_row(path) is None  # not there yet
    path.write_text(CSV_HEADER)
    assert _last_row(path) is None  # a header and no rows
    full = ",".join("1.5" if c == "t_s" else "0" for c in COLUMNS)
    path.write_text(CSV_HEADER + full + "\n" + full.replace("1.5", "1.6")[:20])  # half a row
    got = _last_row(path)
    assert got is not None and got["t_s"] == 1.5


def coupling(**over: Any) -> dict[str, Any]:
    """The report's coupling of a run where B felt A (0.282 -> 0.490 N, 0.70 mm out)."""
    c = {
        "b_force_rise_n": 0.208,
        "b_surface_displacement_mm": 0.70,
        "b_feels_a": True,
        "b_force_at_rest_n": 0.282,
        "b_force_during_a_press_n": 0.490,
        "baseline": "before A's press",
        "rest_window_s": [3.0, 4.9],
        "b_force_before_a_arrives_n": 0.280,
        "b_force_lowest_as_a_arrives_n": 0.268,
        "b_force_dip_as_a_arrives_n": 0.012,
    }
    c.update(over)
    return c


def test_whether_b_felt_a_is_said_in_plain_sentences() -> None:
    lines = coupling_lines(coupling())
    assert lines[0] == (
        "B feels A's press: yes. While A held, the side under B moved 0.70 mm outward and "
        "B's force rose from 0.282 N to 0.490 N (+74%); a hand notices about 10%."
    )
    assert lines[2] == (
        "  As A arrived, B's force held: 0.280 N just before, never below 0.268 N in the second "
        "after."
    )
    # the issue's line: "as A arrived B's force was at least 0.000 N (0.229 N below its 0.229 N
    # just before)"
    dip = coupling(
        b_force_before_a_arrives_n=0.229,
        b_force_lowest_as_a_arrives_n=0.0,
        b_force_dip_as_a_arrives_n=0.229,
    )
    assert coupling_lines(dip)[2] == (
        "  As A arrived, B's force dipped from 0.229 N to 0.000 N for a moment (0.229 N less); "
        "it should only have risen."
    )
    unmeasured = coupling(b_force_rise_n=None)
    assert coupling_lines(unmeasured)[0].startswith("B feels A's press: not measured (")


def report(verdict: str, exit_code: int) -> dict[str, Any]:
    users = {"A": "stable", "B": verdict}
    return {
        "verdict": {"verdict": verdict, "exit_code": exit_code, "users": users},
        "coupling": coupling(),
    }


def test_the_end_is_a_one_line_verdict_the_viewer_and_the_paths(tmp_path: Path) -> None:
    urls = ["http://127.0.0.1:8765/"]
    out = tmp_path / "demo-out"
    good = closing_lines(
        report("stable", 0), urls, out / "report.json", out / "demo.png", tmp_path, kept=False
    )
    assert good[1:] == [
        "verdict: stable (A stable, B stable; B felt A's press; exit status 0: every user stable)",
        "viewer: http://127.0.0.1:8765/ (served while the demo ran)",
        f"report: {(out / 'report.json').resolve()}",
        f"plot:   {(out / 'demo.png').resolve()}",
        "logs:   deleted after a good run (keep them with --workdir DIR)",
    ]
    loaded = closing_lines(report("could not judge", 3), urls, None, None, tmp_path, kept=True)
    assert loaded[1] == (
        "verdict: could not judge (A stable, B could not be judged; B felt A's press; exit status "
        "3: the machine was too loaded to judge; run it again on a quieter machine)"
    )
    assert loaded[3:] == [
        "report: none written (add --report FILE)",
        "plot:   none written (add --plot FILE)",
        f"logs:   {tmp_path.resolve()} (server.log, A.log, B.log; telemetry A.csv, B.csv)",
    ]
    assert run_verdict_line(report("unstable", 1)).endswith(
        "exit status 1: a user unstable or never rendered)"
    )
