"""Agones: the server as a GameServer, through the SDK sidecar's REST gateway.

Agones (agones.dev) runs game servers on Kubernetes; each pod has an SDK sidecar that the game
server tells when it is ready, that it is healthy, and when it is done. This module speaks the
sidecar's REST gateway, plain HTTP and JSON on ``localhost:$AGONES_SDK_HTTP_PORT``, with the
standard library (no Agones package). The contract is Agones' own OpenAPI files
(``sdk.swagger.json`` and ``beta.swagger.json``; copies in tests/data/agones/):

=========================================  =======  =========================================
path                                       method   body
=========================================  =======  =========================================
``/ready``, ``/health``, ``/allocate``,    POST     ``{}`` (``sdkEmpty``)
``/shutdown``
``/metadata/label``                        PUT      ``{"key": K, "value": V}`` (``sdkKeyValue``)
``/gameserver``                            GET      (answers ``sdkGameServer``)
``/v1beta1/lists/{name}:addValue``         POST     ``{"value": V}`` (``SDKAddListValueBody``)
``/v1beta1/lists/{name}:removeValue``      POST     ``{"value": V}`` (``SDKRemoveListValueBody``)
``/v1beta1/counters/{name}``               PATCH    the ``CounterUpdateRequest`` itself:
                                                    ``{"count": "3"}`` (int64 as a string)
=========================================  =======  =========================================

The counter's PATCH body is the request's fields, not an object wrapping them: the swagger
file marks ``counterUpdateRequest`` as required inside that body schema, which is how the
gRPC gateway's generator writes a body bound to one field (``body: "counter_update_request"``),
not a property to send. The count is set (``count``), never incremented (``countDiff``), so a
call repeated after a lost answer cannot count a user twice.

:class:`AgonesAgent` runs in two threads of its own, off the simulation's event loop, and reads
the rooms through a probe it schedules on that loop (:meth:`server.app.ServerApp.room_reports`).
A probe that gets no answer within ``probe_timeout_s`` means the loop is blocked. The agent:

1. waits until every room has ticked, then calls Ready, retrying with backoff (the sidecar may
   start after the server);
2. sets its labels (``/metadata/label``; Agones prefixes them ``agones.dev/sdk-``);
3. keeps the name of every open room (the default one, the configured ones and those made on
   demand, empty or not, until it closes) in the list ``rooms``, whose capacity is the rooms the
   process may run (``haptic server --max-rooms``), so the list's free capacity is the rooms
   this server can still open, which a FleetAutoscaler's List policy keeps a buffer of and the
   allocator's ``minAvailable`` selects on. A room made on demand is put in the list before it
   is built (:meth:`AgonesAgent.claim_room`, the app's ``room_gate``): a full list refuses the
   room (503) with one log line, never a retry. Every ``list_check_s`` it also reads the list as
   Agones holds it (GET ``/gameserver``, ``status.lists.rooms.values``) and removes a name that
   has not been an open room for ``stale_room_grace_s`` (:data:`STALE_ROOM_GRACE_S`) since it
   first saw it so: the lobby's allocation lists a room's name before its first user arrives
   (``lists.rooms.addValues``, :mod:`server.lobby`), and a name whose user never came would
   otherwise hold a slot of the list until the server shuts down;
4. keeps the counter ``users`` at the number of users in all rooms, and on the first arrival at
   a server that is only Ready calls Allocate (people who came straight to its address, past any
   allocator), so that a scale-down never deletes it under them. A count past the counter's
   capacity is said once (the Fleet's capacity must be what the server admits), not retried;
5. calls Health every ``health_period_s`` from a thread that does nothing else (a slow list
   update never delays a ping), from its start, before Ready, while the server builds its rooms
   (``start_grace_s``), then while the process can serve: its event loop answers the probe and
   at least one room ticks. A room that is late or whose process is being restarted
   (:data:`server.room_process.HANG_S`) is logged, not held against the whole GameServer:
   Agones would delete every room with it;
6. calls Shutdown once the server has been empty (no user, no viewer) for ``empty_shutdown_s``
   after someone was in it, or after the GameServer was Allocated (a fresh Ready server waiting
   in the fleet is never shut down for being empty).

The sidecar refuses list and counter calls with plain Go errors, which its REST gateway answers
as HTTP 500 with the error's text (:data:`REFUSALS`, :attr:`SidecarError.kind`): "already
exists" is success for an add, "not found" for a remove.

Sources: Agones' SDK reference (agones.dev/site/docs/guides/client-sdks/, "REST"), the
swagger files named above, and the SDK server's source (pkg/sdkserver/sdkserver.go, Apache-2.0;
excerpts in tests/data/agones/sdkserver-errors.md).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import logging
import math
import os
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

log = logging.getLogger("haptic.agones")

#: The environment variable Agones sets to the sidecar's REST port.
PORT_ENV = "AGONES_SDK_HTTP_PORT"
#: The Agones list holding the names of the rooms this server runs.
ROOMS_LIST = "rooms"
#: The Agones counter holding the number of users in all rooms.
USERS_COUNTER = "users"
#: Default time [s] the server may stay empty before it asks to be shut down.
EMPTY_SHUTDOWN_S = 300.0
#: Time [s] a name in the ``rooms`` list may go without being a room in use before the agent
#: removes it: long enough for a user the lobby sent (it lists the name at allocation) to
#: arrive and join, short beside a session, so a slot a user never took is soon free again.
STALE_ROOM_GRACE_S = 60.0
#: Time [s] between two reads of the ``rooms`` list as Agones holds it (GET ``/gameserver``).
LIST_CHECK_S = 5.0
#: Time [s] from the agent's start during which it sends health pings before Ready: a FEM
#: server took 30 s to build its solid and listen on a loaded machine, and Agones checks health
#: from the Fleet's ``initialDelaySeconds``.
START_GRACE_S = 300.0


#: What a refusal of a list or counter call means, by the start of the SDK server's error text
#: (:attr:`SidecarError.kind`). Source: Agones' pkg/sdkserver/sdkserver.go (``GetList``,
#: ``AddListValue``, ``RemoveListValue``, ``UpdateCounter``; excerpts and licence in
#: tests/data/agones/sdkserver-errors.md): these are plain Go errors, which the REST gateway
#: answers as HTTP 500 (gRPC Unknown) with the text as ``message``, not as 409/404/400.
REFUSALS = (
    ("list not found", "undeclared"),
    ("counter not found", "undeclared"),
    ("already exists", "exists"),
    ("not found", "absent"),
    ("out of range", "full"),
)


class SidecarError(Exception):
    """The sidecar answered with an error, or could not be reached (``status`` 0).

    Attributes
    ----------
    status : int
        The HTTP status: 500 for the SDK server's own refusals (plain Go errors, gRPC
        Unknown), 400 for an invalid argument, 0 when no answer came.
    detail : str
        The gRPC status message of the answer (the Go error's text); "" without one.
    kind : str
        What the refusal means (:data:`REFUSALS`): ``"undeclared"`` (no such list or counter in
        the GameServer), ``"exists"`` (a value already in the list), ``"absent"`` (a value not
        in the list), ``"full"`` (a list at capacity, or a count outside [0, capacity]); ""
        for anything else.
    """

    def __init__(self, status: int, message: str, detail: str = "") -> None:
        super().__init__(message)
        self.status = status
        self.detail = detail
        text = detail.strip().lower()
        self.kind = next((kind for start, kind in REFUSALS if text.startswith(start)), "")


class AgonesSDK:
    """The SDK sidecar's REST gateway: one blocking HTTP call per method.

    Parameters
    ----------
    port : int
        The sidecar's REST port (``$AGONES_SDK_HTTP_PORT``).
    host : str
        Where the sidecar listens: ``localhost`` in an Agones pod.
    timeout_s : float
        Time allowed for each call [s].

    Raises
    ------
    ValueError
        A port outside 1..65535 or a timeout that is not > 0.
    """

    def __init__(self, port: int, host: str = "localhost", timeout_s: float = 2.0) -> None:
        if not 0 < int(port) < 65536:
            raise ValueError(f"{PORT_ENV} must be a port in 1..65535, got {port}")
        if not timeout_s > 0:
            raise ValueError("timeout_s must be > 0")
        self.base = f"http://{host}:{int(port)}"
        self.timeout_s = float(timeout_s)

    @classmethod
    def from_environ(cls, environ: Mapping[str, str] | None = None) -> AgonesSDK | None:
        """The sidecar named by ``$AGONES_SDK_HTTP_PORT``; None when it is not set or empty.

        Raises
        ------
        ValueError
            A value that is not a port number.
        """
        env = os.environ if environ is None else environ
        text = env.get(PORT_ENV, "").strip()
        if not text:
            return None
        try:
            port = int(text)
        except ValueError:
            raise ValueError(f"{PORT_ENV} must be a port number, got {text!r}") from None
        return cls(port)

    def call(self, method: str, path: str, body: dict[str, Any] | None = None) -> dict[str, Any]:
        """One call: ``method`` on ``path`` with the JSON ``body``; returns the JSON answer.

        Raises
        ------
        SidecarError
            An HTTP error status (its gRPC status message in the text), no answer, or an
            answer that is not a JSON object.
        """
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(self.base + path, data=data, method=method)
        req.add_header("Accept", "application/json")
        if data is not None:
            req.add_header("Content-Type", "application/json")
        try:
            with urllib.request.urlopen(req, timeout=self.timeout_s) as resp:
                raw = resp.read()
        except urllib.error.HTTPError as exc:
            detail = exc.read(2000).decode("utf-8", "replace")
            try:
                detail = str(json.loads(detail).get("message", detail))
            except (ValueError, AttributeError):
                pass
            raise SidecarError(
                exc.code, f"{method} {path}: HTTP {exc.code}: {detail}", detail
            ) from None
        except (urllib.error.URLError, OSError) as exc:
            reason = getattr(exc, "reason", exc)
            raise SidecarError(0, f"{method} {path}: no answer: {reason}") from None
        try:
            answer = json.loads(raw or b"{}")
        except ValueError:
            raise SidecarError(200, f"{method} {path}: an answer that is not JSON") from None
        if not isinstance(answer, dict):
            raise SidecarError(200, f"{method} {path}: an answer that is not a JSON object")
        return answer

    def ready(self) -> None:
        """Ready: the server accepts connections (POST ``/ready``)."""
        self.call("POST", "/ready", {})

    def health(self) -> None:
        """One health ping (POST ``/health``)."""
        self.call("POST", "/health", {})

    def allocate(self) -> None:
        """Mark this GameServer Allocated (POST ``/allocate``)."""
        self.call("POST", "/allocate", {})

    def shutdown(self) -> None:
        """Ask Agones to shut this server down (POST ``/shutdown``)."""
        self.call("POST", "/shutdown", {})

    def set_label(self, key: str, value: str) -> None:
        """Label the GameServer ``agones.dev/sdk-KEY: VALUE`` (PUT ``/metadata/label``)."""
        self.call("PUT", "/metadata/label", {"key": key, "value": value})

    def game_server(self) -> dict[str, Any]:
        """The GameServer as the sidecar sees it (GET ``/gameserver``; ``status.state``...)."""
        return self.call("GET", "/gameserver")

    def add_list_value(self, name: str, value: str) -> dict[str, Any]:
        """Add ``value`` to the list ``name``; the list after it.

        Raises
        ------
        SidecarError
            ``kind`` "full" for a list at capacity (checked first, so also for a value already
            in a full list), "exists" for a value already there, "undeclared" for no such list.
        """
        return self.call("POST", f"/v1beta1/lists/{_segment(name)}:addValue", {"value": value})

    def remove_list_value(self, name: str, value: str) -> dict[str, Any]:
        """Remove ``value`` from the list ``name``; the list after it.

        Raises
        ------
        SidecarError
            ``kind`` "absent" for a value not in the list, "undeclared" for no such list.
        """
        return self.call("POST", f"/v1beta1/lists/{_segment(name)}:removeValue", {"value": value})

    def set_counter(self, name: str, count: int) -> dict[str, Any]:
        """Set the counter ``name`` to ``count`` (PATCH with a ``CounterUpdateRequest``).

        Returns the counter after it. int64 values travel as strings (proto3 JSON).

        Raises
        ------
        SidecarError
            ``kind`` "full" for a count outside [0, capacity], "undeclared" for no such counter.
        """
        return self.call("PATCH", f"/v1beta1/counters/{_segment(name)}", {"count": str(int(count))})


def _segment(name: str) -> str:
    return urllib.parse.quote(name, safe="")


class _RoomReport(Protocol):
    """What the agent reads of a room (:class:`server.app.RoomReport`)."""

    @property
    def name(self) -> str: ...
    @property
    def ticks(self) -> int: ...
    @property
    def alive(self) -> bool: ...
    @property
    def users(self) -> int: ...
    @property
    def viewers(self) -> int: ...


@dataclass
class AgonesOptions:
    """How the agent behaves (times in seconds).

    Attributes
    ----------
    health_period_s : float
        Time between health pings (the Fleet's ``health.periodSeconds`` must be at least this).
    empty_shutdown_s : float or None
        Shut down after the server has been empty this long (None: never).
    probe_timeout_s : float
        A probe of the event loop unanswered this long means the loop is blocked.
    poll_s : float
        Time between two looks at the rooms (list and counter follow within it).
    ready_backoff_s : tuple of float
        First and largest wait between Ready attempts; the wait doubles between them.
    labels : dict of str to str
        Labels to set once Ready (without Agones' ``agones.dev/sdk-`` prefix).
    stale_room_grace_s : float
        A name in the ``rooms`` list that is not an open room is removed once the agent has
        seen it so for this long (:data:`STALE_ROOM_GRACE_S`).
    list_check_s : float
        Time between two reads of the ``rooms`` list from the sidecar (:data:`LIST_CHECK_S`).
    start_grace_s : float
        Health pings go out from the agent's start, before Ready, while the server builds its
        rooms and starts listening (:data:`START_GRACE_S`); a server not Ready this long after
        the start gets none until it is (Agones then marks it Unhealthy and replaces it).
    max_rooms, max_users : int or None
        The rooms the server may run (``--max-rooms``) and the users it admits in all of them
        (``haptic server``'s rooms' caps summed): once Ready the agent reads the capacities of
        the ``rooms`` list and the ``users`` counter and says (once) where they differ, since
        the fleet then allocates to this server rooms or users it refuses, or never sends it
        those it could take. None: not checked.
    """

    health_period_s: float = 2.0
    empty_shutdown_s: float | None = EMPTY_SHUTDOWN_S
    probe_timeout_s: float = 1.0
    poll_s: float = 0.25
    ready_backoff_s: tuple[float, float] = (0.25, 8.0)
    labels: dict[str, str] = field(default_factory=dict)
    stale_room_grace_s: float = STALE_ROOM_GRACE_S
    list_check_s: float = LIST_CHECK_S
    start_grace_s: float = START_GRACE_S
    max_rooms: int | None = None
    max_users: int | None = None


class AgonesAgent:
    """Tells the Agones sidecar what the server's rooms are doing; two threads of its own.

    One thread sends the health pings and nothing else, so that no other call to the sidecar
    (a slow list update, a Ready retry) delays them; the other calls Ready and keeps the labels,
    the ``rooms`` list, the ``users`` counter and the shutdown.

    Parameters
    ----------
    sdk : AgonesSDK
        The sidecar.
    loop : asyncio.AbstractEventLoop
        The event loop the rooms run on; ``probe`` is called on it.
    probe : callable
        Returns a report per room (:meth:`server.app.ServerApp.room_reports`); called on
        ``loop``'s thread only. An empty sequence means no room yet (the server is starting).
    options : AgonesOptions
    clock : callable
        Monotonic time [s] (``time.monotonic``).

    Attributes
    ----------
    state : str
        ``starting``, ``ready`` or ``shutdown``.
    ready_attempts, health_sent, health_withheld : int
        Ready calls tried, health pings sent (before Ready included), health periods in which
        no ping was sent because the server could not serve (its event loop blocked, or no room
        alive).
    stale_removed : int
        Names the agent removed from the ``rooms`` list as stale (listed by someone else,
        never or no longer an open room).
    refused_rooms : int
        Rooms :meth:`claim_room` refused because the ``rooms`` list was full.
    """

    def __init__(
        self,
        sdk: AgonesSDK,
        loop: asyncio.AbstractEventLoop,
        probe: Callable[[], Sequence[_RoomReport]],
        options: AgonesOptions | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.sdk = sdk
        self.loop = loop
        self.probe = probe
        self.options = options or AgonesOptions()
        self.clock = clock
        self.state = "starting"
        self.ready_attempts = 0
        self.health_sent = 0
        self.health_withheld = 0
        self.stale_removed = 0
        self.refused_rooms = 0
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._started_at = clock()
        self._listed: set[str] = set()
        self._unlistable: set[str] = set()
        self._labelled: set[str] = set()
        self._users_reported: int | None = None
        self._occupied = False
        self._allocated = False
        self._empty_since: float | None = None
        self._next_allocated_check = -float("inf")
        self._undeclared: set[str] = set()
        self._warned: dict[str, float] = {}
        self._unused_since: dict[str, float] = {}
        self._next_list_check = -float("inf")
        self._late_said: frozenset[str] = frozenset()

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Start the agent's two threads (daemons: they never hold the process up)."""
        self._started_at = self.clock()
        for target, name in ((self._run_health, "agones-health"), (self._run, "agones")):
            thread = threading.Thread(target=target, name=name, daemon=True)
            self._threads.append(thread)
            thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the threads and wait for them (at most ``timeout_s`` [s] each); blocking."""
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout_s)

    # ------------------------------------------------------------------ the rooms
    def look(self) -> list[_RoomReport] | None:
        """The rooms' reports, read on the event loop; None when the loop did not answer
        within ``probe_timeout_s`` (blocked) or is closed."""
        fut: concurrent.futures.Future[list[_RoomReport]] = concurrent.futures.Future()

        def run() -> None:
            if not fut.set_running_or_notify_cancel():
                return
            try:
                fut.set_result(list(self.probe()))
            except BaseException as exc:  # noqa: BLE001 - handed to the waiting thread
                fut.set_exception(exc)

        try:
            self.loop.call_soon_threadsafe(run)
        except RuntimeError:  # the loop is closed
            return None
        try:
            return fut.result(timeout=self.options.probe_timeout_s)
        except concurrent.futures.TimeoutError:
            fut.cancel()
            return None
        except Exception:
            log.exception("reading the rooms failed")
            return None

    def claim_room(self, name: str) -> str | None:
        """Put room ``name`` in the ``rooms`` list before the server opens it; blocking.

        Call it from a worker thread (:meth:`server.app.ServerApp` does, as its
        ``room_gate``) before an on-demand room is built: the list's capacity is the rooms the
        server may run (``--max-rooms``), so a room the list has no slot for is refused here
        instead of running unlisted (the allocator would go on sending names to this server).

        Returns
        -------
        str or None
            None when the room may open: the name is in the list now (added, or already there:
            the lobby's allocation lists it first), or the list cannot be asked (no sidecar
            answer, no ``rooms`` list declared: the server's own ``--max-rooms`` still holds);
            else why not (the list is full), for the refusal's text.
        """
        if ROOMS_LIST in self._undeclared:
            return None
        try:
            self.sdk.add_list_value(ROOMS_LIST, name)
        except SidecarError as exc:
            if exc.kind == "exists":
                return None
            if exc.kind == "undeclared":
                self._undeclared.add(ROOMS_LIST)
                log.warning("Agones: the GameServer declares no %r list (%s)", ROOMS_LIST, exc)
                return None
            if exc.kind != "full":
                self._warn(exc)
                return None
            if name in self._listed_values():  # full, with this name in it (the allocation's)
                return None
            self.refused_rooms += 1
            log.warning(
                "Agones: room %r refused: the %r list is full (%s); the fleet sees this server "
                "as full, as it is",
                name, ROOMS_LIST, exc.detail,
            )  # fmt: skip
            return f"the {ROOMS_LIST!r} list of this GameServer is full"
        return None

    # ------------------------------------------------------------------ the threads
    def _run_health(self) -> None:
        """Health pings every ``health_period_s``, from the start: before Ready (within
        ``start_grace_s``) and after it while the server can serve (:meth:`_can_serve`)."""
        try:
            period = self.options.health_period_s
            withholding = False
            while not self._stop.is_set() and self.state != "shutdown":
                began = self.clock()
                why = self._cannot_serve()
                if why is None:
                    if self._try(self.sdk.health):
                        self.health_sent += 1
                    if withholding:
                        log.info("Agones: the server can serve again, health pings resumed")
                    withholding = False
                else:
                    self.health_withheld += 1
                    if not withholding:
                        log.warning("Agones: no health ping: %s", why)
                    withholding = True
                self._stop.wait(max(0.0, period - (self.clock() - began)))
        except Exception:  # the agent must never take the server down
            log.exception("the Agones health thread stopped")

    def _cannot_serve(self) -> str | None:
        """Why the server cannot serve now, or None when it can.

        Starting (not Ready yet): it can within ``start_grace_s`` of the start, whatever its
        event loop does (building a FEM solid holds it for seconds). Ready: its event loop
        answers a probe within ``probe_timeout_s`` and at least one room ticks; a room that is
        late or restarting is logged but does not stop the pings, so one room's trouble never
        has every room of the GameServer deleted.
        """
        if self.state == "starting":
            waited = self.clock() - self._started_at
            if waited < self.options.start_grace_s:
                return None
            return f"not Ready {waited:.0f} s after the start"
        reports = self.look()
        if reports is None:
            return "the event loop is blocked (no answer)"
        late = frozenset(r.name for r in reports if not r.alive)
        if late != self._late_said and late and len(late) < len(reports):
            log.warning(
                "Agones: rooms %s late or restarting; the others serve, health pings go on",
                ", ".join(sorted(late)),
            )
        self._late_said = late  # said once per set of late rooms (this thread only)
        if not reports or len(late) == len(reports):
            return "no room ticks: " + _stalled(reports)
        return None

    def _run(self) -> None:
        try:
            if self._await_ticking() and self._ready():
                self._serve()
        except Exception:  # the agent must never take the server down
            log.exception("the Agones agent stopped")

    def _await_ticking(self) -> bool:
        """Wait until every room has ticked and is alive; False when stopped first."""
        while not self._stop.is_set():
            reports = self.look()
            if reports and all(r.ticks > 0 and r.alive for r in reports):
                return True
            self._stop.wait(self.options.poll_s)
        return False

    def _ready(self) -> bool:
        """Call Ready until it is taken, with doubling waits; False when stopped first."""
        first, most = self.options.ready_backoff_s
        wait = first
        while not self._stop.is_set():
            self.ready_attempts += 1
            try:
                self.sdk.ready()
            except SidecarError as exc:
                if self.ready_attempts == 1 or self.ready_attempts % 10 == 0:
                    log.warning(
                        "Agones Ready not taken yet (attempt %d): %s", self.ready_attempts, exc
                    )
                self._stop.wait(wait)
                wait = min(most, wait * 2.0)
                continue
            self.state = "ready"
            log.info("Agones: Ready (after %d attempts)", self.ready_attempts)
            self._check_capacities()
            return True
        return False

    def _check_capacities(self) -> None:
        """Say once where the GameServer's ``rooms`` list and ``users`` counter capacities are
        not what this server runs (``max_rooms``, ``max_users`` of the options)."""
        want = {
            (ROOMS_LIST, "lists", "--max-rooms"): self.options.max_rooms,
            (
                USERS_COUNTER,
                "counters",
                "--max-rooms x each room's max_users",
            ): self.options.max_users,
        }
        if all(v is None for v in want.values()):
            return
        try:
            status = self.sdk.game_server().get("status")
        except SidecarError as exc:
            self._warn(exc)
            return
        for (name, kind, what), expected in want.items():
            group = status.get(kind) if isinstance(status, dict) else None
            entry = group.get(name) if isinstance(group, dict) else None
            if expected is None or not isinstance(entry, dict):
                continue
            try:
                capacity = int(entry.get("capacity"))  # type: ignore[arg-type]
            except (TypeError, ValueError):
                continue
            if capacity != expected:
                log.warning(
                    "Agones: the %r %s has capacity %d but this server takes %d (%s): capacity "
                    "must be one number (docs/rooms-operations.md)",
                    name, kind[:-1], capacity, expected, what,
                )  # fmt: skip

    def _serve(self) -> None:
        while not self._stop.is_set() and self.state == "ready":
            reports = self.look()
            if reports is not None:
                self._sync(reports, self.clock())
            if self.state == "ready":
                self._stop.wait(self.options.poll_s)

    def _sync(self, reports: Sequence[_RoomReport], now: float) -> None:
        """Labels, the rooms list, the users counter and the empty timer from one look."""
        for key, value in self.options.labels.items():
            if key not in self._labelled and self._try(self.sdk.set_label, key, value):
                self._labelled.add(key)
        names = {r.name for r in reports}  # every open room, empty or not
        if ROOMS_LIST not in self._undeclared:
            for name in sorted(names - self._listed - self._unlistable):
                self._list(name)
            for name in sorted(self._listed - names):
                if self._try(
                    self.sdk.remove_list_value, ROOMS_LIST, name, ok=("absent",), declares=True
                ):
                    self._listed.discard(name)
                    self._unlistable.clear()  # a slot is free: try those again
            self._unlistable &= names
            if now >= self._next_list_check:
                self._next_list_check = now + self.options.list_check_s
                self._prune_list(names, now)
        users = sum(r.users for r in reports)
        if USERS_COUNTER not in self._undeclared and users != self._users_reported:
            try:
                self.sdk.set_counter(USERS_COUNTER, users)
            except SidecarError as exc:
                if exc.kind == "full":  # said once per count: no retry until the count changes
                    self._users_reported = users
                    log.warning(
                        "Agones: the %r counter cannot hold %d users (%s): its capacity in the "
                        "Fleet must be the users the server admits (docs/rooms-operations.md)",
                        USERS_COUNTER, users, exc.detail,
                    )  # fmt: skip
                elif exc.kind == "undeclared":
                    self._undeclare(USERS_COUNTER, exc)
                else:
                    self._warn(exc)
            else:
                self._users_reported = users
        # empty from when the sidecar has heard so (after this report's calls): Shutdown comes
        # at least empty_shutdown_s after the last change of the users counter it recorded
        self._empty_timer(reports, self.clock())

    def _list(self, name: str) -> None:
        """Add open room ``name`` to the ``rooms`` list (already there: done; the list full
        without it: said once, not asked again until a slot is freed)."""
        try:
            self.sdk.add_list_value(ROOMS_LIST, name)
        except SidecarError as exc:
            if exc.kind == "exists":
                self._listed.add(name)
            elif exc.kind == "undeclared":
                self._undeclare(ROOMS_LIST, exc)
            elif exc.kind == "full":
                if name in self._listed_values():
                    self._listed.add(name)
                    return
                self._unlistable.add(name)
                log.warning(
                    "Agones: room %r is open but the %r list is full (%s): not listed, not "
                    "asked again until a room closes; --max-rooms and the list's capacity in "
                    "the Fleet must be one number (docs/rooms-operations.md)",
                    name, ROOMS_LIST, exc.detail,
                )  # fmt: skip
            else:
                self._warn(exc)
        else:
            self._listed.add(name)

    def _listed_values(self) -> set[str]:
        """The ``rooms`` list's values as the sidecar holds them (GET ``/gameserver``); empty
        when it cannot be read."""
        try:
            gs = self.sdk.game_server()
        except SidecarError as exc:
            self._warn(exc)
            return set()
        status = gs.get("status")
        lists = status.get("lists") if isinstance(status, dict) else None
        entry = lists.get(ROOMS_LIST) if isinstance(lists, dict) else None
        values = entry.get("values") if isinstance(entry, dict) else None
        return {v for v in values or [] if isinstance(v, str)}

    def _prune_list(self, open_rooms: set[str], now: float) -> None:
        """Remove the names of the ``rooms`` list (as the sidecar holds it) that have not been
        open rooms for ``stale_room_grace_s`` since this agent first saw them so."""
        got: list[dict[str, Any]] = []
        if not self._try(lambda: got.append(self.sdk.game_server())):
            return
        status = got[0].get("status")
        lists = status.get("lists") if isinstance(status, dict) else None
        entry = lists.get(ROOMS_LIST) if isinstance(lists, dict) else None
        values = entry.get("values") if isinstance(entry, dict) else None
        listed = {v for v in values or [] if isinstance(v, str)}
        unused = listed - open_rooms
        for name in set(self._unused_since) - unused:  # open now, or gone from the list
            del self._unused_since[name]
        for name in sorted(unused):
            since = self._unused_since.setdefault(name, now)
            if now - since < self.options.stale_room_grace_s:
                continue
            if self._try(self.sdk.remove_list_value, ROOMS_LIST, name, ok=("absent",)):
                del self._unused_since[name]
                self._listed.discard(name)
                self._unlistable.clear()
                self.stale_removed += 1
                log.info(
                    "Agones: room %r listed but not open for %g s; removed from %r",
                    name, now - since, ROOMS_LIST,
                )  # fmt: skip

    def _empty_timer(self, reports: Sequence[_RoomReport], now: float) -> None:
        limit = self.options.empty_shutdown_s
        empty = all(r.users == 0 and r.viewers == 0 for r in reports)
        if not empty:
            if not (self._occupied or self._allocated) and self._try(self.sdk.allocate):
                # people came straight to a Ready server: Allocated, so that the fleet does
                # not scale it down under them
                self._allocated = True
                log.info("Agones: someone joined a Ready server, Allocate")
            self._occupied = True
            self._empty_since = None
            return
        if limit is None:
            return
        if not (self._occupied or self._allocated):
            # a Ready server waits in the fleet for players: empty only counts once Allocated
            # (asked at most once a health period)
            if now < self._next_allocated_check:
                return
            self._next_allocated_check = now + self.options.health_period_s
            try:
                state = self.sdk.game_server().get("status", {}).get("state")
            except SidecarError:
                state = None
            self._allocated = state == "Allocated"
            if not self._allocated:
                return
        if self._empty_since is None:
            self._empty_since = now
            log.info("Agones: the server is empty; Shutdown in %g s unless someone joins", limit)
        if now - self._empty_since >= limit and self._try(self.sdk.shutdown):
            self.state = "shutdown"
            log.info("Agones: empty for %g s, Shutdown", now - self._empty_since)

    def _undeclare(self, what: str, exc: SidecarError) -> None:
        self._undeclared.add(what)
        log.warning("Agones: the GameServer declares no %r (%s); not asked again", what, exc)

    def _warn(self, exc: SidecarError) -> None:
        """Log a failed call, the same failure at most once a minute (the agent retries)."""
        now = self.clock()
        key = str(exc) if exc.status else "unreachable"
        if now - self._warned.get(key, -math.inf) >= 60.0:
            self._warned[key] = now
            log.warning("Agones: %s", exc)

    def _try(
        self, fn: Callable[..., Any], *args: Any, ok: tuple[str, ...] = (), declares: bool = False
    ) -> bool:
        """Call the sidecar; True when it took the call (or refused it as a ``kind`` in ``ok``).

        With ``declares``, an "undeclared" refusal (the GameServer has no such list or counter:
        the Fleet's ``lists``/``counters``) is said once and the list is never asked again.
        """
        try:
            fn(*args)
        except SidecarError as exc:
            if exc.kind and exc.kind in ok:
                return True
            if declares and exc.kind == "undeclared":
                self._undeclare(ROOMS_LIST, exc)
                return False
            self._warn(exc)
            return False
        return True


def _stalled(reports: Sequence[_RoomReport]) -> str:
    names = ", ".join(r.name for r in reports if not r.alive)
    return f"stalled or stopped (rooms {names})" if names else "without rooms"


def start_agones(
    probe: Callable[[], Sequence[_RoomReport]],
    options: AgonesOptions | None = None,
    environ: Mapping[str, str] | None = None,
) -> AgonesAgent | None:
    """Start an :class:`AgonesAgent` when ``$AGONES_SDK_HTTP_PORT`` is set; call on the loop.

    Parameters
    ----------
    probe : callable
        The rooms' reports (:meth:`server.app.ServerApp.room_reports`).
    options : AgonesOptions, optional
    environ : mapping, optional
        The environment (default ``os.environ``).

    Returns
    -------
    AgonesAgent or None
        The running agent; None when the variable is not set (not under Agones).

    Raises
    ------
    ValueError
        A variable that is not a port number.
    """
    sdk = AgonesSDK.from_environ(environ)
    if sdk is None:
        return None
    agent = AgonesAgent(sdk, asyncio.get_running_loop(), probe, options)
    agent.start()
    log.info("Agones: SDK sidecar at %s", sdk.base)
    return agent
