"""Servo telemetry: the ring buffer keeps the newest rows in order and writes a CSV with units."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from haptic_collab.client.recorder import COLUMNS, TelemetryRecorder
from tests.support.helpers import resting_servo


def row(i: int) -> list[float]:
    r = [float(i)] * len(COLUMNS)
    r[0] = i
    return r


def test_ring_keeps_the_newest_rows_oldest_first() -> None:
    rec = TelemetryRecorder(capacity=5)
    for i in range(12):
        rec.append(*row(i))
    assert len(rec) == 5 and rec.total == 12
    assert rec.column("tick").tolist() == [7, 8, 9, 10, 11]
    assert rec.rows().shape == (5, len(COLUMNS))


def test_compute_time_goes_to_the_newest_row() -> None:
    rec = TelemetryRecorder(capacity=3)
    for i in range(4):
        rec.append(*row(i))
        rec.set_compute_s(1e-6 * (i + 1))
    assert rec.column("compute_s").tolist() == pytest.approx([2e-6, 3e-6, 4e-6])


def test_wrong_row_length_and_unknown_column_are_refused() -> None:
    rec = TelemetryRecorder(capacity=3)
    with pytest.raises(Exception, match="pack"):
        rec.append(1.0, 2.0)
    with pytest.raises(ValueError, match="unknown telemetry column"):
        rec.column("force")
    with pytest.raises(ValueError):
        TelemetryRecorder(capacity=0)


def test_servo_ticks_write_a_csv_with_units(tmp_path: Path) -> None:
    anchor, normal = (0.0, 0.0, 0.05), (0.0, 0.0, 1.0)
    core = resting_servo(anchor, normal, k_h=250.0)
    for k in range(600):
        core.tick(k * 1e-3)
        core.record_compute(2e-6)
    path = tmp_path / "servo.csv"
    assert core.recorder.write_csv(path) == 600

    with path.open() as fh:
        header = next(csv.reader(fh))
    assert header == list(COLUMNS)
    for name in ("t_s", "probe_z_m", "penetration_m", "force_n", "k_h_n_per_m", "compute_s"):
        assert name in header
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    col = {name: data[:, i] for i, name in enumerate(header)}
    assert col["tick"].tolist() == list(range(600))
    assert np.allclose(col["t_s"], np.arange(600) * 1e-3)
    assert np.allclose(col["compute_s"], 2e-6)
    # resting 2 mm inside with the hand: in contact at the end, force = K_h * penetration
    assert col["in_contact"][-1] == 1
    assert col["force_n"][-1] == pytest.approx(250.0 * col["penetration_m"][-1], rel=1e-6)
    assert col["force_z_n"][-1] > 0  # outward
    # the proxy is the probe projected onto the surface
    assert np.allclose(col["proxy_z_m"][col["in_contact"] == 1], anchor[2])
