"""``haptic lobby`` on Agones: each room name allocated once, through the allocator's REST API.

The lobby runs in this process against a stand-in allocator (tests/support/agones_allocator.py,
built from Agones' allocation swagger: it validates every request and answers as the allocator
does), never a mock of the lobby's own code. What a user notices: asking for a room gives the
address and port of the GameServer that runs it, the same one every time, with a token that
server accepts for that room; new rooms fill an allocated server's free slots before a Ready one
is taken; two users asking at once for a new room end up on one server.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
import urllib.error
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import pytest

from haptic_collab.cli import build_parser
from haptic_collab.server.lobby import AgonesAllocator, Lobby, allocation_request
from haptic_collab.server.security import MIN_SECRET_BYTES, check_room_token
from tests.support.agones_allocator import FLEET, Allocator, GameServer
from tests.support.agones_allocator import fleet as stand_in_fleet

SECRET = b"k" * MIN_SECRET_BYTES
ASKERS = ThreadPoolExecutor(16, thread_name_prefix="asker")


def fleet(n: int, capacity: int = 2) -> list[GameServer]:
    return stand_in_fleet(n, capacity)


async def ask(lobby: Lobby, path: str) -> tuple[int, dict[str, Any]]:
    def get() -> tuple[int, dict[str, Any]]:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{lobby.port}{path}", timeout=10) as r:
                return r.status, json.loads(r.read())
        except urllib.error.HTTPError as exc:
            return exc.code, json.loads(exc.read())

    return await asyncio.get_running_loop().run_in_executor(ASKERS, get)


class running:
    """A lobby on a free port with the Agones back end, for ``async with``."""

    def __init__(self, allocator_url: str) -> None:
        backend = AgonesAllocator(allocator_url, namespace="labs", match_labels=FLEET)
        self.lobby = Lobby(backend, SECRET, port=0)

    async def __aenter__(self) -> Lobby:
        await self.lobby.start()
        return self.lobby

    async def __aexit__(self, *exc: object) -> None:
        await self.lobby.stop()


async def test_a_room_is_allocated_once_and_found_again_on_the_same_server() -> None:
    with Allocator(fleet(3)) as alloc:
        async with running(alloc.url) as lobby:
            status, first = await ask(lobby, "/rooms/anatomy-1?role=user")
            assert status == 200, first
            assert first["url"] == "ws://127.0.0.1:7000/rooms/anatomy-1/ws"
            assert first["server"] == "haptic-collab-0"
            assert alloc.holding("anatomy-1") == ["haptic-collab-0"]
            assert alloc.state("haptic-collab-0") == "Allocated"
            # the token is for that room and role, signed with the shared secret
            entry = check_room_token(first["token"], SECRET, "anatomy-1", time.time())
            assert entry is not None and entry.role == "user"
            assert check_room_token(first["token"], SECRET, "anatomy-2", time.time()) is None
            assert first["expires"] > time.time() + 60
            assert first["viewer"].startswith("http://127.0.0.1:7000/rooms/anatomy-1/#token=")

            status, again = await ask(lobby, "/rooms/anatomy-1?role=viewer")
            assert status == 200 and again["url"] == first["url"]
            assert (
                check_room_token(again["token"], SECRET, "anatomy-1", time.time()).role == "viewer"
            )  # type: ignore[union-attr]
            # a second room fills the allocated server's free slot; a third takes a Ready one
            _, second = await ask(lobby, "/rooms/anatomy-2")
            _, third = await ask(lobby, "/rooms/anatomy-3")
            assert second["server"] == "haptic-collab-0" and third["server"] == "haptic-collab-1"
            assert alloc.holding("anatomy-1") == ["haptic-collab-0"]  # never listed twice
            assert alloc.state("haptic-collab-2") == "Ready"
    # every request the lobby sent is what the swagger describes
    assert alloc.calls and all(not c.errors for c in alloc.calls), [c.errors for c in alloc.calls]
    assert {c.body["namespace"] for c in alloc.calls} == {"labs"}


async def test_with_tls_on_the_game_port_users_get_wss_and_an_https_viewer() -> None:
    """``haptic lobby --public-scheme wss`` (deploy/lobby/statefulset.yaml, as the Fleet serves
    TLS): the URL and viewer page the user gets speak TLS to the allocated server."""
    args = build_parser().parse_args(
        ["lobby", "--token-secret-file", "unused", "--agones-allocator", "http://h:1"]
    )
    assert args.public_scheme == "ws"  # the default, as before
    with Allocator(fleet(1)) as alloc:
        backend = AgonesAllocator(alloc.url, namespace="labs", scheme="wss")
        lobby = Lobby(backend, SECRET, port=0)
        await lobby.start()
        try:
            status, answer = await ask(lobby, "/rooms/anatomy-1")
        finally:
            await lobby.stop()
    assert status == 200, answer
    assert answer["url"] == "wss://127.0.0.1:7000/rooms/anatomy-1/ws"
    assert answer["viewer"].startswith("https://127.0.0.1:7000/rooms/anatomy-1/#token=")


async def test_two_users_asking_at_once_for_a_new_room_end_on_one_server() -> None:
    body = allocation_request("new-room", match_labels=FLEET)
    # the stand-in matches on a lagging view, as the allocator's cache does: two requests sent
    # straight to it at once for a new name land on two servers
    with Allocator(fleet(3), lag_s=0.3) as alloc:

        def post() -> dict[str, Any]:
            req = urllib.request.Request(
                alloc.url + "/gameserverallocation",
                data=json.dumps(body).encode(),
                headers={"Content-Type": "application/json"},
                method="POST",
            )
            with urllib.request.urlopen(req, timeout=10) as r:
                return json.loads(r.read())

        straight = await asyncio.gather(*(asyncio.to_thread(post) for _ in range(2)))
        assert {a["gameServerName"] for a in straight} == {"haptic-collab-0", "haptic-collab-1"}
        assert len(alloc.holding("new-room")) == 2
    # through the lobby, requests for one name wait for each other: one server
    with Allocator(fleet(3), lag_s=0.3) as alloc:
        async with running(alloc.url) as lobby:
            answers = await asyncio.gather(*(ask(lobby, "/rooms/new-room") for _ in range(4)))
            assert [s for s, _ in answers] == [200] * 4
            assert len({a["url"] for _, a in answers}) == 1
            assert alloc.holding("new-room") == ["haptic-collab-0"]
            assert alloc.state("haptic-collab-1") == "Ready"
            # other names are not held up behind it: each is placed on its own
            _, other = await ask(lobby, "/rooms/other-room")
            assert other["server"] == "haptic-collab-0"


async def test_no_game_server_free_is_a_clear_503_and_no_allocator_a_502() -> None:
    full = fleet(1, capacity=1)
    full[0].state, full[0].lists["rooms"]["values"] = "Allocated", ["taken"]
    with Allocator(full) as alloc:
        async with running(alloc.url) as lobby:
            status, answer = await ask(lobby, "/rooms/lab")
            assert status == 503 and "no game server free" in answer["error"]
            assert alloc.calls[-1].status == 429  # ResourceExhausted, as the allocator says it
            status, answer = await ask(lobby, "/rooms/taken")  # the one it runs: found
            assert status == 200 and answer["server"] == "haptic-collab-0"
    async with running(alloc.url) as lobby:  # the allocator is gone
        status, answer = await ask(lobby, "/rooms/lab")
        assert status == 502 and "cannot be reached" in answer["error"]
        assert (await ask(lobby, "/healthz"))[0] == 200  # and the lobby is still up


@pytest.mark.parametrize(
    ("address", "ports", "why"),
    [(None, [{"name": "default", "port": 7000}], "no address"), ("10.0.0.1", [], "no port")],
)
def test_an_allocation_without_an_address_or_port_is_a_bad_gateway(address, ports, why) -> None:
    backend = AgonesAllocator("http://127.0.0.1:1")
    with pytest.raises(Exception, match="no address or port") as info:
        backend.placement("lab", {"gameServerName": "gs", "address": address, "ports": ports})
    assert info.value.status == 502, why  # type: ignore[attr-defined]


async def test_the_lobby_speaks_the_allocators_mutual_tls(tmp_path) -> None:
    """``haptic lobby --agones-allocator https://... --agones-ca --agones-client-cert/-key``:
    an allocator that requires a client certificate allocates for the lobby; a lobby without
    the certificate is refused and says so (502), and keeps serving."""
    import ssl

    trustme = pytest.importorskip("trustme")
    from haptic_collab.cli import build_parser
    from haptic_collab.cli.run import _lobby_backend

    ca = trustme.CA()
    server_ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ca.issue_cert("127.0.0.1").configure_cert(server_ctx)
    server_ctx.verify_mode = ssl.CERT_REQUIRED
    ca.configure_trust(server_ctx)
    client = ca.issue_cert("haptic-lobby")
    files = {"ca": tmp_path / "ca.pem", "cert": tmp_path / "c.pem", "key": tmp_path / "k.pem"}
    ca.cert_pem.write_to_path(str(files["ca"]))
    client.cert_chain_pems[0].write_to_path(str(files["cert"]))
    client.private_key_pem.write_to_path(str(files["key"]))
    with Allocator(fleet(2), tls=server_ctx) as alloc:
        base = ["lobby", "--token-secret-file", "x", "--agones-allocator", alloc.url,
                "--agones-ca", str(files["ca"]), "--agones-fleet", "haptic-collab"]  # fmt: skip
        with_cert = [*base, "--agones-client-cert", str(files["cert"]),
                     "--agones-client-key", str(files["key"])]  # fmt: skip
        for argv, want in ((with_cert, 200), (base, 502)):
            backend = _lobby_backend(build_parser().parse_args(argv))
            lobby = Lobby(backend, SECRET, port=0)
            await lobby.start()
            try:
                status, answer = await ask(lobby, "/rooms/lab")
                assert status == want, answer
                if want == 200:
                    assert answer["url"] == "ws://127.0.0.1:7000/rooms/lab/ws"
                else:
                    assert "cannot be reached" in answer["error"]
                    assert (await ask(lobby, "/healthz"))[0] == 200
            finally:
                await lobby.stop()
    assert [c.body["gameServerSelectors"][0]["matchLabels"] for c in alloc.calls] == [FLEET]


class RoomServers:
    """Two room servers with tokens and a template for any name (as deploy/agones/ runs them),
    each with its stand-in sidecar and agent, the allocator's fleet backed by those sidecars."""

    def __init__(self, max_rooms: int, max_users: int) -> None:
        from haptic_collab.server.main import ServerOptions

        self.opts = ServerOptions(
            port=0, sim_rate_hz=20.0, subdivisions=1, max_rooms=max_rooms, max_users=max_users
        )
        self.apps: list[Any] = []
        self.agents: list[Any] = []
        self.sidecars: list[Any] = []

    async def __aenter__(self) -> RoomServers:
        from haptic_collab.server.agones import PORT_ENV, AgonesOptions, start_agones
        from haptic_collab.server.app import DEFAULT_ROOM, ServerApp
        from haptic_collab.server.main import RoomTemplates, build_link, build_room
        from tests.support.agones_sidecar import Sidecar

        opts, link = self.opts, build_link(self.opts)
        fast = AgonesOptions(
            empty_shutdown_s=None, health_period_s=0.5, probe_timeout_s=0.5, poll_s=0.05
        )
        for _ in range(2):
            templates = RoomTemplates(opts, {"any": {}}, link, None, SECRET)
            app = ServerApp(
                build_room(opts, DEFAULT_ROOM, {}, link, None, SECRET),
                "127.0.0.1",
                0,
                room_maker=templates,
                room_admits=templates.admits,
                max_rooms=opts.max_rooms,
                room_idle_s=0.5,
            )
            await app.start()
            self.apps.append(app)
            assert opts.max_users is not None
            sc = Sidecar(
                lists={"rooms": opts.max_rooms},
                counters={"users": opts.max_rooms * opts.max_users},
            ).__enter__()
            self.sidecars.append(sc)
            agent = start_agones(app.room_reports, fast, {PORT_ENV: str(sc.port)})
            assert agent is not None
            app.room_gate = lambda name, a=agent: asyncio.to_thread(a.claim_room, name)
            self.agents.append(agent)
        return self

    def fleet(self) -> list[GameServer]:
        return [
            GameServer(f"haptic-collab-{i}", port=app.port, labels=dict(FLEET), sidecar=sc)
            for i, (app, sc) in enumerate(zip(self.apps, self.sidecars, strict=True))
        ]

    async def __aexit__(self, *exc: object) -> None:
        for agent in self.agents:
            await asyncio.to_thread(agent.stop)
        for app in self.apps:
            await app.stop()
        for sc in self.sidecars:
            sc.__exit__()


