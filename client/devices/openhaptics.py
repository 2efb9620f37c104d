"""3D Systems Touch and Phantom devices through OpenHaptics' HD API (``--device openhaptics``).

Why one module: the HD API's codes, our ctypes calls into libHD, the scheduler callback with the
slot it shares and the device that reads and writes that slot are one threading contract with
OpenHaptics' one scheduler per process, and are read together; the pure limits and frames are
:mod:`client.devices.openhaptics_limits`.

Spec: ``openhaptics``, ``openhaptics:DEVICE_NAME`` (the name given in Touch Setup / Phantom
Configuration, default ``Default Device``), and optionally ``,scale=S`` after it
(``openhaptics:Default Device,scale=2`` or ``openhaptics:scale=2``): one metre of stylus motion
is ``S`` metres in the world. docs/device-openhaptics.md has the details.

The vendor binding ``pyOpenHaptics`` (the ``openhaptics`` extra, :func:`shared.extras.install_hint`) is imported
only when the backend is checked, listed or a device opened: it loads ``libHD.so``, which only
3D Systems' OpenHaptics driver provides, and fails with ``OSError`` (not ``ImportError``) without
it.

Threading. OpenHaptics' servo scheduler owns the device clock: the HD state (position, buttons,
force) may only be read and written between ``hdBeginFrame`` and ``hdEndFrame`` inside a callback
the scheduler runs on its own thread, once per tick. Our servo thread must never wait on that
thread. So one asynchronous scheduler callback of ours (a ``ctypes.CFUNCTYPE``, :class:`_Session`)
does, each scheduler tick: begin frame, read position, velocity and buttons, set the latest
commanded force, end frame, then ``hdGetError``. It exchanges data with :meth:`Device.read` and
:meth:`Device.write` through a small lock-protected slot (:class:`_Slot`: latest position in,
latest force out); both sides hold the lock only to copy a few numbers. The binding's
``@hd_callback`` is not used: it turns an HD error code it does not know (among them
``HD_EXCEEDED_MAX_FORCE`` and ``HD_EXCEEDED_MAX_VELOCITY``) into a ``KeyError`` inside the
callback, which ctypes reports as ``HD_CALLBACK_DONE``: the device would silently stop. The
per-tick calls go through our own ctypes function objects on the binding's library
(``lib["hdGetDoublev"]`` makes a new function object), because the binding's helpers reassign
``argtypes`` on a function object shared by every thread at each call. The binding does the rest:
it loads the library, initializes the device (its handle check is wrong: it compares with
``HD_BAD_HANDLE``, not ``HD_INVALID_HANDLE``, so we check the handle and ``hdGetError``
ourselves), reads the model, the limits (before the scheduler starts: its getters are not
thread-safe), starts and stops the scheduler and disables the device. The callback is Python: it
needs the GIL each tick (the servo loop shortens the interpreter's switch interval while it
runs).

Units, frames and limits. HD reports millimetres, mm/s and newtons in the device frame (x to the
user's right, y up, z toward the user); :mod:`client.devices.openhaptics_limits` maps them to the
world frame with the workspace scale and holds the limits (the SDK's, else CHAI3D's table for the
model).

Faults. A failed ``hdInitDevice`` is a :class:`DeviceOpenError` (one line, what to do). Once open,
an HD error in the callback (exceeded max force or velocity, a communication error when the
device is unplugged) or a scheduler that stops calling back sets :attr:`Device.fault`; the
callback then sends one frame of zero force and unschedules itself. :meth:`OpenHapticsDevice.reopen`
tears the HD session down and opens it again.

OpenHaptics has one scheduler per process: one ``openhaptics`` device per client process.
"""

from __future__ import annotations

import atexit
import ctypes
import importlib
import importlib.util
import math
import threading
import time
from dataclasses import dataclass
from typing import Any

