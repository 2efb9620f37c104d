"""The client's network link: websockets only. Joins the room, pumps frames, reconnects.

All protocol decisions are in :class:`client.session.ClientSession`; this module connects, sends
``hello``, sends the servo loop's latest ``state`` every half simulation period (latest wins: an old
state is never queued behind a new one) and a ``ping`` twice a second, hands each patch to the servo
loop through ``on_patch``, and reconnects with exponential backoff when the server goes away. The
servo loop never waits on any of this: when the link falls silent it ramps its forces to zero by its
own timeout.

Two worker processes (:class:`DesignWorkers`; ``haptic client`` forks them first thing, before
it has other threads, so they start with the design code imported) keep the numerical work off
the event loop: one runs gain designs (a second or more each, then the likely next cells) at low
priority, the other the short checks of interim gains (:func:`shared.gains.interim.interim_design`,
about 0.1 s) at normal priority, so a check is never queued behind a design. After each design
or check the checker verifies gains for the neighbouring cells and one more tick of delay ahead
of need. Spawned workers (a link started without them, after other threads exist) import the
design code first; the check a first contact waits for then runs in a thread of this process
rather than waiting for that.

Rejoin: a link that hears nothing from the server for ``silent_s`` (2 s; patches come 20 times
a second and pongs twice) is taken for dead and dropped, as one that closes: a network cut sends
no close, and TCP would wait much longer. The next ``hello`` carries the resume token of the last
``welcome`` (:attr:`client.session.ClientSession.resume_token`), so a rejoin within the server's
hold time (30 s) gets the same seat back: user id, name and contact. Meanwhile the servo has
ramped its forces to zero by its own link timeout (0.25 s); it ramps them back up from zero
(over ``ServoConfig.ramp_s``) once the first patch after the rejoin arrives, so the force does
not step.

Security: the link presents a token in ``hello`` (``token=`` or the ``HAPTIC_TOKEN`` environment
variable) and never logs it; a ``wss://`` URL is verified against the system's CAs or ``ca_file``
(``HAPTIC_CA_FILE``). A server that answers ``unauthorized`` is not retried: :meth:`Link.run`
raises ``ValueError``.

A lobby (``haptic client --lobby URL --room NAME``, :mod:`server.lobby`): the link is given a
``resolve`` coroutine that asks the lobby where the room runs and for a room token, and calls it
before its first join and again before each later attempt once the server said it is draining
(``server_draining``, close code 1012), refused the connection or the token, or could not be
reached: the room may now run on another server. The next ``hello`` still carries the resume
token; a server that does not hold the seat (another server) joins the user as new. A lobby
that cannot be reached then leaves the link on the address it had.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import multiprocessing
import os
import random
import ssl
import threading
from collections.abc import Awaitable, Callable
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass

from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidURI

from haptic_collab.client.session import ClientSession, ServoSample, warm_up_worker
from haptic_collab.client.workers import background_worker, check_worker, stop_pool, timed
from haptic_collab.shared.gains.choose import PLANE_ALONE, likely_next, table_design
from haptic_collab.shared.gains.design import GainDesign
from haptic_collab.shared.gains.interim import interim_design
from haptic_collab.shared.gains.key import GainKey
from haptic_collab.shared.gains.table import design_cell
from haptic_collab.shared.gains.verified_plane import plane_against, verified_plane
from haptic_collab.shared.local_model_update import LocalModelUpdate
from haptic_collab.shared.protocol import ProtocolError, Welcome

log = logging.getLogger("haptic.client")

PING_INTERVAL_S = 0.5
#: No frame from the server for this long [s] after the welcome: the link is dead (a network
#: cut closes nothing), drop it and rejoin. Four pongs and forty patches would have come.
SILENT_LINK_S = 2.0
#: No ``welcome`` within this long [s] of opening: drop the connection and try again.
WELCOME_TIMEOUT_S = 5.0
#: Environment variables read when no token or CA file is given.
TOKEN_ENV = "HAPTIC_TOKEN"
CA_FILE_ENV = "HAPTIC_CA_FILE"


@dataclass
class DesignWorkers:
    """The link's two worker processes: gain designs and checks ahead of need (niced), and the
    checks a contact waits for (normal priority), each one process with one job at a time.

    Built with :meth:`start`. While the client process has a single thread (``haptic client``
    starts them first thing, right after the servo process) they are forked: they start with
    the design code already imported, so even a first contact's check runs in a worker at once,
    never in the link's process. Otherwise they are spawned (forking a process whose other
    threads may hold locks is unsafe) and import the design code while the client joins.

    Attributes
    ----------
    design, check : ProcessPoolExecutor
        The two pools.
    check_warm : Future
        Done once the check worker can take a check (at once when forked).
    """

    design: Executor
    check: Executor
    check_warm: Future[None]

    @classmethod
    def start(cls) -> DesignWorkers:
        """Start both workers now.

        Raises
        ------
        RuntimeError, OSError
            They could not be started (e.g. spawned from a script without a ``__main__`` guard).
        """
        fork = threading.active_count() == 1 and "fork" in multiprocessing.get_all_start_methods()
        ctx = multiprocessing.get_context("fork" if fork else "spawn")
        # the check worker first: forked while this process still has one thread (the design
        # pool's fork comes after the check pool's manager thread started; it touches nothing
        # of that pool)
        check = ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=check_worker)
        warm = check.submit(warm_up_worker)
        design = ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=background_worker)
        design.submit(warm_up_worker)
        return cls(design=design, check=check, check_warm=warm)


class Unauthorized(Exception):
    """The server refused this client's token (``unauthorized``): retrying cannot help."""


