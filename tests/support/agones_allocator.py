"""A stand-in for Agones' allocator service (REST), built from Agones' allocation swagger file.

No Kubernetes cluster or Agones allocator can run here, so the lobby's tests start this one: an
HTTP server on loopback that serves ``POST /gameserverallocation`` of
tests/data/agones/allocation.swagger.json (copied unchanged from Agones v1.56, Apache-2.0: see
tests/data/agones/LICENSE). It validates every request body against the swagger's
``allocationAllocationRequest`` (jsonschema, draft 4 as Swagger 2.0 uses, int64 values as decimal
strings, unknown properties refused as in tests/support/agones_sidecar.py), answers an
``allocationAllocationResponse`` (checked against the swagger too) and records every call.

What it does with a request follows the GameServerAllocation reference
(``allocation.agones.dev/v1``):

- ``gameServerSelectors`` are tried in order; a selector matches a GameServer of its
  ``gameServerState`` (``READY`` by default, or ``ALLOCATED``) whose labels hold its
  ``matchLabels`` and whose lists pass its list selectors (``containsValue``; ``minAvailable``
  and ``maxAvailable`` on capacity less values, 0 meaning no maximum);
- the chosen GameServer becomes Allocated, and ``lists.NAME.addValues`` are appended (a value
  already there is ignored, values past the capacity are dropped);
- nothing matches: HTTP 429 with the gRPC status ResourceExhausted (8), "there is no available
  GameServer to allocate", as grpc-gateway maps it.

Two readings of how the real allocator behaves, both documented Agones behaviour, make races
visible: the selectors are matched against the GameServers as they were when the request
arrived (the allocator matches against its informer cache, which lags), ``lag_s`` before the
allocation is written; and a Ready GameServer is never handed to two allocations (the write is
checked against the GameServer's version: the loser takes the next Ready one). So two requests
for a new name that arrive together land on two servers unless the caller serialises them.
Among several matches the first in the stand-in's order is taken (``Packed`` on one node).

A GameServer may be backed by a stand-in sidecar (``GameServer.sidecar``,
tests/support/agones_sidecar.py), as a real GameServer's status is what its SDK sidecar wrote:
its state and lists are then read from that sidecar, and an allocation is written to it
(:meth:`Sidecar.allocate`), so the room server's own list updates and the allocations meet in
one place, as in a cluster.

:class:`LaggingCacheAllocator` adds a third reading: a cache that lags the writes themselves.
"""

from __future__ import annotations

import copy
import json
import ssl
import threading
import time
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import jsonschema

from tests.support.agones_sidecar import _FORMATS, DATA, Sidecar, _strict

RESOURCE_EXHAUSTED = 8
INVALID_ARGUMENT = 3


@dataclass
class GameServer:
    """One GameServer of the stand-in fleet (its status as the allocator sees it)."""

    name: str
    port: int
    address: str = "127.0.0.1"
    state: str = "Ready"  #: Ready or Allocated
    labels: dict[str, str] = field(default_factory=dict)
    lists: dict[str, dict[str, Any]] = field(default_factory=dict)  #: {capacity, values}
    version: int = 0  #: bumped at every write (Kubernetes' resourceVersion)
    #: The stand-in sidecar whose state and lists this GameServer's are (None: its own).
    sidecar: Sidecar | None = None

    def refresh(self) -> None:
        """Read the state and lists from the sidecar, when backed by one."""
        sc = self.sidecar
        if sc is None:
            return
        with sc._cond:
            self.state = sc.state
            self.lists = copy.deepcopy(sc.lists)


@dataclass
class Call:
    """One request the stand-in received, and what it answered."""

    t: float  #: time.monotonic() on arrival [s]
    path: str
    body: Any
    status: int = 0
    answer: Any = None
    errors: list[str] = field(default_factory=list)  #: schema violations of the request


def _spec() -> dict[str, Any]:
    return json.loads((DATA / "allocation.swagger.json").read_text())


#: The Fleet label every stand-in GameServer of :func:`fleet` carries (deploy/agones/fleet.yaml's).
FLEET = {"agones.dev/fleet": "haptic-collab"}


def fleet(n: int, capacity: int) -> list[GameServer]:
    """``n`` Ready GameServers ``haptic-collab-0..n-1`` on ports 7000+i, labelled :data:`FLEET`,
    each with an empty ``rooms`` list of ``capacity``."""
    return [
        GameServer(
            f"haptic-collab-{i}",
            port=7000 + i,
            labels=dict(FLEET),
            lists={"rooms": {"capacity": capacity, "values": []}},
        )
        for i in range(n)
    ]