from haptic_collab.client.devices._vendor import (
    PLACEHOLDER_CENTER,
    opened_by,
    standoff_center,
    workspace_scale,
)
from haptic_collab.client.devices.backends import (
    DeviceBackend,
    DeviceError,
    DeviceOpenError,
    DeviceOptions,
    one_line,
)
from haptic_collab.client.devices.base import Device, Vec3
from haptic_collab.client.devices.openhaptics_limits import (
    HdLimits,
    device_to_world,
    device_vector_to_world,
    world_force_to_device,
    world_limits,
)
from haptic_collab.shared.extras import install_hint

__all__ = [
    "BACKEND",
    "DEFAULT_DEVICE_NAME",
    "OpenHapticsBackend",
    "OpenHapticsDevice",
    "parse_spec",
]

#: The device ``hdInitDevice`` opens when the spec names none.
DEFAULT_DEVICE_NAME = "Default Device"
#: The Python package of the vendor binding (import name, case-sensitive).
BINDING = "pyOpenHaptics"
#: What to install, for :meth:`OpenHapticsBackend.available`'s message.
INSTALL_HINT = (
    f"{install_hint('openhaptics')} and install the OpenHaptics driver from 3D Systems "
    "(OpenHaptics and the Touch device driver, which provide libHD.so)"
)
#: How long [s] :meth:`OpenHapticsDevice.open` waits for the scheduler's first call of our callback.
FIRST_TICK_TIMEOUT_S = 1.0
#: How long [s] :meth:`OpenHapticsDevice.close` waits for the callback to send its zero force.
STOP_TIMEOUT_S = 0.1
#: A scheduler that has not called our callback for this long [s] is a fault (device gone).
STALE_AFTER_S = 0.5

# -- HD API values (the public OpenHaptics HD API; the binding's hd_define.py has the same) ----------

HD_INVALID_HANDLE = 0xFFFFFFFF
HD_CALLBACK_DONE = 0
HD_CALLBACK_CONTINUE = 1
HD_MAX_SCHEDULER_PRIORITY = 0xFFFF
HD_CURRENT_BUTTONS = 0x2000
HD_CURRENT_POSITION = 0x2050
HD_CURRENT_VELOCITY = 0x2051
HD_DEVICE_MODEL_TYPE = 0x2501
HD_USABLE_WORKSPACE_DIMENSIONS = 0x2551
HD_NOMINAL_MAX_STIFFNESS = 0x2602
HD_NOMINAL_MAX_FORCE = 0x2603
HD_NOMINAL_MAX_CONTINUOUS_FORCE = 0x2604
HD_SOFTWARE_VELOCITY_LIMIT = 0x2606
HD_NOMINAL_MAX_DAMPING = 0x2609
HD_CURRENT_FORCE = 0x2700
HD_FORCE_OUTPUT = 0x4000

#: HD error codes and names (OpenHaptics' ``HD_*`` error constants).
HD_ERRORS: dict[int, str] = {
    0x0100: "HD_INVALID_ENUM",
    0x0101: "HD_INVALID_VALUE",
    0x0103: "HD_INVALID_OPERATION",
    0x0104: "HD_BAD_HANDLE",
    0x0200: "HD_WARM_MOTORS",
    0x0201: "HD_EXCEEDED_MAX_FORCE",
    0x0202: "HD_EXCEEDED_MAX_FORCE_IMPULSE",
    0x0203: "HD_EXCEEDED_MAX_VELOCITY",
    0x0204: "HD_FORCE_ERROR",
    0x0300: "HD_DEVICE_FAULT",
    0x0301: "HD_DEVICE_ALREADY_INITIATED",
    0x0302: "HD_COMM_ERROR",
    0x0303: "HD_COMM_CONFIG_ERROR",
    0x0304: "HD_TIMER_ERROR",
    0x0400: "HD_ILLEGAL_BEGIN",
    0x0401: "HD_ILLEGAL_END",
    0x0402: "HD_FRAME_ERROR",
    0x0500: "HD_INVALID_PRIORITY",
    0x0501: "HD_SCHEDULER_FULL",
    0x0600: "HD_INVALID_LICENSE",
}

