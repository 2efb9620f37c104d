"""Haptic devices: the :class:`Device` interface, simulated devices and HID devices.

:func:`make_device` builds a device from a short spec string (the ``--device`` option):

==================  ============================================================================
``sim:press``       simulated device whose hand presses on ``anchor`` (:class:`Press`)
``sim:rest``        simulated device whose hand rests lightly on ``anchor`` (:class:`Rest`)
``sim:replay:FILE`` simulated device whose hand replays a file (:func:`load_replay`): a
                    ``--record`` CSV (its probe path) or a CSV ``t_s,x_m,y_m,z_m``
``hid:VID:PID``     a real HID device (hex ids): a SpaceMouse, or a device with a JSON profile
==================  ============================================================================

:class:`DeviceOpener` checks a spec and opens the device *before* the client touches the network
(a bad spec or an absent device is a :class:`DeviceError`: one line, what and what to do), and
places it on the object once the server's ``welcome`` says where the object is.

hidapi is only imported when a HID device is opened or listed.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

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
    "DeviceError",
    "DeviceLimits",
    "DeviceOpener",
    "HAND_OPTIONS",
    "HandParams",
    "HapticError",
    "Press",
    "Replay",
    "ReplayError",
    "Rest",
    "SIM_PROFILES",
    "SimDevice",
    "Vec3",
    "hand_depth_for",
    "hand_with_options",
    "list_devices",
    "load_replay",
    "make_device",
    "parse_hid_ids",
]

#: Distance [m] outside the anchor of a HID device's workspace centre.
HID_STANDOFF_M = 0.02

#: Probe columns of a ``haptic client --record`` file (:data:`client.recorder.COLUMNS`).
RECORD_PROBE_COLUMNS = ("t_s", "probe_x_m", "probe_y_m", "probe_z_m")


class DeviceError(ValueError):
    """A device spec that cannot be used, or a device that cannot be opened.

    The message is one line: what is wrong and what to do (``haptic client`` prints it and
    exits 2 before connecting to any server).
    """


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

    Parameters
    ----------
    spec : str
        ``sim:press``, ``sim:rest``, ``sim:replay:FILE`` or ``hid:VID:PID`` (hex).
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
    ValueError
        Malformed spec, unknown profile, bad trajectory option, bad anchor or normal, or a HID
        device with neither SpaceMouse ids nor a profile.
    ReplayError
        The replay file is missing or malformed (a ValueError).
    """
    a = vec3("anchor", anchor)
    n = unit_vec3("normal", normal)
    kind, _, rest = spec.partition(":")
    if kind == "sim":
        prof = get_sim_profile(profile)
        opts = dict(trajectory_options or {})
        hand = hand_with_options(hand, opts)
        what, _, arg = rest.partition(":")
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
            servo_period_s=1.0 / servo_rate_hz,
        )
    if kind == "hid":
        from haptic_collab.client.devices.hid import open_hid_device

        vid, pid = parse_hid_ids(rest)
        hp: HidProfile | None
        if hid_profile is None or isinstance(hid_profile, HidProfile):
            hp = hid_profile
        else:
            hp = load_hid_profile(hid_profile)
        center = (
            a[0] + HID_STANDOFF_M * n[0],
            a[1] + HID_STANDOFF_M * n[1],
            a[2] + HID_STANDOFF_M * n[2],
        )
        return open_hid_device(vid, pid, center, profile=hp, opener=hid_opener)
    raise ValueError(
        f"unknown device spec {spec!r}; use sim:press, sim:rest, sim:replay:FILE or hid:VID:PID"
    )


def _one_line(text: str) -> str:
    return "; ".join(part.strip() for part in str(text).splitlines() if part.strip())


