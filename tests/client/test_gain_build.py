"""A device without a shipped gain table builds its table before joining, and caches it (issue 58).

What a user notices: the cache file holds the cells after the build (the next run finds them
and builds nothing), a progress line on stderr, an interrupted build keeps what it designed, and
no connection is made before the build ends; ``--no-gain-build`` joins at once. The grids here
are one or two cells (a design is seconds), not the shipped grid's 1638 (minutes).
"""

from __future__ import annotations

import asyncio
import io
import json
import socket
import threading
from dataclasses import replace
from pathlib import Path

import pytest

from haptic_collab.client import gain_build
from haptic_collab.client.app import ClientOptions, run_client
from haptic_collab.client.devices import profiles
from haptic_collab.client.gain_build import (
    build_device_table,
    build_table,
    plan_device_build,
    progress_bar,
)
from haptic_collab.client.gain_store import cache_path
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.gains.table_file import SHIP_GRID, design_code_hash, load_table_document

# cells of 100 Hz simulation (N = 10: designs take seconds), no delay, uncoupled
ONE = {
    **SHIP_GRID,
    "sim_rate_hz": (100.0,),
    "delay_ticks": (0,),
    "stiff_ratio": (1.0,),
    "k_o_n_per_m": (1000.0, 1000.0),
}
TWO = {**ONE, "k_o_n_per_m": (1000.0, 1100.0)}
THREE = {**ONE, "k_o_n_per_m": (1000.0, 1210.0)}

# a device of its own limits: no shipped table holds them
K_H_MAX, B_H_MAX = 700.0, 4.0


def _cached_cells() -> int:
    """The designs (cells x local models) in this test's cache file; 0 without one."""
    path = cache_path(design_code_hash())
    if not path.exists():
        return 0
    table = GainTable()
    return load_table_document(table, json.loads(path.read_text()), design_code_hash())


def test_a_build_fills_the_cache_and_the_next_plan_finds_nothing_missing() -> None:
    plan = plan_device_build(K_H_MAX, B_H_MAX, TWO)
    assert (len(plan.jobs), plan.total) == (2, 2)
    shown = io.StringIO()
    assert build_device_table(
        plan, grid=TWO, workers=1, progress=progress_bar("build", stream=shown)
    ) == (2, 0)
    assert _cached_cells() == 4  # two cells, P and PI each
    assert shown.getvalue().endswith("\rbuild [" + "#" * 30 + "] 2/2 cells, done\n")
    assert "1/2 cells, ETA " in shown.getvalue()
    again = plan_device_build(K_H_MAX, B_H_MAX, TWO)
    assert again.jobs == [] and again.total == 2
    assert build_table("again", K_H_MAX, B_H_MAX, out=plan.out, grid=TWO) == (0, 0)


@pytest.mark.parametrize("how", ["stop", "ctrl-c"])
def test_an_interrupted_build_keeps_what_it_designed_and_the_next_does_the_rest(how) -> None:
    plan = plan_device_build(K_H_MAX, B_H_MAX, THREE)
    assert len(plan.jobs) == 3
    stop = threading.Event()

    def progress(done: int, total: int) -> None:
        if done == 1:  # one cell made, the second under way, the third not started
            if how == "ctrl-c":
                raise KeyboardInterrupt
            stop.set()

    if how == "ctrl-c":
        with pytest.raises(KeyboardInterrupt):
            build_device_table(plan, grid=THREE, workers=1, stop=stop, progress=progress)
        done = 1
    else:
        # a design that ended together with the first is kept too
        done, left = build_device_table(plan, grid=THREE, workers=1, stop=stop, progress=progress)
        assert done in (1, 2) and left == 3 - done
    assert _cached_cells() == 2 * done  # each cell made, P and PI
    rest = plan_device_build(K_H_MAX, B_H_MAX, THREE)
    assert len(rest.jobs) == 3 - done
    assert build_device_table(rest, grid=THREE, workers=1) == (3 - done, 0)
    assert _cached_cells() == 6


@pytest.fixture
def custom_device(monkeypatch: pytest.MonkeyPatch) -> str:
    """A simulated profile with limits of its own (K_h <= 700 N/m, B_h <= 4 N*s/m), and the
    one-cell grid as the client's build grid."""
    base = profiles.SIM_PROFILES["touch"]
    limits = replace(base.limits, max_stiffness_n_per_m=K_H_MAX, max_damping_n_s_per_m=B_H_MAX)
    monkeypatch.setitem(
        profiles.SIM_PROFILES, "custom", replace(base, name="custom", limits=limits)
    )
    monkeypatch.setattr(gain_build, "DEVICE_GRID", ONE)
    return "custom"


