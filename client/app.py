"""``haptic client``: one user — device and 1 kHz servo loop in their own process, network link.

Sequence: check the ``--device`` spec and open the device (a HID device's port) *before* any
network, so a bad spec or an absent device fails at once with one line; build the device's gain
table into this machine's cache if neither the shipped tables nor the cache hold it (once per
device and design code, minutes: :func:`build_gains`); start streaming
``--record``; connect and join (the ``welcome`` says where the object is), place the device around
the anchor the trajectory works on (the top of the object for ``press``, a side for ``rest``),
start the servo thread (forces stay off until the first patch), then run until ``--duration``,
Ctrl-C or SIGTERM; on exit the servo ramps forces to zero, the link says ``bye``, the recording
is flushed and closed and the summary written.

A device that faults while running (unplugged) is the device's business: the servo loop ramps
forces to zero and the client reopens the device with backoff (:data:`client.servo_device.DEVICE_REOPEN_BACKOFF_S`);
the network link is never restarted for it.

With a lobby (``--lobby URL --room NAME``, :mod:`server.lobby`) the client asks the lobby where
room NAME runs and for a room token (:func:`ask_lobby`) before it joins, and again when its
server drains (:class:`client.link.Link`'s ``resolve``): it then joins the room where it runs
now, without restarting the device or the servo loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import re
import signal
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol
from urllib.parse import quote, urlsplit

from haptic_collab.client import gain_build
from haptic_collab.client.devices.base import Device, DeviceLimits
from haptic_collab.client.devices.hid import HidPort
from haptic_collab.client.devices.opener import DeviceOpener
from haptic_collab.client.devices.profiles import get_sim_profile
from haptic_collab.client.gain_build import (
    build_device_table,
    build_workers,
    gain_build_default,
    plan_device_build,
    progress_bar,
)
from haptic_collab.client.gain_store import device_coverage, preload, save_cache
from haptic_collab.client.link import DesignWorkers, Link, Resolver
from haptic_collab.client.recorder import CsvRecording, TelemetryRecorder
from haptic_collab.client.servo import (
    ServoConfig,
    ServoCore,
    ServoSnapshot,
    ServoStatus,
)
from haptic_collab.client.servo_device import BuiltDevice, built_device, watch_device
from haptic_collab.client.servo_process import ServoProcess, ServoProcessError
from haptic_collab.client.servo_thread import ServoThread
from haptic_collab.client.session import ClientSession, ServoSample
from haptic_collab.client.summary import client_summary
from haptic_collab.client.theta import threshold_for
from haptic_collab.client.workers import stop_pool
from haptic_collab.shared.gains.table import GainTable
from haptic_collab.shared.local_model import LocalModelParams
from haptic_collab.shared.local_model_update import LocalModelUpdate
from haptic_collab.shared.protocol import DeviceInfo, Welcome
from haptic_collab.shared.stability import rate_ratio

log = logging.getLogger("haptic.client")


@dataclass
class ClientOptions:
    """Options of ``haptic client`` (SI units)."""

    url: str = "ws://127.0.0.1:8765/ws"
    name: str = "A"
    device: str = "sim:press"
    profile: str = "phantom-desktop"
    local_model: Literal["p", "pi"] = "pi"
    servo_rate_hz: float = 1000.0
    record: Path | None = None
    summary: Path | None = None
    duration_s: float | None = None
    #: ``auto``, ``top``, ``side`` (by join order) or ``side:N`` (the server's N-th side, 1-based;
    #: the server lists first the sides a press on the top moves most), :func:`_anchor`.
    anchor: str = "auto"
    trajectory: dict[str, float] = field(default_factory=dict)
    theta_m: float = 0.001
    theta_mode: Literal["auto", "fixed", "variable"] = "auto"
    passivity: Literal["auto", "on", "off"] = "auto"
    margin: float = 0.15
    join_timeout_s: float = 20.0
    hid_profile: str | None = None
    #: Stop cleanly on SIGINT and SIGTERM (``haptic client``); needs the main thread's loop.
    stop_on_signals: bool = False
    #: ``opener(vendor_id, product_id) -> port`` for HID devices (default hidapi; tests a fake).
    hid_opener: Callable[[int, int], HidPort] | None = None
    #: ``server``: render the server's recommended gains when they fit this device and no better
    #: design of the client's own is ready (an interim recommendation yields to a full design);
    #: ``local``: always design the gains here (client.session.ClientSession).
    gains: Literal["server", "local"] = "server"
    #: Render the rest plane a patch carries while the user is alone on the object
    #: (shared.gains.rest_plane; ``haptic client --no-rest-plane``: never).
    rest_plane: bool = True
    #: ``button``: the user engages forces with the device's first button (a stylus button, as
    #: vendor examples do); ``auto``: forces come on with the first checked patch; ``default``:
    #: ``button`` for a device with buttons (``Device.has_buttons``), ``auto`` otherwise.
    engage: Literal["default", "button", "auto"] = "default"
    #: The server's token, sent in ``hello`` (None: ``$HAPTIC_TOKEN``, else none).
    token: str | None = None
    #: CA file [PEM] a ``wss://`` server is verified against (None: ``$HAPTIC_CA_FILE``, else
    #: the system's CAs).
    ca_file: str | None = None
    #: ``process``: the servo loop (device, local model, safety, telemetry) runs in a process of
    #: its own (client.servo_process); ``thread``: in a thread of this process; ``auto``:
    #: ``process`` unless ``hid_opener`` is given (a fake port cannot cross processes).
    servo: Literal["auto", "process", "thread"] = "auto"
    #: Keep the gain designs this client makes in its cache and start from it
    #: (client.gain_store; ``haptic client --no-gain-cache``: the shipped tables only).
    gain_cache: bool = True
    #: Before joining, build the gain table of a device neither the shipped tables nor the cache
    #: cover, into the cache (:func:`build_gains`; needs ``gain_cache``); False
    #: (``haptic client --no-gain-build``): its cells are designed during contact. Default True
    #: unless ``$HAPTIC_GAIN_BUILD`` is 0 (client.gain_build.gain_build_default).
    gain_build: bool = field(default_factory=gain_build_default)
    #: A lobby (``http(s)://HOST:PORT``, ``haptic lobby``) that says where ``room`` runs and
    #: gives a room token; ``url`` and ``token`` are then unused (None: join ``url``).
    lobby: str | None = None
    #: The room to ask the lobby for.
    room: str | None = None
    #: The lobby's own token (``Authorization: Bearer``), when it asks for one (None:
    #: ``$HAPTIC_LOBBY_TOKEN``, else none).
    lobby_token: str | None = None


#: Environment variable read when no lobby token is given.
LOBBY_TOKEN_ENV = "HAPTIC_LOBBY_TOKEN"
#: Time to wait for the lobby's answer [s], and the largest answer read [bytes].
LOBBY_TIMEOUT_S = 10.0
LOBBY_ANSWER_BYTES = 64 * 1024


def ask_lobby(
    lobby_url: str,
    room: str,
    role: Literal["user", "viewer"] = "user",
    *,
    token: str | None = None,
    timeout_s: float = LOBBY_TIMEOUT_S,
) -> dict[str, Any]:
    """Ask a lobby (``haptic lobby``) where room ``room`` runs; blocking (run it in a thread).

    ``GET LOBBY/rooms/ROOM?role=ROLE`` (:mod:`server.lobby`).

    Parameters
    ----------
    lobby_url : str
        The lobby, ``http(s)://HOST:PORT``.
    room : str
        The room's name (the lobby checks it).
    role : {"user", "viewer"}
    token : str, optional
        The lobby's token (``Authorization: Bearer``), when it asks for one.
    timeout_s : float
        Time to wait for the answer [s].

    Returns
    -------
    dict
        The lobby's answer: ``url`` (the room's websocket), ``token`` (a room token),
        ``expires`` (Unix time [s]), ``viewer`` (the room's viewer page with the token),
        ``server``.

    Raises
    ------
    ValueError
        A bad lobby URL, or the lobby refused (4xx but 429: a bad name, no such room anywhere,
        a token it does not accept): asking again cannot help.
    ConnectionError
        The lobby cannot be reached, is busy (429) or has no room now (5xx): asking again later
        may help.
    """
    parts = urlsplit(lobby_url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"--lobby is http(s)://HOST:PORT, got {lobby_url!r}")
    url = f"{lobby_url.rstrip('/')}/rooms/{quote(room, safe='')}?role={role}"
    req = urllib.request.Request(url, headers={"Accept": "application/json"})
    if token:
        req.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(req, timeout=timeout_s) as resp:
            answer = json.loads(resp.read(LOBBY_ANSWER_BYTES))
    except urllib.error.HTTPError as exc:
        try:
            why = json.loads(exc.read(LOBBY_ANSWER_BYTES)).get("error", exc.reason)
        except (ValueError, AttributeError):
            why = exc.reason
        if exc.code >= 500 or exc.code == 429:
            raise ConnectionError(f"the lobby {lobby_url}: {why} ({exc.code})") from None
        raise ValueError(
            f"the lobby {lobby_url} refused room {room!r}: {why} ({exc.code})"
        ) from None
    except (OSError, ValueError) as exc:
        raise ConnectionError(f"the lobby {lobby_url} cannot be reached: {exc}") from None
    if not isinstance(answer, dict) or not isinstance(answer.get("url"), str):
        raise ConnectionError(f"the lobby {lobby_url} answered without a room URL")
    return answer


def lobby_resolver(lobby_url: str, room: str, token: str | None = None) -> Resolver:
    """The ``resolve`` of a :class:`client.link.Link` that joins room ``room`` through a lobby:
    its websocket URL and room token, asked anew each call (:func:`ask_lobby`, in a thread)."""
    lobby_token = token if token is not None else (os.environ.get(LOBBY_TOKEN_ENV) or None)

    async def resolve() -> tuple[str, str | None]:
        answer = await asyncio.to_thread(ask_lobby, lobby_url, room, "user", token=lobby_token)
        room_token = answer.get("token")
        return answer["url"], room_token if isinstance(room_token, str) else None

    return resolve


def _device_info(opts: ClientOptions, limits: DeviceLimits | None = None) -> DeviceInfo:
    """What ``hello`` declares about the device: its limits as the opened device states them
    (the server designs the recommended gains for them), capped to the protocol's ranges."""
    if limits is None and opts.device.startswith("sim:"):
        limits = get_sim_profile(opts.profile).limits
    if limits is None:
        return DeviceInfo(profile=opts.device[:64])
    return DeviceInfo(
        profile=(opts.profile if opts.device.startswith("sim:") else opts.device)[:64],
        max_force_n=min(100.0, limits.max_force_n),
        max_stiffness_n_per_m=min(1e5, limits.max_stiffness_n_per_m),
        max_damping_n_s_per_m=min(1e3, limits.max_damping_n_s_per_m),
    )


#: Time [s] over which the force step of new gains in the middle of a press is carried off
#: (:class:`shared.local_model.LocalModelParams`): long enough that the hand feels a change of
#: stiffness, not a tap (the demo's hold saw a 0.56 N step in one tick without it), short next to
#: the seconds a new cell's design takes.
GAIN_TRANSFER_S = 0.25


def _anchor(
    opts: ClientOptions, welcome: Welcome
) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """Where the scripted hand works: (point [m], outward normal) on the object's rest surface.

    ``top`` is the object's top; ``side`` one of its side anchors, chosen by join order (the
    number in the user id: u1 on the first side, u2 on the second, ...) so that users resting on
    a side spread apart; ``side:N`` the N-th side anchor (1-based, modulo their number) whatever
    the join order: the server lists first the sides a press on the top moves most
    (:func:`server.room.order_sides_by_coupling`); ``auto`` is ``side`` for ``sim:rest`` and
    ``top`` otherwise.
    """
    obj = welcome.object
    which = check_anchor(opts.anchor)
    if which == "auto":
        which = "side" if opts.device.startswith("sim:rest") else "top"
    if which.startswith("side"):
        sides = [(p.point_m, p.normal) for p in obj.sides] or [(obj.side_m, obj.side_normal)]
        if which.startswith("side:"):
            order = int(which[5:]) - 1
        else:
            digits = re.search(r"(\d+)$", welcome.user_id)
            order = int(digits.group(1)) - 1 if digits else 0
        return sides[max(order, 0) % len(sides)]
    return obj.top_m, obj.top_normal


def check_anchor(anchor: str) -> str:
    """``anchor`` if it is ``auto``, ``top``, ``side`` or ``side:N`` (N >= 1).

    Raises
    ------
    ValueError
        Anything else.
    """
    if anchor in ("auto", "top", "side") or re.fullmatch(r"side:[1-9]\d{0,2}", anchor):
        return anchor
    raise ValueError(f"anchor must be auto, top, side or side:N (N >= 1), got {anchor!r}")


def _sample(servo: ServoHandle) -> ServoSample | None:
    snap = servo.latest()
    return None if snap is None else ServoSample.from_snapshot(snap)


class ServoHandle(Protocol):
    """What the link side uses of a running servo loop (:class:`client.servo_thread.ServoThread` or
    :class:`client.servo_process.ServoProcess`)."""

    def set_patch(self, update: LocalModelUpdate) -> LocalModelUpdate: ...
    def enable_forces(self) -> None: ...
    def latest(self) -> ServoSnapshot | None: ...
    def status(self) -> ServoStatus: ...
    def stop(self, timeout_s: float | None = None) -> bool: ...

    @property
    def overruns(self) -> int: ...


class _ThreadServo:
    """The servo loop as a thread of this process (``--servo thread``): the device opened here
    (:class:`client.devices.DeviceOpener`), a :class:`client.servo_thread.ServoThread` and a thread that
    reopens a faulted device (:func:`client.servo_device.watch_device`). The same set-up calls
    as :class:`client.servo_process.ServoProcess`."""

    def __init__(self, opener: DeviceOpener, capacity: int, clock: Callable[[], float]) -> None:
        self.opener = opener
        self.recorder = TelemetryRecorder(capacity=capacity)
        self.clock = clock
        self.counters = {"device_faults": 0, "device_reopens": 0}
        self.realtime = False
        self.device: Device | None = None
        self.servo: ServoThread | None = None
        self._watch_stop = threading.Event()

    def check(self) -> None:
        self.opener.check()

    @property
    def limits(self) -> DeviceLimits | None:
        return self.opener.limits

    def build(self, anchor: tuple[float, ...], normal: tuple[float, ...]) -> BuiltDevice:
        self.device = self.opener.build(anchor, normal)
        return built_device(self.device)

    def start(self, config: ServoConfig, local_model: LocalModelParams) -> ServoThread:
        assert self.device is not None
        core = ServoCore(self.device, config, local_model=local_model, recorder=self.recorder)
        self.servo = ServoThread(core, clock=self.clock)
        self.servo.start()
        self.realtime = self.servo.realtime
        threading.Thread(
            target=watch_device,
            args=(self.device, self.counters, self._watch_stop),
            name="device-watch",
            daemon=True,
        ).start()
        return self.servo

    def close(self) -> None:
        self._watch_stop.set()
        if self.servo is not None:
            self.servo.stop()
        if self.device is not None:
            self.device.close()
        self.opener.close()


def _servo_host(opts: ClientOptions, origin_s: float, capacity: int) -> _ThreadServo | ServoProcess:
    """Where the servo loop will run (``opts.servo``), not started yet."""
    kwargs: dict[str, Any] = {
        "spec": opts.device,
        "profile": opts.profile,
        "trajectory_options": opts.trajectory or None,
        "servo_rate_hz": opts.servo_rate_hz,
        "hid_profile": opts.hid_profile,
    }
    if opts.servo == "process" or (opts.servo == "auto" and opts.hid_opener is None):
        if opts.hid_opener is not None:
            raise ValueError("--servo process opens the device in the servo process: no hid_opener")
        return ServoProcess(kwargs, clock_origin_s=origin_s, capacity=capacity)
    opener = DeviceOpener(kwargs.pop("spec"), hid_opener=opts.hid_opener, **kwargs)

    def clock() -> float:
        return time.perf_counter() - origin_s

    return _ThreadServo(opener, capacity, clock)


async def run_client(opts: ClientOptions) -> dict[str, Any]:
    """Run one user until the duration elapses, a stop signal, or the task is cancelled.

    The device is checked and (a HID device) opened before any network: a bad ``--device`` or
    a device that cannot be opened raises :class:`client.devices.DeviceError` at once, with no
    connection made. With the servo in its own process (``opts.servo``), that process is
    started first (forked: in a few milliseconds) and opens the device. ``--record`` streams to
    its file
    while the client runs (:class:`client.recorder.CsvRecording`); the recording and the summary
    are written however the run ends (duration, SIGINT or SIGTERM with ``stop_on_signals``,
    cancellation, error).

    Returns
    -------
    dict
        The summary (also written to ``opts.summary``).

    Raises
    ------
    DeviceError
        Bad device spec, or the device cannot be opened (a ValueError).
    ValueError
        Bad options (profile, trajectory option, server URL).
    ConnectionError
        The server could not be joined within ``join_timeout_s``.
    ServoProcessError
        The servo process could not be started, or died while the client ran.
    OSError
        The recording file cannot be created.
    GainBuildInterrupted
        SIGINT or SIGTERM (``stop_on_signals``) during the gain table's build: nothing was
        connected; the cells designed are in the cache.
    """
    origin_s = time.perf_counter()
    # bounded memory: the ring holds the last two minutes; --record streams everything to disk
    capacity = int(opts.servo_rate_hz * min(opts.duration_s or 120.0, 120.0)) + 2000
    host = _servo_host(opts, origin_s, capacity)
    workers: DesignWorkers | None = None
    try:
        if isinstance(host, ServoProcess):
            host.spawn()
        try:  # forked while this process has one thread: the first check runs there at once
            workers = DesignWorkers.start()
        except (RuntimeError, OSError) as exc:
            log.warning("gain design runs in a thread, not a worker process: %s", exc)
        if isinstance(host, ServoProcess):  # it checks and opens the device before any network
            await asyncio.to_thread(host.wait_checked)
        else:
            host.check()  # before any network: DeviceError with one line
        # the device's limits are known now; the servo loop is not started (forces are off)
        built = await build_gains(opts, _device_info(opts, host.limits))
        return await _run(opts, host, origin_s, workers, built)
    finally:
        if workers is not None:  # the link stops them too; this covers a link never run
            stop_pool(workers.design)
            stop_pool(workers.check)
        host.close()


async def _run(
    opts: ClientOptions,
    host: _ThreadServo | ServoProcess,
    origin_s: float,
    workers: DesignWorkers | None,
    built: dict[str, Any],
) -> dict[str, Any]:
    run = _ClientRun(opts, host, origin_s, workers)
    run.gain_build = built
    return await run.run()


class GainBuildInterrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM while :func:`build_gains` built the device's gain table: the client
    stops without connecting (``haptic`` exits with status 130); the cells designed so far are
    in the cache, and the next run builds only the rest."""


async def build_gains(opts: ClientOptions, info: DeviceInfo) -> dict[str, Any]:
    """Build the device's gain table into the cache if it is not there, before any network.

    The session's gains come from the gain table; a cell it lacks is designed during the
    contact that needs it, and the hand feels interim or fallback gains until then
    (docs/gains.md). The built-in profiles ship their tables; any other device's limits are
    designed here once, the shipped grid (:data:`client.gain_build.DEVICE_GRID`, for a 1 kHz
    servo and a 20 Hz simulation) on every core, into this machine's cache
    (:mod:`client.gain_store`), with a progress bar on stderr. The next run finds them there
    and does not build. Nothing runs with ``gain_build`` or ``gain_cache`` off, for a device that
    states no limits, or a servo rate or margin the grid is not for.

    Parameters
    ----------
    opts : ClientOptions
    info : DeviceInfo
        The device's limits as ``hello`` declares them (:func:`_device_info`): K_h max [N/m]
        and B_h max [N*s/m] capped to the protocol's ranges, as the session's gain keys carry
        them.

    Returns
    -------
    dict
        For the summary (``gain_build``): ``ran`` (bool), ``cells`` (designed now), ``missing``
        (cells of the grid missing before), ``of`` (the grid's cells for this device),
        ``seconds`` (the build's wall time [s]), ``workers``; or ``skipped`` (why not), or
        ``error`` (a build that failed: the cache cannot be written, a worker died; the client
        then joins and designs during contact, as with ``--no-gain-build``).

    Raises
    ------
    GainBuildInterrupted
        SIGINT or SIGTERM (``opts.stop_on_signals``) during the build.
    asyncio.CancelledError
        The task was cancelled during the build (it is stopped and what it made written first).
    """
    k_h_max, b_h_max = info.max_stiffness_n_per_m, info.max_damping_n_s_per_m
    if not opts.gain_build:
        return {"ran": False, "skipped": "no-gain-build"}
    if not opts.gain_cache:
        return {"ran": False, "skipped": "no-gain-cache"}
    if k_h_max is None or b_h_max is None:
        return {"ran": False, "skipped": "the device states no limits"}
    grid = gain_build.DEVICE_GRID  # read now: a test may give a smaller one
    if opts.servo_rate_hz != grid["servo_rate_hz"] or opts.margin != grid["margin"]:
        return {
            "ran": False,
            "skipped": f"the table's grid is for a {grid['servo_rate_hz']:g} Hz servo and "
            f"margin {grid['margin']:g}",
        }
    plan = await asyncio.to_thread(plan_device_build, k_h_max, b_h_max, grid)
    if not plan.jobs:
        return {"ran": False, "missing": 0, "of": plan.total}
    log.warning(
        "gains: no table holds %d of the %d cells of this device (K_h <= %g N/m, B_h <= %g "
        "N*s/m): designing them now, before joining, so that every contact renders designed "
        "gains (minutes, once: cached in %s for the next run; skip with --no-gain-build; "
        "Ctrl-C stops, keeping what is made)",
        len(plan.jobs), plan.total, k_h_max, b_h_max, plan.out,
    )  # fmt: skip
    stop = threading.Event()
    loop = asyncio.get_running_loop()
    signals: list[signal.Signals] = []
    if opts.stop_on_signals:
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                loop.add_signal_handler(sig, stop.set)
                signals.append(sig)
    workers = build_workers()
    t0 = time.perf_counter()
    build = asyncio.ensure_future(
        asyncio.to_thread(
            build_device_table,
            plan,
            grid=grid,
            workers=workers,
            stop=stop,
            progress=progress_bar("gains: designing"),
        )
    )
    try:
        done, left = await asyncio.shield(build)
    except asyncio.CancelledError:
        stop.set()  # the designs under way are abandoned; what was made is written
        with contextlib.suppress(Exception):
            await build
        print(file=sys.stderr)  # end the progress bar's line
        log.warning("gains: the build was stopped; the cells designed are cached in %s", plan.out)
        raise
    except (OSError, RuntimeError) as exc:  # a cache that cannot be written, a worker killed
        print(file=sys.stderr)
        log.warning(
            "gains: the table could not be built (%s); its cells are designed during contact",
            exc,
        )
        return {"ran": False, "error": str(exc), "missing": len(plan.jobs), "of": plan.total}
    finally:
        for sig in signals:
            loop.remove_signal_handler(sig)
    seconds = time.perf_counter() - t0
    if stop.is_set():
        print(file=sys.stderr)  # end the progress bar's line
        log.warning(
            "gains: stopped after %d of %d cells (%.0f s); they are cached in %s and the next "
            "run builds only the other %d; nothing was connected",
            done, len(plan.jobs), seconds, plan.out, left,
        )  # fmt: skip
        raise GainBuildInterrupted(f"gain table build stopped after {done} cells")
    log.info(
        "gains: %d cells designed in %.0f s on %d workers, cached in %s", done, seconds, workers,
        plan.out,
    )  # fmt: skip
    return {
        "ran": True,
        "cells": done,
        "missing": len(plan.jobs),
        "of": plan.total,
        "seconds": round(seconds, 3),
        "workers": workers,
    }


def _no_join(url: str, waited_s: float, link: Link) -> str:
    """Why no join came within ``waited_s`` [s], and what to check."""
    if link.refused and not link.joins:
        return (
            f"could not join {url} within {waited_s:g} s: nothing listens there "
            f"({link.refused} attempts refused); is `haptic server` running, and is --url right? "
            "(the server prints its URL when it starts)"
        )
    why = f" (last: {link.last_error})" if link.last_error else ""
    return (
        f"could not join {url} within {waited_s:g} s{why}; is the server reachable from here, "
        "and does it accept this client's token?"
    )


class _ClientRun:
    """One run of :func:`run_client` once the device is checked: the session, the link, the
    servo started at the ``welcome``, and what stopped the run.

    The link calls :meth:`on_welcome`, :meth:`on_patch` and :meth:`sample` from the event loop;
    :meth:`run` waits for the join and then the duration, a stop signal or a fault, and always
    ends with forces ramped to zero, the recording closed and the summary written.
    """

    def __init__(
        self,
        opts: ClientOptions,
        host: _ThreadServo | ServoProcess,
        origin_s: float,
        workers: DesignWorkers | None,
    ) -> None:
        self.opts = opts
        self.host = host
        self.origin_s = origin_s
        self.workers = workers
        info = _device_info(opts, host.limits)
        self.session = ClientSession(
            opts.name,
            servo_rate_hz=opts.servo_rate_hz,
            device=info,
            mode=opts.local_model,
            margin=opts.margin,
            b_h_max=info.max_damping_n_s_per_m,
            gains=opts.gains,
            rest_plane=opts.rest_plane,
        )
        #: What the session's gain table started with (client.gain_store.preload), and its
        #: cells then: the designs made after them go to the cache when the run ends.
        self.gain_preload = preload(self.session.gain_table, cache=opts.gain_cache)
        #: What :func:`build_gains` did before the run (the summary's ``gain_build``).
        self.gain_build: dict[str, Any] = {"ran": False}
        self._preloaded = {(k, c) for k, c, _ in self.session.gain_table.cells()}
        #: The servo once started (at the first ``welcome``), and the task starting it.
        self.servo: ServoHandle | None = None
        self.starting: asyncio.Future[None] | None = None
        #: What stops the run: the first fault, or the name of a stop signal.
        self.error: BaseException | None = None
        self.signal: str | None = None
        #: Where the scripted hand works: {"point_m", "normal"} once placed.
        self.anchor: dict[str, list[float]] | None = None
        self.updates: list[LocalModelUpdate] = []
        self.halt = asyncio.Event()  # a stop signal or a fault
        self.loop = asyncio.get_running_loop()

    def clock(self) -> float:
        """Servo and link time [s] since this client started (scripted hands start at 0)."""
        return time.perf_counter() - self.origin_s

    # -- what stops the run -----------------------------------------------------------------------
    def on_signal(self, sig: signal.Signals) -> None:
        log.info("%s: stopping (forces ramp to zero, recording and summary are written)", sig.name)
        self.signal = sig.name
        self.halt.set()

    def fail(self, exc: BaseException) -> None:
        """Stop the run with ``exc`` (the first fault wins)."""
        if self.error is None:
            self.error = exc
        self.halt.set()

    def on_servo_death(self, reason: str) -> None:
        """The servo process died (called from the servo monitor's thread): the run stops once
        the last force has ramped to zero (the link reports it meanwhile, ServoProcess.latest)."""
        host = self.host
        assert isinstance(host, ServoProcess)
        self.loop.call_soon_threadsafe(
            self.loop.call_later, host.ramp_s + 0.05, self.fail, ServoProcessError(reason)
        )

    # -- the link's callbacks ---------------------------------------------------------------------
    def on_welcome(self, welcome: Welcome) -> None:
        if self.starting is not None or self.error is not None:
            return  # a reconnection: keep the running device and servo loop
        self.starting = asyncio.ensure_future(self._start_servo_or_fail(welcome))

    def on_patch(self, update: LocalModelUpdate, now_s: float) -> None:
        if self.servo is None:
            return
        self.servo.set_patch(update)
        self.updates.append(update)

    def sample(self) -> ServoSample | None:
        return None if self.servo is None else _sample(self.servo)

    # -- the servo, started at the welcome --------------------------------------------------------
    async def _start_servo_or_fail(self, welcome: Welcome) -> None:
        try:
            await self._start_servo(welcome)
        except Exception as exc:  # never a network retry: the client stops with this error
            self.fail(exc)

    def _report_coverage(self, sim_rate_hz: float) -> None:
        """Say whether this device's gains are designed ahead (the shipped tables and the
        cache, :func:`client.gain_store.device_coverage`), and if not how to make them so: the
        cells missing are designed during contact, and feel different until each is ready."""
        s = self.session
        k_h_max, b_h_max = s.device.max_stiffness_n_per_m, s.b_h_max
        held, of = device_coverage(
            s.gain_table, k_h_max=k_h_max, b_h_max=b_h_max, mode=s.mode,
            servo_rate_hz=s.servo_rate_hz, sim_rate_hz=sim_rate_hz,
        )  # fmt: skip
        self.gain_preload["device_cells"] = {"held": held, "of": of}
        if of == 0:
            log.info(
                "gains: no table is built for %g Hz servo / %g Hz simulation; cells are "
                "designed as contacts need them",
                s.servo_rate_hz,
                sim_rate_hz,
            )
        elif held < of:
            log.warning(
                "gains: %d of %d cells of this device's table are designed (K_h <= %g N/m, "
                "B_h <= %g N*s/m); the others are designed as contacts need them and feel "
                "different until ready. Build them once (minutes, cached): run haptic client "
                "without --no-gain-build, or haptic gains-table --cache --max-stiffness %g "
                "--max-damping %g",
                held, of, k_h_max, b_h_max, k_h_max, b_h_max,
            )  # fmt: skip

    async def _start_servo(self, welcome: Welcome) -> None:
        opts, host, session = self.opts, self.host, self.session
        _check_whole_rate_ratio(opts.servo_rate_hz, welcome.sim_rate_hz)
        anchor, normal = _anchor(opts, welcome)
        self.anchor = {"point_m": list(anchor), "normal": list(normal)}
        if isinstance(host, ServoProcess):  # checked before the network (run_client)
            device = await asyncio.to_thread(host.build, anchor, normal)
        else:
            device = host.build(anchor, normal)
        lim = device.limits
        # gains are designed for this device's real limits (a HID profile's, not the defaults)
        session.device = DeviceInfo(
            profile=session.device.profile,
            max_force_n=min(100.0, lim.max_force_n),
            max_stiffness_n_per_m=min(1e5, lim.max_stiffness_n_per_m),
            max_damping_n_s_per_m=min(1e3, lim.max_damping_n_s_per_m),
        )
        session.b_h_max = min(1e3, lim.max_damping_n_s_per_m)
        self._report_coverage(welcome.sim_rate_hz)
        lm = _local_model_params(opts, device, welcome.sim_rate_hz)
        passivity = passivity_on(opts.passivity, opts.local_model)
        by_button = opts.engage == "button" or (opts.engage == "default" and device.has_buttons)
        if by_button:
            log.info("press the device's first button to engage forces (again to disengage)")
        config = ServoConfig(
            servo_rate_hz=opts.servo_rate_hz, passivity=passivity, engage_with_button=by_button
        )
        servo: ServoHandle
        if isinstance(host, ServoProcess):
            await asyncio.to_thread(host.start, config, lm)
            servo = host
        else:
            servo = host.start(config, lm)
        servo.enable_forces()
        self.servo = servo
        log.info(
            "%s joined as %s; device %s on %s (servo in its own %s%s)",
            opts.name,
            welcome.user_id,
            opts.device,
            anchor,
            "process" if isinstance(host, ServoProcess) else "thread",
            ", real-time priority" if host.realtime else "",
        )

    # -- the run ----------------------------------------------------------------------------------
    async def run(self) -> dict[str, Any]:
        """Join, run until the duration, a stop signal or a fault, then stop and summarise.

        Raises what stopped the run (a fault, the link's error, ConnectionError when the
        server could not be joined within ``join_timeout_s``); the summary is written anyway.
        """
        opts, host, loop = self.opts, self.host, self.loop
        recording = None if opts.record is None else CsvRecording(host.recorder, opts.record)
        if recording is not None:
            recording.start()
            log.info("recording every servo tick to %s", opts.record)
        signals: list[signal.Signals] = []
        if opts.stop_on_signals:
            for sig in (signal.SIGINT, signal.SIGTERM):
                with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                    loop.add_signal_handler(sig, self.on_signal, sig)
                    signals.append(sig)
        if isinstance(host, ServoProcess):
            host.on_death = self.on_servo_death
        resolve = None
        if opts.lobby is not None:
            if not opts.room:
                raise ValueError("--lobby needs --room NAME")
            resolve = lobby_resolver(opts.lobby, opts.room, opts.lobby_token)
        link = Link(
            "" if resolve is not None else opts.url,
            self.session,
            on_patch=self.on_patch,
            sample=self.sample,
            clock=self.clock,
            on_welcome=self.on_welcome,
            token=opts.token,
            ca_file=opts.ca_file,
            workers=self.workers,
            resolve=resolve,
        )
        stop = asyncio.Event()
        link_task = asyncio.create_task(link.run(stop))
        try:
            await self._until_done(link, link_task)
        finally:
            starting = self.starting
            if starting is not None and not starting.done():
                with contextlib.suppress(Exception, asyncio.CancelledError):
                    await asyncio.wait_for(starting, 5.0)
            if self.servo is not None:
                await asyncio.to_thread(self.servo.stop)
            stop.set()
            with contextlib.suppress(Exception, asyncio.CancelledError):
                await asyncio.wait_for(link_task, 3.0)
            for sig in signals:
                loop.remove_signal_handler(sig)
            if recording is not None:
                recording.close()
            if opts.gain_cache:
                await asyncio.to_thread(self._save_designs)
            summary = self._summary(link, recording)
        return summary

    def _save_designs(self) -> None:
        """Add the designs this run made to the cache (client.gain_store.save_cache)."""
        table = self.session.gain_table
        new = GainTable(table.hand_box, table.grid_ratio)
        for key, cell, design in table.cells():
            if (key, cell) not in self._preloaded:
                new.store(key, cell, design)
        if len(new):
            save_cache(new, str(self.gain_preload["design_code"]))
        self.gain_preload["saved"] = len(new)

    async def _until_done(self, link: Link, link_task: asyncio.Task[None]) -> None:
        """Wait for the join, then for the duration, a halt or the link's end; raise a fault."""
        opts = self.opts
        joined = asyncio.create_task(link.connected.wait())
        halted = asyncio.create_task(self.halt.wait())
        t_start = self.clock()
        # the join counts against --duration too: a run never outlasts it
        join_timeout = opts.join_timeout_s
        if opts.duration_s is not None:
            join_timeout = min(join_timeout, opts.duration_s)
        try:
            done, _ = await asyncio.wait(
                {joined, halted, link_task},
                timeout=join_timeout,
                return_when=asyncio.FIRST_COMPLETED,
            )
            if self.error is not None:
                raise self.error
            if link_task in done:
                link_task.result()  # e.g. ValueError: a bad URL
            if not done:
                raise ConnectionError(_no_join(link.url or str(opts.lobby), join_timeout, link))
            if not self.halt.is_set():
                remaining = (
                    None
                    if opts.duration_s is None
                    else max(0.0, opts.duration_s - (self.clock() - t_start))
                )
                done, _ = await asyncio.wait(
                    {halted, link_task}, timeout=remaining, return_when=asyncio.FIRST_COMPLETED
                )
                if self.error is not None:
                    raise self.error
                if link_task in done:
                    link_task.result()
        finally:
            for task in (joined, halted):
                task.cancel()

    def _summary(self, link: Link, recording: CsvRecording | None) -> dict[str, Any]:
        """The run's summary (:func:`client.summary.client_summary`), written to ``--summary``."""
        opts, host = self.opts, self.host
        head = {
            "name": opts.name,
            "device": opts.device,
            "profile": opts.profile,
            "local_model": opts.local_model,
        }
        summary = client_summary(head, self.session, link, self.servo, host.recorder, self.updates)
        summary["gain_tables"] = self.gain_preload  # shipped and cached designs loaded
        summary["gain_build"] = self.gain_build  # the device's table built before joining
        summary["anchor"] = self.anchor  # where the scripted hand worked
        summary["clock_origin_s"] = self.origin_s  # time.perf_counter() at t_s = 0
        summary["stopped_by"] = self.signal or ("error" if self.error is not None else "end")
        summary["servo_rate_hz_set"] = opts.servo_rate_hz
        summary["servo_host"] = "process" if isinstance(host, ServoProcess) else "thread"
        summary["servo_realtime"] = host.realtime
        if opts.lobby is not None:  # where the lobby sent this client, in order
            summary["lobby"] = {
                "room": opts.room,
                "asks": link.lobby_asks,
                "joined": list(link.joined_urls),
            }
        summary.update(host.counters)
        if recording is not None:
            summary["record"] = {
                "path": str(opts.record),
                "rows": recording.rows_written,
                "rows_dropped": recording.rows_dropped,
                "error": recording.error,
            }
        if opts.summary is not None:
            opts.summary.parent.mkdir(parents=True, exist_ok=True)
            opts.summary.write_text(json.dumps(summary, indent=2))
        return summary


def _check_whole_rate_ratio(servo_rate_hz: float, sim_rate_hz: float) -> None:
    """N must be whole: the local model's lifted loop (paper section 3).

    Raises
    ------
    ValueError
        The servo rate is not a whole multiple of the server's simulation rate; the message
        names the ``--servo-rate`` that would fit.
    """
    try:
        rate_ratio(servo_rate_hz, sim_rate_hz)
    except ValueError:
        fit = max(1, round(servo_rate_hz / sim_rate_hz)) * sim_rate_hz
        raise ValueError(
            f"the server simulates at {sim_rate_hz:g} Hz and this client's servo rate "
            f"{servo_rate_hz:g} Hz is not a whole multiple of it; run the client with "
            f"--servo-rate {fit:g}, or the server at a rate that divides "
            f"{servo_rate_hz:g} Hz"
        ) from None


def passivity_on(choice: Literal["auto", "on", "off"], local_model: Literal["p", "pi"]) -> bool:
    """Whether the servo runs the passivity observer and controller at the device port
    (``--passivity``): ``auto`` (the default) for either local model.

    Once only for PI. With its damper kept at the device port (the object is pushed by the
    coupling: :class:`client.servo.ServoCore`), it also stops the compensated P model's ring on a
    damper the server does not report: 28-31 mm with the box's heavy, soft, lightly damped hand,
    0.07-0.09 mm with it (docs/stability.md). ``local_model`` is kept for callers that ask per
    model."""
    del local_model
    return choice != "off"


def _local_model_params(
    opts: ClientOptions, device: BuiltDevice, sim_rate_hz: float
) -> LocalModelParams:
    """The local model's fixed parameters for this device (gains come with each patch)."""
    lim = device.limits
    period = 1.0 / opts.servo_rate_hz
    return LocalModelParams(
        k_h=1.0,
        servo_period_s=period,
        threshold=threshold_for(
            opts.theta_mode,
            opts.local_model,
            opts.theta_m,
            device.encoder_resolution_m,
            period,
        ),
        release_time_s=2.0 / sim_rate_hz,
        # anti-windup at what the device may display for long: its continuous force when it
        # states one (a hold must not ask for the peak force for seconds), else its peak
        integral_limit_n=lim.max_continuous_force_n or lim.max_force_n,
        # new gains in the middle of a press change the force smoothly, never in one tick
        gain_transfer_s=GAIN_TRANSFER_S,
    )
