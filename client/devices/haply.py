"""Haply Inverse3 through Haply's HaplyHardwareAPI binding, on the device's own serial port.

``haptic client --device haply:/dev/ttyACM0`` (docs/device-haply.md). The binding
(the ``haply`` extra, :func:`shared.extras.install_hint`) is imported only when a device is opened or the backend
is checked; it talks to the Inverse3 directly over its USB serial port (no Haply service). The
spec's options and the Inverse3's assumed limits are :mod:`client.devices.haply_spec`'s.

One serial round trip per servo tick
    The binding has no scheduler of its own here: ``Inverse3.end_effector_force([fx, fy, fz])``
    sends a force [N] and returns the state ``(position [m], velocity [m/s])`` in one round trip.
    :meth:`Inverse3Device.read` performs that exchange, with the force the previous tick's
    :meth:`Inverse3Device.write` stored, and returns the fresh position; ``write`` only stores.
    So every tick costs exactly one round trip, ``read`` always returns a measurement taken at
    this tick (also when nobody writes, or while forces are disabled: a zero force is sent), and a
    silent device is noticed in ``read``, where the servo loop checks :attr:`Device.fault` right
    away. The price is that a force reaches the device at the next tick's ``read``; with one
    round trip per tick that one-tick delay exists whichever call does the exchange.
    :meth:`Inverse3Device.disable_forces` exchanges a zero force at once (the servo loop's last
    call before it stops), and :meth:`Inverse3Device.close` releases the port after that.

Faults
    The binding does not raise on a timeout: it prints ``[err] ... timeout`` on the process's
    standard error and returns zeros (or leftovers). A call that took at least the timeout, an
    exception, or a reply that is all-zero, non-finite or implausible is a fault: :attr:`fault`
    is set, a zero force is sent without waiting for an answer, and the device stops touching the
    port until :meth:`Inverse3Device.reopen`. ``read`` and ``write`` never raise.

Frames and units
    The binding speaks N, m and m/s in the Inverse3's right-handed frame, whose origin is on the
    mounting plate; its z axis is up (as in the world frame), so device axes map to world axes
    unchanged. A workspace scale ``S`` maps device metres to world metres around the workspace
    centre, placed :data:`HID_STANDOFF_M` outside the anchor:
    ``world = centre + S * (device - WORKSPACE_CENTER_DEVICE_M)``. Forces are not scaled. The
    limits the device publishes are folded accordingly (stiffness and damping / S, velocity * S,
    workspace * S, forces unchanged).

Safety traps of the binding (verified on 0.1.13): ``SerialStream(path)`` never raises and writes
into whatever ``path`` is, a regular file included, so the port is checked to be a character
device first; the ``SerialStream`` must outlive its ``Inverse3`` (which does not own it: dropping
the stream first crashes the process); ``detect_inverse3s()`` writes a wake-up byte to every
``/dev/ttyACM*`` and ``/dev/ttyUSB*`` port, so it runs only when the spec names no port.
"""

from __future__ import annotations

import importlib
import math
import os
import stat
import struct
import threading
import time
import uuid as uuidlib
from collections.abc import Sequence
from typing import Any

from haptic_collab.client.devices._vendor import PLACEHOLDER_CENTER, opened_by, standoff_center
from haptic_collab.client.devices.backends import DeviceBackend, DeviceOptions, one_line
from haptic_collab.client.devices.base import Device, Vec3
from haptic_collab.client.devices.haply_spec import (
    DEFAULT_TIMEOUT_S,
    Inverse3Specs,
    parse_haply_args,
)
from haptic_collab.shared.extras import install_hint

__all__ = [
    "BACKEND",
    "BINDING",
    "DEFAULT_OPEN_TIMEOUT_S",
    "HaplyBackend",
    "INSTALL_HINT",
    "Inverse3Device",
    "SERIAL_BY_ID",
]