#: ``resolve()`` of a link with a lobby: the room's websocket URL and a token for it.
Resolver = Callable[[], Awaitable[tuple[str, str | None]]]
#: Close codes after which a link with a lobby asks it again: 1012 (service restart: a draining
#: server, or a room process restarting) and 1013 (try again later: a room closed meanwhile).
REASK_CLOSE_CODES = frozenset({1012, 1013})


class Link:
    """Runs one session over a websocket until ``stop`` is set.

    Parameters
    ----------
    url : str
        ``ws://HOST:PORT/ws``.
    session : ClientSession
        Protocol state.
    on_patch : callable(LocalModelUpdate, float)
        Called with each new patch and the local time [s] it arrived (hand it to the servo loop).
    sample : callable() -> ServoSample or None
        The servo loop's latest sample (None: nothing to report yet).
    clock : callable() -> float
        Monotonic clock [s], the same one the servo loop uses.
    on_welcome : callable(Welcome), optional
        Called on every (re)join.
    backoff_s : (float, float)
        First and largest reconnect delay [s].
    design_executor : Executor, optional
        Where gain designs and checks ahead of need run (default: one worker process at low
        priority, started with the link, so a design never holds the event loop or the servo
        thread's interpreter lock).
    check_executor : Executor, optional
        Where the interim gains a contact waits for are checked (default: a second worker
        process, at normal priority; with a
        ``design_executor`` given and no ``check_executor``, the design executor).
    token : str, optional
        Sent in ``hello`` (default: ``$HAPTIC_TOKEN``; none when unset or empty).
    ca_file : str, optional
        PEM file of the CA that signed a ``wss://`` server's certificate (default:
        ``$HAPTIC_CA_FILE``, else the system's CAs).
    workers : DesignWorkers, optional
        Worker processes started earlier (:meth:`DesignWorkers.start`, forked before the client
        had other threads); the link uses them as its own and stops them on close. Default:
        started with the link. Ignored with a ``design_executor``.
    silent_s : float
        No frame from the server for this long [s] after the welcome (:data:`SILENT_LINK_S`):
        the link is dropped and rejoined (with the resume token, so the seat is kept).
    resolve : coroutine function, optional
        Asks a lobby where the room runs now: returns its websocket URL and a room token
        (:func:`client.app.lobby_resolver`). Called before the first join and before each attempt
        after a drain, a refusal or a failure to connect; raises ``ValueError`` when the lobby
        refuses (the link then stops) or ``ConnectionError`` when it cannot answer (the link
        keeps the URL it had, or waits when it has none). ``url`` and ``token`` are then only
        the starting values.
    """

    def __init__(
        self,
        url: str,
        session: ClientSession,
        *,
        on_patch: Callable[[LocalModelUpdate, float], None],
        sample: Callable[[], ServoSample | None],
        clock: Callable[[], float],
        on_welcome: Callable[[Welcome], None] | None = None,
        backoff_s: tuple[float, float] = (0.2, 5.0),
        design_executor: Executor | None = None,
        check_executor: Executor | None = None,
        token: str | None = None,
        ca_file: str | None = None,
        workers: DesignWorkers | None = None,
        silent_s: float = SILENT_LINK_S,
        resolve: Resolver | None = None,
    ) -> None:
        self.url = url
        self.resolve = resolve
        #: Answers of the lobby (``resolve``) the link has used, and the URLs it has joined, in
        #: order (a link moved by a drain lists two servers).
        self.lobby_asks = 0
        self.joined_urls: list[str] = []
        self._reask = resolve is not None
        self.silent_s = float(silent_s)
        #: Links dropped because the server fell silent (:attr:`silent_s`).
        self.silent_drops = 0
        #: Joins that got the seat of the session before back (``welcome.resumed``), and the
        #: user id of every join, in order.
        self.resumes = 0
        self.user_ids: list[str] = []
        self._last_rx_s = -float("inf")
        self._workers = workers
        self._token = token if token is not None else (os.environ.get(TOKEN_ENV) or None)
        self.ca_file = ca_file if ca_file is not None else (os.environ.get(CA_FILE_ENV) or None)
        self.session = session
        self.on_patch = on_patch
        self.sample = sample
        self.clock = clock
        self.on_welcome = on_welcome
        self.backoff_s = backoff_s
        self.connected = asyncio.Event()
        self.joins = 0
        #: Connection attempts refused (nothing listening), and the last failure, for the
        #: message when no join comes (client.app).
        self.refused = 0
        self.last_error: str | None = None
        self.protocol_errors = 0
        self.designs = 0
        self.checks = 0
        self._executor = design_executor
        self._checker = check_executor if check_executor is not None else design_executor
        self._own_executor = False
        self._design_task: asyncio.Task[None] | None = None
        self._plane_task: asyncio.Task[None] | None = None
        #: Verified planes checked (:func:`shared.gains.verified_plane.verified_plane`).
        self.plane_checks = 0
        self._check_task: asyncio.Task[None] | None = None
        self._first_pool: ThreadPoolExecutor | None = None
        # checks (key, cell, candidates, when asked [s]) needed now / ahead of need
        self._check_queue: list[tuple[GainKey, int, tuple[GainDesign, ...], float]] = []
        self._ahead_queue: list[tuple[GainKey, int, tuple[GainDesign, ...], float]] = []
        self._ahead_task: asyncio.Task[None] | None = None
        # the check worker's warm-up (None: an executor given, or none started yet)
        self._checker_warm: Future[None] | None = None
        #: Time [s] from a needed interim check's request to its gains, per check.
        self.check_wait_s: list[float] = []

    def _start_design(self) -> None:
        """Run the design the session asks for in the design executor (one at a time)."""
        want = self.session.design_wanted
        if want is None or (self._design_task is not None and not self._design_task.done()):
            return
        self.session.design_wanted = None
        key, k_o = want
        table = self.session.gain_table
        cell = table.cell(k_o)
        if table_design(table, key, k_o)[0] is not None:
            return
        self._ensure_executor()

        async def run() -> None:
            loop = asyncio.get_running_loop()
            try:
                design = await loop.run_in_executor(
                    self._executor, timed, design_cell, key, cell, table.grid_ratio, table.hand_box
                )
            except ValueError as exc:
                log.error("no stable gains for K_o = %.0f N/m: %s", k_o, exc)
                return
            table.store(key, cell, design)
            self.designs += 1
            log.debug("designed gains for K_o = %.0f N/m in %.0f ms", k_o, design.design_ms)
            self._deliver_waiting()
            # the neighbours most likely needed next (:func:`likely_next`). First check these
            # gains there (fast), then design them (slow), both in this worker.
            near = tuple((nk, table.grid_point(nc) * 1.0001) for nk, nc in likely_next(key, cell))
            for nk, nko in near:
                self._queue_check(nk, table.cell(nko), (design,), ahead=True)
            self._start_check()
            for nk, nko in near:
                if table_design(table, nk, nko)[0] is None:
                    try:
                        nd = await loop.run_in_executor(
                            self._executor,
                            timed,
                            design_cell,
                            nk,
                            table.cell(nko),
                            table.grid_ratio,
                            table.hand_box,
                        )
                    except ValueError:
                        continue
                    table.store(nk, table.cell(nko), nd)
                    self.designs += 1
                if self.session.design_wanted is not None:
                    break  # something is needed now: let the next patch start it

        self._design_task = asyncio.get_running_loop().create_task(run())

    def _start_plane(self) -> None:
        """Check the verified plane the session asks for (:attr:`ClientSession.plane_wanted`),
        or else the next one it checks ahead (:meth:`ClientSession.next_plane_ahead`), in the
        design worker, one at a time: nothing waits for it (the contact renders its design
        meanwhile), so it never holds up a check a contact needs."""
        session = self.session
        busy = self._plane_task is not None and not self._plane_task.done()
        designing = self._design_task is not None and not self._design_task.done()
        if busy or designing:
            return
        want: tuple[GainKey, int, int] | None = None
        while want is None and session.plane_wanted:
            # after the designs: a plane check (a second or more) must not hold up a design
            # needed, but for a plane asked alone (a contact verified in a cell not designed
            # yet): it renders until the design is made, and a design may take many seconds
            if session.design_wanted is not None and session.plane_wanted[-1][2] != PLANE_ALONE:
                return
            # the newest first: a press through a stiffening object asks for each cell it
            # crosses, and is likeliest still in the last
            want = session.plane_wanted.pop()
            if want in session.planes:
                want = None  # checked ahead meanwhile
        if want is None and session.design_wanted is None:
            ahead = session.next_plane_ahead()
            if ahead is not None:
                want = (*ahead, PLANE_ALONE)
        if want is None:
            return
        key, cell, design_cell = want
        table = session.gain_table
        # a plane checked alone before is only compared with the design now made
        checked_alone = (key, cell, PLANE_ALONE) in session.planes
        alone = session.planes.get((key, cell, PLANE_ALONE))
        self._ensure_executor()

        async def run() -> None:
            loop = asyncio.get_running_loop()
            try:
                # the design of the K_o reported's cell, if made: the plane (of the cell of the
                # stiffness identified) renders only if felt closer on that object
                design = (
                    None
                    if design_cell == PLANE_ALONE
                    else table_design(table, key, table.grid_point(design_cell) * 1.0001)[0]
                )
                if checked_alone:
                    plane = await loop.run_in_executor(
                        self._executor, plane_against, alone, key, design
                    )
                else:
                    plane = await loop.run_in_executor(
                        self._executor,
                        verified_plane,
                        key,
                        cell,
                        table.grid_ratio,
                        table.hand_box,
                        design,
                    )
            except ValueError as exc:  # gains or rates it cannot check: render the design
                log.warning("no verified plane for cell %d: %s", cell, exc)
                plane = None
            except Exception as exc:  # a broken worker: the design renders (not asked again)
                log.warning("verified plane for cell %d not checked: %s", cell, exc)
                return
            session.store_plane(key, cell, plane, design_cell)
            self.plane_checks += 1
            log.debug("verified plane for cell %d: %s", cell, "none" if plane is None else plane)
            # the next one asked meanwhile, or checked ahead, once this task is done
            loop.call_soon(self._start_plane)

        self._plane_task = asyncio.get_running_loop().create_task(run())

    def _queue_check(
        self, key: GainKey, cell: int, candidates: tuple[GainDesign, ...], *, ahead: bool
    ) -> None:
        if ahead:
            if all((k, c) != (key, cell) for k, c, _, _ in self._ahead_queue):
                self._ahead_queue.append((key, cell, candidates, self.clock()))
        else:
            # needed now: the newest first (a contact moving through K_o cells needs the one it
            # is in, not the ones it left)
            self._check_queue.insert(0, (key, cell, candidates, self.clock()))

    def _start_check(self) -> None:
        """Check interim gains: the ones the session needs now in the check executor, the ones
        ahead of need in the design executor, each in turn.

        The check worker runs the checks a rendered contact waits for: one ahead of need there
        (0.1-0.5 s each, seconds on a busy 2-core machine) held up a needed one behind it, and
        meanwhile the contact rendered conservative unverified gains (:mod:`client.session`).
        The one exception is the coupled classes ahead of need (:func:`likely_next`): they go to
        the check worker while no needed check waits, one at a time. Behind the design worker's
        full designs (seconds each) they came 5-15 s after the first contact, after a second
        user's press in the demo, which then rendered unverified gains; a needed check now waits
        behind at most one of them.
        """
        want = self.session.interim_wanted
        if want is not None:
            self.session.interim_wanted = None
            self._queue_check(*want, ahead=False)
        if (self._check_queue or self._coupled_ahead() is not None) and (
            self._check_task is None or self._check_task.done()
        ):
            self._ensure_executor()
            self._check_task = asyncio.get_running_loop().create_task(self._run_checks(False))
        if self._ahead_queue and (self._ahead_task is None or self._ahead_task.done()):
            self._ensure_executor()
            self._ahead_task = asyncio.get_running_loop().create_task(self._run_checks(True))

    def _to_checker(self, key: GainKey) -> bool:
        """Whether a check of ``key`` ahead of need is the check worker's: a coupled class, when
        the checks have a worker of their own (:meth:`_start_check`)."""
        return key.stiff_ratio > 1.0 and not (
            self._checker is not None and self._checker is self._executor
        )

    def _coupled_ahead(self) -> int | None:
        """Index of the first check ahead of need that is the check worker's, if any."""
        for i, (key, _, _, _) in enumerate(self._ahead_queue):
            if self._to_checker(key):
                return i
        return None

    def _next_check(
        self, ahead_task: bool
    ) -> tuple[tuple[GainKey, int, tuple[GainDesign, ...], float], bool] | None:
        """The next check of the check task (``ahead_task`` False: the needed ones, then the
        coupled classes ahead of need) or of the ahead-of-need task (the others), and whether it
        is ahead of need."""
        if not ahead_task:
            if self._check_queue:
                return self._check_queue.pop(0), False
            i = self._coupled_ahead()
            return None if i is None else (self._ahead_queue.pop(i), True)
        for j, (key, _, _, _) in enumerate(self._ahead_queue):
            if not self._to_checker(key):
                return self._ahead_queue.pop(j), True
        return None

    async def _run_checks(self, ahead_task: bool) -> None:
        session = self.session
        table = session.gain_table
        loop = asyncio.get_running_loop()
        while (nxt := self._next_check(ahead_task)) is not None:
            (key, cell, candidates, asked_s), ahead = nxt
            if (key, cell) in session.interim or table_design(
                table, key, table.grid_point(cell) * 1.0001
            )[0]:
                continue
            # Before anything is rendered (a first contact, or after a rejoin) forces are off:
            # while a spawned check worker is still importing, check in a thread here, at once
            # (a forked worker is ready at once and this never happens). With the servo as a
            # thread of this process that thread shares the servo's interpreter lock (0.7 s for
            # a check of 0.1 s in the FEM demo, 3.5 s and more on Ecoflex's K_o of 3.4 kN/m);
            # with the servo in its own process it holds up only this link.
            first = not ahead and session.last_update is None and not self._checker_ready()
            executor = (
                self._first_thread() if first else self._executor if ahead_task else self._checker
            )
            try:
                d = await loop.run_in_executor(
                    executor,
                    timed,
                    interim_design,
                    key,
                    cell,
                    table.grid_ratio,
                    table.hand_box,
                    candidates,
                    not ahead,  # a check ahead of need never falls back to a slow design
                )
            except Exception as exc:  # ValueError: nothing passed; or a broken worker
                if not ahead:
                    session.interim_failed(key, cell)
                    log.warning("no interim gains for cell %d: %s", cell, exc)
                continue
            session.store_interim(key, cell, d)
            self.checks += 1
            log.debug(
                "interim gains for K_o = %.0f N/m (%s%s) in %.0f ms",
                d.k_o,
                d.mode,
                ", ahead of need" if ahead else "",
                d.design_ms,
            )
            if not ahead:
                self.check_wait_s.append(self.clock() - asked_s)
                self._deliver_waiting()
                # and ahead of need: where this contact is likely to go next
                for nk, nc in likely_next(key, cell):
                    self._queue_check(nk, nc, (d,), ahead=True)
                self._start_check()

    def _checker_ready(self) -> bool:
        """The check worker has started and imported the design code (a given executor: yes)."""
        warm = self._checker_warm
        return warm is None or (warm.done() and warm.exception() is None)

    def _first_thread(self) -> Executor:
        if self._first_pool is None:
            self._first_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="first-check")
        return self._first_pool

    def _deliver_waiting(self) -> None:
        """Hand the servo loop the patch that waited for gains, if it can render now."""
        now = self.clock()
        update = self.session.retry_waiting(now)
        if update is not None:
            self.on_patch(update, now)

    def _ensure_executor(self) -> None:
        if self._executor is None:
            self._own_executor = True
            try:
                # designs and checks ahead of need at low priority; the checks a rendered
                # contact waits for at normal priority (haptic_collab.client.workers)
                workers = self._workers if self._workers is not None else DesignWorkers.start()
                self._workers = None
                self._executor, self._checker = workers.design, workers.check
                self._checker_warm = workers.check_warm
            except (RuntimeError, OSError) as exc:
                # e.g. a script without the ``if __name__ == "__main__"`` guard: design in a
                # thread instead (it then shares the interpreter lock with the servo thread)
                log.warning("gain design runs in a thread, not a worker process: %s", exc)
                for ex in (self._executor, self._checker):
                    if ex is not None:
                        ex.shutdown(wait=False, cancel_futures=True)
                self._executor = ThreadPoolExecutor(max_workers=1)
                self._checker = ThreadPoolExecutor(max_workers=1)
        elif self._checker is None:
            self._checker = self._executor

    def close(self) -> None:
        """Stop the workers (if this link started them, or was handed them)."""
        if self._workers is not None:  # handed over but never used
            stop_pool(self._workers.design)
            stop_pool(self._workers.check)
            self._workers = None
        if self._own_executor:
            for ex in {id(e): e for e in (self._executor, self._checker) if e is not None}.values():
                stop_pool(ex)  # a running design must not hold up the client's exit
            self._executor = self._checker = None
        if self._first_pool is not None:
            stop_pool(self._first_pool)
            self._first_pool = None

    async def run(self, stop: asyncio.Event) -> None:
        """Connect, serve, reconnect with backoff until ``stop`` is set.

        The wait before each new attempt starts at ``backoff_s[0]``, doubles after every attempt
        up to ``backoff_s[1]`` (each wait drawn within +-20 %), and returns to ``backoff_s[0]``
        once a session has joined, not merely when the websocket opened.
        ``stop`` ends a wait at once. A refused token (``unauthorized``) or a bad URL raises
        ``ValueError`` instead of retrying.

        This loop is written out rather than websockets' own reconnecting iterator (``async for
        ws in connect(...)``) because that iterator resets its backoff as soon as the opening
        handshake succeeds: the server accepts the websocket and then refuses the ``hello``
        (``room_full``, ``too_many_connections``, ``rate_limited``: an error and a close), so a
        refused client would reconnect at once, forever, with no wait. Its hook
        (``process_exception``) only sees failures to open, and an exception raised in the loop
        body ends the loop instead of retrying.

        Raises
        ------
        ValueError
            The server refused this client's token, the URL is not a websocket URL, or the TLS
            settings cannot be used (:meth:`ssl_context`).
        """
        if self.session.role == "user":
            self._ensure_executor()
        delay = self.backoff_s[0]
        tls = None if self.resolve is not None else self.ssl_context()
        while not stop.is_set():
            joins = self.joins
            fresh = False  # this attempt's URL and token are the lobby's answer of just now
            if self.resolve is not None and self._reask:
                fresh = await self._ask_lobby()
            if self.resolve is not None:
                tls = self.ssl_context() if self.url else None
            try:
                if not self.url:  # no lobby answer yet: wait and ask again
                    raise ConnectionError("the lobby has not said yet where the room runs")
                async with connect(
                    self.url, max_size=8 * 1024 * 1024, open_timeout=5.0, ssl=tls
                ) as ws:
                    await self._serve(ws, stop)
            except Unauthorized as exc:
                if self.resolve is None or fresh:
                    self.close()
                    raise ValueError(f"{self.url} refused this client: {exc}") from None
                # a token of an earlier answer (expired, or for a server the room left)
                log.info("%s refused the lobby's earlier token; asking the lobby again", self.url)
                self._reask = True
            except (OSError, InvalidHandshake, TimeoutError, ConnectionClosed) as exc:
                self.last_error = f"{type(exc).__name__}: {exc}"
                if isinstance(exc, ConnectionRefusedError):
                    self.refused += 1
                if self.resolve is not None and (
                    not isinstance(exc, ConnectionClosed)
                    or (exc.rcvd is not None and exc.rcvd.code in REASK_CLOSE_CODES)
                ):
                    self._reask = True  # the room may run elsewhere now: ask the lobby
                if not stop.is_set():
                    if (
                        self.refused == 1
                        and not self.joins
                        and isinstance(exc, ConnectionRefusedError)
                    ):
                        log.warning(
                            "nothing listens at %s: is `haptic server` running there, and is "
                            "--url right? (the server prints its URL when it starts); retrying",
                            self.url,
                        )
                    log.info("link to %s down (%s); retrying in %.1f s", self.url, exc, delay)
            except InvalidURI as exc:
                self.close()
                raise ValueError(f"bad server URL {self.url!r}: {exc}") from None
            finally:
                self.connected.clear()
                if self.joins > joins:
                    delay = self.backoff_s[0]  # a session that joined resets the backoff
            if stop.is_set():
                break
            if self._reask and self.joins > joins:
                continue  # moved by a drain: ask the lobby and join at once
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), delay * (0.8 + 0.4 * random.random()))
            delay = min(self.backoff_s[1], delay * 2.0)
        self.close()

    async def _ask_lobby(self) -> bool:
        """Ask the lobby (``resolve``) where the room runs; True when it answered.

        Raises
        ------
        ValueError
            The lobby refused (a bad room name, a token it does not accept): the link stops.
        """
        assert self.resolve is not None
        try:
            url, token = await self.resolve()
        except ConnectionError as exc:
            self.last_error = f"lobby: {exc}"
            log.warning(
                "the lobby did not answer (%s); %s",
                exc,
                f"trying {self.url} again" if self.url else "asking again",
            )
            return False
        except ValueError:
            self.close()
            raise
        self.lobby_asks += 1
        if url != self.url:
            log.info("the lobby places the room at %s", url)
        self.url, self._token = url, token
        self._reask = False
        return True

    def ssl_context(self) -> ssl.SSLContext | None:
        """TLS context for a ``wss://`` URL (verifying against ``ca_file`` if given), else None.

        Raises
        ------
        ValueError
            A CA file given for a ``ws://`` URL, or one that cannot be read.
        """
        if not self.url.lower().startswith("wss://"):
            if self.ca_file:
                raise ValueError(f"--ca-file needs a wss:// URL, got {self.url!r}")
            return None
        try:
            return ssl.create_default_context(cafile=self.ca_file)
        except (OSError, ssl.SSLError) as exc:
            raise ValueError(f"cannot use CA file {self.ca_file}: {exc}") from None

    def hello_frame(self) -> str:
        """The session's ``hello`` with this link's token, if any."""
        frame = self.session.hello(self.clock())
        if self._token is None:
            return frame
        msg = json.loads(frame)
        msg["token"] = self._token
        return json.dumps(msg, separators=(",", ":"))

    async def _serve(self, ws: ClientConnection, stop: asyncio.Event) -> None:
        self._last_rx_s = self.clock()
        await ws.send(self.hello_frame())
        sender = asyncio.create_task(self._send_loop(ws))
        stopper = asyncio.create_task(stop.wait())
        watchdog = asyncio.create_task(self._watch_silence(ws))
        try:
            receiver = asyncio.create_task(self._receive_loop(ws))
            done, _ = await asyncio.wait({receiver, stopper}, return_when=asyncio.FIRST_COMPLETED)
            if stopper in done:
                with contextlib.suppress(ConnectionClosed):
                    await ws.send('{"type":"bye"}')
                receiver.cancel()
                with contextlib.suppress(asyncio.CancelledError, ConnectionClosed):
                    await receiver
            else:
                receiver.result()  # re-raise ConnectionClosed and the like
        finally:
            sender.cancel()
            stopper.cancel()
            watchdog.cancel()
            with contextlib.suppress(asyncio.CancelledError, ConnectionClosed):
                await sender

    async def _watch_silence(self, ws: ClientConnection) -> None:
        """Drop the connection when the server has sent nothing for :attr:`silent_s` since the
        welcome (or no welcome came within :data:`WELCOME_TIMEOUT_S`): the receive loop then
        ends as for a closed link, and :meth:`run` rejoins."""
        while True:
            limit = self.silent_s if self.connected.is_set() else WELCOME_TIMEOUT_S
            quiet = self.clock() - self._last_rx_s
            if quiet > limit:
                self.silent_drops += 1
                log.info("no frame from the server for %.1f s: dropping the link", quiet)
                ws.transport.abort()  # no close handshake: the peer cannot answer it
                return
            await asyncio.sleep(min(0.25, limit - quiet + 0.01))

    async def _receive_loop(self, ws: ClientConnection) -> None:
        async for frame in ws:
            now = self.clock()
            self._last_rx_s = now
            n_errors = len(self.session.errors)
            welcome_before = self.session.welcome
            try:
                update = self.session.receive(frame, now)
            except ProtocolError as exc:
                self.protocol_errors += 1
                log.warning("ignoring a bad frame from the server: %s", exc)
                continue
            if len(self.session.errors) > n_errors:
                err = self.session.errors[-1]
                # a draining server (SIGTERM) or a room whose process is restarted is a
                # restart, not a fault: the link retries (a restarted room stays on its server,
                # so only a drain asks the lobby again)
                level = (
                    logging.INFO
                    if err.code in ("server_draining", "room_restarting")
                    else logging.ERROR
                    if err.fatal
                    else logging.WARNING
                )
                log.log(level, "server: %s (%s)", err.message, err.code)
                if err.code == "server_draining" and self.resolve is not None:
                    self._reask = True  # its rooms go elsewhere: ask the lobby before rejoining
                if err.fatal and err.code == "unauthorized":
                    raise Unauthorized(f"{err.message} (unauthorized)")
            if self.session.checks_ahead:
                for nk, nc, candidates in self.session.checks_ahead:
                    self._queue_check(nk, nc, candidates, ahead=True)
                self.session.checks_ahead.clear()
                self._start_check()
            elif self.session.interim_wanted is not None:
                self._start_check()
            if self.session.design_wanted is not None:
                self._start_design()
            if self.session.plane_wanted or self.session.plane_ahead:
                self._start_plane()
            if update is not None:
                self.on_patch(update, now)
            elif (
                (welcome := self.session.welcome) is not None
                and welcome is not welcome_before
                and not self.connected.is_set()
            ):
                # joined only on a new welcome: after a rejoin the session still holds the old
                # one, and a refusal (room_full, rate_limited) must not count as a join
                self.joins += 1
                self.user_ids.append(welcome.user_id)
                self.joined_urls.append(self.url)
                if welcome.resumed:
                    self.resumes += 1
                    log.info("rejoined: seat %s (%s) resumed", welcome.user_id, welcome.name)
                self.connected.set()
                if self.on_welcome:
                    self.on_welcome(welcome)

    async def _send_loop(self, ws: ClientConnection) -> None:
        await self.connected.wait()
        next_ping = self.clock()
        while True:
            interval = self.session.state_interval_s
            if self.session.role == "user":
                sample = self.sample()
                if sample is not None:
                    try:
                        frame = self.session.state(sample)
                    except ValueError as exc:  # e.g. a non-finite sample: skip it, keep the link
                        log.warning("not sending an invalid state: %s", exc)
                    else:
                        await ws.send(frame)
            now = self.clock()
            if now >= next_ping:
                await ws.send(self.session.ping(now))
                next_ping = now + PING_INTERVAL_S
            await asyncio.sleep(interval)
