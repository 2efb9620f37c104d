"""Building and opening a device from a ``--device`` spec (:func:`make_device`, the opener).

:func:`make_device` builds a device (not opened) through the backend the spec's prefix names;
:class:`DeviceOpener` checks a spec and opens the device *before* the client touches the network
(a bad spec or an absent device is a :class:`DeviceError`: one line, what and what to do), and
places it on the object once the server's ``welcome`` says where the object is;
:func:`list_devices` is what ``haptic devices`` prints.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from haptic_collab.client.devices.backends import (
    DeviceBackend,
    DeviceError,
    DeviceOpenError,
    DeviceOptions,
    list_backends,
    one_line,
    usable_backend,
)
from haptic_collab.client.devices.base import Device, DeviceLimits
from haptic_collab.client.devices.profiles import HidProfile
from haptic_collab.client.devices.sim import HandParams
from haptic_collab.shared.primitives import unit_vec3, vec3

if TYPE_CHECKING:
    from haptic_collab.client.devices.hid import HidPort

__all__ = ["DeviceOpener", "list_devices", "make_device"]


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