#: What an HD error in the servo callback means to the user.
_ERROR_HINTS: dict[int, str] = {
    0x0200: "the motors are too warm; let the device cool down",
    0x0201: "the commanded force exceeded the device's maximum",
    0x0202: "the force changed faster than the device allows",
    0x0203: "the stylus moved faster than the driver's velocity limit",
    0x0300: "device unplugged or powered off?",
    0x0302: "device unplugged or powered off?",
    0x0304: "the driver's timer failed",
}


def hd_error_text(code: int, internal: int = 0) -> str:
    """``0x0201 HD_EXCEEDED_MAX_FORCE`` (and the driver's internal code when it gave one)."""
    name = HD_ERRORS.get(code, "unknown HD error")
    return f"HD error 0x{code:04x} {name}" + (f" (internal {internal})" if internal else "")


# -- spec -----------------------------------------------------------------------------------------------

SPEC_FORM = "openhaptics[:DEVICE_NAME][,scale=S]"


def parse_spec(args: str) -> tuple[str, float]:
    """``(device name, scale)`` of the ``ARGS`` of ``openhaptics:ARGS``.

    ``ARGS`` is ``[DEVICE_NAME][,scale=S]``: comma-separated parts; a part with ``=`` is an option
    (only ``scale``, a number in (0, 100]: :func:`_vendor.workspace_scale`), the other part (at most one) the device
    name. A device name cannot contain ``,`` or ``=``.

    Raises
    ------
    DeviceError
        An unknown option, a bad scale, or two names.
    """
    spec = f"openhaptics:{args}" if args else "openhaptics"
    name: str | None = None
    scale = 1.0
    for part in args.split(","):
        key, eq, value = part.partition("=")
        if eq:
            if key.strip() != "scale":
                raise DeviceError(
                    f"unknown option {key.strip()!r} in {spec!r}: the spec is {SPEC_FORM} "
                    "(see docs/device-openhaptics.md)"
                )
            scale = workspace_scale(spec, value, f"the spec is {SPEC_FORM}")
        elif part.strip():
            if name is not None:
                raise DeviceError(
                    f"{spec!r} names two devices ({name!r}, {part.strip()!r}): the spec is "
                    f"{SPEC_FORM}"
                )
            name = part.strip()
    return (name or DEFAULT_DEVICE_NAME), scale


# -- the binding and our own calls into its library ----------------------------------------------------


def _binding() -> Any:
    """``pyOpenHaptics.hd`` (imported now: it loads libHD.so).

    Raises
    ------
    ImportError
        pyOpenHaptics is not installed.
    OSError
        libHD.so cannot be loaded (the OpenHaptics driver is not installed).
    """
    return importlib.import_module(f"{BINDING}.hd")


def _missing_message() -> str | None:
    """None when the binding imports and libHD loads; else one line: what is missing, what to do."""
    try:
        found = importlib.util.find_spec(BINDING) is not None
    except (ImportError, ValueError):
        found = False
    if not found:
        return f"the openhaptics backend needs the {BINDING} package, which is not installed: {INSTALL_HINT}"
    try:
        _binding()
    except ImportError as exc:
        return f"the openhaptics backend cannot import {BINDING} ({one_line(exc)}): {INSTALL_HINT}"
    except OSError as exc:
        return (
            f"the openhaptics backend cannot load libHD.so, the OpenHaptics driver's library "
            f"({one_line(exc)}): {INSTALL_HINT}"
        )
    return None


class _ErrorInfo(ctypes.Structure):
    """HD's ``HDErrorInfo`` (returned by value by ``hdGetError``)."""

    _fields_ = [
        ("errorCode", ctypes.c_uint),
        ("internalErrorCode", ctypes.c_int),
        ("hHD", ctypes.c_uint),
    ]