async def join(answer: dict[str, Any]) -> Any:
    """A user who asked the lobby joins with its token; the open websocket once welcomed."""
    from websockets.asyncio.client import connect

    ws = await connect(answer["url"])
    await ws.send(
        json.dumps(
            {"type": "hello", "protocol": 1, "role": "user", "name": "u", "token": answer["token"]}
        )
    )
    got = json.loads(await asyncio.wait_for(ws.recv(), 30.0))
    assert got["type"] == "welcome", got
    return ws


async def test_a_full_server_sends_the_next_name_elsewhere_and_a_closed_room_frees_its_slot():
    """Capacity is one number: a server of 3 rooms (the default one and 2 made on demand) is
    filled through the lobby and the allocator, the next name goes to the other server, and
    once a room closes its slot takes a new name; nobody is answered 503."""

    async def place(name: str) -> dict[str, Any]:
        status, answer = await ask(lobby, f"/rooms/{name}")
        assert status == 200, answer
        return answer

    async with RoomServers(max_rooms=3, max_users=2) as rs:
        a, b = rs.apps
        for sc in rs.sidecars:  # Ready, with the default room listed
            ready = lambda sc=sc: sc.state == "Ready" and sc.lists["rooms"]["values"]  # noqa: E731
            assert await asyncio.to_thread(sc.wait, ready)
        with Allocator(rs.fleet()) as alloc, contextlib.ExitStack():
            backend = AgonesAllocator(alloc.url, match_labels=FLEET)
            lobby = Lobby(backend, SECRET, port=0)
            await lobby.start()
            users = []
            try:
                for name in ("anatomy-1", "anatomy-2"):
                    answer = await place(name)
                    assert answer["server"] == "haptic-collab-0", answer
                    users.append(await join(answer))
                assert sorted(a.rooms()) == ["anatomy-1", "anatomy-2", "default"]
                # full: 3 rooms, 3 names listed; the next name goes to the other server
                answer = await place("anatomy-3")
                assert answer["server"] == "haptic-collab-1", answer
                users.append(await join(answer))
                assert "anatomy-3" in b.rooms()
                # anatomy-1 empties and closes: its slot is free again for a new name
                await users.pop(0).close()
                sc0 = rs.sidecars[0]
                closed = lambda: "anatomy-1" not in sc0.lists["rooms"]["values"]  # noqa: E731
                assert await asyncio.to_thread(sc0.wait, closed)
                answer = await place("anatomy-4")
                assert answer["server"] == "haptic-collab-0", answer
                users.append(await join(answer))
                assert sorted(a.rooms()) == ["anatomy-2", "anatomy-4", "default"]
                assert all(c.status == 200 for c in alloc.calls)
            finally:
                for ws in users:
                    await ws.close()
                await lobby.stop()