#: The vendor binding's import name (PyPI ``HaplyHardwareAPI``; no license declared: we depend on
#: it and never ship it).
BINDING = "HaplyHardwareAPI"
#: What to run when the binding is missing.
INSTALL_HINT = install_hint("haply")
#: Longest wait [s] for the wake-up reply and the first state when the device is opened.
DEFAULT_OPEN_TIMEOUT_S = 0.5
#: Wake-up attempts when opening (the first may meet bytes left from an earlier session).
WAKEUP_ATTEMPTS = 2
#: Wait [s] for the wake-up reply in :meth:`Inverse3Device.reopen` (called from the client's
#: network thread, which it holds up: keep it short).
REOPEN_TIMEOUT_S = 0.1
#: A coordinate [m] farther than this from the device origin is garbage (the arm is ~0.3 m long).
MAX_PLAUSIBLE_POSITION_M = 1.0
#: A speed component [m/s] above this is garbage.
MAX_PLAUSIBLE_SPEED_M_S = 50.0
#: The wire form of "force (0, 0, 0)" (command 0x2A, three little-endian float32), sent without
#: waiting for the reply when the device faults.
ZERO_FORCE_COMMAND = bytes([0x2A]) + struct.pack("<3f", 0.0, 0.0, 0.0)
#: Where udev lists serial ports by their USB identity (read only: :meth:`HaplyBackend.detect`).
SERIAL_BY_ID = "/dev/serial/by-id"

_ZERO: Vec3 = (0.0, 0.0, 0.0)


def _import_binding() -> Any:
    """HaplyHardwareAPI, imported now (the import is lazy: only when a device needs it)."""
    return importlib.import_module(BINDING)


def _missing_binding_message() -> str | None:
    """None when HaplyHardwareAPI imports; else one line: what is missing and what to install."""
    try:
        _import_binding()
    except Exception as exc:  # an ImportError, or a compiled module that fails to load
        return (
            f"the haply backend needs Haply's {BINDING} binding, which does not import here "
            f"({one_line(exc) or type(exc).__name__}): {INSTALL_HINT}"
        )
    return None


def check_port(port: str) -> None:
    """Make sure ``port`` is a serial port this user may open, before the binding touches it.

    HaplyHardwareAPI's ``SerialStream`` never fails: it opens whatever path it gets (and writes
    into a regular file), so this is where an absent or wrong port is told apart.

    Raises
    ------
    FileNotFoundError
        No such port (the Inverse3 is unplugged, or it is another port).
    PermissionError
        The user may not read and write it (the serial-port group).
    OSError
        It is not a character device.
    """
    try:
        st = os.stat(port)
    except FileNotFoundError:
        raise FileNotFoundError(
            f"{port} does not exist: plug the Inverse3 in (USB and its power supply) or name its "
            "port (ls /dev/ttyACM* /dev/serial/by-id)"
        ) from None
    if not stat.S_ISCHR(st.st_mode):
        raise OSError(f"{port} is not a serial port (not a character device)")
    if not os.access(port, os.R_OK | os.W_OK):
        raise PermissionError(
            f"permission denied on {port}: add your user to the group that owns it (ls -l "
            f"{port}; usually `sudo usermod -aG dialout $USER`), then log in again"
        )


def _wakeup_problem(reply: Any, took_s: float, timeout_s: float) -> str | None:
    """What is wrong with a wake-up reply (``device_wakeup_dict()``), or None."""
    if took_s >= timeout_s:
        return f"no wake-up reply within {timeout_s * 1e3:.0f} ms"
    if not isinstance(reply, dict) or "device_id_ext" not in reply:
        return f"a malformed wake-up reply ({reply!r})"
    ext = reply["device_id_ext"]
    try:
        number = ext.int if isinstance(ext, uuidlib.UUID) else uuidlib.UUID(str(ext)).int
    except (TypeError, ValueError, AttributeError):
        return f"a wake-up reply without a device UUID ({ext!r})"
    if number == 0:  # what the binding returns when the reply never came, or was not an Inverse3's
        return "a wake-up reply without a device UUID (not an Inverse3?)"
    return None