#: ``HDCallbackCode (*)(void *)``: a scheduler callback.
_CALLBACK = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_void_p)


class _Native:
    """Our own function objects on the binding's libHD (their argtypes are ours alone)."""

    def __init__(self, lib: Any) -> None:
        def fn(name: str, restype: Any, *argtypes: Any) -> Any:
            f = lib[name]  # a new function object each time (lib.NAME is shared and cached)
            f.restype = restype
            f.argtypes = list(argtypes)
            return f

        u, d, i = ctypes.c_uint, ctypes.POINTER(ctypes.c_double), ctypes.POINTER(ctypes.c_int)
        self.begin_frame = fn("hdBeginFrame", None, u)
        self.end_frame = fn("hdEndFrame", None, u)
        self.get_doublev = fn("hdGetDoublev", None, u, d)
        self.get_integerv = fn("hdGetIntegerv", None, u, i)
        self.set_doublev = fn("hdSetDoublev", None, u, d)
        self.get_error = fn("hdGetError", _ErrorInfo)
        self.enable = fn("hdEnable", None, u)
        self.disable = fn("hdDisable", None, u)
        self.schedule_async = fn(
            "hdScheduleAsynchronous", ctypes.c_ulong, _CALLBACK, ctypes.c_void_p, ctypes.c_ushort
        )
        self.unschedule = fn("hdUnschedule", None, ctypes.c_ulong)

    def errors(self, limit: int = 16) -> list[tuple[int, int]]:
        """Pop the pending HD errors: ``[(code, internal code), ...]`` (empty: none)."""
        out: list[tuple[int, int]] = []
        for _ in range(limit):
            e = self.get_error()
            if not e.errorCode:
                break
            out.append((int(e.errorCode), int(e.internalErrorCode)))
        return out


@dataclass
class _Connection:
    """An initialized device (``hdInitDevice`` done, scheduler not started)."""

    hd: Any
    native: _Native
    handle: int
    model: str
    vendor: str
    limits: HdLimits
    released: bool = False

    def release(self) -> None:
        """``hdDisableDevice`` (once); never raises."""
        if self.released:
            return
        self.released = True
        try:
            self.native.disable(HD_FORCE_OUTPUT)
            self.hd.close_device(self.handle)
            self.native.errors()
        except Exception:  # a driver that errors while we let go of it: nothing more to do
            pass


#: Serializes opening and closing (OpenHaptics has one scheduler per process).
_HD_LOCK = threading.RLock()


def _connect(device_name: str, spec: str) -> _Connection:
    """Initialize the device and read its model and limits (scheduler not started).

    Raises
    ------
    DeviceOpenError
        The binding cannot be loaded, or ``hdInitDevice`` failed (one line, what to do).
    """
    try:
        hd = _binding()
    except (ImportError, OSError):
        raise DeviceOpenError(
            f"cannot open {spec}: {_missing_message() or 'the binding cannot be loaded'}"
        ) from None
    native = _Native(hd._lib_hd)
    native.errors()  # stale errors of an earlier session
    handle = hd.init_device(device_name)  # the binding: None or HD_INVALID_HANDLE on failure
    errs = native.errors()
    if handle is None or int(handle) == HD_INVALID_HANDLE or errs:
        why = "; ".join(hd_error_text(c, i) for c, i in errs) or "invalid device handle"
        if handle is not None and int(handle) != HD_INVALID_HANDLE:
            _Connection(hd, native, int(handle), "", "", HdLimits.fallback("")).release()
        raise DeviceOpenError(
            f"cannot open {spec}: hdInitDevice({device_name!r}) failed ({why}); plug the device "
            "in and power it, check its name and that it is configured in Touch Setup (or "
            "Phantom Configuration), and that no other program holds it"
        )
    handle = int(handle)

    def text(getter: Any) -> str:
        try:
            return str(getter())
        except Exception:  # a NULL string (AttributeError on None.decode()) or a driver error
            return ""

    model, vendor = text(hd.get_model), text(hd.get_vendor)
    native.errors()

    def one(code: int) -> float | None:
        v = hd._get_doublev(code, ctypes.c_double).value
        return None if native.errors() else float(v)

    ws_raw = hd._get_doublev(HD_USABLE_WORKSPACE_DIMENSIONS, ctypes.c_double * 6)
    ws = None if native.errors() else [float(v) for v in ws_raw]
    limits = HdLimits.from_sdk(
        model,
        max_force=one(HD_NOMINAL_MAX_FORCE),
        max_continuous_force=one(HD_NOMINAL_MAX_CONTINUOUS_FORCE),
        max_stiffness_n_per_mm=one(HD_NOMINAL_MAX_STIFFNESS),
        max_damping_n_per_mm_s=one(HD_NOMINAL_MAX_DAMPING),
        velocity_limit_mm_s=one(HD_SOFTWARE_VELOCITY_LIMIT),
        usable_workspace_mm=ws,
    )
    return _Connection(hd, native, handle, model, vendor, limits)


