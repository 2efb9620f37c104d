"""Haptic devices: the :class:`Device` interface, simulated devices and HID devices.

:func:`make_device` builds a device from a short spec string (the ``--device`` option):

==================  ============================================================================
``sim:press``       simulated device whose hand presses on ``anchor`` (:class:`Press`)
``sim:rest``        simulated device whose hand rests lightly on ``anchor`` (:class:`Rest`)
``sim:replay:FILE`` simulated device whose hand replays a file (:func:`load_replay`): a
                    ``--record`` CSV (its probe path) or a CSV ``t_s,x_m,y_m,z_m``
``hid:VID:PID``     a real HID device (hex ids): a SpaceMouse, or a device with a JSON profile
``NAME:ARGS``       a device of an installed backend (entry-point group ``haptic_collab.devices``)
==================  ============================================================================

The prefix names a *backend* (:mod:`client.devices.backends`, docs/devices.md): ``sim`` and
``hid`` are built in (:data:`SIM_BACKEND`, :data:`HID_BACKEND`); a lab adds its own device by
installing a package that registers one.

:class:`DeviceOpener` checks a spec and opens the device *before* the client touches the network
(a bad spec or an absent device is a :class:`DeviceError`: one line, what and what to do), and
places it on the object once the server's ``welcome`` says where the object is.

hidapi is only imported when a HID device is opened or listed.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from haptic_collab.client.devices.backends import (
    ENTRY_POINT_GROUP,
    DeviceBackend,
    DeviceError,
    DeviceOpenError,
    DeviceOptions,
    list_backends,
    one_line,
    usable_backend,
)
from haptic_collab.client.devices.base import Device, DeviceLimits, HapticError, Vec3
from haptic_collab.client.devices.profiles import (
    SIM_PROFILES,
    HidProfile,
    get_sim_profile,
    load_hid_profile,
    sim_profile_names,
)
from haptic_collab.client.devices.sim import HandParams, SimDevice
from haptic_collab.client.devices.trajectories import (
    Press,
    Replay,
    ReplayError,
    Rest,
    hand_depth_for,
)
from haptic_collab.shared.primitives import unit_vec3, vec3

if TYPE_CHECKING:
    from haptic_collab.client.devices.hid import HidPort

__all__ = [
    "Device",
    "DeviceBackend",
    "DeviceError",
    "DeviceLimits",
    "DeviceOpenError",
    "DeviceOpener",
    "DeviceOptions",
    "ENTRY_POINT_GROUP",
    "HAND_OPTIONS",
    "HID_BACKEND",
    "HandParams",
    "HapticError",
    "Press",
    "Replay",
    "ReplayError",
    "Rest",
    "SIM_BACKEND",
    "SIM_PROFILES",
    "SimDevice",
    "Vec3",
    "hand_depth_for",
    "hand_with_options",
    "list_backends",
    "list_devices",
    "load_replay",
    "make_device",
    "parse_hid_ids",
]

#: Distance [m] outside the anchor of a HID device's workspace centre.
HID_STANDOFF_M = 0.02

#: Probe columns of a ``haptic client --record`` file (:data:`client.recorder.COLUMNS`).
RECORD_PROBE_COLUMNS = ("t_s", "probe_x_m", "probe_y_m", "probe_z_m")


def load_replay(path: str | Path) -> Replay:
    """The hand trajectory of ``sim:replay:FILE``: a ``--record`` file or a ``t_s,x_m,y_m,z_m`` CSV.

    A ``haptic client --record`` CSV (header with ``t_s,probe_x_m,probe_y_m,probe_z_m``) replays
    its recorded probe path, with the time of its first row taken as t = 0 (the replaying
    device's first read); rows whose time does not increase are skipped. Any other CSV must hold
    ``t_s,x_m,y_m,z_m`` (:meth:`Replay.from_csv`, times used as they are). Positions are in the
    world frame [m].

    Parameters
    ----------
    path : str or Path
        The file.

    Returns
    -------
    Replay
        Linear interpolation of the samples, holding the first before and the last after.

    Raises
    ------
    ReplayError
        Missing file, missing columns, a non-numeric or non-finite cell, or no data rows.
    """
    p = Path(path)
    try:
        with p.open(encoding="utf-8") as fh:
            first = ""
            for line in fh:
                if line.strip() and not line.lstrip().startswith("#"):
                    first = line
                    break
    except OSError as exc:
        raise ReplayError(f"cannot open replay file {str(p)!r}: {exc}") from exc
    names = [h.strip() for h in first.strip().split(",")]
    if not all(c in names for c in RECORD_PROBE_COLUMNS):
        return Replay.from_csv(p)
    cols = [names.index(c) for c in RECORD_PROBE_COLUMNS]
    try:
        data = np.loadtxt(p, delimiter=",", skiprows=1, usecols=cols, ndmin=2, comments="#")
    except ValueError as exc:
        raise ReplayError(f"{p}: not a readable --record file: {exc}") from None
    if data.shape[0] == 0:
        raise ReplayError(f"{p}: no data rows")
    if not np.isfinite(data).all():
        bad = int(np.flatnonzero(~np.isfinite(data).all(axis=1))[0])
        raise ReplayError(f"{p}, data row {bad + 1}: non-finite value in {data[bad].tolist()}")
    t = data[:, 0]
    keep = np.ones(t.size, dtype=bool)
    keep[1:] = t[1:] > np.maximum.accumulate(t)[:-1]
    data = data[keep]
    times = tuple((data[:, 0] - data[0, 0]).tolist())
    positions = tuple(map(tuple, data[:, 1:4].tolist()))
    return Replay(times, positions)  # type: ignore[arg-type]


def parse_hid_ids(text: str) -> tuple[int, int]:
    """Parse ``VID:PID`` (hex, optional ``0x``) into ints.

    Raises
    ------
    ValueError
        Not two hex numbers in 0..0xffff separated by a colon.
    """
    parts = text.split(":")
    if len(parts) != 2:
        raise ValueError(f"expected VID:PID in hex (e.g. 256f:c635), got {text!r}")
    try:
        vid, pid = (int(p, 16) for p in parts)
    except ValueError:
        raise ValueError(f"expected VID:PID in hex (e.g. 256f:c635), got {text!r}") from None
    if not (0 <= vid <= 0xFFFF and 0 <= pid <= 0xFFFF):
        raise ValueError(f"VID and PID must be in 0..ffff, got {text!r}")
    return vid, pid


#: ``trajectory_options`` keys that set the simulated hand's own values (:class:`HandParams`
#: field each one sets); the device's mass and damping are added by :class:`SimDevice`.
HAND_OPTIONS: dict[str, str] = {
    "hand_mass_kg": "mass_kg",
    "hand_stiffness_n_per_m": "stiffness_n_per_m",
    "hand_damping_n_s_per_m": "damping_n_s_per_m",
}


def hand_with_options(hand: HandParams | None, options: dict[str, float]) -> HandParams | None:
    """Take the :data:`HAND_OPTIONS` keys out of ``options`` and apply them to ``hand``.

    Parameters
    ----------
    hand : HandParams or None
        The hand to start from (None: the default :class:`HandParams`).
    options : dict
        Trajectory options; the hand keys are removed from it (in place).

    Returns
    -------
    HandParams or None
        ``hand`` unchanged when ``options`` holds no hand key, else a new HandParams.

    Raises
    ------
    ValueError
        A hand value out of range (see :class:`HandParams`).
    """
    values = {HAND_OPTIONS[k]: float(options.pop(k)) for k in list(options) if k in HAND_OPTIONS}
    if not values:
        return hand
    return replace(hand if hand is not None else HandParams(), **values)


#: Where :meth:`DeviceBackend.open` builds a device before the server says where the object is
#: (:meth:`DeviceBackend.place` builds or moves it around the real anchor after the welcome).
PLACEHOLDER_ANCHOR: Vec3 = (0.0, 0.0, 0.0)
PLACEHOLDER_NORMAL: Vec3 = (0.0, 0.0, 1.0)


def _is_device(obj: object, backend: DeviceBackend, what: str) -> Device:
    if not isinstance(obj, Device):
        raise DeviceError(
            f"device backend {backend.name!r} returned {type(obj).__name__} from {what}(), not a "
            "Device (see docs/devices.md)"
        )
    return obj


def make_device(
    spec: str,
    anchor: Sequence[float],
    normal: Sequence[float],
    profile: str = "phantom-desktop",
    *,
    hand: HandParams | None = None,
    trajectory_options: Mapping[str, float] | None = None,
    servo_rate_hz: float = 1000.0,
    hid_profile: str | Path | HidProfile | None = None,
    hid_opener: Callable[[int, int], HidPort] | None = None,
) -> Device:
    """Build a device (not opened) from a spec string.

    The spec's prefix names the backend (:func:`client.devices.backends.get_backend`): its
    :meth:`~DeviceBackend.open` builds the device from the rest of the spec (without touching the
    hardware: ``DeviceOptions.acquire`` is False) and its :meth:`~DeviceBackend.place` puts it
    around ``anchor``.

    Parameters
    ----------
    spec : str
        ``sim:press``, ``sim:rest``, ``sim:replay:FILE``, ``hid:VID:PID`` (hex), or
        ``NAME:ARGS`` of an installed backend.
    anchor : (3,) float
        Surface point [m] of the object the user works on. Scripted hands press/rest on it; the
        simulated workspace is centred on it; a HID device's workspace is centred
        ``HID_STANDOFF_M`` outside it.
    normal : (3,) float
        Outward surface normal at ``anchor`` (normalized here).
    profile : str
        Simulated device profile (:func:`sim_profile_names`: ``phantom-desktop``, ``touch``).
    hand : HandParams, optional
        The simulated hand (default 300 N/m, 5 N*s/m, 0.45 kg).
    trajectory_options : mapping, optional
        Overrides of the scripted trajectory's keyword arguments, e.g. ``{"delay_s": 2.0,
        "depth_m": 0.025}`` (see :class:`Press` and :class:`Rest` for names and defaults).
        The keys of :data:`HAND_OPTIONS` (``hand_mass_kg``, ``hand_stiffness_n_per_m``,
        ``hand_damping_n_s_per_m``) override the hand's own values instead (``haptic client
        --hand-mass/--hand-stiffness/--hand-damping``), for any ``sim:`` device.
    servo_rate_hz : float
        Servo rate [Hz] the simulation sub-steps against (default 1000).
    hid_profile : str, Path or HidProfile, optional
        Generic HID profile (bundled name, file, or loaded) for a non-SpaceMouse device.
    hid_opener : callable, optional
        ``opener(vendor_id, product_id) -> port`` a HID device opens its port with (default
        hidapi; :class:`DeviceOpener` hands over a port it opened early, tests a fake).

    Returns
    -------
    Device

    Raises
    ------
    DeviceError
        Unknown prefix (the message lists the known backends), a backend that cannot be loaded,
        or one that is not available here (its message).
    ValueError
        Malformed spec, unknown profile, bad trajectory option, bad anchor or normal, or a HID
        device with neither SpaceMouse ids nor a profile.
    ReplayError
        The replay file is missing or malformed (a ValueError).
    """
    a = vec3("anchor", anchor)
    n = unit_vec3("normal", normal)
    backend, args = usable_backend(spec)
    options = DeviceOptions(
        profile=profile,
        trajectory_options=dict(trajectory_options or {}),
        hand=hand,
        servo_rate_hz=servo_rate_hz,
        hid_profile=hid_profile,
        hid_opener=hid_opener,
    )
    dev = _is_device(backend.open(args, options), backend, "open")
    return _is_device(backend.place(dev, a, n), backend, "place")


# -- the built-in backends ---------------------------------------------------------------------------


def _make_sim(args: str, options: DeviceOptions, a: Vec3, n: Vec3) -> SimDevice:
    """The simulated device ``sim:args`` around anchor ``a`` (outward normal ``n``)."""
    spec = f"sim:{args}" if args else "sim"
    prof = get_sim_profile(options.profile)
    opts = dict(options.trajectory_options)
    hand = hand_with_options(options.hand, opts)
    what, _, arg = args.partition(":")
    traj: Press | Rest | Replay
    try:
        if what == "press" and not arg:
            traj = Press(a, n, **opts)
        elif what == "rest" and not arg:
            traj = Rest(a, n, **opts)
        elif what == "replay" and arg:
            if opts:
                raise ValueError("sim:replay takes no trajectory options")
            traj = load_replay(arg)
        else:
            raise ValueError(
                f"unknown simulated device {spec!r}; use sim:press, sim:rest or sim:replay:FILE"
            )
    except TypeError as exc:
        raise ValueError(f"bad trajectory option for {spec!r}: {exc}") from None
    center = a if not isinstance(traj, Replay) else traj(0.0)
    return SimDevice(
        prof,
        traj,
        hand,
        limits=prof.limits.centered_at(center),
        servo_period_s=1.0 / options.servo_rate_hz,
    )


class SimBackend(DeviceBackend):
    """``sim:press``, ``sim:rest``, ``sim:replay:FILE``: a simulated device and hand.

    :meth:`open` builds the device around a placeholder anchor (every option is checked, a replay
    file is read); :meth:`place` builds it again around the real anchor, except a replayed hand,
    which is in world coordinates already (the device :meth:`open` returned is used as it is).
    """

    name = "sim"
    description = (
        "a simulated device held by a simulated hand: sim:press, sim:rest or sim:replay:FILE "
        "(--profile NAME)"
    )

    def __init__(self) -> None:
        self._opened: weakref.WeakKeyDictionary[Device, tuple[str, DeviceOptions]] = (
            weakref.WeakKeyDictionary()
        )

    def detect(self) -> list[dict[str, Any]]:
        """One entry per simulated profile (``kind`` ``sim``, ``spec`` ``sim:press``, limits)."""
        out: list[dict[str, Any]] = []
        for name in sim_profile_names():
            lim = SIM_PROFILES[name].limits
            out.append(
                {
                    "kind": "sim",
                    "spec": "sim:press",
                    "profile": name,
                    "max_force_n": lim.max_force_n,
                    "max_stiffness_n_per_m": lim.max_stiffness_n_per_m,
                }
            )
        return out

    def open(self, args: str, options: DeviceOptions) -> Device:
        dev = _make_sim(args, options, PLACEHOLDER_ANCHOR, PLACEHOLDER_NORMAL)
        self._opened[dev] = (args, options)
        return dev

    def place(self, device: Device, anchor: Vec3, normal: Vec3) -> Device:
        if isinstance(getattr(device, "trajectory", None), Replay):
            return device  # a replayed hand is in world coordinates already
        plan = self._opened.get(device)
        if plan is None:
            raise DeviceError(f"{device.name} was not opened by the sim backend")
        return _make_sim(plan[0], plan[1], anchor, normal)


def _hid_center(a: Vec3, n: Vec3) -> Vec3:
    """A HID device's workspace centre: ``HID_STANDOFF_M`` outside the anchor."""
    return (
        a[0] + HID_STANDOFF_M * n[0],
        a[1] + HID_STANDOFF_M * n[1],
        a[2] + HID_STANDOFF_M * n[2],
    )


