"""What the vendor device backends (forcedimension, openhaptics, haply) share.

Each of them places the device's workspace centre
:data:`~client.devices.backends.HID_STANDOFF_M` outside the anchor along the anchor's outward
normal, like a HID device's: at a placeholder before the server's welcome says where the object
is, then where :meth:`DeviceBackend.place` is told.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TypeVar

from haptic_collab.client.devices.backends import (
    HID_STANDOFF_M,
    PLACEHOLDER_ANCHOR,
    PLACEHOLDER_NORMAL,
    DeviceBackend,
    DeviceError,
)
from haptic_collab.client.devices.base import Device, Vec3

__all__ = ["PLACEHOLDER_CENTER", "opened_by", "standoff_center"]

_D = TypeVar("_D", bound=Device)

#: Largest workspace scale a vendor spec accepts (``,scale=S``): world metres per device metre.
MAX_SCALE = 100.0


def workspace_scale(spec: str, text: str, hint: str = "") -> float:
    """The workspace scale ``S`` of a ``,scale=S`` option, ``text`` as written in ``spec``.

    Returns
    -------
    float
        S, world metres per metre of device motion, in (0, :data:`MAX_SCALE`].

    Raises
    ------
    DeviceError
        ``bad workspace scale in SPEC: 'TEXT' (need a number > 0 and <= 100, world metres per
        metre of device motion)``, then ``hint`` (e.g. the spec's form) if given.
    """
    try:
        scale = float(text)
    except ValueError:
        scale = math.nan
    if not (math.isfinite(scale) and 0.0 < scale <= MAX_SCALE):
        raise DeviceError(
            f"bad workspace scale in {spec!r}: {text.strip()!r} (need a number > 0 and <= "
            f"{MAX_SCALE:g}, world metres per metre of device motion)"
            + (f"; {hint}" if hint else "")
        )
    return scale


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