class DeviceOpener:
    """Check a ``--device`` spec and open the device before the network; place it on the object later.

    ``haptic client`` calls :meth:`check` before it connects: the whole spec is parsed (kind,
    simulated profile, trajectory options, replay file, HID ids and profile) by building the
    device around a placeholder anchor, and a HID device's port is opened and kept open. Once the
    server's ``welcome`` says where the object is, :meth:`build` makes the device around the real
    anchor and opens it, a HID device on the port :meth:`check` opened (a replayed hand does not
    depend on the anchor: the checked device is used as it is). A device that faults later
    reopens through the same opener (:meth:`Device.reopen`).

    Parameters
    ----------
    spec : str
        ``sim:press``, ``sim:rest``, ``sim:replay:FILE`` or ``hid:VID:PID``.
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
        self._base_opener = hid_opener
        self._early: HidPort | None = None
        self._checked: Device | None = None
        self.hid_ids: tuple[int, int] | None = None

    def _open_port(self, vendor_id: int, product_id: int) -> HidPort:
        """The port :meth:`check` opened (once), else a newly opened one."""
        port, self._early = self._early, None
        if port is not None:
            return port
        if self._base_opener is not None:
            return self._base_opener(vendor_id, product_id)
        from haptic_collab.client.devices.hid import _hid_open

        return _hid_open(vendor_id, product_id)

    def _make(self, anchor: Sequence[float], normal: Sequence[float]) -> Device:
        return make_device(
            self.spec,
            anchor,
            normal,
            profile=self.profile,
            trajectory_options=self.trajectory_options or None,
            servo_rate_hz=self.servo_rate_hz,
            hid_profile=self.hid_profile,
            hid_opener=self._open_port,
        )

    def check(self) -> None:
        """Parse the spec and open a HID device now (before any network).

        Raises
        ------
        DeviceError
            A bad spec (unknown kind, profile or trajectory option, unreadable replay file, a
            HID device with no profile) or a HID device that cannot be opened (absent, no
            permission, busy), as one line with what to do.
        """
        try:
            dev = self._make((0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
        except ValueError as exc:
            raise DeviceError(_one_line(str(exc))) from None
        self._checked = dev
        if self.spec.startswith("hid:"):
            vid, pid = parse_hid_ids(self.spec.partition(":")[2])
            self.hid_ids = (vid, pid)
            try:
                self._early = self._open_port(vid, pid)
            except OSError as exc:
                from haptic_collab.client.devices.hid import open_error_message

                raise DeviceError(open_error_message(vid, pid, exc)) from None

    def build(self, anchor: Sequence[float], normal: Sequence[float]) -> Device:
        """The device placed on the object (anchor (3,) [m], outward normal (3,)), opened.

        Raises
        ------
        DeviceError
            Bad anchor or normal, or the device cannot be opened (it went away since
            :meth:`check`).
        """
        if self._checked is not None and isinstance(
            getattr(self._checked, "trajectory", None), Replay
        ):
            dev = self._checked  # a replayed hand is in world coordinates already
        else:
            try:
                dev = self._make(anchor, normal)
            except ValueError as exc:
                raise DeviceError(_one_line(str(exc))) from None
        try:
            dev.open()
        except OSError as exc:
            if self.hid_ids is None:
                raise DeviceError(f"cannot open {self.spec}: {exc}") from None
            from haptic_collab.client.devices.hid import open_error_message

            raise DeviceError(open_error_message(*self.hid_ids, exc)) from None
        return dev

    def close(self) -> None:
        """Release a port :meth:`check` opened that :meth:`build` never used."""
        port, self._early = self._early, None
        if port is not None:
            try:
                port.close()
            except OSError:
                pass


def list_devices() -> list[dict[str, Any]]:
    """Every device one could use now: attached HID devices, then the simulated profiles.

    Returns
    -------
    list of dict
        HID entries as :func:`client.devices.hid.list_devices` (``kind`` spacemouse,
        profile:NAME or unsupported), then one entry per simulated profile with ``kind`` ``sim``,
        ``spec`` ``sim:press``, ``profile``, ``max_force_n`` and ``max_stiffness_n_per_m``. The
        bundled generic HID profile files are listed by
        :func:`client.devices.profiles.hid_profile_names`.
    """
    from haptic_collab.client.devices.hid import list_devices as list_hid

    out = list_hid()
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