class _EarlyPort:
    """The port opened before the network, lent to the unplaced device until the placed one
    takes it (:meth:`take`); closed with it if the client stops before the welcome."""

    def __init__(self, port: HidPort) -> None:
        self._port: HidPort | None = port

    def take(self) -> HidPort | None:
        port, self._port = self._port, None
        return port

    def read(self, max_length: int) -> Sequence[int]:
        return self._port.read(max_length) if self._port is not None else []

    def write(self, data: bytes) -> int:
        return self._port.write(data) if self._port is not None else 0

    def close(self) -> None:
        port = self.take()
        if port is not None:
            port.close()


class _HidPorts:
    """The opener of every device built for one ``hid:VID:PID`` spec.

    The port :meth:`acquire` opened before the network goes to the first device that opens (the
    placed one); later opens (a reopen after an unplug) open a new port. A first open that fails
    says why in one line (:func:`client.devices.hid.open_error_message`).
    """

    def __init__(
        self, vendor_id: int, product_id: int, base: Callable[[int, int], HidPort] | None
    ) -> None:
        self.ids = (vendor_id, product_id)
        self._base = base
        self._early: _EarlyPort | None = None
        self._opened = False

    def _open(self, vendor_id: int, product_id: int) -> HidPort:
        if self._base is not None:
            return self._base(vendor_id, product_id)
        from haptic_collab.client.devices.hid import _hid_open

        return _hid_open(vendor_id, product_id)

    def acquire(self) -> None:
        """Open the port now (before the network).

        Raises
        ------
        DeviceError
            It cannot be opened (absent, no permission, busy), as one line with what to do.
        """
        from haptic_collab.client.devices.hid import open_error_message

        try:
            port = self._open(*self.ids)
        except OSError as exc:
            raise DeviceError(open_error_message(*self.ids, exc)) from None
        self._early = _EarlyPort(port)

    def lend(self, vendor_id: int, product_id: int) -> HidPort:
        """The early port, for the unplaced device (its close() closes the port if untaken)."""
        if self._early is None:
            raise OSError("no port was opened early")
        return self._early

    def __call__(self, vendor_id: int, product_id: int) -> HidPort:
        early, self._early = self._early, None
        port = early.take() if early is not None else None
        if port is None:
            try:
                port = self._open(vendor_id, product_id)
            except OSError as exc:
                if self._opened:
                    raise
                from haptic_collab.client.devices.hid import open_error_message

                raise DeviceOpenError(open_error_message(vendor_id, product_id, exc)) from exc
        self._opened = True
        return port