class Allocator:
    """The stand-in allocator on ``127.0.0.1:port`` (0: a free port); a context manager.

    Parameters
    ----------
    servers : list of GameServer
        The fleet.
    lag_s : float
        Time from a request's arrival (when its selectors are matched) to the allocation's write.
    tls : ssl.SSLContext, optional
        Serve https with it (the allocator speaks mutual TLS: a context that requires a client
        certificate refuses a caller without one).
    """

    def __init__(
        self,
        servers: list[GameServer],
        lag_s: float = 0.0,
        port: int = 0,
        tls: ssl.SSLContext | None = None,
    ) -> None:
        spec = _spec()
        op = spec["paths"]["/gameserverallocation"]["post"]
        (param,) = [p for p in op["parameters"] if p["in"] == "body"]
        self._request_schema = {
            **_strict(param["schema"]),
            "definitions": _strict(spec["definitions"]),
        }
        self._answer_schema = {
            **op["responses"]["200"]["schema"],
            "definitions": spec["definitions"],
        }
        self.servers = servers
        self.lag_s = float(lag_s)
        self.calls: list[Call] = []
        self._lock = threading.Lock()
        allocator = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args: Any) -> None:  # quiet
                pass

            def do_POST(self) -> None:
                allocator._serve(self)

            def do_GET(self) -> None:
                allocator._reply(self, 404, {"code": 5, "message": "Not Found", "details": []})

        self._http = ThreadingHTTPServer(("127.0.0.1", port), Handler)
        self._http.daemon_threads = True
        if tls is not None:
            self._http.socket = tls.wrap_socket(self._http.socket, server_side=True)
        self.port = int(self._http.server_address[1])
        self.url = f"{'https' if tls is not None else 'http'}://127.0.0.1:{self.port}"

    def __enter__(self) -> Allocator:
        threading.Thread(target=self._http.serve_forever, daemon=True).start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._http.shutdown()
        self._http.server_close()

    # ------------------------------------------------------------------ for the tests
    def holding(self, value: str, list_name: str = "rooms") -> list[str]:
        """The GameServers whose list holds ``value``."""
        with self._lock:
            return [
                s.name
                for s in self.servers
                if value in s.lists.get(list_name, {}).get("values", [])
            ]

    def state(self, name: str) -> str:
        with self._lock:
            return next(s.state for s in self.servers if s.name == name)

    # ------------------------------------------------------------------ serving
    @staticmethod
    def _reply(h: BaseHTTPRequestHandler, status: int, answer: Any) -> None:
        data = json.dumps(answer).encode()
        h.send_response(status)
        h.send_header("Content-Type", "application/json")
        h.send_header("Content-Length", str(len(data)))
        h.end_headers()
        h.wfile.write(data)

    def _serve(self, h: BaseHTTPRequestHandler) -> None:
        length = int(h.headers.get("Content-Length") or 0)
        raw = h.rfile.read(length) if length else b""
        call = Call(time.monotonic(), h.path.split("?", 1)[0], None)
        with self._lock:
            self.calls.append(call)
        if call.path != "/gameserverallocation":
            call.status, call.answer = 404, {"code": 5, "message": "Not Found", "details": []}
            call.errors.append("no such path in the swagger file")
            return self._reply(h, call.status, call.answer)
        try:
            call.body = json.loads(raw)
        except ValueError:
            call.errors.append("the body is not JSON")
        else:
            v = jsonschema.Draft4Validator(self._request_schema, format_checker=_FORMATS)
            call.errors += [e.message for e in v.iter_errors(call.body)]
        if call.errors:
            call.status = 400
            call.answer = {
                "code": INVALID_ARGUMENT,
                "message": "; ".join(call.errors),
                "details": [],
            }
            return self._reply(h, call.status, call.answer)
        view = self._view()  # the informer's view when the request arrives
        chosen = self._match(call.body, view)
        if self.lag_s:
            time.sleep(self.lag_s)
        with self._lock:
            answer = self._write(call.body, chosen)
        if answer is None:
            call.status = 429
            call.answer = {
                "code": RESOURCE_EXHAUSTED,
                "message": "there is no available GameServer to allocate",
                "details": [],
            }
        else:
            jsonschema.Draft4Validator(self._answer_schema, format_checker=_FORMATS).validate(
                answer
            )
            call.status, call.answer = 200, answer
        self._reply(h, call.status, call.answer)

    def _view(self) -> list[GameServer]:
        """The GameServers as the selectors see them: as they are now (one backed by a sidecar
        as that sidecar last wrote it)."""
        with self._lock:
            for gs in self.servers:
                gs.refresh()
            view = [copy.copy(gs) for gs in self.servers]
            for gs in view:
                gs.lists = copy.deepcopy(gs.lists)
            return view

    @staticmethod
    def _passes(sel: dict[str, Any], gs: GameServer) -> bool:
        want = {"READY": "Ready", "ALLOCATED": "Allocated"}[sel.get("gameServerState", "READY")]
        if gs.state != want:
            return False
        if any(gs.labels.get(k) != v for k, v in (sel.get("matchLabels") or {}).items()):
            return False
        for name, ls in (sel.get("lists") or {}).items():
            lst = gs.lists.get(name)
            if lst is None:
                return False
            values, available = lst["values"], lst["capacity"] - len(lst["values"])
            if ls.get("containsValue") and ls["containsValue"] not in values:
                return False
            if available < int(ls.get("minAvailable", "0")):
                return False
            top = int(ls.get("maxAvailable", "0"))
            if top and available > top:
                return False
        return True

    def _match(self, body: dict[str, Any], view: list[GameServer]) -> tuple[str, str] | None:
        """(GameServer name, selector state) of the first selector that matches, in the view."""
        for sel in body.get("gameServerSelectors") or [{}]:
            for gs in view:
                if self._passes(sel, gs):
                    return gs.name, sel.get("gameServerState", "READY")
        return None

    def _write(self, body: dict[str, Any], chosen: tuple[str, str] | None) -> dict[str, Any] | None:
        if chosen is None:
            return None
        name, state = chosen
        for server in self.servers:
            server.refresh()
        gs = next(s for s in self.servers if s.name == name)
        if state == "READY" and gs.state != "Ready":  # taken meanwhile: the next Ready one
            sel = next(
                s
                for s in body.get("gameServerSelectors") or [{}]
                if s.get("gameServerState", "READY") == "READY"
            )
            gs = next((s for s in self.servers if self._passes(sel, s)), None)  # type: ignore[assignment]
            if gs is None:
                return None
        if gs.sidecar is not None:  # the sidecar holds the GameServer's status
            adds = {n: list(a.get("addValues") or []) for n, a in (body.get("lists") or {}).items()}
            gs.sidecar.allocate({n: v for n, v in adds.items() if n in gs.sidecar.lists})
            gs.refresh()
        gs.state = "Allocated"
        for lname, action in (body.get("lists") or {}).items():
            lst = gs.lists.get(lname)
            if lst is None:
                continue
            for value in action.get("addValues") or []:
                if value not in lst["values"] and len(lst["values"]) < lst["capacity"]:
                    lst["values"].append(value)
        gs.version += 1
        return {
            "gameServerName": gs.name,
            "ports": [{"name": "default", "port": gs.port}],
            "address": gs.address,
            "addresses": [{"type": "InternalIP", "address": gs.address}],
            "nodeName": "stand-in-node",
            "source": "local",
            "metadata": {"labels": dict(gs.labels), "annotations": {}},
            "lists": {
                n: {"values": list(v["values"]), "capacity": str(v["capacity"])}
                for n, v in gs.lists.items()
            },
        }


