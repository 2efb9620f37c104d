"""The opened device as the servo's hosts handle it: what the link knows of it, and its reopening.

Both hosts of the servo loop use it: the servo process (:mod:`client.servo_child`) describes the
device it opened to the link process (:class:`BuiltDevice`, :func:`built_device`, pickled across
the pipe) and reopens a faulted device from a helper thread (:func:`reopen_device`); a servo
thread (``--servo thread``) has :func:`watch_device` beside it. A device fault is the device's
business: the servo loop ramps forces down while it lasts, the network link is not touched.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass

from haptic_collab.client.devices.base import Device, DeviceLimits

log = logging.getLogger("haptic.client")

__all__ = [
    "DEVICE_REOPEN_BACKOFF_S",
    "DEVICE_WATCH_PERIOD_S",
    "BuiltDevice",
    "built_device",
    "encoder_resolution",
    "reopen_device",
    "watch_device",
]

#: First and largest delay [s] between two attempts to reopen a faulted device.
DEVICE_REOPEN_BACKOFF_S = (0.5, 5.0)
#: How often [s] the device's fault flag is looked at.
DEVICE_WATCH_PERIOD_S = 0.05


@dataclass(frozen=True)
class BuiltDevice:
    """What the link process needs to know of the device the servo process placed and opened.

    Attributes
    ----------
    name : str
        The device's name.
    limits : DeviceLimits
        Its limits (workspace on the object).
    has_buttons : bool
        It reports buttons (``--engage default`` then engages forces with the first).
    encoder_resolution_m : float
        Its position quantum [m] (0: unknown), :func:`encoder_resolution`.
    """

    name: str
    limits: DeviceLimits
    has_buttons: bool
    encoder_resolution_m: float


def encoder_resolution(device: Device) -> float:
    """Position quantum [m] of the device: a simulated profile's encoder, or the coarsest integer
    axis of an absolute-position HID profile (metres per count); 0 when unknown."""
    profile = getattr(device, "profile", None)
    res = getattr(profile, "encoder_resolution_m", None)
    if isinstance(res, int | float) and math.isfinite(res):
        return float(res)
    layout = getattr(profile, "input", None)
    if getattr(layout, "mode", None) == "absolute":
        scales = [
            abs(float(ax.scale))
            for ax in getattr(layout, "axes", ())
            if getattr(ax, "type", "float32") != "float32"
        ]
        if scales and all(math.isfinite(v) for v in scales):
            return max(scales)
    return 0.0


def built_device(device: Device) -> BuiltDevice:
    """The :class:`BuiltDevice` of an opened device."""
    return BuiltDevice(
        name=str(getattr(device, "name", "device")),
        limits=device.limits,
        has_buttons=bool(getattr(device, "has_buttons", False)),
        encoder_resolution_m=encoder_resolution(device),
    )


def reopen_device(
    device: Device,
    counters: dict[str, int],
    stop: threading.Event,
    *,
    backoff_s: tuple[float, float] = DEVICE_REOPEN_BACKOFF_S,
) -> None:
    """Handle one fault of ``device`` (it was unplugged): reopen it with backoff until the fault
    clears, the device says it cannot be reopened, or ``stop``.

    A device fault is the device's business: the servo loop ramps forces to zero while
    :attr:`Device.fault` is set and back up once it clears; the network link is not touched. A
    device that cannot be reopened (:meth:`Device.reopen` returns False, e.g. simulated) stays
    faulted, forces off, logged once. Counts ``device_faults`` and ``device_reopens`` in
    ``counters``. Runs on a thread of its own, never the servo loop's.
    """
    counters["device_faults"] += 1
    log.warning(
        "device fault: %s; forces ramp to zero, reopening the device (the server link stays)",
        device.fault,
    )
    delay = backoff_s[0]
    while device.fault is not None and not stop.wait(delay):
        try:
            ok = device.reopen()
        except OSError as exc:
            delay = min(backoff_s[1], 2.0 * delay)
            log.info("device still unavailable (%s); next try in %.1f s", exc, delay)
            continue
        if not ok:
            if device.fault is not None:
                log.error("device %s cannot be reopened; forces stay off", device.name)
                while device.fault is not None and not stop.wait(DEVICE_WATCH_PERIOD_S):
                    pass
            return
        counters["device_reopens"] += 1
        log.warning("device %s is back; forces ramp up again", device.name)
        return


def watch_device(device: Device, counters: dict[str, int], stop: threading.Event) -> None:
    """Look at ``device``'s fault flag every :data:`DEVICE_WATCH_PERIOD_S` until ``stop`` and
    handle each fault with :func:`reopen_device` (the servo thread's companion in ``--servo
    thread``; the servo process starts :func:`reopen_device` only when a fault appears, so no
    other thread ever competes with its loop for the interpreter lock)."""
    while not stop.wait(DEVICE_WATCH_PERIOD_S):
        if device.fault is not None:
            reopen_device(device, counters, stop)
