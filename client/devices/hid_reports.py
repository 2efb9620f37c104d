"""HID report bytes to probe positions and forces to report bytes: pure functions, no hidapi.

The devices of :mod:`client.devices.hid` parse what they read and encode what they write with
these functions of the report bytes alone, so tests feed them recorded reports:

- :func:`parse_spacemouse_report`: the public SpaceMouse layout. Report id 1 carries translation
  x, y, z as int16 little-endian in bytes 1-6; report id 2 carries rotation rx, ry, rz likewise;
  newer models send translation and rotation together in one 13-byte report id 1 (12 data bytes).
  Raw axes: x right, y toward the user, z down (pressing the cap gives +z); counts up to about
  +-350 at full deflection.
- :func:`spacemouse_position` / :func:`integrate_rate`: counts to a position in the workspace,
  either by scaling the deflection (``position`` mode: the cap is a spring-centred joystick, the
  probe springs back when released) or by integrating it as a velocity (``rate`` mode).
- :func:`decode_input` / :func:`encode_output`: the generic layout of a JSON profile
  (:mod:`client.devices.profiles`).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from haptic_collab.client.devices.base import Vec3
from haptic_collab.client.devices.profiles import HidInputLayout, HidOutputLayout

__all__ = [
    "SpaceMouseMapping",
    "decode_input",
    "encode_output",
    "integrate_rate",
    "parse_spacemouse_report",
    "spacemouse_position",
    "spacemouse_velocity",
]

_I16X3 = struct.Struct("<hhh")


def parse_spacemouse_report(
    data: bytes | Sequence[int],
) -> tuple[tuple[int, int, int] | None, tuple[int, int, int] | None]:
    """Decode one SpaceMouse input report into (translation, rotation) counts.

    Parameters
    ----------
    data : bytes or sequence of int
        The report as hidapi returns it, report id first.

    Returns
    -------
    translation, rotation : (3,) int or None
        Raw counts (x, y, z) and (rx, ry, rz); None for the part the report does not carry
        (a buttons report gives (None, None)).

    Raises
    ------
    ValueError
        A translation or rotation report shorter than 7 bytes.
    """
    b = bytes(data)
    if not b:
        return (None, None)
    rid = b[0]
    if rid not in (1, 2):
        return (None, None)
    if len(b) < 7:
        raise ValueError(f"SpaceMouse report id {rid} too short: {len(b)} bytes, need 7")
    first: tuple[int, int, int] = _I16X3.unpack_from(b, 1)
    if rid == 2:
        return (None, first)
    rot: tuple[int, int, int] | None = _I16X3.unpack_from(b, 7) if len(b) >= 13 else None
    return (first, rot)


@dataclass(frozen=True, slots=True)
class SpaceMouseMapping:
    """How SpaceMouse counts become a probe position (world frame = device frame, z up).

    Parameters
    ----------
    mode : {"position", "rate"}
        ``position``: offset = travel * counts / full_scale from the workspace centre.
        ``rate``: velocity = speed * counts / full_scale, integrated and kept in the workspace.
    full_scale_counts : float
        Counts at full deflection (default 350); larger values are clipped.
    travel_m : float
        Offset [m] at full deflection in position mode (default 0.04).
    speed_m_s : float
        Speed [m/s] at full deflection in rate mode (default 0.1).
    signs : (3,) float
        Raw axis to world axis signs; default (1, -1, -1): x right, y away from the user, z up
        (pressing the cap moves the probe down).
    """

    mode: Literal["position", "rate"] = "position"
    full_scale_counts: float = 350.0
    travel_m: float = 0.04
    speed_m_s: float = 0.1
    signs: tuple[float, float, float] = (1.0, -1.0, -1.0)


def _unit_counts(c: float, full: float) -> float:
    u = c / full
    return 1.0 if u > 1.0 else (-1.0 if u < -1.0 else u)


def spacemouse_position(
    counts: tuple[int, int, int], center: Vec3, mapping: SpaceMouseMapping
) -> Vec3:
    """Position [m] for translation ``counts`` in ``position`` mode, around ``center`` (3,) [m]."""
    fs, tr, s = mapping.full_scale_counts, mapping.travel_m, mapping.signs
    return (
        center[0] + s[0] * tr * _unit_counts(counts[0], fs),
        center[1] + s[1] * tr * _unit_counts(counts[1], fs),
        center[2] + s[2] * tr * _unit_counts(counts[2], fs),
    )


def integrate_rate(
    position: Vec3,
    velocity: Vec3,
    dt_s: float,
    lo: Vec3,
    hi: Vec3,
) -> Vec3:
    """One explicit step ``position + dt * velocity`` [m], clamped into the box [lo, hi] (3,) [m]."""
    return (
        min(max(position[0] + dt_s * velocity[0], lo[0]), hi[0]),
        min(max(position[1] + dt_s * velocity[1], lo[1]), hi[1]),
        min(max(position[2] + dt_s * velocity[2], lo[2]), hi[2]),
    )


def spacemouse_velocity(counts: tuple[int, int, int], mapping: SpaceMouseMapping) -> Vec3:
    """Velocity [m/s] for translation ``counts`` in ``rate`` mode."""
    fs, sp, s = mapping.full_scale_counts, mapping.speed_m_s, mapping.signs
    return (
        s[0] * sp * _unit_counts(counts[0], fs),
        s[1] * sp * _unit_counts(counts[1], fs),
        s[2] * sp * _unit_counts(counts[2], fs),
    )


def decode_input(layout: HidInputLayout, data: bytes | Sequence[int]) -> Vec3 | None:
    """Decode x, y, z from one input report of a generic profile.

    Returns
    -------
    (3,) float or None
        Absolute mode: position [m] in the device frame (scale * count + offset_m). Rate mode:
        velocity [m/s]. None if the report id is not the layout's.

    Raises
    ------
    ValueError
        The report is too short for the layout.
    """
    b = bytes(data)
    if layout.report_id is not None and (not b or b[0] != layout.report_id):
        return None
    out = [0.0, 0.0, 0.0]
    for i, ax in enumerate(layout.axes):
        if len(b) < ax.end:
            raise ValueError(f"report of {len(b)} bytes too short: axis {i} needs {ax.end}")
        raw = ax.struct.unpack_from(b, ax.byte)[0]
        out[i] = raw * ax.scale + (ax.offset_m if layout.mode == "absolute" else 0.0)
        if not math.isfinite(out[i]):
            raise ValueError(f"axis {i} decoded to a non-finite value")
    return (out[0], out[1], out[2])


_RANGES = {
    "int8": (-(2**7), 2**7 - 1),
    "uint8": (0, 2**8 - 1),
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
}


def encode_output(layout: HidOutputLayout, fx: float, fy: float, fz: float) -> bytes:
    """Encode the force (fx, fy, fz) [N] into an output report of a generic profile.

    Counts are ``round(f / scale)`` clipped to the field's integer range; the report id (0 when
    the layout has none) is the first byte, as hidapi's ``write`` expects.
    """
    buf = bytearray(layout.length)
    buf[0] = layout.report_id if layout.report_id is not None else 0
    for ax, f in zip(layout.axes, (fx, fy, fz), strict=True):
        v = f / ax.scale if math.isfinite(f) else 0.0
        if ax.type == "float32":
            ax.struct.pack_into(buf, ax.byte, v)
        else:
            lo, hi = _RANGES[ax.type]
            ax.struct.pack_into(buf, ax.byte, min(max(round(v), lo), hi))
    return bytes(buf)
