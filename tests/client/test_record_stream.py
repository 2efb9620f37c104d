"""Recordings that survive: ``--record`` streams every servo tick to disk with bounded memory, is
flushed and closed on SIGINT and SIGTERM with the summary; ``sim:replay`` replays it; ``haptic
plot`` draws it."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from haptic_collab.client.devices.opener import make_device
from haptic_collab.client.recorder import COLUMNS, CsvRecording, TelemetryRecorder, load_recording
from haptic_collab.client.servo import ServoConfig, ServoCore
from tests.support.helpers import resting_servo

ROOT = Path(__file__).resolve().parents[2]


def row(i: int) -> list[float]:
    r = [0.5 * i] * len(COLUMNS)
    r[0] = i
    for flag in ("in_contact", "ramping", "fault", "force_limited"):
        r[COLUMNS.index(flag)] = i % 2
    return r


def test_a_long_run_streams_every_row_through_a_small_ring(tmp_path: Path) -> None:
    rec = TelemetryRecorder(capacity=1000)  # one second at 1 kHz
    out = CsvRecording(rec, tmp_path / "run.csv", flush_interval_s=0.05)
    out.start()
    n = 4000  # four times what the ring holds

    def servo() -> None:  # about 1 kHz, as the servo thread, never waiting for the disk
        for i in range(n):
            rec.append(*row(i))
            if i % 10 == 9:
                time.sleep(0.01)

    th = threading.Thread(target=servo)
    th.start()
    th.join()
    assert out.close() == n
    assert out.rows_dropped == 0 and out.error is None
    cols = load_recording(tmp_path / "run.csv")
    assert cols["tick"].tolist() == list(range(n))
    assert np.array_equal(cols["force_n"], 0.5 * np.arange(n))
    assert np.array_equal(cols["in_contact"], np.arange(n) % 2)


def test_rows_overwritten_before_they_were_written_are_counted(tmp_path: Path) -> None:
    rec = TelemetryRecorder(capacity=10)
    out = CsvRecording(rec, tmp_path / "run.csv", flush_interval_s=3600.0)
    out.start()
    for i in range(25):  # the writer does not wake up: 15 rows are lost
        rec.append(*row(i))
    assert out.close() == 10 and out.rows_dropped == 15
    assert load_recording(tmp_path / "run.csv")["tick"].tolist() == list(range(15, 25))


def _complete_ticks(path: Path, tmp_path: Path) -> list[int]:
    """Ticks of the complete lines of a recording still being written (as a reader sees it: the
    writer may be in the middle of a line)."""
    text = path.read_text()
    snap = tmp_path / "snapshot.csv"
    snap.write_text(text[: text.rfind("\n") + 1])
    return [int(t) for t in load_recording(snap)["tick"].tolist()]


def test_the_file_grows_while_the_client_runs(tmp_path: Path) -> None:
    rec = TelemetryRecorder(capacity=1000)
    out = CsvRecording(rec, tmp_path / "run.csv", flush_interval_s=0.02)
    out.start()
    for i in range(300):
        rec.append(*row(i))
    deadline = time.monotonic() + 5.0
    path = tmp_path / "run.csv"
    while len(_complete_ticks(path, tmp_path)) < 299 and time.monotonic() < deadline:
        time.sleep(0.02)
    # on disk before close: all but the newest row (its compute time may still change)
    assert _complete_ticks(path, tmp_path) == list(range(299))
    out.close()
    assert len(load_recording(tmp_path / "run.csv")["tick"]) == 300


# -- replay ---------------------------------------------------------------------------------------


def test_replay_of_a_record_file_follows_the_recorded_probe_path(tmp_path: Path) -> None:
    anchor, normal = (0.01, -0.02, 0.08), (0.0, 0.0, 1.0)
    dev = make_device(
        "sim:press",
        anchor,
        normal,
        trajectory_options={"delay_s": 0.2, "approach_s": 0.6, "press_s": 0.8, "hold_s": 0.5},
    )
    dev.open()
    core = ServoCore(dev, ServoConfig(link_timeout_s=float("inf")))  # free hand: no patch
    t0 = 0.731  # a client's servo starts some time after the client did
    for k in range(3500):
        core.tick(t0 + k * 1e-3)
    path = tmp_path / "A.csv"
    core.recorder.write_csv(path)
    rec = load_recording(path)
    rec_probe = np.stack([rec["probe_x_m"], rec["probe_y_m"], rec["probe_z_m"]], axis=1)
    assert np.ptp(rec_probe[:, 2]) > 0.04  # it really moved: 50 mm from 30 mm out to 20 mm in

    replay = make_device(f"sim:replay:{path}", (0, 0, 0), (1, 0, 0))  # anchor is not used
    replay.open()
    got = np.array([replay.read(5.0 + k * 1e-3) for k in range(3500)])  # any clock origin
    err = np.linalg.norm(got - rec_probe, axis=1)
    # the simulated hand pulls the handle along the recorded path: it follows it with the lag of
    # its spring-damper (measured 1.5 mm at the fastest point, 0.45 mm rms, over 50 mm of motion)
    assert err.max() < 2.5e-3 and np.sqrt(np.mean(err**2)) < 1e-3, err.max()
    assert err[-1] < 0.2e-3  # and ends where the recording ended


def test_replay_still_reads_the_documented_t_x_y_z_format(tmp_path: Path) -> None:
    path = tmp_path / "hand.csv"
    path.write_text("t_s,x_m,y_m,z_m\n0.0,0,0,0.1\n1.0,0,0,0.05\n")
    dev = make_device(f"sim:replay:{path}", (0, 0, 0), (0, 0, 1))
    assert dev.trajectory(0.5) == pytest.approx((0.0, 0.0, 0.075))  # type: ignore[attr-defined]


# -- the client process ---------------------------------------------------------------------------


def _haptic(*args: str, **kw) -> subprocess.Popen[str]:  # type: ignore[no-untyped-def]
    return subprocess.Popen(
        [sys.executable, "-m", "haptic_collab.cli", *args],
        cwd=ROOT,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        **kw,
    )


@pytest.fixture(scope="module")
def server_url():  # type: ignore[no-untyped-def]
    proc = _haptic("server", "--port", "0", "--subdivisions", "3", "--log-level", "warning")
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()  # "viewer: http://127.0.0.1:PORT/"
        m = re.search(r"http://127\.0\.0\.1:(\d+)/", line)
        assert m, line + (proc.stderr.read() if proc.stderr else "")
        yield f"ws://127.0.0.1:{m.group(1)}/ws"
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_flushes_the_recording_and_writes_the_summary(
    server_url: str, tmp_path: Path, sig: signal.Signals
) -> None:
    record, summary = tmp_path / "A.csv", tmp_path / "A.json"
    proc = _haptic(
        "client", "--url", server_url, "--record", str(record), "--summary", str(summary),
        "--trajectory", "delay_s=0.5,approach_s=0.5,press_s=0.5,hold_s=100",
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60.0
        # wait until the client presses (the file is written while it runs)
        while time.monotonic() < deadline:
            time.sleep(0.25)
            try:  # the writer may be caught mid-line: read again on the next poll
                cols = load_recording(record) if record.exists() else {"force_n": np.empty(0)}
            except ValueError:
                continue
            if cols["force_n"].size > 500 and cols["force_n"][-1] > 0.2:
                break
        else:
            raise AssertionError("the client never pressed")
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err[-2000:]
    s = json.loads(summary.read_text())
    assert s["stopped_by"] == sig.name and s["joins"] == 1
    cols = load_recording(record)
    n = cols["tick"].size
    assert s["record"] == {"path": str(record), "rows": n, "rows_dropped": 0, "error": None}
    assert cols["tick"].tolist() == list(range(n))  # every tick, none lost, none twice
    assert cols["force_n"].max() > 0.2
    # the servo ramped the force down before it stopped: the last row is a zero force
    assert cols["force_n"][-1] == 0.0 and s["max_force_n"] > 0.2


# -- haptic plot ----------------------------------------------------------------------------------


def _haptic_plot(path: Path) -> subprocess.CompletedProcess[str]:
    """``haptic plot PATH`` run as a user runs it, its output captured."""
    return subprocess.run(
        [sys.executable, "-m", "haptic_collab.cli", "plot", str(path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_haptic_plot_draws_a_recording(tmp_path: Path) -> None:
    core = resting_servo((0.0, 0.0, 0.05), (0.0, 0.0, 1.0))
    for k in range(800):
        core.tick(k * 1e-3)
    path = tmp_path / "B.csv"
    core.recorder.write_csv(path)
    res = _haptic_plot(path)
    assert res.returncode == 0, res.stderr
    png = tmp_path / "B.png"
    assert f"wrote {png}" in res.stdout
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    # not a recording: exit 2 with one line
    bad = tmp_path / "hand.csv"
    bad.write_text("t_s,x_m,y_m,z_m\n0,0,0,0\n")
    res = _haptic_plot(bad)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "not a --record file" in lines[0]
