"""Force Dimension devices (omega, sigma, delta, lambda, and the Novint Falcon) through forcedimension-core.

``--device forcedimension`` opens the first device the Force Dimension SDK finds,
``forcedimension:ID`` the device of enumeration index ``ID`` (0, 1, ...; ``haptic devices`` lists
them), and ``,scale=S`` after either maps device metres to world metres (default 1), e.g.
``forcedimension:0,scale=2`` or ``forcedimension:scale=2`` (like the other vendor backends'
``,scale=S``; ``:`` also separates). docs/device-forcedimension.md is the user's guide.

The binding, ``forcedimension_core`` (PyPI ``forcedimension-core``, Python < 3.13), loads the SDK's
``libdrd`` when it is imported; it is imported only when this backend is used or listed
(:meth:`ForceDimensionBackend.available`), with what it prints on stderr kept quiet.

No vendor scheduler: the servo thread reads and writes the device directly, once per tick
(``dhdGetPosition``, ``dhdGetLinearVelocity``, ``dhdGetButtonMask`` in :meth:`read`,
``dhdSetForce`` in :meth:`write`). The SDK's units are already SI (m, m/s, N).

Frames. The SDK reports positions in the device's frame: x toward the user, y to the user's
right, z up (H3D's HAPI, src/ForceDimensionHapticsDevice.cpp, reads ``dhdGetPosition(&z, &x, &y)`` into
its x-right, y-up, z-toward-the-user frame; CHAI3D 3.3.0 passes the positions through unchanged,
adding only a per-model workspace offset, src/devices/CDeltaDevices.cpp:1299-1304). The client's
device convention is x right, y away from the user, z up (:class:`client.devices.hid_reports.SpaceMouseMapping`),
so world = centre + S * (y_d, -x_d, z_d) with S the workspace scale and (x_d, y_d, z_d) the
position plus the model's workspace offset; a world force (fx, fy, fz) is sent as (-fy, fx, fz),
unscaled. The workspace centre is placed :data:`HID_STANDOFF_M` outside the anchor, like a HID
device's.

Limits are CHAI3D's specification of the model ``dhdGetSystemType`` names (:data:`MODELS`), capped
by the SDK's software force limit (``dhdGetMaxForce``) when one is set, and expressed in the world
frame: forces unchanged, stiffness and damping divided by S, velocity and workspace multiplied by
S. No source states a continuous force for these devices (``max_continuous_force_n`` is None).
The model is known once the device is open: ``make_device`` (which does not touch the hardware)
builds it with :data:`DEFAULT_MODEL`'s limits, :meth:`ForceDimensionDevice.open` sets the real
ones; ``haptic client`` opens the device before the network, so its limits are the model's from
the start.

Faults. A failed open is an error before any network (``DeviceError``) or at
:meth:`ForceDimensionDevice.open` (``DeviceOpenError``). Once open, a negative return from
``dhdGetPosition``, ``dhdSetForce`` or ``dhdEnableForce`` (the device was unplugged, switched off
or stopped answering) sets :attr:`Device.fault` to the call and ``dhdErrorGetLastStr``, and the
force is set to zero once; the device then leaves the hardware alone until
:meth:`ForceDimensionDevice.reopen` opens it again. A failed ``dhdGetLinearVelocity`` is not a
fault (the SDK's velocity estimator times out when positions are sparse, and the servo loop does
not use it): the last velocity is kept and counted in ``velocity_errors``.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import io
import math
import re
import sys
from dataclasses import dataclass
from typing import Any

from haptic_collab.client.devices._vendor import PLACEHOLDER_CENTER, opened_by, workspace_scale
from haptic_collab.client.devices._vendor import standoff_center as workspace_center
from haptic_collab.client.devices.backends import (
    DeviceBackend,
    DeviceError,
    DeviceOpenError,
    DeviceOptions,
    one_line,
)
from haptic_collab.client.devices.base import Device, DeviceLimits, Vec3
from haptic_collab.shared.extras import install_hint

__all__ = [
    "BACKEND",
    "DEFAULT_MODEL",
    "MAX_PYTHON",
    "MAX_VELOCITY_M_S",
    "MODELS",
    "FdModel",
    "ForceDimensionBackend",
    "ForceDimensionDevice",
    "parse_args",
    "workspace_center",
    "world_limits",
]

#: The first Python version forcedimension-core 1.0 does not support (Requires-Python <3.13).
MAX_PYTHON = (3, 13)

#: Probe speed [m/s, device frame] above which the servo loop ramps forces down. No Force
#: Dimension or CHAI3D source states one; this is the project's choice for desktop devices.
MAX_VELOCITY_M_S = 1.0


_SPEC_HELP = (
    "use forcedimension (the first device), forcedimension:ID (device index 0, 1, ...; "
    "`haptic devices` lists them), optionally followed by ,scale=S (world metres per device "
    "metre), e.g. forcedimension:0,scale=2 or forcedimension:scale=2"
)

_INSTALL = install_hint("forcedimension")
_SDK = "install the Force Dimension SDK and set FDSDK to its folder"
_GUIDE = "(docs/device-forcedimension.md)"


@dataclass(frozen=True, slots=True)
class FdModel:
    """A device model's specification, device frame (CHAI3D's ``cHapticDeviceInfo``).

    Attributes
    ----------
    name : str
        Model name.
    max_force_n, max_stiffness_n_per_m, max_damping_n_s_per_m, workspace_radius_m : float
        CHAI3D's ``m_maxLinearForce``, ``m_maxLinearStiffness``, ``m_maxLinearDamping``,
        ``m_workspaceRadius``.
    offset_m : (3,) float
        CHAI3D's ``m_posWorkspaceOffset``: added to the SDK's position to centre the workspace.
    source : str
        Where the numbers come from.
    """

    name: str
    max_force_n: float
    max_stiffness_n_per_m: float
    max_damping_n_s_per_m: float
    workspace_radius_m: float
    offset_m: Vec3
    source: str


def _chai3d(lines: str) -> str:
    return f"chai3d 3.3.0 src/devices/CDeltaDevices.cpp:{lines}"


def _model(
    name: str, f: float, k: float, b: float, r: float, lines: str, offset: Vec3 = (0.0, 0.0, 0.0)
) -> FdModel:
    return FdModel(name, f, k, b, r, offset, _chai3d(lines))


# CHAI3D 3.3.0, src/devices/CDeltaDevices.cpp, cDeltaDevice::open(): the specification of each
# system type (force N, stiffness N/m, damping N*s/m, workspace radius m, workspace offset m).
# Keys are the SDK's system types (forcedimension_core.constants.DeviceType).
#: The device models by ``dhdGetSystemType`` value.
MODELS: dict[int, FdModel] = {
    63: _model("delta.3", 20.0, 5000.0, 30.0, 0.15, "778-793"),  # DELTA3
    33: _model("omega.3", 12.0, 5000.0, 30.0, 0.075, "810-825"),  # OMEGA3
    36: _model("omega.6 left", 12.0, 5000.0, 30.0, 0.075, "842-856"),  # OMEGA6_LEFT
    34: _model("omega.6 right", 12.0, 5000.0, 30.0, 0.075, "873-887"),  # OMEGA6_RIGHT
    37: _model("omega.7 left", 12.0, 5000.0, 30.0, 0.075, "904-918"),  # OMEGA7_LEFT
    35: _model("omega.7 right", 12.0, 5000.0, 30.0, 0.075, "936-950"),  # OMEGA7_RIGHT
    105: _model(  # SIGMA7_LEFT
        "sigma.7 left", 12.0, 4000.0, 30.0, 0.075, "969-993", (-0.01, -0.02, 0.0)
    ),
    104: _model(  # SIGMA7_RIGHT
        "sigma.7 right", 12.0, 4000.0, 30.0, 0.075, "1007-1031", (-0.01, 0.02, 0.0)
    ),
    109: _model("lambda.7 left", 12.0, 8000.0, 30.0, 0.1125, "1051-1065"),  # LAMBDA7_LEFT
    108: _model("lambda.7 right", 12.0, 8000.0, 30.0, 0.1125, "1096-1110"),  # LAMBDA7_RIGHT
    60: _model("Novint Falcon", 8.0, 3000.0, 20.0, 0.04, "1132-1146"),  # FALCON
}

#: Any other system type (sigma.3, lambda.3, controllers, custom): CHAI3D's default.
DEFAULT_MODEL = _model("Force Dimension device", 12.0, 5000.0, 30.0, 0.075, "747-759")


def world_limits(
    model: FdModel, scale: float, center: Vec3, sdk_max_force_n: float | None = None
) -> DeviceLimits:
    """The limits of ``model`` in the world frame, workspace centred on ``center``.

    Parameters
    ----------
    model : FdModel
        The device's specification (device frame).
    scale : float
        World metres per device metre (> 0).
    center : (3,) float
        Workspace centre [m], world frame.
    sdk_max_force_n : float, optional
        ``dhdGetMaxForce``: the SDK's software force limit [N]; None or <= 0: none set.

    Returns
    -------
    DeviceLimits
        Force as the model's (capped by the SDK's limit), stiffness and damping / ``scale``,
        velocity and workspace * ``scale``; the device's own damping is not stated (0).
    """
    f = model.max_force_n
    if sdk_max_force_n is not None and math.isfinite(sdk_max_force_n) and sdk_max_force_n > 0.0:
        f = min(f, sdk_max_force_n)
    r = model.workspace_radius_m
    return (
        DeviceLimits(
            max_force_n=f,
            max_stiffness_n_per_m=model.max_stiffness_n_per_m,
            max_velocity_m_s=MAX_VELOCITY_M_S,
            damping_n_s_per_m=0.0,
            workspace_min_m=(-r, -r, -r),
            workspace_max_m=(r, r, r),
            max_damping_n_s_per_m=model.max_damping_n_s_per_m,
            max_continuous_force_n=None,
        )
        .scaled(scale)
        .centered_at(center)
    )


def parse_args(args: str) -> tuple[int | None, float]:
    """``ARGS`` of ``forcedimension:ARGS`` as (device index or None for the first, scale).

    Raises
    ------
    DeviceError
        An unknown part, a bad index (0..127) or a bad scale (0 < S <= 100), as one line.
    """
    spec = f"forcedimension:{args}" if args else "forcedimension"
    index: int | None = None
    scale: float | None = None
    for part in re.split(r"[,:]", args) if args else []:
        key, eq, value = part.partition("=")
        key = key.strip()
        if eq and key == "scale" and scale is None:
            scale = workspace_scale(spec, value, _SPEC_HELP)
        elif not eq and key.isdigit() and index is None:
            index = int(key)
            if index > 127:
                raise DeviceError(f"bad device index in {spec!r} (0..127); {_SPEC_HELP}")
        else:
            raise DeviceError(
                f"unknown device spec {spec!r}: {part!r} is not understood; {_SPEC_HELP}"
            )
    return index, (1.0 if scale is None else scale)


# -- the binding, imported on first use ---------------------------------------------------------

_dhd: Any = None


class _BindingError(ImportError):
    """The binding did not import; ``said`` is what it printed on stderr (one line)."""

    def __init__(self, message: str, said: str) -> None:
        super().__init__(message)
        self.said = said


def _load_dhd() -> Any:
    """``forcedimension_core.dhd``, imported once (what it prints on stderr is kept quiet).

    Raises
    ------
    ImportError
        Not installed, or libdrd missing or too old (a ``_BindingError`` whose ``said`` is what
        the binding printed on stderr).
    """
    global _dhd
    if _dhd is None:
        noise = io.StringIO()
        try:
            with contextlib.redirect_stderr(noise):
                _dhd = importlib.import_module("forcedimension_core.dhd")
        except ImportError as exc:
            raise _BindingError(one_line(exc), one_line(noise.getvalue())) from exc
    return _dhd


def _installed() -> bool:
    try:
        return importlib.util.find_spec("forcedimension_core") is not None
    except (ImportError, ValueError):
        return True  # half imported by an earlier attempt: it is installed


def _missing() -> str | None:
    """None when the binding and libdrd load here; else one line: what is missing, what to do."""
    if sys.version_info[:2] >= MAX_PYTHON:
        v = sys.version_info
        return (
            "the forcedimension backend needs forcedimension-core, which supports Python < "
            f"{MAX_PYTHON[0]}.{MAX_PYTHON[1]} only (this is Python {v[0]}.{v[1]}): run the client "
            f"with Python 3.11 or 3.12, {_INSTALL}, then {_SDK} {_GUIDE}"
        )
    if not _installed():
        return (
            "the forcedimension backend needs forcedimension-core and the Force Dimension SDK: "
            f"{_INSTALL}, then {_SDK} {_GUIDE}"
        )
    try:
        _load_dhd()
    except _BindingError as exc:
        said = exc.said or str(exc)
        return (
            "the forcedimension backend cannot load libdrd, the Force Dimension SDK's library "
            f"(forcedimension-core says: {said}): {_SDK} (it looks for FDSDK/lib/release/"
            f"lin-<machine>-gcc/libdrd.so.*; SDK 3.16 or newer); {_INSTALL} installs the binding "
            f"{_GUIDE}"
        )
    except Exception as exc:  # a broken installation must not break `haptic devices`
        return (
            f"forcedimension-core failed to import ({one_line(exc) or type(exc).__name__}): "
            f"reinstall it with {_INSTALL} and check the Force Dimension SDK (FDSDK) {_GUIDE}"
        )
    return None


# -- the device ---------------------------------------------------------------------------------


class ForceDimensionDevice(Device):
    """One Force Dimension device (or Falcon) whose workspace centre sits at ``center`` [m].

    Parameters
    ----------
    index : int or None
        Enumeration index for ``dhdOpenID`` (None: ``dhdOpen``, the first device).
    scale : float
        World metres per device metre.
    center : (3,) float
        Workspace centre [m], world frame.

    Attributes
    ----------
    device_id : int or None
        The SDK's ID of the open device (what ``dhdOpen``/``dhdOpenID`` returned); None: closed.
    model : FdModel or None
        The model, once the device has been opened.
    limits : DeviceLimits
        World-frame limits. Before the first open (``make_device``, which does not touch the
        hardware) they are :data:`DEFAULT_MODEL`'s; :meth:`open` sets the model's.
    """

    has_buttons = True  # --engage default: the first button engages forces

    def __init__(self, index: int | None, scale: float = 1.0, center: Vec3 = PLACEHOLDER_CENTER):
        self.index = index
        self.scale = scale
        self.center: Vec3 = center
        self.spec = "forcedimension" if index is None else f"forcedimension:{index}"
        self.name = self.spec
        self.model: FdModel | None = None
        self.sdk_max_force_n: float | None = None
        self.limits = world_limits(DEFAULT_MODEL, scale, center)
        self.fault: str | None = None
        self.device_id: int | None = None
        self._opened = False
        self._enabled = False
        self._buttons = 0
        self._last: Vec3 = center
        self._velocity: Vec3 = (0.0, 0.0, 0.0)
        self._p = [0.0, 0.0, 0.0]
        self._v = [0.0, 0.0, 0.0]
        #: Ticks whose ``dhdGetLinearVelocity`` failed (the last velocity was kept).
        self.velocity_errors = 0

    # -- hardware session ------------------------------------------------------------------

    def _connect(self) -> tuple[int, FdModel, float | None]:
        """Open the device; its ID, model and software force limit. Raises OSError (one line)."""
        try:
            dhd = _load_dhd()
        except ImportError as exc:
            raise OSError(_missing() or one_line(exc)) from None
        dev_id = int(dhd.open() if self.index is None else dhd.openID(self.index))
        if dev_id < 0:
            raise OSError(
                f"{dhd.errorGetLastStr()}; check that it is plugged in, powered and initialised, "
                "that you may use it (udev rules) and that no other program holds it; "
                f"`haptic devices` lists the attached devices {_GUIDE}"
            )
        try:
            model = self._identify(dhd, dev_id)
            limit = float(dhd.getMaxForce(dev_id))
        except BaseException:
            with contextlib.suppress(Exception):
                dhd.close(dev_id)
            raise
        return dev_id, model, (limit if limit > 0.0 else None)

    @staticmethod
    def _identify(dhd: Any, dev_id: int) -> FdModel:
        """The model of the open device ``dev_id``. Raises OSError when the SDK cannot say."""
        try:
            system_type: int | None = int(dhd.getSystemType(dev_id))
        except ValueError:  # -1 (an error) or a type this binding does not name
            system_type = None
        if system_type is not None and system_type in MODELS:
            return MODELS[system_type]
        name = dhd.getSystemName(dev_id)
        if system_type is None and name is None:
            raise OSError(f"cannot read the device type: {dhd.errorGetLastStr()}")
        label = name if name else f"system type {system_type}"
        return FdModel(
            f"{DEFAULT_MODEL.name} ({label})",
            DEFAULT_MODEL.max_force_n,
            DEFAULT_MODEL.max_stiffness_n_per_m,
            DEFAULT_MODEL.max_damping_n_s_per_m,
            DEFAULT_MODEL.workspace_radius_m,
            DEFAULT_MODEL.offset_m,
            DEFAULT_MODEL.source,
        )

    def _adopt(self, dev_id: int, model: FdModel, limit: float | None) -> None:
        self.device_id = dev_id
        self.model = model
        self.sdk_max_force_n = limit
        self.name = f"{self.spec} ({model.name})"
        self._update_limits()

    def _update_limits(self) -> None:
        model = self.model if self.model is not None else DEFAULT_MODEL
        self.limits = world_limits(model, self.scale, self.center, self.sdk_max_force_n)

    def acquire(self) -> None:
        """Open the hardware now (before the network) and keep it; :meth:`close` releases it.

        Raises
        ------
        OSError
            It cannot be opened (one line).
        """
        if self.device_id is None:
            self._adopt(*self._connect())

    def move_to(self, center: Vec3) -> None:
        """Put the workspace centre at ``center`` [m] (world frame)."""
        self.center = center
        self._last = center
        self._update_limits()

    # -- Device ------------------------------------------------------------------------------

    def open(self) -> None:
        """Open the device (or take over the one :meth:`acquire` opened); forces disabled.

        Raises
        ------
        DeviceOpenError
            It cannot be opened: ``cannot open SPEC: why; what to do``.
        """
        if self.device_id is None:
            try:
                self.acquire()
            except OSError as exc:
                raise DeviceOpenError(f"cannot open {self.spec}: {one_line(exc)}") from None
        self._opened = True
        self._enabled = False
        self.fault = None

    def close(self) -> None:
        """Zero the force, disable it and close the device; safe twice and before open."""
        dev_id, self.device_id = self.device_id, None
        self._opened = False
        self._enabled = False
        if dev_id is None or _dhd is None:
            return
        for call in (
            lambda: _dhd.setForce((0.0, 0.0, 0.0), dev_id),
            lambda: _dhd.enableForce(False, dev_id),
            lambda: _dhd.close(dev_id),
        ):
            with contextlib.suppress(Exception):
                call()

    def _set_fault(self, call: str, why: str | None = None) -> None:
        """Record that ``call`` failed (``why``, default the SDK's last error) and try once to
        zero the force."""
        dhd, dev_id = _dhd, self.device_id
        if why is None:
            try:
                why = str(dhd.errorGetLastStr())
            except Exception as exc:
                why = one_line(exc) or type(exc).__name__
        self.fault = f"{self.name}: {call} failed ({why}); device unplugged or switched off?"
        if dev_id is not None:
            with contextlib.suppress(Exception):
                dhd.setForce((0.0, 0.0, 0.0), dev_id)

    def read(self, t_s: float) -> Vec3:
        """Handle position [m], world frame; never raises (a failed call sets :attr:`fault`)."""
        dev_id = self.device_id
        if dev_id is None or not self._opened or self.fault is not None:
            return self._last
        dhd, p, v = _dhd, self._p, self._v
        try:
            if dhd.getPosition(p, dev_id) < 0:
                self._set_fault("dhdGetPosition")
                return self._last
            if dhd.getLinearVelocity(v, dev_id) < 0:
                # the SDK's estimator can time out without being a fault: keep the last velocity
                self.velocity_errors += 1
            else:
                s = self.scale
                self._velocity = (s * v[1], -s * v[0], s * v[2])
            self._buttons = int(dhd.getButtonMask(dev_id))
        except Exception as exc:  # never raise from the servo thread
            self._set_fault("read", one_line(exc) or type(exc).__name__)
            return self._last
        o = self.model.offset_m if self.model is not None else (0.0, 0.0, 0.0)
        c, s = self.center, self.scale
        self._last = (
            c[0] + s * (p[1] + o[1]),
            c[1] - s * (p[0] + o[0]),
            c[2] + s * (p[2] + o[2]),
        )
        return self._last

    def write(self, fx: float, fy: float, fz: float) -> None:
        """Display the world force (fx, fy, fz) [N]; never raises (a failure sets :attr:`fault`).

        Ignored while forces are disabled and once faulted (the fault zeroed the force).
        """
        dev_id = self.device_id
        if dev_id is None or not self._enabled or self.fault is not None:
            return
        try:
            if _dhd.setForce((-fy, fx, fz), dev_id) < 0:
                self._set_fault("dhdSetForce")
        except Exception as exc:  # never raise from the servo thread
            self._set_fault("write", one_line(exc) or type(exc).__name__)

    def enable_forces(self) -> None:
        """Switch the device's force mode on (``dhdEnableForce``); a failure sets :attr:`fault`."""
        self._enabled = True
        dev_id = self.device_id
        if dev_id is None or self.fault is not None:
            return
        try:
            if _dhd.enableForce(True, dev_id) < 0:
                self._set_fault("dhdEnableForce")
        except Exception as exc:
            self._set_fault("dhdEnableForce", one_line(exc) or type(exc).__name__)

    def disable_forces(self) -> None:
        """Zero the force and switch the force mode off; writes are ignored until re-enabled."""
        was, self._enabled = self._enabled, False
        dev_id = self.device_id
        if dev_id is None or not was:
            return
        with contextlib.suppress(Exception):
            _dhd.setForce((0.0, 0.0, 0.0), dev_id)
        with contextlib.suppress(Exception):
            _dhd.enableForce(False, dev_id)

    def buttons(self) -> int:
        """``dhdGetButtonMask`` as of the last :meth:`read` (bit 0: the first button)."""
        return self._buttons

    @property
    def velocity_m_s(self) -> Vec3:
        """``dhdGetLinearVelocity`` [m/s] as of the last :meth:`read`, world frame (scaled)."""
        return self._velocity

    def reopen(self) -> bool:
        """Close the faulted device and open it again (it was unplugged and came back).

        Called from the network thread while :attr:`fault` is set (read and write then leave
        the hardware alone); the fault is cleared last. Forces are switched on again if they
        were enabled.

        Returns
        -------
        bool
            True when the device answers again; False when it was not faulted.

        Raises
        ------
        OSError
            The device cannot be opened yet, or another model answered.
        """
        if self.fault is None or not self._opened:
            return False
        old, self.device_id = self.device_id, None
        if old is not None:
            with contextlib.suppress(Exception):
                _dhd.close(old)
        dev_id, model, limit = self._connect()
        if self.model is not None and model != self.model:
            with contextlib.suppress(Exception):
                _dhd.close(dev_id)
            raise OSError(f"a {model.name} answered instead of the {self.model.name}")
        self.device_id = dev_id
        self.sdk_max_force_n = limit
        self._update_limits()
        if self._enabled and _dhd.enableForce(True, dev_id) < 0:
            why = _dhd.errorGetLastStr()
            self.device_id = None
            with contextlib.suppress(Exception):
                _dhd.close(dev_id)
            raise OSError(f"dhdEnableForce failed ({why})")
        self.fault = None
        return True


# -- the backend --------------------------------------------------------------------------------


class ForceDimensionBackend(DeviceBackend):
    """``forcedimension[:ID][,scale=S]``: a Force Dimension device or a Novint Falcon.

    :meth:`open` parses the spec and, with ``options.acquire``, opens the device (the device it
    returns holds it); :meth:`place` moves that device's workspace centre to just outside the
    anchor and returns it.
    """

    name = "forcedimension"
    description = (
        "a Force Dimension omega/sigma/delta/lambda or a Novint Falcon through the Force Dimension "
        "SDK (forcedimension-core): forcedimension or forcedimension:ID, optionally ,scale=S "
        "(e.g. forcedimension:0,scale=2)"
    )

    def available(self) -> str | None:
        return _missing()

    def detect(self) -> list[dict[str, Any]]:
        """One entry per device the SDK counts (``dhdGetDeviceCount``), by enumeration index."""
        dhd = _load_dhd()
        count = int(dhd.getDeviceCount())
        if count < 0:
            raise OSError(f"dhdGetDeviceCount failed: {dhd.errorGetLastStr()}")
        return [{"spec": f"forcedimension:{i}", "index": i} for i in range(count)]

    def open(self, args: str, options: DeviceOptions) -> Device:
        index, scale = parse_args(args)
        dev = ForceDimensionDevice(index, scale)
        if options.acquire:
            try:
                dev.acquire()
            except OSError as exc:
                raise DeviceError(f"cannot open {dev.spec}: {one_line(exc)}") from None
        return dev

    def place(self, device: Device, anchor: Vec3, normal: Vec3) -> Device:
        opened_by(self, device, ForceDimensionDevice).move_to(workspace_center(anchor, normal))
        return device


#: The backend (entry point ``forcedimension`` in pyproject.toml).
BACKEND = ForceDimensionBackend()