class HidBackend(DeviceBackend):
    """``hid:VID:PID``: a 3Dconnexion SpaceMouse, or a HID device with a JSON profile.

    :meth:`open` checks the ids and the profile and, with ``options.acquire``, opens the port
    (the unplaced device holds it); :meth:`place` builds the device around the real anchor on
    that port.
    """

    name = "hid"
    description = (
        "a real HID device through hidapi: hid:VID:PID (hex ids), a 3Dconnexion SpaceMouse or a "
        "device with a JSON profile (--hid-profile NAME|FILE.json)"
    )

    def __init__(self) -> None:
        self._opened: weakref.WeakKeyDictionary[
            Device, tuple[int, int, HidProfile | None, _HidPorts]
        ] = weakref.WeakKeyDictionary()

    def available(self) -> str | None:
        import importlib.util

        if importlib.util.find_spec("hid") is None:
            return "the hid backend needs hidapi, which is not installed: pip install hidapi"
        return None

    def detect(self) -> list[dict[str, Any]]:
        """Attached HID devices (:func:`client.devices.hid.list_devices`)."""
        from haptic_collab.client.devices.hid import list_devices as list_hid

        return list_hid()

    def open(self, args: str, options: DeviceOptions) -> Device:
        from haptic_collab.client.devices.hid import open_hid_device

        vid, pid = parse_hid_ids(args)
        hp: HidProfile | None
        if options.hid_profile is None or isinstance(options.hid_profile, HidProfile):
            hp = options.hid_profile
        else:
            hp = load_hid_profile(options.hid_profile)
        ports = _HidPorts(vid, pid, options.hid_opener)
        center = _hid_center(PLACEHOLDER_ANCHOR, PLACEHOLDER_NORMAL)
        opener = ports.lend if options.acquire else ports
        dev = open_hid_device(vid, pid, center, profile=hp, opener=opener)
        if options.acquire:
            ports.acquire()
            dev.open()  # holds the early port: its close() releases it if it is never placed
        self._opened[dev] = (vid, pid, hp, ports)
        return dev

    def place(self, device: Device, anchor: Vec3, normal: Vec3) -> Device:
        from haptic_collab.client.devices.hid import open_hid_device

        plan = self._opened.get(device)
        if plan is None:
            raise DeviceError(f"{device.name} was not opened by the hid backend")
        vid, pid, hp, ports = plan
        return open_hid_device(vid, pid, _hid_center(anchor, normal), profile=hp, opener=ports)