def _state_problem(pos: Any, vel: Any, took_s: float, timeout_s: float) -> str | None:
    """What is wrong with a state reply of ``end_effector_force``, or None."""
    if took_s >= timeout_s:
        return f"no state reply within {timeout_s * 1e3:.0f} ms"
    try:
        p = [float(x) for x in pos]
        v = [float(x) for x in vel]
    except (TypeError, ValueError):
        return f"a malformed state reply ({pos!r}, {vel!r})"
    if len(p) != 3 or len(v) != 3:
        return f"a malformed state reply ({pos!r}, {vel!r})"
    if not all(math.isfinite(x) for x in (*p, *v)):
        return "a non-finite state reply"
    if p[0] == 0.0 and p[1] == 0.0 and p[2] == 0.0:  # the binding's value when the reply failed
        return "an all-zero state reply"
    if any(abs(x) > MAX_PLAUSIBLE_POSITION_M for x in p) or any(
        abs(x) > MAX_PLAUSIBLE_SPEED_M_S for x in v
    ):
        return "an implausible state reply (garbage on the line)"
    return None


class Inverse3Device(Device):
    """A Haply Inverse3 on its serial port, through HaplyHardwareAPI (see the module notes).

    Parameters
    ----------
    port : str or None
        The serial port (``/dev/ttyACM0``); None: HaplyHardwareAPI's detection finds it when the
        device is opened (it writes a wake-up byte to every ``/dev/ttyACM*`` and ``/dev/ttyUSB*``).
    center : (3,) float
        World position [m] of the workspace centre (:meth:`move_to` changes it).
    scale : float
        World metres per device metre (default 1).
    specs : Inverse3Specs, optional
        The device's own limits (default: the assumed ones).
    timeout_s : float
        Longest wait [s] for a state reply in the servo loop.
    open_timeout_s : float
        Longest wait [s] for the wake-up reply and the first state in :meth:`open`.
    binding : module, optional
        HaplyHardwareAPI (default: imported when the device is opened).

    Attributes
    ----------
    info : dict or None
        The wake-up reply (``device_id``, ``device_model_number``, ``hardware_version``,
        ``firmware_version``, ``device_id_ext``) once open.
    device_position : (3,) float
        The last position [m] in the Inverse3's frame; ``velocity`` is the last velocity [m/s],
        world frame.
    exchanges : int
        Successful serial round trips so far.
    """

    #: The Inverse3 has no buttons (the VerseGrip is another port): ``--engage default`` engages
    #: forces with the first patch, and :meth:`buttons` is always 0.
    has_buttons = False

    def __init__(
        self,
        port: str | None,
        *,
        center: Sequence[float] = (0.0, 0.0, 0.0),
        scale: float = 1.0,
        specs: Inverse3Specs | None = None,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        open_timeout_s: float = DEFAULT_OPEN_TIMEOUT_S,
        binding: Any = None,
    ) -> None:
        if not (math.isfinite(timeout_s) and timeout_s > 0.0):
            raise ValueError(f"timeout_s must be finite and > 0, got {timeout_s!r}")
        if not (math.isfinite(open_timeout_s) and open_timeout_s > 0.0):
            raise ValueError(f"open_timeout_s must be finite and > 0, got {open_timeout_s!r}")
        self.port = port
        self.name = f"haply:{port}" if port else "haply"
        self.scale = float(scale)
        self.specs = specs if specs is not None else Inverse3Specs()
        self.center: Vec3 = (float(center[0]), float(center[1]), float(center[2]))
        self.limits = self.specs.world_limits(self.scale, self.center)
        self.fault: str | None = None
        self.timeout_s = float(timeout_s)
        self.open_timeout_s = float(open_timeout_s)
        self.info: dict[str, Any] | None = None
        self.device_position: Vec3 = self.specs.workspace_center_m
        self.velocity: Vec3 = _ZERO
        self.exchanges = 0
        self._binding = binding
        self._lock = threading.Lock()  # one exchange on the port at a time
        # _inverse3 is declared first so that even a device dropped without close() lets go of it
        # before the stream (attributes are released in order); the stream must outlive it.
        self._inverse3: Any = None
        self._stream: Any = None  # kept alive as long as _inverse3: it does not own the stream
        self._enabled = False
        self._force: Vec3 = _ZERO  # device frame, sent by the next read()
        self._pos: Vec3 = self.center

    # -- placement -----------------------------------------------------------------------------------

    def move_to(self, center: Sequence[float]) -> None:
        """Put the workspace centre at ``center`` (3,) [m], world frame (the limits follow)."""
        self.center = (float(center[0]), float(center[1]), float(center[2]))
        self.limits = self.specs.world_limits(self.scale, self.center)
        self._pos = self._to_world(self.device_position)

    def _to_world(self, p: Sequence[float]) -> Vec3:
        c, s, d = self.center, self.scale, self.specs.workspace_center_m
        return (
            c[0] + s * (float(p[0]) - d[0]),
            c[1] + s * (float(p[1]) - d[1]),
            c[2] + s * (float(p[2]) - d[2]),
        )

    # -- connection ------------------------------------------------------------------------------------

    @property
    def is_open(self) -> bool:
        """Whether the device holds its port."""
        return self._inverse3 is not None

    def _module(self) -> Any:
        if self._binding is None:
            try:
                self._binding = _import_binding()
            except Exception as exc:  # ImportError, or a compiled module that fails to load
                raise OSError(
                    f"{BINDING} does not import ({one_line(exc) or type(exc).__name__}): "
                    f"{INSTALL_HINT}"
                ) from None
        return self._binding

    def _find_port(self, binding: Any) -> str:
        """The port HaplyHardwareAPI's detection finds (it writes 0x0A to every serial port)."""
        try:
            found = [str(p) for p in binding.detect_inverse3s()]
        except Exception as exc:  # a third party's scan: say it failed, do not crash
            raise OSError(f"{BINDING}'s detection failed: {one_line(exc)}") from None
        if not found:
            raise FileNotFoundError(
                "no Inverse3 answered on /dev/ttyACM* or /dev/ttyUSB*; plug it in (USB and its "
                "power supply), check the port's permissions, or name the port: "
                "--device haply:/dev/ttyACM0"
            )
        if len(found) > 1:
            raise OSError(
                f"several Inverse3 answered ({', '.join(found)}); name one: --device haply:{found[0]}"
            )
        return found[0]

    def _connect(self, wakeup_timeout_s: float, attempts: int) -> None:
        """Open the port, check the wake-up reply and one state, and keep hold of the port.

        Raises
        ------
        OSError
            The port is absent, not a serial port or not ours to open, or nothing on it answers
            like an Inverse3.
        """
        binding = self._module()
        port = self.port if self.port is not None else self._find_port(binding)
        check_port(port)
        adjustable = hasattr(binding.Inverse3, "set_read_timeout")
        first_timeout = wakeup_timeout_s if adjustable else self.timeout_s
        stream = binding.SerialStream(port)
        inverse3 = binding.Inverse3(stream, first_timeout)
        try:
            problem: str | None = "no wake-up attempted"
            info: Any = None
            for _ in range(max(1, attempts)):
                if hasattr(inverse3, "flush_input"):
                    inverse3.flush_input()  # bytes left from an earlier session
                t0 = time.perf_counter()
                info = inverse3.device_wakeup_dict()
                problem = _wakeup_problem(info, time.perf_counter() - t0, first_timeout)
                if problem is None:
                    break
            if problem is not None:
                raise OSError(f"nothing on {port} answers like an Inverse3 ({problem})")
            t0 = time.perf_counter()
            pos, vel = inverse3.end_effector_force([0.0, 0.0, 0.0])
            problem = _state_problem(pos, vel, time.perf_counter() - t0, first_timeout)
            if problem is not None:
                raise OSError(f"the Inverse3 on {port} woke up but sent {problem}")
            if adjustable:
                inverse3.set_read_timeout(self.timeout_s)
        except OSError:
            del inverse3  # the Inverse3 goes before the stream it uses
            del stream
            raise
        except Exception as exc:  # the binding raised something else: the port is unusable
            del inverse3
            del stream
            raise OSError(f"{BINDING} failed on {port}: {one_line(exc)}") from None
        with self._lock:
            self._stream, self._inverse3 = stream, inverse3
        self.port = port
        self.name = f"haply:{port}"
        self.info = dict(info)
        self._set_state(pos, vel)

    def _release(self) -> None:
        """Let go of the port: the Inverse3 object first, then the stream it uses."""
        with self._lock:
            inverse3, stream = self._inverse3, self._stream
            self._inverse3 = self._stream = None
        del inverse3  # the Inverse3 goes first: it uses the stream but does not own it
        del stream

    def open(self) -> None:
        """Open the port and wake the Inverse3 (forces disabled).

        A device that already holds its port (opened before the network) checks that the
        Inverse3 still answers, and opens it again if not.

        Raises
        ------
        OSError
            The port is absent, not a serial port or not ours to open, or nothing on it answers
            like an Inverse3 (one line: what and what to do).
        """
        self._enabled = False
        self._force = _ZERO
        if self._inverse3 is not None:
            with self._lock:
                if hasattr(self._inverse3, "flush_input"):
                    self._inverse3.flush_input()
            self.fault = None
            if self._exchange(_ZERO):
                return
            self._release()  # it stopped answering since: open it afresh
        self.fault = None
        self._connect(self.open_timeout_s, WAKEUP_ATTEMPTS)

    def reopen(self) -> bool:
        """Open a faulted device's port again (it was unplugged and came back, or answers again).

        Called from the client's network thread while :attr:`fault` is set (the servo thread no
        longer touches the port then); the fault clears last, once the port is in place. Forces
        stay enabled as they were, starting from zero.

        Returns
        -------
        bool
            True when the Inverse3 answers again; False if the device was not faulted.

        Raises
        ------
        OSError
            It still does not answer (the fault stays set).
        """
        if self.fault is None:
            return False
        self._release()
        self._force = _ZERO
        self._connect(min(REOPEN_TIMEOUT_S, self.open_timeout_s), 1)
        self.fault = None
        return True

    def close(self) -> None:
        """Send a zero force (if forces were on), disable forces and release the port.

        Safe to call twice, and on a device that was never opened.
        """
        self.disable_forces()
        self._release()

    # -- the servo tick -------------------------------------------------------------------------------

    def _set_state(self, pos: Sequence[float], vel: Sequence[float]) -> None:
        self.device_position = (float(pos[0]), float(pos[1]), float(pos[2]))
        s = self.scale
        self.velocity = (s * float(vel[0]), s * float(vel[1]), s * float(vel[2]))
        self._pos = self._to_world(self.device_position)

    def _exchange(self, force: Vec3) -> bool:
        """One round trip: send ``force`` [N] (device frame), take the state; False on a fault."""
        with self._lock:
            inverse3 = self._inverse3
            if inverse3 is None:
                return False
            t0 = time.perf_counter()
            try:
                pos, vel = inverse3.end_effector_force([force[0], force[1], force[2]])
                problem = _state_problem(pos, vel, time.perf_counter() - t0, self.timeout_s)
            except Exception as exc:  # never raise from the servo tick: a failed call is a fault
                problem = f"the exchange failed ({one_line(exc) or type(exc).__name__})"
            if problem is not None:
                self._fail(inverse3, problem)
                return False
            self._set_state(pos, vel)
            self.exchanges += 1
            return True

    def _fail(self, inverse3: Any, problem: str) -> None:
        """Set the fault and send a zero force without waiting for a reply (lock held)."""
        self.fault = f"{self.name}: {problem}; is the Inverse3 unplugged or without power?"
        self._force = _ZERO
        send_raw = getattr(inverse3, "send_raw", None)
        if send_raw is not None:
            try:
                send_raw(ZERO_FORCE_COMMAND)
            except Exception:  # the port is gone: nothing more can be done here
                pass

    def read(self, t_s: float) -> Vec3:
        """Exchange the stored force for the handle's position [m], world frame.

        One serial round trip (with a zero force while forces are disabled). Never raises: on a
        fault, :attr:`fault` is set and the last position is returned without touching the port.
        """
        if self.fault is None and self._inverse3 is not None:
            self._exchange(self._force if self._enabled else _ZERO)
        return self._pos

    def write(self, fx: float, fy: float, fz: float) -> None:
        """Store the force (fx, fy, fz) [N] (world frame) for the next :meth:`read` to send.

        The world and device axes agree and the workspace scale does not touch forces, so the
        force is sent as it is, clamped to ``limits.max_force_n`` (a non-finite force is zero).
        Ignored while forces are disabled or the device is faulted. Never raises.
        """
        if not self._enabled or self.fault is not None:
            return
        if not (math.isfinite(fx) and math.isfinite(fy) and math.isfinite(fz)):
            self._force = _ZERO
            return
        norm = math.sqrt(fx * fx + fy * fy + fz * fz)
        fmax = self.limits.max_force_n
        if norm > fmax:
            k = fmax / norm
            fx, fy, fz = fx * k, fy * k, fz * k
        self._force = (fx, fy, fz)

    def enable_forces(self) -> None:
        """Let :meth:`write` command forces (starting from zero)."""
        self._enabled = True

    def disable_forces(self) -> None:
        """Zero the force now (one round trip) and ignore writes until enabled again."""
        was = self._enabled
        self._enabled = False
        self._force = _ZERO
        if was and self.fault is None and self._inverse3 is not None:
            self._exchange(_ZERO)


