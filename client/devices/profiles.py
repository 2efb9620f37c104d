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
float32. Endianness: little or big. Optional keys not shown: ``input.report_id`` and
``output.report_id`` (default null), ``input.mode`` (default absolute), ``endian`` (default
little), ``offset_m`` (default 0), ``limits.damping_n_s_per_m`` and
``limits.max_damping_n_s_per_m`` (default 0); ``silence_timeout_s`` defaults to 0.1 s, null turns
the check off. Numbers must be JSON numbers (finite; no strings, no booleans); unknown keys are
ignored.

The schema is the pydantic model :class:`HidProfileModel`; ``HidProfileModel.model_json_schema()``
is its JSON Schema (draft 2020-12) for editors and validators. A file that does not follow it is
refused with a :class:`ProfileError` naming the file and, for each problem, the key's path and
what is wrong, e.g. ``my.json: input.axes[1].endian: Input should be 'little' or 'big', got
'middle'``.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    Strict,
    ValidationError,
    WithJsonSchema,
    model_validator,
)
from pydantic_core import ErrorDetails, PydanticCustomError

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

# JSON numbers only: no "1" for 1, no true for 1 (a JSON integer is accepted where a float is
# expected); no NaN or Infinity (``allow_inf_nan=False`` on every model).
_StrictFinite = Annotated[float, Strict()]
_Positive = Annotated[_StrictFinite, Field(gt=0)]
_NonNegative = Annotated[_StrictFinite, Field(ge=0)]
_ReportId = Annotated[int, Strict(), Field(ge=0, le=255)]


def _non_zero(value: float) -> float:
    if value == 0:
        raise PydanticCustomError("non_zero", "Input should be non-zero")
    return value


def _usb_id(value: Any) -> Any:
    """A USB vendor or product id from a hex string (``"0x046d"``, ``"046d"``) or an int."""
    try:
        v = int(value, 16) if isinstance(value, str) else int(value)
    except (TypeError, ValueError):
        raise PydanticCustomError(
            "usb_id", "Input should be a hex string like '0x046d' or an int"
        ) from None
    if not 0 <= v <= 0xFFFF:
        raise PydanticCustomError("usb_id", "Input should be in 0..0xffff")
    return v


_UsbId = Annotated[
    int,
    BeforeValidator(_usb_id),
    WithJsonSchema(
        {
            "anyOf": [
                {"type": "integer", "minimum": 0, "maximum": 0xFFFF},
                {"type": "string", "pattern": "^(0[xX])?[0-9a-fA-F]+$"},
            ]
        }
    ),
]


class _Model(BaseModel):
    model_config = ConfigDict(extra="ignore", allow_inf_nan=False, frozen=True)


class HidField(_Model):
    """One number in a HID report: where it is, how it is encoded, and its scale.

    Parameters
    ----------
    byte : int
        Offset of the first byte, counted from the first byte hidapi returns / is given, >= 0.
    type : str
        One of int8, uint8, int16, uint16, int32, uint32, float32.
    endian : {"little", "big"}
        Byte order (default little).
    scale : float
        Input: metres (absolute) or m/s (rate) per count. Output: newtons per count. Finite,
        non-zero.
    offset_m : float
        Added to an absolute input after scaling [m] (default 0); unused for outputs.
    """

    byte: Annotated[int, Strict(), Field(ge=0)]
    type: Literal["int8", "uint8", "int16", "uint16", "int32", "uint32", "float32"]
    endian: Literal["little", "big"] = "little"
    scale: Annotated[
        _StrictFinite, AfterValidator(_non_zero), Field(json_schema_extra={"not": {"const": 0}})
    ]
    offset_m: _StrictFinite = 0.0

    @property
    def struct(self) -> struct.Struct:
        """The :class:`struct.Struct` that decodes this field."""
        return struct.Struct(("<" if self.endian == "little" else ">") + _INT_TYPES[self.type])

    @property
    def end(self) -> int:
        """One past the last byte of the field."""
        return self.byte + self.struct.size


_Axes = tuple[HidField, HidField, HidField]


class HidInputLayout(_Model):
    """Where a device puts x, y, z in its input report (see the module schema).

    ``report_id`` (0..255) is the first byte of each report, or None for an unnumbered report;
    ``mode`` is ``absolute`` (position = scale * count + offset_m) or ``rate`` (velocity = scale *
    count, integrated); ``axes`` are x, y, z of the world frame.
    """

    report_id: _ReportId | None = None
    mode: Literal["absolute", "rate"] = "absolute"
    axes: _Axes


