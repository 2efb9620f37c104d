"""Haptic devices: the public face of the package (the names a lab's backend and the client use).

The code lives in modules by job, and this module only re-exports their public names:
:mod:`~client.devices.base` (the :class:`Device` interface and its limits),
:mod:`~client.devices.backends` (the plug-in point: :class:`DeviceBackend`, :class:`DeviceError`,
:class:`DeviceOptions`), :mod:`~client.devices.opener` (:func:`make_device`,
:class:`DeviceOpener`, :func:`list_devices`), :mod:`~client.devices.sim_backend` and
:mod:`~client.devices.hid_backend` (the built-in backends), and the devices themselves
(:mod:`~client.devices.sim`, :mod:`~client.devices.hid`, the vendor backends).

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

from haptic_collab.client.devices.backends import (
    ENTRY_POINT_GROUP,
    HID_STANDOFF_M,
    DeviceBackend,
    DeviceError,
    DeviceOpenError,
    DeviceOptions,
    list_backends,
)
from haptic_collab.client.devices.base import Device, DeviceLimits, HapticError, Vec3
from haptic_collab.client.devices.hid_backend import HID_BACKEND, parse_hid_ids
from haptic_collab.client.devices.opener import DeviceOpener, list_devices, make_device
from haptic_collab.client.devices.profiles import SIM_PROFILES
from haptic_collab.client.devices.sim import HandParams, SimDevice
from haptic_collab.client.devices.sim_backend import (
    HAND_OPTIONS,
    SIM_BACKEND,
    hand_with_options,
    load_replay,
)
from haptic_collab.client.devices.trajectories import (
    Press,
    Replay,
    ReplayError,
    Rest,
    hand_depth_for,
)

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
    "HID_STANDOFF_M",
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
