"""Real devices through hidapi: a 3Dconnexion SpaceMouse and generic devices described by a profile.

Every call into hidapi lives in this module, and ``hid`` is imported only when a device is opened
or listed, so the rest of the client imports on machines without hidapi or without a HID backend.
Report parsing is done by pure functions of the report bytes, in
:mod:`client.devices.hid_reports` (the SpaceMouse's report layout and its counts to a position,
a JSON profile's generic layout).

A device that errors (``read`` raising ``OSError``, the unplugged case) or, for a device that
streams, stays silent past its profile's ``silence_timeout_s`` gets :attr:`Device.fault` set; the
servo loop then ramps its forces down. Reads are non-blocking and drain every queued report each
tick, keeping the newest.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from haptic_collab.client.devices.base import Device, DeviceLimits, Vec3
from haptic_collab.client.devices.hid_reports import (
    SpaceMouseMapping,
    decode_input,
    encode_output,
    integrate_rate,
    parse_spacemouse_report,
    spacemouse_position,
    spacemouse_velocity,
)
from haptic_collab.client.devices.profiles import HidProfile, find_hid_profile
from haptic_collab.shared.protocol import MAX_REPORTED_FORCE_N

#: 3Dconnexion's own USB vendor id (every device of theirs is treated as a SpaceMouse).
VID_3DCONNEXION = 0x256F
#: Logitech's vendor id, used by older 3Dconnexion devices.
VID_LOGITECH = 0x046D
#: Older 3Dconnexion product ids sold under Logitech's vendor id.
LOGITECH_SPACEMOUSE_PIDS = frozenset(
    {0xC603, 0xC621, 0xC623, 0xC625, 0xC626, 0xC627, 0xC628, 0xC629, 0xC62B, 0xC62E, 0xC62F}
)

#: Reports drained per read at most (a burst larger than this waits for the next tick).
MAX_REPORTS_PER_READ = 64
#: Largest report read at once [bytes].
REPORT_SIZE = 64


def is_spacemouse(vendor_id: int, product_id: int) -> bool:
    """Whether (vendor_id, product_id) is a 3Dconnexion SpaceMouse-family device."""
    return vendor_id == VID_3DCONNEXION or (
        vendor_id == VID_LOGITECH and product_id in LOGITECH_SPACEMOUSE_PIDS
    )


# ---------------------------------------------------------------------------------------------
# Devices
# ---------------------------------------------------------------------------------------------


class HidPort(Protocol):
    """The part of ``hid.device`` the devices use (tests substitute a fake)."""

    def read(self, max_length: int) -> Sequence[int]: ...

    def write(self, data: bytes) -> int: ...

    def close(self) -> None: ...


Opener = Callable[[int, int], HidPort]


def _hid_open(vendor_id: int, product_id: int) -> HidPort:
    """Open (vendor_id, product_id) with hidapi in non-blocking mode.

    Raises
    ------
    OSError
        hidapi is not installed, has no backend, or the device cannot be opened.
    """
    try:
        import hid
    except ImportError as exc:  # pragma: no cover - hidapi is a declared dependency
        raise OSError(f"hidapi is not available: {exc}") from exc
    dev = hid.device()
    dev.open(vendor_id, product_id)
    dev.set_nonblocking(1)
    port: HidPort = dev
    return port


class _HidDevice(Device):
    """Shared plumbing: open/close through an opener, drain reports, set ``fault`` on errors."""

    def __init__(
        self,
        vendor_id: int,
        product_id: int,
        name: str,
        limits: DeviceLimits,
        opener: Opener | None,
        silence_timeout_s: float | None,
    ) -> None:
        self.vendor_id = vendor_id
        self.product_id = product_id
        self.name = name
        self.limits = limits
        self.fault: str | None = None
        self._zeroed_after_fault = False
        self._opener: Opener = opener if opener is not None else _hid_open
        self._port: HidPort | None = None
        self._silence_s = silence_timeout_s
        self._last_report_t: float | None = None
        self._enabled = False
        self.bad_reports = 0

    def open(self) -> None:
        """Open the device (hidapi, non-blocking).

        Raises
        ------
        OSError
            The device is absent, busy, or hidapi has no backend.
        """
        self._port = self._opener(self.vendor_id, self.product_id)
        self.fault = None
        self._last_report_t = None

    def reopen(self) -> bool:
        """Release the port of a faulted device and open it again (the device came back).

        Called from another thread than the servo loop's, only while :attr:`fault` is set: a
        faulted device no longer touches its port in :meth:`read` (and in :meth:`write` after one
        zero-force report), so the port can be swapped; :attr:`fault` is cleared last, once the
        new port is in place. Forces stay enabled as they were (the servo loop ramps them back
        up from zero when the fault clears).

        Returns
        -------
        bool
            True when the device is open and healthy again; False if it was not faulted.

        Raises
        ------
        OSError
            The device cannot be opened (still unplugged); the fault stays set.
        """
        if self.fault is None:
            return False
        old, self._port = self._port, None
        if old is not None:
            try:
                old.close()
            except OSError:
                pass
        port = self._opener(self.vendor_id, self.product_id)
        self._port = port
        self._last_report_t = None
        self._zeroed_after_fault = False
        self.fault = None
        return True

    def close(self) -> None:
        """Zero the force, release the device; safe to call twice."""
        if self._port is not None:
            self.disable_forces()
            try:
                self._port.close()
            except OSError:
                pass
            self._port = None

    def enable_forces(self) -> None:
        """Allow forces to be written (no effect on a position-only device)."""
        self._enabled = True

    def disable_forces(self) -> None:
        """Write a zero force once and ignore further writes."""
        if self._enabled and self.limits.has_force_output:
            self._send(0.0, 0.0, 0.0)
        self._enabled = False

    def _send(self, fx: float, fy: float, fz: float) -> None:
        """Write one force report (subclasses with force output override)."""

    def write(self, fx: float, fy: float, fz: float) -> None:
        """Send the force (fx, fy, fz) [N]; a no-op unless enabled and the device has an output.

        After a fault (silence, a failed read) the output may still work: one zero-force report is
        attempted so the device never keeps the last force, then writes stop.
        """
        if not (self._enabled and self.limits.has_force_output):
            return
        if self.fault is None:
            self._send(fx, fy, fz)
        elif not self._zeroed_after_fault:
            self._zeroed_after_fault = True
            try:
                self._send(0.0, 0.0, 0.0)
            except OSError:
                pass

    def _drain(self, t_s: float, handle: Callable[[bytes], bool]) -> None:
        """Read every queued report, pass each to ``handle`` (True if it was used)."""
        port = self._port
        if port is None or self.fault is not None:
            return
        if self._last_report_t is None:
            self._last_report_t = t_s
        try:
            for _ in range(MAX_REPORTS_PER_READ):
                data = port.read(REPORT_SIZE)
                if not data:
                    break
                try:
                    if handle(bytes(data)):
                        self._last_report_t = t_s
                except ValueError:
                    self.bad_reports += 1
        except (OSError, ValueError) as exc:
            self.fault = f"{self.name}: read failed ({exc}); device unplugged?"
            return
        if self._silence_s is not None and t_s - self._last_report_t > self._silence_s:
            self.fault = (
                f"{self.name}: no report for {t_s - self._last_report_t:.3f} s "
                f"(> {self._silence_s} s); device unplugged?"
            )


class SpaceMouseDevice(_HidDevice):
    """A 3Dconnexion SpaceMouse as a position input (no force output).

    Parameters
    ----------
    vendor_id, product_id : int
        USB ids.
    center : (3,) float
        Workspace centre [m] in the world: where the probe sits with the cap at rest (position
        mode) or where it starts (rate mode).
    mapping : SpaceMouseMapping
        Counts to position.
    max_force_n : float
        Cap [N] on the coupling force sent to the object (the device itself displays none);
        default the protocol's limit on any user's reported force
        (:data:`shared.protocol.MAX_REPORTED_FORCE_N`), under which the server bounds it by the
        object's geometry like every other user's.
    opener : callable, optional
        ``opener(vendor_id, product_id) -> port``; default opens through hidapi.

    Notes
    -----
    A SpaceMouse sends nothing while its cap is still, so silence is not a fault; a failing read
    (``OSError``, the unplugged case) is.
    """

    def __init__(
        self,
        vendor_id: int,
        product_id: int,
        center: Sequence[float],
        mapping: SpaceMouseMapping | None = None,
        *,
        max_force_n: float = MAX_REPORTED_FORCE_N,
        opener: Opener | None = None,
    ) -> None:
        self.mapping = mapping if mapping is not None else SpaceMouseMapping()
        c = (float(center[0]), float(center[1]), float(center[2]))
        reach = self.mapping.travel_m if self.mapping.mode == "position" else 0.1
        limits = DeviceLimits(
            max_force_n=max_force_n,
            # a position input: no stiffness or speed limit comes from it (the gain design picks
            # K_h from K_o), and its push is bounded as every user's is: by the protocol's limit
            # on a reported force and, on the server, by the object's own geometry
            max_stiffness_n_per_m=math.inf,
            max_velocity_m_s=math.inf,
            damping_n_s_per_m=0.0,
            workspace_min_m=(c[0] - reach, c[1] - reach, c[2] - reach),
            workspace_max_m=(c[0] + reach, c[1] + reach, c[2] + reach),
            has_force_output=False,
        )
        super().__init__(
            vendor_id,
            product_id,
            f"spacemouse:{vendor_id:04x}:{product_id:04x}",
            limits,
            opener,
            None,
        )
        self.center: Vec3 = c
        self._counts: tuple[int, int, int] = (0, 0, 0)
        self._pos: Vec3 = c
        self._t: float | None = None

    def _handle(self, data: bytes) -> bool:
        trans, _rot = parse_spacemouse_report(data)
        if trans is None:
            return False
        self._counts = trans
        return True

    def read(self, t_s: float) -> Vec3:
        """Probe position (x, y, z) [m] from the newest translation report."""
        self._drain(t_s, self._handle)
        m = self.mapping
        if m.mode == "position":
            self._pos = spacemouse_position(self._counts, self.center, m)
        else:
            dt = 0.0 if self._t is None else max(0.0, t_s - self._t)
            v = spacemouse_velocity(self._counts, m)
            lim = self.limits
            self._pos = integrate_rate(self._pos, v, dt, lim.workspace_min_m, lim.workspace_max_m)
        self._t = t_s
        return self._pos


class ProfileHidDevice(_HidDevice):
    """A generic HID device described by a :class:`~client.devices.profiles.HidProfile`.

    Parameters
    ----------
    profile : HidProfile
        Report layouts, limits, silence timeout.
    origin : (3,) float
        World position [m] of the device frame's origin (the workspace box is centred on it).
    opener : callable, optional
        ``opener(vendor_id, product_id) -> port``; default opens through hidapi.
    """

    def __init__(
        self, profile: HidProfile, origin: Sequence[float], *, opener: Opener | None = None
    ) -> None:
        o = (float(origin[0]), float(origin[1]), float(origin[2]))
        super().__init__(
            profile.vendor_id,
            profile.product_id,
            f"hid:{profile.name}",
            profile.limits.centered_at(o),
            opener,
            profile.silence_timeout_s,
        )
        self.profile = profile
        self.origin: Vec3 = o
        self._value: Vec3 = (0.0, 0.0, 0.0)
        self._pos: Vec3 = o
        self._t: float | None = None

    def _handle(self, data: bytes) -> bool:
        v = decode_input(self.profile.input, data)
        if v is None:
            return False
        self._value = v
        return True

    def read(self, t_s: float) -> Vec3:
        """Probe position (x, y, z) [m] from the newest input report."""
        self._drain(t_s, self._handle)
        v, o = self._value, self.origin
        if self.profile.input.mode == "absolute":
            self._pos = (o[0] + v[0], o[1] + v[1], o[2] + v[2])
        else:
            dt = 0.0 if self._t is None else max(0.0, t_s - self._t)
            lim = self.limits
            self._pos = integrate_rate(self._pos, v, dt, lim.workspace_min_m, lim.workspace_max_m)
        self._t = t_s
        return self._pos

    def _send(self, fx: float, fy: float, fz: float) -> None:
        out = self.profile.output
        if out is None or self._port is None:
            return
        try:
            self._port.write(encode_output(out, fx, fy, fz))
        except (OSError, ValueError) as exc:
            self.fault = f"{self.name}: write failed ({exc}); device unplugged?"


def open_hid_device(
    vendor_id: int,
    product_id: int,
    center: Sequence[float],
    *,
    profile: HidProfile | None = None,
    mapping: SpaceMouseMapping | None = None,
    opener: Opener | None = None,
) -> Device:
    """The right device object for (vendor_id, product_id) (not opened yet).

    A SpaceMouse-family id gives a :class:`SpaceMouseDevice`; otherwise ``profile``, or the
    bundled profile with these ids, gives a :class:`ProfileHidDevice`.

    Raises
    ------
    ValueError
        Neither a SpaceMouse nor a known profile for these ids.
    """
    if profile is not None:
        return ProfileHidDevice(profile, center, opener=opener)
    if is_spacemouse(vendor_id, product_id):
        return SpaceMouseDevice(vendor_id, product_id, center, mapping, opener=opener)
    found = find_hid_profile(vendor_id, product_id)
    if found is None:
        raise ValueError(
            f"no HID profile for {vendor_id:04x}:{product_id:04x}: it is not a SpaceMouse and no "
            "bundled profile has these ids; write a JSON profile for it (docs/client.md) and pass "
            "--hid-profile FILE.json; `haptic devices` lists what is attached"
        )
    return ProfileHidDevice(found, center, opener=opener)


#: How to let a user open hidraw devices on Linux (one line, docs/client.md shows the file).
UDEV_HINT = (
    "give your user access with a udev rule, e.g. "
    '\'KERNEL=="hidraw*", ATTRS{{idVendor}}=="{vid:04x}", MODE="0660", TAG+="uaccess"\' '
    "in /etc/udev/rules.d/70-haptic.rules, then `sudo udevadm control --reload` and replug "
    "(docs/client.md)"
)


def open_error_message(
    vendor_id: int,
    product_id: int,
    error: BaseException,
    attached: Sequence[dict[str, Any]] | None = None,
) -> str:
    """One line saying why (vendor_id, product_id) could not be opened and what to do.

    hidapi says only "open failed"; the cause is told apart by what is attached: nothing with
    these ids (not plugged in), a ``/dev/hidraw*`` node the user may not read and write (a
    missing udev rule), or attached but busy or refused.

    Parameters
    ----------
    vendor_id, product_id : int
        The ids that failed to open.
    error : BaseException
        What the opener raised.
    attached : sequence of dict, optional
        ``hid.enumerate()`` entries (``vendor_id``, ``product_id``, ``path``); default: ask
        hidapi now (an empty list when hidapi is unavailable).

    Returns
    -------
    str
        ``cannot open hid:VID:PID: <what>; <what to do>``, without a newline.
    """
    spec = f"hid:{vendor_id:04x}:{product_id:04x}"
    if attached is None:
        try:
            import hid

            attached = list(hid.enumerate(vendor_id, product_id))
        except (ImportError, OSError, RuntimeError):
            attached = []
    mine = [
        d
        for d in attached
        if int(d.get("vendor_id", -1)) == vendor_id and int(d.get("product_id", -1)) == product_id
    ]
    detail = str(error).strip() or type(error).__name__
    if isinstance(error, ImportError) or "hidapi is not available" in detail:
        return f"cannot open {spec}: {detail}; install hidapi (pip install hidapi)"
    if not mine:
        return (
            f"cannot open {spec}: no device with these ids is attached ({detail}); plug it in, "
            "or run `haptic devices` to list what is attached"
        )
    paths = []
    for d in mine:
        raw = d.get("path") or b""
        path = raw.decode(errors="replace") if isinstance(raw, bytes) else str(raw)
        paths.append(path)
    denied = [p for p in paths if p.startswith("/dev/") and not os.access(p, os.R_OK | os.W_OK)]
    if denied or isinstance(error, PermissionError):
        where = f" on {denied[0]}" if denied else ""
        return f"cannot open {spec}: permission denied{where}; " + UDEV_HINT.format(vid=vendor_id)
    return (
        f"cannot open {spec}: it is attached but refused to open ({detail}); close any other "
        "program using it (a vendor driver or daemon), or check its permissions: "
        + UDEV_HINT.format(vid=vendor_id)
    )


def list_devices() -> list[dict[str, Any]]:
    """HID devices attached now, one entry per vendor/product id (``haptic devices``).

    Returns
    -------
    list of dict
        Keys: ``spec`` (``hid:VID:PID`` for ``make_device``), ``vendor_id``, ``product_id``
        (ints), ``manufacturer``, ``product`` (str), ``kind`` (``spacemouse``,
        ``profile:NAME`` or ``unsupported``). Empty when hidapi is missing or has no backend.
    """
    try:
        import hid

        infos = hid.enumerate()
    except (ImportError, OSError, RuntimeError):
        return []
    seen: set[tuple[int, int]] = set()
    out: list[dict[str, Any]] = []
    for d in infos:
        vid, pid = int(d.get("vendor_id", 0)), int(d.get("product_id", 0))
        if (vid, pid) in seen:
            continue
        seen.add((vid, pid))
        if is_spacemouse(vid, pid):
            kind = "spacemouse"
        else:
            prof = find_hid_profile(vid, pid)
            kind = f"profile:{prof.name}" if prof is not None else "unsupported"
        out.append(
            {
                "spec": f"hid:{vid:04x}:{pid:04x}",
                "vendor_id": vid,
                "product_id": pid,
                "manufacturer": d.get("manufacturer_string") or "",
                "product": d.get("product_string") or "",
                "kind": kind,
            }
        )
    return out