# -- the scheduler side ----------------------------------------------------------------------------------

_ZERO: Vec3 = (0.0, 0.0, 0.0)


class _Slot:
    """What the scheduler callback and the servo thread exchange (under :attr:`lock`).

    In (callback -> servo): position [mm] and velocity [mm/s] in the device frame, buttons, the
    number of ticks, the first HD error. Out (servo -> callback): the force [N] in the device frame,
    and ``stop``.
    """

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.position_mm: Vec3 = _ZERO
        self.velocity_mm_s: Vec3 = _ZERO
        self.buttons = 0
        self.ticks = 0
        self.error: tuple[int, int] | None = None
        #: The exception that ended the callback (error code -1), as one line.
        self.exception: str | None = None
        self.force_n: Vec3 = _ZERO
        self.stop = False
        #: Set by the callback once it returned HD_CALLBACK_DONE (after a zero-force frame).
        self.finished = threading.Event()
        #: Set by the callback after its first tick.
        self.started = threading.Event()


class _Session:
    """The scheduler running our callback on one connection."""

    def __init__(self, conn: _Connection) -> None:
        self.conn = conn
        self.slot = _Slot()
        self.callback = _CALLBACK(self._tick)  # kept alive as long as the scheduler may call it
        self.sched_handle: int | None = None
        self.stopped = False
        native, handle, slot = conn.native, conn.handle, self.slot
        pos = (ctypes.c_double * 3)()
        vel = (ctypes.c_double * 3)()
        force = (ctypes.c_double * 3)()
        btn = ctypes.c_int(0)
        begin, end = native.begin_frame, native.end_frame
        get_d, get_i, set_d, get_error = (
            native.get_doublev,
            native.get_integerv,
            native.set_doublev,
            native.get_error,
        )

        def tick() -> int:
            with slot.lock:
                last = slot.stop or slot.error is not None
                f = _ZERO if last else slot.force_n
            force[0], force[1], force[2] = f
            begin(handle)
            try:
                get_d(HD_CURRENT_POSITION, pos)
                get_d(HD_CURRENT_VELOCITY, vel)
                get_i(HD_CURRENT_BUTTONS, ctypes.byref(btn))
                set_d(HD_CURRENT_FORCE, force)
            finally:
                end(handle)
            e = get_error()
            with slot.lock:
                slot.position_mm = (pos[0], pos[1], pos[2])
                slot.velocity_mm_s = (vel[0], vel[1], vel[2])
                slot.buttons = int(btn.value)
                slot.ticks += 1
                if e.errorCode and slot.error is None:
                    slot.error = (int(e.errorCode), int(e.internalErrorCode))
            slot.started.set()
            if last:  # this frame sent zero force: done
                slot.finished.set()
                return HD_CALLBACK_DONE
            return HD_CALLBACK_CONTINUE

        self._do_tick = tick

    def _tick(self, _user_data: int | None) -> int:
        """The scheduler callback (HD's servo thread): never raises into ctypes."""
        try:
            return self._do_tick()
        except BaseException as exc:  # an exception must not cross into C
            slot = self.slot
            with slot.lock:
                if slot.error is None:
                    slot.error = (-1, 0)
                slot.exception = f"{type(exc).__name__}: {one_line(exc)}"
            slot.finished.set()
            return HD_CALLBACK_DONE

    def start(self, spec: str) -> None:
        """Schedule the callback, enable forces, start the scheduler, wait for the first tick.

        Raises
        ------
        DeviceOpenError
            The scheduler did not start or did not call back (the session is stopped).
        """
        conn = self.conn
        native = conn.native
        native.errors()
        self.sched_handle = int(
            native.schedule_async(self.callback, None, HD_MAX_SCHEDULER_PRIORITY)
        )
        native.enable(HD_FORCE_OUTPUT)
        conn.hd.start_scheduler()
        errs = native.errors()
        if errs or not self.slot.started.wait(FIRST_TICK_TIMEOUT_S):
            self.stop()
            why = (
                "; ".join(hd_error_text(c, i) for c, i in errs)
                or f"the HD scheduler did not call back within {FIRST_TICK_TIMEOUT_S:g} s"
            )
            raise DeviceOpenError(
                f"cannot open {spec}: the HD servo scheduler did not start ({why}); check the "
                "device with Touch Diagnostic and that no other program holds it"
            )
        atexit.register(self.stop)

    def stop(self) -> None:
        """Zero the force, end the callback, stop the scheduler, disable the device; never
        raises, safe twice."""
        if self.stopped:
            return
        self.stopped = True
        atexit.unregister(self.stop)
        slot, conn = self.slot, self.conn
        with slot.lock:
            slot.force_n = _ZERO
            slot.stop = True
        try:
            if slot.started.is_set() and not slot.finished.wait(STOP_TIMEOUT_S):
                pass  # the scheduler stopped calling back: unschedule it below
            if not slot.finished.is_set() and self.sched_handle is not None:
                conn.native.unschedule(self.sched_handle)
            conn.hd.stop_scheduler()
        except Exception:  # closing must not raise; the device is disabled below in any case
            pass
        conn.release()


