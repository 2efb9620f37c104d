"""``haptic bench load``: real users and viewers against a real server process.

The short run goes through the command line, as a user would type it: the server is a separate
``haptic server --port 0`` process, the clients run in worker processes. What it catches is a
bench that does not run, a server that drops users, users that get no patches, and patches
counted twice. How fast the patches come on this machine is the benchmark's output, never
asserted here (the machine is shared).
"""

from __future__ import annotations

import json

import pytest

from haptic_collab.bench.load import REQUIRED_KEYS
from haptic_collab.cli import main

SIM_RATE_HZ = 20.0


@pytest.mark.timeout(120)
def test_bench_load_reports_every_user_getting_its_patches(
    capsys: pytest.CaptureFixture[str],
) -> None:
    argv = ["bench", "load", "--users", "3", "--viewers", "1", "--duration", "4"]
    argv += ["--sim-rate", f"{SIM_RATE_HZ:g}", "--subdivisions", "3", "--workers", "2", "--json"]
    assert main(argv) == 0
    result = json.loads(capsys.readouterr().out)

    assert set(REQUIRED_KEYS) <= set(result), set(REQUIRED_KEYS) - set(result)
    assert result["users"] == 3 and result["viewers"] == 1
    assert result["sim_rate_hz"] == SIM_RATE_HZ
    assert result["duration_s"] == pytest.approx(4.0, abs=0.5)
    assert result["errors"] == 0, (result["error_codes"], result["server_warnings_first"])
    # every user got patches, and nothing was counted twice (at most one patch per tick)
    rates = result["per_user_patch_rate_hz"]
    assert len(rates) == 3
    assert result["patch_rate_hz_min"] > 0.0, rates
    assert result["patch_rate_hz_p1"] >= result["patch_rate_hz_min"]
    assert max(rates.values()) <= 1.1 * SIM_RATE_HZ, rates
    # the server's numbers are there and make sense
    assert 0.0 < result["tick_ms_p50"] <= result["tick_ms_p99"]
    assert 0.0 <= result["overruns_fraction"] <= 1.0
    assert result["ticks"] > 0
    assert result["rss_mb_start"] > 10.0 and result["rss_mb_end"] > 10.0  # a Python server
    assert result["vertices"] == 642


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--users", "33"], "--users must be in [0, 32]"),
        (["--vertices", "1000"], "2562, 10242"),
        (["--users", "0", "--viewers", "0"], "nothing to run"),
    ],
)
def test_bench_load_refuses_bad_options_before_starting_anything(
    args: list[str], says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench", "load", *args, "--json"]) == 2
    err = capsys.readouterr().err
    assert says in err, err
    assert "starting the server" not in err