class HaplyBackend(DeviceBackend):
    """``haply:PORT[,KEY=VALUE...]``: a Haply Inverse3 through HaplyHardwareAPI.

    :meth:`open` parses the spec and, with ``options.acquire``, opens the port and checks the
    wake-up reply before any network (the device keeps the port); :meth:`place` moves the
    workspace centre :data:`HID_STANDOFF_M` outside the anchor and returns the same device.
    """

    name = "haply"
    description = (
        "a Haply Inverse3 on its USB serial port through HaplyHardwareAPI: "
        "haply:/dev/ttyACM0[,scale=S] (haply alone detects it, writing 0x0A to every "
        "/dev/ttyACM* and /dev/ttyUSB* port)"
    )

    def available(self) -> str | None:
        """None when HaplyHardwareAPI imports; else one line naming the extra to install."""
        return _missing_binding_message()

    def detect(self) -> list[dict[str, Any]]:
        """Inverse3 ports udev names after Haply (:data:`SERIAL_BY_ID`); never writes to a port.

        HaplyHardwareAPI's own detection writes a wake-up byte to every serial port, which a
        listing must not do; this only reads the names of ``/dev/serial/by-id`` entries that
        contain ``haply`` or ``inverse3``. Whether the Inverse3's USB descriptor puts either word
        there has not been checked on a real device: an empty list proves nothing.
        """
        try:
            names = sorted(os.listdir(SERIAL_BY_ID))
        except OSError:
            return []
        out: list[dict[str, Any]] = []
        for n in names:
            low = n.lower()
            if "haply" in low or "inverse3" in low:
                path = os.path.join(SERIAL_BY_ID, n)
                out.append(
                    {
                        "spec": f"haply:{path}",
                        "kind": "inverse3",
                        "port": os.path.realpath(path),
                        "by_id": n,
                    }
                )
        return out

    def open(self, args: str, options: DeviceOptions) -> Device:
        cfg = parse_haply_args(args)
        dev = Inverse3Device(
            cfg.port,
            center=PLACEHOLDER_CENTER,
            scale=cfg.scale,
            specs=cfg.specs,
            timeout_s=cfg.timeout_s,
        )
        if options.acquire:
            dev.open()  # OSError: "cannot open haply:...: <why>; <what to do>"
        return dev

    def place(self, device: Device, anchor: Vec3, normal: Vec3) -> Device:
        opened_by(self, device, Inverse3Device).move_to(standoff_center(anchor, normal))
        return device


#: The backend (entry point ``haply`` in pyproject.toml, and ``BUILTIN_BACKENDS``).
BACKEND = HaplyBackend()