# -- the device -------------------------------------------------------------------------------------------


class OpenHapticsDevice(Device):
    """A Touch / Phantom device through OpenHaptics' HD API (see the module's docstring).

    Parameters
    ----------
    device_name : str
        The name ``hdInitDevice`` opens (``Default Device``).
    scale : float
        World metres per metre of stylus motion, > 0.
    center : (3,) float
        Where [m, world frame] the centre of the device's usable workspace goes.
    spec : str, optional
        The ``--device`` text, for messages (default ``openhaptics:DEVICE_NAME``).

    Attributes
    ----------
    hd_limits : HdLimits
        The device's limits in its own frame (CHAI3D's for an unknown model until the device is
        initialized, then the SDK's).
    velocity_m_s : (3,) float
        The stylus velocity [m/s, world frame] as of the last :meth:`read`.
    model, vendor : str
        What the driver says (empty until initialized).
    """

    has_buttons = True

    def __init__(
        self, device_name: str, scale: float, center: Vec3, spec: str | None = None
    ) -> None:
        self.device_name = device_name
        self.scale = float(scale)
        self.center = center
        self.spec = spec or f"openhaptics:{device_name}"
        self.name = self.spec
        self.model = ""
        self.vendor = ""
        self.hd_limits = HdLimits.fallback("")
        self.limits = world_limits(self.hd_limits, self.scale, center)
        self.fault: str | None = None
        self.velocity_m_s: Vec3 = _ZERO
        self._conn: _Connection | None = None
        self._session: _Session | None = None
        self._enabled = False
        self._last: Vec3 = center
        self._buttons = 0
        self._seen_ticks = -1
        self._seen_t = 0.0

    # -- set-up (not on the servo thread) --

    def _adopt(self, conn: _Connection) -> None:
        self._conn = conn
        self.model, self.vendor = conn.model, conn.vendor
        self.hd_limits = conn.limits
        self.limits = world_limits(conn.limits, self.scale, self.center)
        if conn.model:
            self.name = f"{self.spec} ({conn.model})"

    def acquire(self) -> None:
        """Initialize the device now and keep it (before the network); read its limits.

        Raises
        ------
        DeviceOpenError
            It cannot be initialized (one line, what to do).
        """
        with _HD_LOCK:
            if self._conn is None and self._session is None:
                self._adopt(_connect(self.device_name, self.spec))

    def place_at(self, center: Vec3) -> None:
        """Move the workspace centre to ``center`` [m, world frame] (before :meth:`open`)."""
        self.center = center
        self.limits = world_limits(self.hd_limits, self.scale, center)
        self._last = center

    def _start(self) -> _Session:
        """A running session on the held connection (initialized now if none is held)."""
        if self._conn is None or self._conn.released:
            self._adopt(_connect(self.device_name, self.spec))
        conn = self._conn
        assert conn is not None
        self._conn = None
        session = _Session(conn)
        session.start(self.spec)  # stops and releases the connection if it fails
        return session

    def open(self) -> None:
        """Initialize the device (unless :meth:`acquire` did), start the servo scheduler.

        Raises
        ------
        DeviceOpenError
            The device cannot be initialized or its scheduler does not run.
        """
        with _HD_LOCK:
            if self._session is not None:
                return
            session = self._start()
            self._session = session
            self._enabled = False
            self._seen_ticks, self._seen_t = -1, time.monotonic()
            self.fault = None
            self.read(0.0)

    def reopen(self) -> bool:
        """Tear the faulted HD session down and open it again (the device came back).

        Runs on the client's network thread while :attr:`fault` is set; :meth:`read` and
        :meth:`write` touch only the slot of the session they find, so the session is swapped
        safely. Forces stay enabled as they were; :attr:`fault` is cleared last.

        Raises
        ------
        OSError
            The device cannot be opened yet (the fault stays set).
        """
        with _HD_LOCK:
            if self.fault is None:
                return False
            old, self._session = self._session, None
            if old is not None:
                old.stop()
            session = self._start()
            self._seen_ticks, self._seen_t = -1, time.monotonic()
            self._session = session
            self.fault = None
            return True

    def close(self) -> None:
        """Zero the force, stop the scheduler, disable the device; safe twice."""
        with _HD_LOCK:
            self._enabled = False
            session, self._session = self._session, None
            conn, self._conn = self._conn, None
            if session is not None:
                session.stop()
            if conn is not None:
                conn.release()

    # -- the servo thread --

    def read(self, t_s: float) -> Vec3:
        """The stylus position [m, world frame] the scheduler's last tick read; never raises."""
        session = self._session
        if session is None or self.fault is not None:
            return self._last
        slot = session.slot
        with slot.lock:
            p, v, buttons, ticks, error = (
                slot.position_mm,
                slot.velocity_mm_s,
                slot.buttons,
                slot.ticks,
                slot.error,
            )
        if error is not None:
            self.fault = self._error_message(session, error)
            return self._last
        now = time.monotonic()
        if ticks != self._seen_ticks:
            self._seen_ticks, self._seen_t = ticks, now
        elif now - self._seen_t > STALE_AFTER_S:
            self.fault = (
                f"{self.name}: the HD servo scheduler has not run for "
                f"{now - self._seen_t:.2f} s; device unplugged or driver stopped?"
            )
            return self._last
        s = self.scale
        self._last = device_to_world(
            (p[0] * 1e-3, p[1] * 1e-3, p[2] * 1e-3), self.center, self.hd_limits.center_m, s
        )
        self.velocity_m_s = device_vector_to_world((v[0] * 1e-3, v[1] * 1e-3, v[2] * 1e-3), s)
        self._buttons = buttons
        return self._last

    def _error_message(self, session: _Session, error: tuple[int, int]) -> str:
        code, internal = error
        if code == -1:
            what = session.slot.exception or "an exception"
            return f"{self.name}: the servo callback failed ({what}); forces off"
        hint = _ERROR_HINTS.get(code)
        return (
            f"{self.name}: {hd_error_text(code, internal)} in the servo callback"
            + (f" ({hint})" if hint else "")
            + "; forces off"
        )

    def write(self, fx: float, fy: float, fz: float) -> None:
        """Hand the force (fx, fy, fz) [N, world frame] to the next scheduler tick; never raises.

        Ignored while forces are disabled or the device is faulted (the callback then sends zero
        force). Not clamped here: the servo loop clamps to ``limits.max_force_n``, and the
        driver's own check is a fault.
        """
        session = self._session
        if session is None:
            return
        f = world_force_to_device((fx, fy, fz))
        if not (self._enabled and self.fault is None) or not all(map(math.isfinite, f)):
            f = _ZERO
        slot = session.slot
        with slot.lock:
            slot.force_n = f

    def enable_forces(self) -> None:
        """Let :meth:`write` command forces."""
        self._enabled = True

    def disable_forces(self) -> None:
        """Command zero force from the next tick on and ignore writes until enabled."""
        self._enabled = False
        session = self._session
        if session is not None:
            with session.slot.lock:
                session.slot.force_n = _ZERO

    def buttons(self) -> int:
        """The stylus buttons as of the last :meth:`read` (bit 0: the first button)."""
        return self._buttons