#: The built-in backends (pyproject.toml registers them as entry points ``sim`` and ``hid``).
SIM_BACKEND = SimBackend()
HID_BACKEND = HidBackend()


# -- opening a device for haptic client ---------------------------------------------------------------


class DeviceOpener:
    """Check a ``--device`` spec and open the device before the network; place it on the object later.

    ``haptic client`` calls :meth:`check` before it connects: the spec's backend must be known and
    available, and its :meth:`~DeviceBackend.open` checks the rest (for ``sim``: profile,
    trajectory options, replay file; for ``hid``: ids and profile, and the port is opened and kept
    open). Once the server's ``welcome`` says where the object is, :meth:`build` has the backend
    place the device around the real anchor (:meth:`~DeviceBackend.place`) and opens it (a HID
    device on the port :meth:`check` opened; a replayed hand, which does not depend on the anchor,
    is the checked device as it is). A device that faults later reopens through the same opener
    (:meth:`Device.reopen`).

    Parameters
    ----------
    spec : str
        ``sim:press``, ``sim:rest``, ``sim:replay:FILE``, ``hid:VID:PID`` or ``NAME:ARGS`` of an
        installed backend.
    profile, trajectory_options, servo_rate_hz, hid_profile
        As :func:`make_device`.
    hid_opener : callable, optional
        ``opener(vendor_id, product_id) -> port`` (default: hidapi, non-blocking).
    """

    def __init__(
        self,
        spec: str,
        *,
        profile: str = "phantom-desktop",
        trajectory_options: Mapping[str, float] | None = None,
        servo_rate_hz: float = 1000.0,
        hid_profile: str | Path | HidProfile | None = None,
        hid_opener: Callable[[int, int], HidPort] | None = None,
    ) -> None:
        self.spec = spec
        self.profile = profile
        self.trajectory_options = dict(trajectory_options or {})
        self.servo_rate_hz = servo_rate_hz
        self.hid_profile = hid_profile
        #: What the backend gets (``acquire``: the hardware is checked and held before the network).
        self.options = DeviceOptions(
            profile=profile,
            trajectory_options=self.trajectory_options,
            servo_rate_hz=servo_rate_hz,
            hid_profile=hid_profile,
            hid_opener=hid_opener,
            acquire=True,
        )
        self.backend: DeviceBackend | None = None
        self._checked: Device | None = None
        self._built: Device | None = None

    def _cannot_open(self, exc: BaseException) -> str:
        if isinstance(exc, DeviceOpenError):
            return one_line(exc)
        return f"cannot open {self.spec}: {one_line(exc) or type(exc).__name__}"

    def check(self) -> None:
        """Check the spec and open the device's hardware now (before any network).

        Raises
        ------
        DeviceError
            An unknown backend (the message lists the known ones), a backend that is not
            available here (its message: what is missing and what to install), a bad spec
            (unknown kind, profile or trajectory option, unreadable replay file, a HID device with
            no profile) or a device that cannot be opened (absent, no permission, busy), as one
            line with what to do.
        """
        backend, args = usable_backend(self.spec)
        self.close()  # a second check: release what the first one held
        self._checked = None
        try:
            dev = backend.open(args, self.options)
        except ValueError as exc:
            raise DeviceError(one_line(exc)) from None
        except OSError as exc:
            raise DeviceError(self._cannot_open(exc)) from None
        self.backend, self._checked = backend, _is_device(dev, backend, "open")

    @property
    def limits(self) -> DeviceLimits | None:
        """The checked device's limits (before placement: its workspace is not on the object
        yet); None before :meth:`check`."""
        return None if self._checked is None else self._checked.limits

    def build(self, anchor: Sequence[float], normal: Sequence[float]) -> Device:
        """The device placed on the object (anchor (3,) [m], outward normal (3,)), opened.

        Raises
        ------
        DeviceError
            Bad anchor or normal, or the device cannot be opened (it went away since
            :meth:`check`).
        """
        if self.backend is None or self._checked is None:
            self.check()
        assert self.backend is not None and self._checked is not None
        try:
            a = vec3("anchor", anchor)
            n = unit_vec3("normal", normal)
            dev = _is_device(self.backend.place(self._checked, a, n), self.backend, "place")
        except ValueError as exc:
            raise DeviceError(one_line(exc)) from None
        try:
            dev.open()
        except OSError as exc:
            raise DeviceError(self._cannot_open(exc)) from None
        self._built = dev
        return dev

    def close(self) -> None:
        """Release what :meth:`check` opened (a HID port) when :meth:`build` never used it."""
        dev = self._checked
        if dev is not None and self._built is None:
            try:
                dev.close()
            except OSError:
                pass


def list_devices() -> list[dict[str, Any]]:
    """Every device one could use now, then every backend (``haptic devices``).

    Returns
    -------
    list of dict
        First the devices each available backend detects, backend by backend (built-in first):
        HID entries as :func:`client.devices.hid.list_devices` (``kind`` spacemouse,
        profile:NAME or unsupported), one entry per simulated profile with ``kind`` ``sim``,
        ``spec`` ``sim:press``, ``profile``, ``max_force_n`` and ``max_stiffness_n_per_m``, then
        those of installed backends (``spec``, ``kind`` defaulting to the backend's name); every
        entry says its ``backend``. Then one entry per backend with ``kind`` ``backend``:
        ``name``, ``spec`` (``NAME:``), ``description``, ``available`` (bool), ``message`` (None,
        or what is missing and what to install), ``entry_point`` and ``devices``
        (:func:`client.devices.backends.list_backends`). The bundled generic HID profile files
        are listed by :func:`client.devices.profiles.hid_profile_names`.
    """
    backends = list_backends()
    out: list[dict[str, Any]] = [d for b in backends for d in b["devices"]]
    for b in backends:
        out.append({"kind": "backend", **b, "devices": [dict(d) for d in b["devices"]]})
    return out
