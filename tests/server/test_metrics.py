"""``GET /metrics``: what a Prometheus scrape of a running server shows, and who may scrape."""

from __future__ import annotations

import asyncio
import contextlib
import json
import urllib.error
import urllib.request

import pytest
from prometheus_client.parser import text_string_to_metric_families
from websockets.asyncio.client import connect

from haptic_collab.server.app import DEFAULT_ROOM, ServerApp
from haptic_collab.server.main import ServerOptions, build_metrics_token, build_world
from haptic_collab.server.metrics import Buckets, scrape_allowed
from haptic_collab.server.room import Room
from haptic_collab.server.security import TokenTable

SIM_RATE = 20.0
TOKEN = "metrics-token-0123456789abcdef"


def get(port: int, path: str, headers: dict[str, str] | None = None) -> tuple[int, str, str]:
    req = urllib.request.Request(f"http://127.0.0.1:{port}{path}", headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=10) as resp:
            return resp.status, resp.headers.get("Content-Type", ""), resp.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.headers.get("Content-Type", ""), exc.read().decode()


async def scrape(port: int, **headers: str) -> dict[str, float]:
    """``{"name{label=value,...}": value}`` of one scrape."""
    status, ctype, text = await asyncio.to_thread(get, port, "/metrics", headers)
    assert status == 200 and ctype.startswith("text/plain"), (status, text)
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            labels = ",".join(f"{k}={v}" for k, v in sorted(s.labels.items()))
            out[f"{s.name}{{{labels}}}"] = s.value
    return out


async def start_app(**kwargs) -> ServerApp:
    world = build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=2))
    app = ServerApp(Room(world, SIM_RATE), "127.0.0.1", 0, **kwargs)
    await app.start()
    return app


R = f"room={DEFAULT_ROOM}"


async def test_a_scrape_shows_the_rooms_ticks_users_patches_and_viewer_bytes():
    app = await start_app()
    patches = 0
    viewer_bytes = 0
    try:
        url = f"ws://127.0.0.1:{app.port}/ws"
        async with connect(url) as user, connect(url) as viewer:
            await user.send(
                json.dumps({"type": "hello", "protocol": 1, "role": "user", "name": "A"})
            )
            await viewer.send(
                json.dumps({"type": "hello", "protocol": 1, "role": "viewer", "name": "V"})
            )
            state = {"type": "state", "seq": 1, "probe_m": [0, 0, 0.2], "force_n": [0, 0, 0]}
            await user.send(json.dumps(state))

            async def read_user() -> None:
                nonlocal patches
                async for frame in user:
                    patches += json.loads(frame)["type"] == "patch"

            async def read_viewer() -> None:
                nonlocal viewer_bytes
                async for frame in viewer:
                    if isinstance(frame, bytes):
                        viewer_bytes += len(frame)

            readers = [asyncio.create_task(read_user()), asyncio.create_task(read_viewer())]
            while patches < 10 or viewer_bytes == 0:
                await asyncio.sleep(0.05)
            # what the clients had read before the scrape (a patch may arrive during it)
            seen_patches, seen_bytes = patches, viewer_bytes
            first = await scrape(app.port)
            while patches < first[f"haptic_room_patches_sent_total{{{R}}}"] + 10:
                await asyncio.sleep(0.05)
            second = await scrape(app.port)
            for task in readers:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        status = app.status()
    finally:
        await app.stop()

    assert first[f"haptic_room_users{{{R}}}"] == 1 and first[f"haptic_room_viewers{{{R}}}"] == 1
    assert first[f"haptic_room_sim_rate_hertz{{{R}}}"] == SIM_RATE
    # the server wrote at least what the clients read
    assert first[f"haptic_room_patches_sent_total{{{R}}}"] >= seen_patches
    assert first[f"haptic_room_viewer_bytes_sent_total{{{R}}}"] >= seen_bytes
    assert (
        second[f"haptic_room_patches_sent_total{{{R}}}"]
        >= first[f"haptic_room_patches_sent_total{{{R}}}"] + 10
    )
    # every tick run is in the histograms, however many a busy loop skipped (the scrape is
    # served on the loop between ticks); their buckets are cumulative
    for scraped in (first, second):
        ticks = scraped[f"haptic_room_ticks_total{{{R}}}"]
        assert scraped[f"haptic_room_tick_seconds_count{{{R}}}"] == ticks
        assert scraped[f"haptic_room_tick_lateness_seconds_count{{{R}}}"] == ticks
        buckets = sorted(
            (float(k.split("le=")[1].split(",")[0].rstrip("}")), v)
            for k, v in scraped.items()
            if k.startswith("haptic_room_tick_seconds_bucket")
        )
        assert [v for _, v in buckets] == sorted(v for _, v in buckets)
        assert buckets[-1][1] == scraped[f"haptic_room_tick_seconds_count{{{R}}}"]
    assert second[f"haptic_room_ticks_total{{{R}}}"] > first[f"haptic_room_ticks_total{{{R}}}"]
    assert second[f"haptic_room_overruns_total{{{R}}}"] <= status["overruns"]
    assert second["haptic_send_timeouts_total{}"] == 0