# ------------------------------------------------------------ an informer that lags the writes
class LaggingCacheAllocator(Allocator):
    """The stand-in with a cache that lags the writes by ``cache_lag_s``, as an allocator pod's
    informer does (and another pod's more so): a request is matched against the GameServers as
    they were ``cache_lag_s`` before it arrived, so an allocation that follows another for the
    same name within that time does not see its list entry. (:class:`Allocator`'s ``lag_s`` is
    the other race: two requests matched against one view.) Used by the lobby's tests; the
    interface is :class:`Allocator`'s, with ``cache_lag_s`` [s] added.
    """

    def __init__(self, servers: list[GameServer], cache_lag_s: float, **kw: Any) -> None:
        super().__init__(servers, **kw)
        self.cache_lag_s = float(cache_lag_s)
        #: (time.monotonic() of a write, the fleet after it), oldest first
        self._history: list[tuple[float, list[GameServer]]] = [
            (-float("inf"), copy.deepcopy(servers))
        ]

    def _view(self) -> list[GameServer]:
        seen = time.monotonic() - self.cache_lag_s
        with self._lock:
            return copy.deepcopy([v for t, v in self._history if t <= seen][-1])

    def _write(self, body: dict[str, Any], chosen: tuple[str, str] | None) -> dict[str, Any] | None:
        answer = super()._write(body, chosen)  # called under the lock
        if answer is not None:
            self._history.append((time.monotonic(), copy.deepcopy(self.servers)))
        return answer
