"""The built-in ``hid`` backend: a real HID device through hidapi (``--device hid:VID:PID``).

:class:`HidBackend` (:data:`HID_BACKEND`, the entry point ``hid``) parses the ids
(:func:`parse_hid_ids`), finds the profile, and opens the port before the network when the client
asks (:class:`_HidPorts` lends that port to the unplaced device and hands it to the placed one).
The device classes and every call into hidapi are in :mod:`client.devices.hid`, imported only when
a HID device is opened or listed.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from haptic_collab.client.devices.backends import (
    HID_STANDOFF_M,
    PLACEHOLDER_ANCHOR,
    PLACEHOLDER_NORMAL,
    DeviceBackend,
    DeviceError,
    DeviceOpenError,
    DeviceOptions,
)
from haptic_collab.client.devices.base import Device, Vec3
from haptic_collab.client.devices.profiles import HidProfile, load_hid_profile

if TYPE_CHECKING:
    from haptic_collab.client.devices.hid import HidPort

__all__ = ["HID_BACKEND", "HidBackend", "parse_hid_ids"]


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


#: The built-in HID backend (pyproject.toml registers it as the entry point ``hid``).
HID_BACKEND = HidBackend()