class HidOutputLayout(_Model):
    """Where a device takes fx, fy, fz in its output report (see the module schema).

    ``report_id`` (0..255, None: unnumbered) is written as the first byte (0 when None);
    ``length`` [bytes], >= 1, is the size of the report written, report id included; every axis
    must end within it.
    """

    report_id: _ReportId | None = None
    length: Annotated[int, Strict(), Field(ge=1)]
    axes: _Axes

    @model_validator(mode="after")
    def _axes_fit(self) -> HidOutputLayout:
        if any(a.end > self.length for a in self.axes):
            raise PydanticCustomError(
                "axes_past_length",
                "axes run past output.length {length}",
                {"length": self.length},
            )
        return self


class HidLimits(_Model):
    """The ``limits`` block of a profile file: the device's published limits, SI units.

    Forces [N], stiffness [N/m], velocity [m/s], damping [N*s/m] and the workspace box's size [m]
    (centred on the origin of the device frame). See :class:`~client.devices.base.DeviceLimits`.
    """

    max_force_n: _NonNegative
    max_stiffness_n_per_m: _Positive
    max_velocity_m_s: _Positive
    damping_n_s_per_m: _NonNegative = 0.0
    max_damping_n_s_per_m: _NonNegative = 0.0
    workspace_size_m: tuple[_Positive, _Positive, _Positive]


class HidProfileModel(_Model):
    """The schema of a generic HID profile file (module docstring); validates a decoded file.

    ``HidProfileModel.model_json_schema()`` is the file's JSON Schema (draft 2020-12); unknown keys
    are ignored. :func:`parse_hid_profile` validates with this model and returns a
    :class:`HidProfile`.
    """

    name: Annotated[str, Strict(), Field(min_length=1)]
    description: str = ""
    vendor_id: _UsbId
    product_id: _UsbId
    input: HidInputLayout
    output: HidOutputLayout | None = None
    limits: HidLimits
    silence_timeout_s: _Positive | None = 0.1


@dataclass(frozen=True, slots=True)
class HidProfile:
    """A generic HID device described by a JSON profile file (module docstring has the schema).

    ``limits`` has its workspace box centred on the origin (the device frame); ``make_device``
    moves it into the world. ``silence_timeout_s`` [s]: no report for this long is a fault (None:
    never).
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


def _where(loc: tuple[int | str, ...]) -> str:
    """``("input", "axes", 0, "type")`` -> ``input.axes[0].type``."""
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _problem(err: ErrorDetails) -> str:
    """One validation error as ``path: problem, got value``."""
    # a nested model's own name means nothing to someone writing a JSON file
    msg = "Input should be a JSON object" if err["type"] == "model_type" else err["msg"]
    value = err.get("input")
    if err["type"] != "missing" and not isinstance(value, dict | list):
        shown = repr(value)
        msg += f", got {shown if len(shown) <= 40 else shown[:37] + '...'}"
    where = _where(err["loc"])
    return f"{where}: {msg}" if where else msg


def parse_hid_profile(data: Any, source: str = "<profile>") -> HidProfile:
    """Validate a decoded JSON profile (module docstring schema) into a :class:`HidProfile`.

    Parameters
    ----------
    data : dict
        The decoded file.
    source : str
        Where it came from (a path), named first in every error message.

    Raises
    ------
    ProfileError
        Any missing key or invalid value. The message names ``source``, then each problem as the
        key's path and what is wrong with it, e.g. ``f.json: input.axes[1].endian: Input should be
        'little' or 'big', got 'middle'`` (several problems are joined with ``; ``).
    """
    try:
        model = HidProfileModel.model_validate(data)
    except ValidationError as exc:
        problems = "; ".join(_problem(err) for err in exc.errors(include_url=False))
        raise ProfileError(f"{source}: {problems}") from None
    lim = model.limits
    lo, hi = _box(*lim.workspace_size_m)
    try:
        limits = DeviceLimits(
            max_force_n=lim.max_force_n,
            max_stiffness_n_per_m=lim.max_stiffness_n_per_m,
            max_velocity_m_s=lim.max_velocity_m_s,
            damping_n_s_per_m=lim.damping_n_s_per_m,
            max_damping_n_s_per_m=lim.max_damping_n_s_per_m,
            workspace_min_m=(lo[0], lo[1], lo[2]),
            workspace_max_m=(hi[0], hi[1], hi[2]),
            has_force_output=model.output is not None,
        )
    except ValueError as exc:
        raise ProfileError(f"{source}: limits: {exc}") from None
    return HidProfile(
        name=model.name,
        vendor_id=model.vendor_id,
        product_id=model.product_id,
        input=model.input,
        output=model.output,
        limits=limits,
        silence_timeout_s=model.silence_timeout_s,
        description=model.description,
    )


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
