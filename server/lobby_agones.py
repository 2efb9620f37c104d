"""The lobby's Agones back end: one GameServerAllocation per room name (:mod:`server.lobby`).

:class:`AgonesAllocator` (``--agones-allocator URL``) posts a GameServerAllocation
(``allocation.agones.dev/v1``) to the allocator service's REST API (``POST
/gameserverallocation``, Agones' ``allocation.swagger.json``) with three selectors in order: a
server of the fleet whose ``rooms`` list holds the name, else an Allocated one with a free slot
in ``rooms``, else a Ready one; the allocation adds the name to the chosen server's ``rooms``
list (``lists.rooms.addValues``, which ignores a value already there).

The allocator matches selectors against a cache of the GameServers that lags their writes
(each allocator pod its own), so an allocation for a name just placed can miss its list entry.
The back end remembers each placement for :data:`REMEMBER_S` and answers a name asked again
within that from memory; across lobby replicas, each name's owner (:mod:`server.lobby_peers`)
is the only one that allocates it.
"""

from __future__ import annotations

import asyncio
import logging
import ssl
import time
from collections import OrderedDict
from collections.abc import Callable
from http import HTTPStatus
from typing import Any
from urllib.parse import urlsplit

from haptic_collab.server.lobby_backends import (
    BACKEND_TIMEOUT_S,
    LobbyError,
    Placement,
    _http_json,
    _in_pool,
    _timed_out,
)
from haptic_collab.server.urls import url_host

log = logging.getLogger("haptic.lobby")

#: The Agones list that names the rooms a GameServer runs (server/agones.py lists them).
ROOMS_LIST = "rooms"
#: Allocations retried when the allocator answers Contention (409) [attempts].
CONTENTION_RETRIES = 3
#: Time a placement is remembered and given again without asking the allocator [s]: longer
#: than the allocator's cache takes to see the name's list entry, short enough that a server
#: drained or gone is not handed out for long.
REMEMBER_S = 3.0
#: Placements remembered at most (the oldest are forgotten first).
REMEMBER_KEPT = 4096


def allocation_request(
    name: str,
    *,
    namespace: str = "default",
    match_labels: dict[str, str] | None = None,
    list_name: str = ROOMS_LIST,
) -> dict[str, Any]:
    """The GameServerAllocation request (allocator REST, ``allocationAllocationRequest``) that
    places room ``name``.

    Three ``gameServerSelectors``, tried in order by Agones: an Allocated server whose list
    ``list_name`` contains ``name``; an Allocated one with at least one free slot in that list;
    a Ready one. ``lists.<list_name>.addValues`` adds the name to whichever is chosen (Agones
    ignores a value already there), so the next request for the name matches the first
    selector. ``Packed`` scheduling fills Allocated servers before it takes a Ready one.
    int64 fields are decimal strings (proto3 JSON).

    Parameters
    ----------
    name : str
        A room name (:func:`server.urls.valid_room_name`).
    namespace : str
        The Kubernetes namespace of the fleet.
    match_labels : dict, optional
        Labels every selector requires, e.g. ``{"agones.dev/fleet": "haptic-collab"}``.
    list_name : str
        The Fleet's list of rooms (:data:`ROOMS_LIST`).

    Returns
    -------
    dict
        The request body.

    Source
    ------
    Agones ``pkg/allocation/go/allocation.swagger.json`` (v1.56) and the GameServerAllocation
    reference (``allocation.agones.dev/v1``: selectors, Counters and Lists actions).
    """
    labels = dict(match_labels or {})

    def selector(state: str, lists: dict[str, Any] | None) -> dict[str, Any]:
        sel: dict[str, Any] = {"gameServerState": state}
        if labels:
            sel["matchLabels"] = labels
        if lists is not None:
            sel["lists"] = {list_name: lists}
        return sel

    return {
        "namespace": namespace,
        "gameServerSelectors": [
            selector("ALLOCATED", {"containsValue": name}),
            selector("ALLOCATED", {"minAvailable": "1"}),
            selector("READY", None),
        ],
        "scheduling": "Packed",
        "lists": {list_name: {"addValues": [name]}},
    }