# -- the backend ------------------------------------------------------------------------------------------


class OpenHapticsBackend(DeviceBackend):
    """``openhaptics[:DEVICE_NAME][,scale=S]``: a 3D Systems Touch / Phantom through OpenHaptics.

    :meth:`open` parses the spec and, when the client is about to run (``options.acquire``),
    initializes the device and reads its limits before any network; :meth:`place` moves the
    device's workspace centre just outside the anchor (the device keeps what it holds).
    """

    name = "openhaptics"
    description = (
        "a 3D Systems Touch or Phantom through OpenHaptics (pyOpenHaptics): "
        "openhaptics[:DEVICE_NAME][,scale=S]"
    )

    def available(self) -> str | None:
        """None when pyOpenHaptics imports and libHD.so loads; else one line."""
        return _missing_message()

    def detect(self) -> list[dict[str, Any]]:
        """The default device when it can be initialized now (it is released at once)."""
        with _HD_LOCK:
            try:
                conn = _connect(DEFAULT_DEVICE_NAME, "openhaptics")
            except OSError:
                return []
            try:
                lim = conn.limits
                return [
                    {
                        "spec": "openhaptics",
                        "kind": "openhaptics",
                        "device_name": DEFAULT_DEVICE_NAME,
                        "model": conn.model,
                        "vendor": conn.vendor,
                        "max_force_n": lim.max_force_n,
                        "max_continuous_force_n": lim.max_continuous_force_n,
                        "max_stiffness_n_per_m": lim.max_stiffness_n_per_m,
                    }
                ]
            finally:
                conn.release()

    def open(self, args: str, options: DeviceOptions) -> Device:
        name, scale = parse_spec(args)
        spec = f"openhaptics:{args}" if args else "openhaptics"
        dev = OpenHapticsDevice(name, scale, PLACEHOLDER_CENTER, spec=spec)
        if options.acquire:
            dev.acquire()  # DeviceOpenError: one line, before any network
        return dev

    def place(self, device: Device, anchor: Vec3, normal: Vec3) -> Device:
        opened_by(self, device, OpenHapticsDevice).place_at(standoff_center(anchor, normal))
        return device


BACKEND = OpenHapticsBackend()
