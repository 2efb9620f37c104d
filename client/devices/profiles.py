"""Named device profiles: the simulated devices' specifications and the generic HID profile files.

Simulated profiles (:data:`SIM_PROFILES`) carry a device's published limits (DESIGN section 7,
CHAI3D's device specification) plus what the simulation needs: the apparent moving mass at the
handle and the encoder resolution. The numbers are plausible values for the two desktop devices
whose names they borrow, not vendor-certified data:

=================  =======  ==============  ========  =========  ==========  ==========  ===============
profile            F_max N  K_max N/m @1kHz  mass kg  b N*s/m    B_max N*s/m encoder mm  workspace mm
=================  =======  ==============  ========  =========  ==========  ==========  ===============
phantom-desktop    7.9      1000            0.045     0.5        10          0.023       160 x 120 x 120
touch              3.3      400             0.045     0.2        5           0.055       160 x 120 x 70
=================  =======  ==============  ========  =========  ==========  ==========  ===============

F_max is the peak force; both devices also state a continuous force (24 hours): 1.75 N for the
Phantom Desktop and 0.88 N for the Touch (3D Systems' datasheets). The PI local model's integral
is limited to the continuous force (``haptic client``): a hold never asks the motors for their
peak force for seconds; the peak stays available to the proportional part.

B_max is the largest virtual damping the local model may add on the probe velocity (CHAI3D's
``m_maxLinearDamping``; CHAI3D declares 20-40 N*s/m for Force Dimension devices); it is a plausible
value for these desktop devices, like the rest of the table.

The largest stable stiffness follows the sampled virtual-wall bound K_max = 2 b / T (Colgate and
Schenkel) with the device damping b and servo period T = 1 ms; the simulated hand's own damping
adds margin.

Generic HID profiles are JSON files in the ``profiles/`` folder beside this module (or any path).
They describe where a device puts its position in an input report and, optionally, where it takes
a force in an output report. Schema (all keys required unless marked optional)::

    {
      "name": "example-3dof",                  # str
      "description": "...",                    # optional str
      "vendor_id": "0x1234", "product_id": "0x5678",   # hex strings or ints
      "input": {
        "report_id": 1,                        # first byte of each report, or null if unnumbered
        "mode": "absolute",                    # "absolute": position = scale * count
                                               # "rate": velocity = scale * count, integrated
        "axes": [                              # exactly 3: x, y, z of the world frame
          {"byte": 1, "type": "int16", "endian": "little", "scale": 1e-5, "offset_m": 0.0},
          ...
        ]
      },
      "output": {                              # optional: omit for a position-only device
        "report_id": 2,                        # written as the first byte (0 if unnumbered)
        "length": 7,                           # bytes written, report id included
        "axes": [{"byte": 1, "type": "int16", "endian": "little", "scale": 0.001}, ...]
      },                                       # scale [N per count]: count = round(f / scale)
      "limits": {"max_force_n": 3.0, "max_stiffness_n_per_m": 500.0, "max_velocity_m_s": 0.5,
                 "damping_n_s_per_m": 0.0, "workspace_size_m": [0.2, 0.2, 0.2]},
      "silence_timeout_s": 0.1                 # optional: no report for this long -> fault
    }

``byte`` counts from the first byte hidapi returns (the report id, for a numbered report). Input
``scale`` is metres per count (absolute) or metres per second per count (rate); ``offset_m`` is
added after scaling (absolute mode only). Types: int8, uint8, int16, uint16, int32, uint32,
float32. Endianness: little or big.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from haptic_collab.client.devices.base import DeviceLimits

#: Folder of the bundled generic HID profile files.
HID_PROFILE_DIR = Path(__file__).resolve().parent / "profiles"

_INT_TYPES: dict[str, str] = {
    "int8": "b",
    "uint8": "B",
    "int16": "h",
    "uint16": "H",
    "int32": "i",
    "uint32": "I",
    "float32": "f",
}


@dataclass(frozen=True, slots=True)
class SimProfile:
    """Specification of a simulated device.

    Parameters
    ----------
    name : str
        Profile name (``phantom-desktop``, ``touch``).
    limits : DeviceLimits
        Published limits; the workspace box is centred on the origin (moved by ``make_device``).
    mass_kg : float
        Apparent moving mass [kg] of the device at the handle, > 0.
    encoder_resolution_m : float
        Position quantum [m] of the reported position, >= 0 (0: no quantization).
    """

    name: str
    limits: DeviceLimits
    mass_kg: float
    encoder_resolution_m: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.mass_kg) and self.mass_kg > 0.0):
            raise ValueError(f"mass_kg must be > 0, got {self.mass_kg!r}")
        if not (math.isfinite(self.encoder_resolution_m) and self.encoder_resolution_m >= 0.0):
            raise ValueError(
                f"encoder_resolution_m must be >= 0, got {self.encoder_resolution_m!r}"
            )


def _box(wx: float, wy: float, wz: float) -> tuple[tuple[float, float, float], ...]:
    return ((-wx / 2, -wy / 2, -wz / 2), (wx / 2, wy / 2, wz / 2))


SIM_PROFILES: dict[str, SimProfile] = {
    "phantom-desktop": SimProfile(
        name="phantom-desktop",
        limits=DeviceLimits(
            max_force_n=7.9,
            max_continuous_force_n=1.75,  # 3D Systems' datasheet: 24 h continuous, 0.4 lbf
            max_stiffness_n_per_m=1000.0,
            max_velocity_m_s=0.6,
            damping_n_s_per_m=0.5,
            max_damping_n_s_per_m=10.0,
            workspace_min_m=_box(0.16, 0.12, 0.12)[0],
            workspace_max_m=_box(0.16, 0.12, 0.12)[1],
        ),
        mass_kg=0.045,
        encoder_resolution_m=0.023e-3,
    ),
    "touch": SimProfile(
        name="touch",
        limits=DeviceLimits(
            max_force_n=3.3,
            max_continuous_force_n=0.88,  # 3D Systems' datasheet: 24 h continuous, 0.2 lbf
            max_stiffness_n_per_m=400.0,
            max_velocity_m_s=0.5,
            damping_n_s_per_m=0.2,
            max_damping_n_s_per_m=5.0,
            workspace_min_m=_box(0.16, 0.12, 0.07)[0],
            workspace_max_m=_box(0.16, 0.12, 0.07)[1],
        ),
        mass_kg=0.045,
        encoder_resolution_m=0.055e-3,
    ),
}


def sim_profile_names() -> list[str]:
    """Names of the simulated device profiles, sorted."""
    return sorted(SIM_PROFILES)


def get_sim_profile(name: str) -> SimProfile:
    """The simulated profile called ``name``.

    Raises
    ------
    ValueError
        Unknown name (the message lists the known ones).
    """
    try:
        return SIM_PROFILES[name]
    except KeyError:
        raise ValueError(
            f"unknown device profile {name!r}; known: {', '.join(sim_profile_names())}"
        ) from None


# ---------------------------------------------------------------------------------------------
# Generic HID profiles
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class HidField:
    """One number in a HID report: where it is, how it is encoded, and its scale.

    Parameters
    ----------
    byte : int
        Offset of the first byte, counted from the first byte hidapi returns / is given.
    type : str
        One of int8, uint8, int16, uint16, int32, uint32, float32.
    endian : {"little", "big"}
        Byte order.
    scale : float
        Input: metres (absolute) or m/s (rate) per count. Output: newtons per count. Non-zero.
    offset_m : float
        Added to an absolute input after scaling [m]; unused for outputs.
    """

    byte: int
    type: str
    endian: Literal["little", "big"]
    scale: float
    offset_m: float = 0.0

    @property
    def struct(self) -> struct.Struct:
        """The :class:`struct.Struct` that decodes this field."""
        return struct.Struct(("<" if self.endian == "little" else ">") + _INT_TYPES[self.type])

    @property
    def end(self) -> int:
        """One past the last byte of the field."""
        return self.byte + self.struct.size


@dataclass(frozen=True, slots=True)
class HidInputLayout:
    """Where a device puts x, y, z in its input report (see the module schema)."""

    report_id: int | None
    mode: Literal["absolute", "rate"]
    axes: tuple[HidField, HidField, HidField]


@dataclass(frozen=True, slots=True)
class HidOutputLayout:
    """Where a device takes fx, fy, fz in its output report (see the module schema)."""

    report_id: int | None
    length: int
    axes: tuple[HidField, HidField, HidField]


@dataclass(frozen=True, slots=True)
class HidProfile:
    """A generic HID device described by a JSON profile file (module docstring has the schema).

    ``limits`` has its workspace box centred on the origin (the device frame); ``make_device``
    moves it into the world.
    """

    name: str
    vendor_id: int
    product_id: int
    input: HidInputLayout
    output: HidOutputLayout | None
    limits: DeviceLimits
    silence_timeout_s: float | None
    description: str = ""


class ProfileError(ValueError):
    """A HID profile file is missing, not JSON, or does not follow the schema."""


def _req(d: dict[str, Any], key: str, where: str) -> Any:
    if not isinstance(d, dict):
        raise ProfileError(f"{where} must be an object")
    if key not in d:
        raise ProfileError(f"{where}: missing key {key!r}")
    return d[key]


def _hex_or_int(value: Any, where: str) -> int:
    try:
        v = int(value, 16) if isinstance(value, str) else int(value)
    except (TypeError, ValueError):
        raise ProfileError(f"{where} must be a hex string like '0x046d' or an int") from None
    if not 0 <= v <= 0xFFFF:
        raise ProfileError(f"{where} must be in 0..0xffff, got {value!r}")
    return v


def _report_id(value: Any, where: str) -> int | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 255:
        raise ProfileError(f"{where} must be null or an int in 0..255, got {value!r}")
    return value


def _field(d: Any, where: str, *, input_side: bool) -> HidField:
    byte = _req(d, "byte", where)
    typ = _req(d, "type", where)
    endian = d.get("endian", "little")
    scale = _req(d, "scale", where)
    offset_m = d.get("offset_m", 0.0) if input_side else 0.0
    if isinstance(byte, bool) or not isinstance(byte, int) or byte < 0:
        raise ProfileError(f"{where}.byte must be an int >= 0, got {byte!r}")
    if typ not in _INT_TYPES:
        raise ProfileError(f"{where}.type must be one of {sorted(_INT_TYPES)}, got {typ!r}")
    if endian not in ("little", "big"):
        raise ProfileError(f"{where}.endian must be 'little' or 'big', got {endian!r}")
    for name, v in (("scale", scale), ("offset_m", offset_m)):
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise ProfileError(f"{where}.{name} must be a finite number, got {v!r}")
    if scale == 0:
        raise ProfileError(f"{where}.scale must be non-zero")
    return HidField(
        byte=byte, type=typ, endian=endian, scale=float(scale), offset_m=float(offset_m)
    )


def _axes(d: Any, where: str, *, input_side: bool) -> tuple[HidField, HidField, HidField]:
    axes = _req(d, "axes", where)
    if not isinstance(axes, list) or len(axes) != 3:
        raise ProfileError(f"{where}.axes must be a list of 3 fields (x, y, z)")
    f = [_field(a, f"{where}.axes[{i}]", input_side=input_side) for i, a in enumerate(axes)]
    return (f[0], f[1], f[2])


def parse_hid_profile(data: dict[str, Any], source: str = "<profile>") -> HidProfile:
    """Validate a decoded JSON profile (module docstring schema) into a :class:`HidProfile`.

    Raises
    ------
    ProfileError
        Any missing key or out-of-range value; the message names ``source`` and the key.
    """
    try:
        name = _req(data, "name", source)
        if not isinstance(name, str) or not name:
            raise ProfileError(f"{source}: name must be a non-empty string")
        vid = _hex_or_int(_req(data, "vendor_id", source), f"{source}: vendor_id")
        pid = _hex_or_int(_req(data, "product_id", source), f"{source}: product_id")
        inp = _req(data, "input", source)
        mode = inp.get("mode", "absolute") if isinstance(inp, dict) else None
        if mode not in ("absolute", "rate"):
            raise ProfileError(f"{source}: input.mode must be 'absolute' or 'rate', got {mode!r}")
        in_layout = HidInputLayout(
            report_id=_report_id(inp.get("report_id"), f"{source}: input.report_id"),
            mode=mode,
            axes=_axes(inp, f"{source}: input", input_side=True),
        )
        out_layout = None
        out = data.get("output")
        if out is not None:
            axes = _axes(out, f"{source}: output", input_side=False)
            length = _req(out, "length", f"{source}: output")
            if isinstance(length, bool) or not isinstance(length, int) or length < 1:
                raise ProfileError(f"{source}: output.length must be an int >= 1")
            if any(a.end > length for a in axes):
                raise ProfileError(f"{source}: output axes run past output.length {length}")
            out_layout = HidOutputLayout(
                report_id=_report_id(out.get("report_id"), f"{source}: output.report_id"),
                length=length,
                axes=axes,
            )
        lim = _req(data, "limits", source)
        size = _req(lim, "workspace_size_m", f"{source}: limits")
        if not isinstance(size, list) or len(size) != 3:
            raise ProfileError(f"{source}: limits.workspace_size_m must be 3 numbers")
        lo, hi = _box(*(float(s) for s in size))
        limits = DeviceLimits(
            max_force_n=float(_req(lim, "max_force_n", f"{source}: limits")),
            max_stiffness_n_per_m=float(_req(lim, "max_stiffness_n_per_m", f"{source}: limits")),
            max_velocity_m_s=float(_req(lim, "max_velocity_m_s", f"{source}: limits")),
            damping_n_s_per_m=float(lim.get("damping_n_s_per_m", 0.0)),
            max_damping_n_s_per_m=float(lim.get("max_damping_n_s_per_m", 0.0)),
            workspace_min_m=(lo[0], lo[1], lo[2]),
            workspace_max_m=(hi[0], hi[1], hi[2]),
            has_force_output=out_layout is not None,
        )
        silence = data.get("silence_timeout_s", 0.1)
        if silence is not None and not (
            isinstance(silence, int | float) and math.isfinite(silence) and silence > 0
        ):
            raise ProfileError(f"{source}: silence_timeout_s must be null or > 0 s")
        return HidProfile(
            name=name,
            vendor_id=vid,
            product_id=pid,
            input=in_layout,
            output=out_layout,
            limits=limits,
            silence_timeout_s=None if silence is None else float(silence),
            description=str(data.get("description", "")),
        )
    except ProfileError:
        raise
    except (TypeError, ValueError, AttributeError) as exc:
        raise ProfileError(f"{source}: {exc}") from exc


def load_hid_profile(name_or_path: str | Path) -> HidProfile:
    """Load a generic HID profile by bundled name (``profiles/NAME.json``) or by file path.

    Raises
    ------
    ProfileError
        The file does not exist, is not JSON, or does not follow the schema.
    """
    path = Path(name_or_path)
    if not path.suffix and not path.exists():
        path = HID_PROFILE_DIR / f"{name_or_path}.json"
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        known = ", ".join(hid_profile_names()) or "none"
        raise ProfileError(
            f"cannot read HID profile {str(path)!r} ({exc}); bundled: {known}"
        ) from exc
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ProfileError(f"{path}: not valid JSON: {exc}") from exc
    return parse_hid_profile(data, str(path))


def hid_profile_names() -> list[str]:
    """Names of the bundled generic HID profiles (files in :data:`HID_PROFILE_DIR`), sorted."""
    if not HID_PROFILE_DIR.is_dir():
        return []
    return sorted(p.stem for p in HID_PROFILE_DIR.glob("*.json"))


def find_hid_profile(vendor_id: int, product_id: int) -> HidProfile | None:
    """The bundled profile whose vendor and product id match, or None."""
    for name in hid_profile_names():
        prof = load_hid_profile(name)
        if prof.vendor_id == vendor_id and prof.product_id == product_id:
            return prof
    return None