class AgonesAllocator:
    """The Agones back end: the allocator service's REST API (``POST /gameserverallocation``).

    Parameters
    ----------
    url : str
        The allocator service, ``https://HOST:PORT`` (the allocator speaks mutual TLS: give
        ``context`` with the client certificate), or ``http://`` for a stand-in.
    namespace : str
        The fleet's namespace.
    match_labels : dict, optional
        Labels every selector requires (e.g. the fleet's ``agones.dev/fleet``).
    port_name : str, optional
        The GameServer port clients use (default: the first port of the answer).
    scheme : {"ws", "wss"}
        What clients speak to the servers (``wss`` behind TLS).
    context : ssl.SSLContext, optional
        TLS context for the allocator (client certificate and CA).
    timeout_s : float
        Time to wait for the allocator [s].
    remember_s : float
        Time a placement is given again without asking the allocator [s] (:data:`REMEMBER_S`;
        0: ask every time).
    clock : callable
        Monotonic time [s] (``time.monotonic``).
    """

    def __init__(
        self,
        url: str,
        *,
        namespace: str = "default",
        match_labels: dict[str, str] | None = None,
        port_name: str | None = None,
        scheme: str = "ws",
        context: ssl.SSLContext | None = None,
        timeout_s: float = BACKEND_TIMEOUT_S,
        remember_s: float = REMEMBER_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        parts = urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            raise ValueError(f"the Agones allocator is https://HOST:PORT, got {url!r}")
        if scheme not in ("ws", "wss"):
            raise ValueError(f"scheme must be ws or wss, got {scheme!r}")
        self.url = url.rstrip("/")
        self.namespace = namespace
        self.match_labels = dict(match_labels or {})
        self.port_name = port_name
        self.scheme = scheme
        self.context = context
        self.timeout_s = float(timeout_s)
        #: The allocator's answers by HTTP status (``"200"``, ``"429"``, ...), ``"timeout"``
        #: (none within ``timeout_s``) and ``"unreachable"`` (the lobby's ``/metrics``).
        self.answers: dict[str, int] = {}
        self.remember_s = float(remember_s)
        self.clock = clock
        #: name -> (placement, when it was allocated [s, ``clock``]), oldest first.
        self._recent: OrderedDict[str, tuple[Placement, float]] = OrderedDict()

    def _count(self, outcome: str) -> None:
        self.answers[outcome] = self.answers.get(outcome, 0) + 1

    def describe(self) -> dict[str, Any]:
        return {"backend": "agones", "allocator": self.url, "namespace": self.namespace}

    def placement(self, name: str, answer: Any) -> Placement:
        """Where an ``allocationAllocationResponse`` says room ``name`` runs.

        Raises
        ------
        LobbyError
            502 when the answer has no address or no port (of ``port_name``).
        """
        if not isinstance(answer, dict):
            raise LobbyError(HTTPStatus.BAD_GATEWAY, "the allocator's answer is not an object")
        address = answer.get("address")
        ports = [p for p in answer.get("ports") or [] if isinstance(p, dict)]
        if self.port_name is not None:
            ports = [p for p in ports if p.get("name") == self.port_name]
        port = ports[0].get("port") if ports else None
        if not isinstance(address, str) or not address or not isinstance(port, int):
            raise LobbyError(
                HTTPStatus.BAD_GATEWAY, "the allocator's answer has no address or port"
            )
        values = ((answer.get("lists") or {}).get(ROOMS_LIST) or {}).get("values")
        if isinstance(values, list) and name not in values:
            log.warning(
                "allocated %s, but its rooms list lacks %r", answer.get("gameServerName"), name
            )
        host = f"{url_host(address)}:{port}"
        http = "https" if self.scheme == "wss" else "http"
        return Placement(
            f"{self.scheme}://{host}", f"{http}://{host}", str(answer.get("gameServerName", host))
        )

    async def place(self, name: str) -> Placement:
        """Allocate the server of room ``name`` (:func:`allocation_request`).

        Raises
        ------
        LobbyError
            503 when Agones has no server to allocate (429, ResourceExhausted), stays in
            contention (409, Aborted) after :data:`CONTENTION_RETRIES` tries or does not answer
            within ``timeout_s``; 502 when the allocator cannot be reached or answers
            otherwise. :attr:`answers` counts each answer.
        """
        now = self.clock()
        kept = self._recent.get(name)
        if kept is not None and now - kept[1] < self.remember_s:
            return kept[0]  # allocated moments ago: the allocator's cache may not show it yet
        placement = await self._allocate(name)
        self._recent.pop(name, None)
        self._recent[name] = (placement, self.clock())
        while len(self._recent) > REMEMBER_KEPT or (
            self._recent and now - next(iter(self._recent.values()))[1] >= self.remember_s
        ):
            self._recent.popitem(last=False)
        return placement

    async def _allocate(self, name: str) -> Placement:
        """One allocation for room ``name``, retried on contention (see :meth:`place`)."""
        body = allocation_request(name, namespace=self.namespace, match_labels=self.match_labels)
        for attempt in range(CONTENTION_RETRIES):
            try:
                code, answer = await _in_pool(
                    _http_json, "POST", self.url + "/gameserverallocation", body,
                    timeout_s=self.timeout_s, context=self.context,
                )  # fmt: skip
            except OSError as exc:
                self._count("timeout" if _timed_out(exc) else "unreachable")
                if _timed_out(exc):
                    log.error(
                        "the Agones allocator %s: no answer in %g s", self.url, self.timeout_s
                    )
                    raise LobbyError(
                        HTTPStatus.SERVICE_UNAVAILABLE,
                        f"the Agones allocator did not answer within {self.timeout_s:g} s; "
                        "try again",
                    ) from None
                log.error("the Agones allocator %s cannot be reached: %s", self.url, exc)
                raise LobbyError(
                    HTTPStatus.BAD_GATEWAY, "the Agones allocator cannot be reached"
                ) from None
            self._count(str(code))
            if code == 200:
                return self.placement(name, answer)
            if code == HTTPStatus.TOO_MANY_REQUESTS:  # ResourceExhausted: nothing to allocate
                raise LobbyError(
                    HTTPStatus.SERVICE_UNAVAILABLE, f"no game server free for room {name!r}"
                )
            if code != HTTPStatus.CONFLICT:  # Aborted: contention, try again
                break
            await asyncio.sleep(0.05 * (attempt + 1))
        log.error("the Agones allocator answered %s: %.200s", code, answer)
        if code == HTTPStatus.CONFLICT:
            raise LobbyError(HTTPStatus.SERVICE_UNAVAILABLE, "the allocator is busy; try again")
        raise LobbyError(HTTPStatus.BAD_GATEWAY, f"the Agones allocator answered {code}")