async def test_a_metrics_token_is_required_when_one_is_set(tmp_path):
    path = tmp_path / "metrics-token"
    path.write_text(TOKEN + "\n")
    token = build_metrics_token(ServerOptions(metrics_token_file=str(path)))
    app = await start_app(metrics_token=token)
    try:
        none = await asyncio.to_thread(get, app.port, "/metrics")
        wrong = await asyncio.to_thread(
            get, app.port, "/metrics", {"Authorization": "Bearer " + TOKEN[::-1]}
        )
        assert none[0] == 401 and wrong[0] == 401
        assert "haptic_room" not in none[2] + wrong[2]
        scraped = await scrape(app.port, Authorization=f"Bearer {TOKEN}")
        assert f"haptic_room_ticks_total{{{R}}}" in scraped
    finally:
        await app.stop()


def test_who_may_scrape():
    token = TokenTable.single(TOKEN)
    assert scrape_allowed(True, None, None)  # loopback, no token: local processes only
    assert not scrape_allowed(False, None, None)  # off loopback without a token: nobody
    assert not scrape_allowed(False, f"Basic {TOKEN}", token)
    assert not scrape_allowed(True, None, token)  # a token set is required everywhere
    assert scrape_allowed(False, f"Bearer {TOKEN}", token)


def test_a_bad_metrics_token_file_is_refused_without_showing_it(tmp_path):
    path = tmp_path / "metrics-token"
    path.write_text("short secret\n")
    with pytest.raises(ValueError) as err:
        build_metrics_token(ServerOptions(metrics_token_file=str(path)))
    assert "secret" not in str(err.value) and str(path) in str(err.value)


def test_buckets_count_a_value_on_a_bound_in_that_bound():
    b = Buckets((0.01, 0.02))
    for v in (0.005, 0.01, 0.015, 0.5):
        b.add(v)
    assert b.cumulative() == [("0.01", 2.0), ("0.02", 3.0), ("+Inf", 4.0)]
    assert b.total == pytest.approx(0.53)


async def test_a_scrape_shows_every_room_each_with_its_own_figures():
    world = build_world(ServerOptions(sim_rate_hz=50.0, subdivisions=1))
    app = await start_app(rooms={"lab": Room(world, 50.0)})
    try:
        async with connect(f"ws://127.0.0.1:{app.port}/rooms/lab/ws") as user:
            await user.send(
                json.dumps({"type": "hello", "protocol": 1, "role": "user", "name": "A"})
            )
            await asyncio.wait_for(user.recv(), 10.0)  # welcome
            lab = app.rooms()["lab"]
            for _ in range(500):  # bounded: until the room has ticked
                if lab.tick_count >= 1:
                    break
                await asyncio.sleep(0.02)
            got = await scrape(app.port)
        assert got["haptic_room_users{room=lab}"] == 1 and got[f"haptic_room_users{{{R}}}"] == 0
        assert got["haptic_room_sim_rate_hertz{room=lab}"] == 50.0
        assert got[f"haptic_room_sim_rate_hertz{{{R}}}"] == SIM_RATE
        assert got["haptic_room_ticks_total{room=lab}"] >= 1
    finally:
        await app.stop()


async def test_off_loopback_status_needs_the_metrics_token():
    """``/status`` names every room (and room processes' ids): a server listening off loopback
    answers it only with the metrics token; on loopback, as the lobby of docs/usage.md reads
    it, anyone local. (Listens on 0.0.0.0; every request goes to 127.0.0.1.)"""
    table = TokenTable.single(TOKEN)
    for token in (None, table):
        world = build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=2))
        app = ServerApp(Room(world, SIM_RATE), "0.0.0.0", 0, metrics_token=token)
        await app.start()
        try:
            code, _, body = await asyncio.to_thread(get, app.port, "/status")
            assert code == (403 if token is None else 401) and "rooms" not in body
            if token is not None:
                wrong = {"Authorization": "Bearer " + TOKEN[::-1]}
                assert (await asyncio.to_thread(get, app.port, "/status", wrong))[0] == 401
                right = {"Authorization": f"Bearer {TOKEN}"}
                code, _, body = await asyncio.to_thread(get, app.port, "/status", right)
                assert code == 200 and DEFAULT_ROOM in json.loads(body)["rooms"]
        finally:
            await app.stop()
    app = await start_app()  # on loopback: open to local readers
    try:
        code, _, body = await asyncio.to_thread(get, app.port, "/status")
        assert code == 200 and DEFAULT_ROOM in json.loads(body)["rooms"]
    finally:
        await app.stop()