async def _listener(seen: list[int]) -> asyncio.Server:
    """A TCP port that notes the cache's designs at each connection, then hangs up."""

    async def on_connect(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        seen.append(_cached_cells())
        writer.close()

    return await asyncio.start_server(on_connect, "127.0.0.1", 0)


def _options(profile: str, port: int, summary: Path, **kw: object) -> ClientOptions:
    return ClientOptions(
        url=f"ws://127.0.0.1:{port}/ws",
        device="sim:press",
        profile=profile,
        servo="thread",
        summary=summary,
        join_timeout_s=2.0,
        **kw,  # type: ignore[arg-type]
    )


def test_a_client_builds_its_devices_table_before_it_connects(custom_device, tmp_path, capsys):
    seen: list[int] = []

    async def main() -> None:
        server = await _listener(seen)
        port = server.sockets[0].getsockname()[1]
        async with server:
            await run_client(_options(custom_device, port, tmp_path / "A.json", gain_build=True))

    with pytest.raises(ConnectionError, match="could not join"):
        asyncio.run(main())
    assert seen, "the client never tried to connect"
    assert all(n == 2 for n in seen)  # the cell (P and PI) was cached before the first connection
    err = capsys.readouterr().err
    assert "1/1 cells, done" in err
    built = json.loads((tmp_path / "A.json").read_text())["gain_build"]
    assert built["ran"] is True and built["cells"] == 1 and built["seconds"] > 0.0

    # the next run finds the cache: it connects without building
    seen.clear()
    with pytest.raises(ConnectionError, match="could not join"):
        asyncio.run(main())
    assert seen and all(n == 2 for n in seen)
    assert "cells, done" not in capsys.readouterr().err
    again = json.loads((tmp_path / "A.json").read_text())["gain_build"]
    assert again == {"ran": False, "missing": 0, "of": 1}


@pytest.mark.parametrize("off", [{"gain_build": False}, {"gain_build": True, "gain_cache": False}])
def test_no_gain_build_joins_without_building(custom_device, tmp_path, capsys, off) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed when the block ends: nothing listens
    with pytest.raises(ConnectionError, match="nothing listens there"):
        asyncio.run(run_client(_options(custom_device, port, tmp_path / "A.json", **off)))
    assert _cached_cells() == 0
    assert "cells, done" not in capsys.readouterr().err
    built = json.loads((tmp_path / "A.json").read_text())["gain_build"]
    assert built["ran"] is False
    assert built["skipped"] == ("no-gain-build" if off["gain_build"] is False else "no-gain-cache")


def test_a_cache_that_cannot_be_written_lets_the_client_join_without_a_table(
    custom_device, tmp_path, monkeypatch, capsys
) -> None:
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    monkeypatch.setenv("HAPTIC_GAIN_CACHE", str(blocker))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed when the block ends: nothing listens
    opts = _options(custom_device, port, tmp_path / "A.json", gain_build=True)
    with pytest.raises(ConnectionError, match="nothing listens there"):  # it went on to join
        asyncio.run(run_client(opts))
    assert "cells, done" not in capsys.readouterr().err
    built = json.loads((tmp_path / "A.json").read_text())["gain_build"]
    assert built["ran"] is False and "not-a-folder" in built["error"]


def test_the_cli_default_follows_haptic_gain_build_and_no_gain_cache_implies_no_build(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from haptic_collab.cli import build_parser
    from haptic_collab.cli.run import _client_options

    def opts(*argv: str) -> ClientOptions:
        return _client_options(build_parser().parse_args(["client", *argv]))  # type: ignore[no-any-return]

    monkeypatch.delenv("HAPTIC_GAIN_BUILD", raising=False)
    assert opts().gain_build is True
    assert opts("--no-gain-build").gain_build is False
    assert opts("--no-gain-cache").gain_build is False
    monkeypatch.setenv("HAPTIC_GAIN_BUILD", "0")
    assert opts().gain_build is False
    assert ClientOptions().gain_build is False


def test_ctrl_c_during_the_build_keeps_the_cells_and_connects_nowhere(
    custom_device, tmp_path, monkeypatch, caplog
) -> None:
    import os
    import signal

    from haptic_collab.client import app

    monkeypatch.setattr(gain_build, "DEVICE_GRID", THREE)
    shown = app.progress_bar

    def ctrl_c_after_one(label: str):  # the user presses Ctrl-C once a cell is made
        bar = shown(label)

        def show(done: int, total: int) -> None:
            bar(done, total)
            if done == 1:
                os.kill(os.getpid(), signal.SIGINT)

        return show

    monkeypatch.setattr(app, "progress_bar", ctrl_c_after_one)
    seen: list[int] = []

    async def main() -> None:
        server = await _listener(seen)
        port = server.sockets[0].getsockname()[1]
        async with server:
            opts = _options(custom_device, port, tmp_path / "A.json", gain_build=True)
            opts.stop_on_signals = True
            await run_client(opts)

    with pytest.raises(app.GainBuildInterrupted):
        asyncio.run(main())
    assert seen == []  # nothing connected
    made = _cached_cells() // 2
    assert made >= 1  # the cells designed (P and PI each) are in the cache
    assert len(plan_device_build(K_H_MAX, B_H_MAX, THREE).jobs) == 3 - made
    assert "nothing was connected" in caplog.text
