"""What the vendor device backends (forcedimension, openhaptics, haply) share.

Each of them places the device's workspace centre :data:`~client.devices.HID_STANDOFF_M` outside
the anchor along the anchor's outward normal, like a HID device's: at a placeholder before the
server's welcome says where the object is, then where :meth:`DeviceBackend.place` is told.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TypeVar

from haptic_collab.client.devices import HID_STANDOFF_M, PLACEHOLDER_ANCHOR, PLACEHOLDER_NORMAL
from haptic_collab.client.devices.backends import DeviceBackend, DeviceError
from haptic_collab.client.devices.base import Device, Vec3

__all__ = ["PLACEHOLDER_CENTER", "opened_by", "standoff_center"]

_D = TypeVar("_D", bound=Device)


def standoff_center(anchor: Sequence[float], normal: Sequence[float]) -> Vec3:
    """The workspace centre (3,) [m]: :data:`HID_STANDOFF_M` outside ``anchor`` (3,) [m] along
    the outward unit ``normal`` (3,)."""
    return (
        anchor[0] + HID_STANDOFF_M * normal[0],
        anchor[1] + HID_STANDOFF_M * normal[1],
        anchor[2] + HID_STANDOFF_M * normal[2],
    )


#: Where the workspace centre sits before the server's welcome says where the object is [m].
PLACEHOLDER_CENTER: Vec3 = standoff_center(PLACEHOLDER_ANCHOR, PLACEHOLDER_NORMAL)


def opened_by(backend: DeviceBackend, device: Device, cls: type[_D]) -> _D:
    """``device``, checked to be the ``cls`` that ``backend`` opens.

    Raises
    ------
    DeviceError
        ``device`` is not a ``cls``: "NAME was not opened by the BACKEND backend".
    """
    if not isinstance(device, cls):
        raise DeviceError(f"{device.name} was not opened by the {backend.name} backend")
    return device
