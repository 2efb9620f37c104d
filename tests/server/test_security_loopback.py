"""The attacks of docs/security.md against a real server on loopback, each next to a well-behaved user.

Distinct source addresses are real: the attackers bind to 127.0.0.2 (all of 127.0.0.0/8 is
loopback on Linux), the well-behaved users connect from 127.0.0.1.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import ssl
import time
import urllib.request

import numpy as np
import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed, InvalidStatus

from haptic_collab.client.app import ClientOptions, run_client
from haptic_collab.server.app import ServerApp
from haptic_collab.server.main import ServerOptions, build_world
from haptic_collab.server.room import Room
from haptic_collab.server.security import TokenTable
from tests.support.processes import good_user

pytestmark = pytest.mark.slow

SIM_RATE = 20.0
TOKEN = "user-token-for-the-tests-0123"
ATTACKER = ("127.0.0.2", 0)


async def start(
    auth: TokenTable | None = None, subdivisions: int = 3, **kwargs: object
) -> ServerApp:
    world = build_world(ServerOptions(sim_rate_hz=SIM_RATE, subdivisions=subdivisions))
    app = ServerApp(Room(world, SIM_RATE, auth=auth), "127.0.0.1", 0, **kwargs)  # type: ignore[arg-type]
    await app.start()
    return app


def every_tick(good: list[int], overruns: int) -> bool:
    """The user got a patch on every tick the server ran (ticks skipped by overruns excepted).

    Behaviour, not wall time: a loaded machine may skip ticks (counted as overruns), but no tick
    the server ran may miss this user.
    """
    span = good[-1] - good[0] + 1
    return len(good) >= span - overruns - 1 and len(good) >= 0.5 * span


def hello(name: str, token: str | None = None, role: str = "user") -> str:
    msg = {"type": "hello", "protocol": 1, "role": role, "name": name}
    if token:
        msg["token"] = token
    return json.dumps(msg)


async def test_missing_or_wrong_token_is_unauthorized_and_a_real_client_joins_with_its_token(
    monkeypatch,
):
    app = await start(auth=TokenTable.single(TOKEN))
    url = f"ws://127.0.0.1:{app.port}/ws"
    try:
        for token in (None, "not-the-right-token-0123"):
            async with connect(url) as ws:
                await ws.send(hello("X", token))
                err = json.loads(await ws.recv())
                assert err["code"] == "unauthorized" and err["fatal"]
                with pytest.raises(ConnectionClosed):
                    await asyncio.wait_for(ws.recv(), 5.0)
        monkeypatch.setenv("HAPTIC_TOKEN", "not-the-right-token-0123")
        with pytest.raises(ValueError, match="unauthorized"):  # the client says so and stops
            await run_client(ClientOptions(url=url, name="A", device="sim:rest", duration_s=3.0))
        monkeypatch.setenv("HAPTIC_TOKEN", TOKEN)
        summary = await run_client(
            ClientOptions(url=url, name="A", device="sim:rest", duration_s=3.0)
        )
        assert summary["joins"] >= 1 and summary["server_errors"] == []
    finally:
        await app.stop()


async def test_a_page_from_another_origin_cannot_join():
    app = await start()
    url = f"ws://127.0.0.1:{app.port}/ws"
    try:
        with pytest.raises(InvalidStatus) as info:
            async with connect(url, origin="http://evil.example"):  # type: ignore[arg-type]
                pass
        assert info.value.response.status_code == 403
        # the page the server served itself, and non-browser clients (no Origin), join
        async with connect(url, origin=f"http://127.0.0.1:{app.port}") as ws:  # type: ignore[arg-type]
            await ws.send(hello("own"))
            assert json.loads(await ws.recv())["type"] == "welcome"
        assert app.status()["origins_refused"] == 1
    finally:
        await app.stop()


async def test_tls_serves_wss_and_https_and_the_client_verifies_with_its_ca_file(
    tmp_path, monkeypatch
):
    trustme = pytest.importorskip("trustme")
    ca = trustme.CA()
    cert = ca.issue_cert("127.0.0.1", "localhost")
    server_ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    cert.configure_cert(server_ctx)
    ca_file = tmp_path / "ca.pem"
    ca.cert_pem.write_to_path(str(ca_file))
    app = await start(auth=TokenTable.single(TOKEN), ssl_context=server_ctx)
    url = f"wss://127.0.0.1:{app.port}/ws"
    try:
        client_ctx = ssl.create_default_context(cafile=str(ca_file))
        status = await asyncio.to_thread(
            lambda: urllib.request.urlopen(
                f"https://127.0.0.1:{app.port}/status", context=client_ctx, timeout=10
            ).read()
        )
        assert json.loads(status)["tls"] is True
        with pytest.raises(ssl.SSLCertVerificationError):  # a client that does not trust the CA
            async with connect(url, open_timeout=10):
                pass
        monkeypatch.setenv("HAPTIC_TOKEN", TOKEN)
        monkeypatch.setenv("HAPTIC_CA_FILE", str(ca_file))
        summary = await run_client(
            ClientOptions(url=url, name="A", device="sim:rest", duration_s=3.0)
        )
        assert summary["joins"] >= 1 and summary["server_errors"] == []
    finally:
        await app.stop()


async def test_looping_sockets_from_one_address_do_not_lock_out_a_reconnecting_user():
    app = await start()
    url = f"ws://127.0.0.1:{app.port}/ws"
    stop = asyncio.Event()
    cycles = 0

    async def looper() -> None:  # connect, say nothing, hang up, again
        nonlocal cycles
        while not stop.is_set():
            with contextlib.suppress(OSError, ConnectionClosed, InvalidStatus, TimeoutError):
                async with connect(url, local_addr=ATTACKER, open_timeout=5) as ws:
                    cycles += 1
                    with contextlib.suppress(TimeoutError, ConnectionClosed):
                        await asyncio.wait_for(ws.recv(), 1.0)
            await asyncio.sleep(0.01)

    loopers = [asyncio.create_task(looper()) for _ in range(60)]
    try:
        for _ in range(600):  # the attack is under way: 60 connections made (however long)
            if cycles >= 60:
                break
            await asyncio.sleep(0.05)
        assert cycles >= 60, cycles  # the attack really ran
        before = cycles
        joined = []
        for _ in range(3):  # a user that reconnects three times: each join succeeds at once
            t0 = time.monotonic()
            async with connect(url, open_timeout=10) as ws:
                await ws.send(hello("good"))
                msg = json.loads(await asyncio.wait_for(ws.recv(), 10.0))
                joined.append((msg["type"], time.monotonic() - t0))
        assert [j[0] for j in joined] == ["welcome"] * 3, joined
        # and the attack went on around the joins: the loopers connect again after them (each
        # waits up to a second on a silent server, so the joins may all fall inside one round)
        for _ in range(600):
            if cycles > before:
                break
            await asyncio.sleep(0.05)
        assert cycles > before, (cycles, before)
        print("join times [s] under the attack:", [round(j[1], 3) for j in joined])
    finally:
        stop.set()
        await asyncio.gather(*loopers, return_exceptions=True)
        await app.stop()


async def test_padded_floods_from_one_address_do_not_cost_a_user_its_patch_rate():
    app = await start()
    url = f"ws://127.0.0.1:{app.port}/ws"
    pad = "x" * 15_000
    closes: list[str] = []

    async def flooder(i: int) -> None:  # legal frames at 380/s, each padded to 15 KB
        try:
            async with connect(url, local_addr=ATTACKER) as ws:
                await ws.send(hello(f"flood{i}"))
                await ws.recv()
                for k in range(4000):
                    await ws.send(json.dumps({"type": "ping", "id": k, "t_client_s": 0, "p": pad}))
                    await asyncio.sleep(1 / 380)
        except ConnectionClosed as exc:
            closes.append(exc.rcvd.reason if exc.rcvd else "")

    try:
        good, _ = await asyncio.gather(
            good_user(url, 5.0), asyncio.gather(*(flooder(i) for i in range(12)))
        )
        overruns = app.room.stats.overruns
    finally:
        await app.stop()
    assert len(closes) == 12  # every flooder was cut off
    assert every_tick(good, overruns) and good[-1] - good[0] > 3.0 * SIM_RATE


async def test_a_viewer_that_never_reads_is_dropped_and_a_user_keeps_its_rate():
    app = await start(subdivisions=4, send_timeout_s=2.0)
    url = f"ws://127.0.0.1:{app.port}/ws"
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.bind(ATTACKER)
    sock.setblocking(False)
    await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", app.port))
    try:
        async with connect(url, sock=sock, max_queue=1) as ws:  # reads nothing after hello
            await ws.send(hello("stuck", role="viewer"))
            good = await good_user(url, 6.0)  # meanwhile, 6 s of a normal user
            for _ in range(400):  # the stuck viewer is dropped (generous bound: 40 s)
                if not app.room.viewers:
                    break
                await asyncio.sleep(0.1)
            # by the send timeout or by the keepalive, whichever sees it first
            assert app.room.viewers == []
            overruns = app.room.stats.overruns
    finally:
        await app.stop()
    assert every_tick(good, overruns) and good[-1] - good[0] > 4.0 * SIM_RATE


async def test_a_send_that_never_completes_drops_the_consumer_after_the_send_timeout():
    """The send timeout itself, with a connection whose buffer never drains (no keepalive)."""
    app = ServerApp(Room(build_world(ServerOptions(subdivisions=2)), SIM_RATE), send_timeout_s=0.5)

    class Stuck:
        aborted = False

        class transport:  # noqa: N801 - stands in for the asyncio transport
            @staticmethod
            def abort() -> None:
                Stuck.aborted = True

        async def send(self, data: object) -> None:
            await asyncio.Event().wait()  # the peer never reads: drain never returns

    from haptic_collab.server.app import _Peer
    from haptic_collab.server.latency import LinkShaper
    from haptic_collab.shared.protocol import LinkConditions

    app.room.connect("v", 0.0, "10.0.0.1")
    app.room.receive("v", hello("v", role="viewer"), 0.0)
    peer = _Peer("v", Stuck(), LinkShaper(LinkConditions()), LinkShaper(LinkConditions()))  # type: ignore[arg-type]
    app._peers["v"] = peer
    sender = asyncio.create_task(app._sender(peer))
    app._dispatch(app.room.tick(1, 0.05))
    await asyncio.wait_for(sender, 10.0)  # returns once the timeout fired
    assert Stuck.aborted and app.send_timeouts == 1 and app.room.viewers == []


async def test_bye_closes_the_socket():
    app = await start()
    try:
        async with connect(f"ws://127.0.0.1:{app.port}/ws") as ws:
            await ws.send(hello("A"))
            await ws.recv()
            await ws.send('{"type":"bye"}')
            await asyncio.wait_for(ws.wait_closed(), 5.0)
            assert ws.close_code == 1000
        assert app.room.users == []
    finally:
        await app.stop()


async def test_a_49_n_push_out_of_contact_does_not_dent_the_balloon_or_shake_a_resting_user():
    app = await start()
    url = f"ws://127.0.0.1:{app.port}/ws"
    info = app.room.object_info
    top = np.array(info.top_m)
    side, side_n = np.array(info.side_m), np.array(info.side_normal)
    rest_top = float(app.room.world.vertices[:, 2].max())
    pen_b: list[tuple[float, float]] = []
    errors: list[str] = []
    t0 = time.monotonic()

    async def rester() -> None:  # B rests 2 mm into the side with an honest, stable P model
        async with connect(url) as ws:
            await ws.send(hello("B"))
            await ws.recv()
            probe = list(side - 0.002 * side_n)
            seq, patch = 0, None
            while time.monotonic() - t0 < 6.0:
                seq += 1
                e = patch["penetration_m"] if patch else 0.0
                f = list(50.0 * max(e, 0.0) * side_n)
                await ws.send(json.dumps({"type": "state", "seq": seq, "probe_m": probe,
                                          "force_n": f, "k_h": 50.0}))  # fmt: skip
                with contextlib.suppress(TimeoutError):
                    while True:
                        m = json.loads(await asyncio.wait_for(ws.recv(), 0.025))
                        if m["type"] == "patch":
                            patch = m
                            pen_b.append((time.monotonic() - t0, m["penetration_m"]))

    async def attacker() -> None:  # A: 0 <-> 49 N at 10 Hz, probe 1 mm above the top
        async with connect(url, local_addr=ATTACKER) as ws:
            await ws.send(hello("A"))
            await ws.recv()
            await asyncio.sleep(2.0)
            seq = 0
            while time.monotonic() - t0 < 6.0:
                seq += 1
                f = 49.0 if (seq // 2) % 2 else 0.0
                await ws.send(json.dumps({"type": "state", "seq": seq,
                                          "probe_m": list(top + [0, 0, 0.001]),
                                          "force_n": [0, 0, f], "k_h": 1e5, "i_gain": 1e7}))  # fmt: skip
                with contextlib.suppress(TimeoutError):
                    while True:
                        m = json.loads(await asyncio.wait_for(ws.recv(), 0.05))
                        if m["type"] == "error":
                            errors.append(m["code"])

    try:
        await asyncio.gather(rester(), attacker())
        dent = rest_top - float(app.room.world.vertices[:, 2].max())
    finally:
        await app.stop()
    before = [e for t, e in pen_b if 1.0 < t < 2.0]
    during = [e for t, e in pen_b if 2.5 < t < 6.0]
    assert before and during
    # B feels no change: its penetration moves by less than 0.1 mm (5 mN at 50 N/m)
    assert np.ptp(during) < 1e-4 and abs(np.mean(during) - np.mean(before)) < 1e-4
    assert dent < 1e-3  # the top is not dented (it was by 163 mm)
    assert errors and set(errors) == {"force_clamped"}
    assert app.room.clamp_counts.get("A", 0) > 10
