"""A Touch / Phantom's limits and its frames: pure values for the openhaptics backend, no libHD.

Units and frames. HD reports millimetres, mm/s and newtons in the device frame: x to the user's
right, y up, z toward the user. The world frame has z up (the object's up); the device's x stays
x, its y becomes z, and its z (toward the user) becomes -y (so the world's y points away from the
user, into the device): ``world = centre + S * R (p_device - c_device)``, where ``c_device`` is the
centre of the device's usable workspace and ``centre`` lies :data:`HID_STANDOFF_M` outside the
anchor along its normal, as for HID devices. Forces are rotated back with the same ``R`` (no
scale: a newton is a newton). The limits are reported in the world frame with the scale folded
in: stiffness and damping / S, velocity and workspace * S, forces unchanged, so the gains the
client designs for these limits render within the device's own.

Limits come from the SDK (``HD_NOMINAL_MAX_FORCE``, ``HD_NOMINAL_MAX_CONTINUOUS_FORCE``,
``HD_NOMINAL_MAX_STIFFNESS`` [N/mm], ``HD_NOMINAL_MAX_DAMPING`` [N/(mm/s)],
``HD_USABLE_WORKSPACE_DIMENSIONS`` [mm], ``HD_SOFTWARE_VELOCITY_LIMIT`` [mm/s]); a value the SDK
does not give (an HD error, 0, not finite, implausible) falls back to CHAI3D's table for the
model (:data:`CHAI3D_MODELS`).

:class:`client.devices.openhaptics.OpenHapticsDevice` reads the SDK's values into
:class:`HdLimits` (:meth:`HdLimits.from_sdk`) and maps each position, velocity and force with the
functions here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from haptic_collab.client.devices.base import DeviceLimits, Vec3

__all__ = [
    "CHAI3D_DEFAULT",
    "CHAI3D_MODELS",
    "DEFAULT_MAX_VELOCITY_M_S",
    "VELOCITY_MARGIN",
    "HdLimits",
    "ModelSpec",
    "chai3d_spec",
    "device_to_world",
    "device_vector_to_world",
    "world_force_to_device",
    "world_limits",
]

#: The servo loop ramps forces down at this fraction of the SDK's software velocity limit, before
#: the driver's own check stops the device with ``HD_EXCEEDED_MAX_VELOCITY``.
VELOCITY_MARGIN = 0.8
#: Velocity limit [m/s] when the SDK states none (the simulated ``touch`` profile's).
DEFAULT_MAX_VELOCITY_M_S = 0.5

# -- limits -------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ModelSpec:
    """A model's limits as CHAI3D declares them (SI units; ``workspace_radius_m`` of a cube)."""

    max_force_n: float
    max_stiffness_n_per_m: float
    max_damping_n_s_per_m: float
    workspace_radius_m: float


#: CHAI3D's limits per OpenHaptics model (substring of the model string, lower case), the fallback
#: for a value the SDK does not give. From CHAI3D 3.3.0, src/devices/CPhantomDevices.cpp,
#: cPhantomDevice::cPhantomDevice(): "Touch" lines 495-507, "PHANTOM Omni" 519-531,
#: "PHANTOM Desktop" 543-555, "PHANTOM Premium 1.5 6DOF" 567-579, "PHANTOM Premium 3.0 6DOF"
#: 591-603 (m_maxLinearForce, m_maxLinearStiffness, m_maxLinearDamping, m_workspaceRadius).
#: CHAI3D states no continuous force and no velocity limit. The first key found in the model string
#: wins (a "Touch X", which CHAI3D does not list, gets the Touch's smaller values).
CHAI3D_MODELS: tuple[tuple[str, ModelSpec], ...] = (
    ("touch", ModelSpec(3.3, 400.0, 4.0, 0.075)),
    ("omni", ModelSpec(3.3, 700.0, 5.0, 0.10)),
    ("desktop", ModelSpec(7.9, 1000.0, 5.0, 0.10)),
    ("premium 1.5", ModelSpec(8.5, 800.0, 5.0, 0.12)),
    ("premium 3.0", ModelSpec(22.0, 1000.0, 5.0, 0.25)),
)
#: CHAI3D's values for any other PHANTOM (same file, lines 436-448: the default specification).
CHAI3D_DEFAULT = ModelSpec(6.0, 1000.0, 8.0, 0.10)


def chai3d_spec(model: str) -> ModelSpec:
    """CHAI3D's limits for an OpenHaptics model string (:data:`CHAI3D_DEFAULT` if unknown)."""
    m = model.lower()
    for key, spec in CHAI3D_MODELS:
        if key in m:
            return spec
    return CHAI3D_DEFAULT


@dataclass(frozen=True, slots=True)
class HdLimits:
    """A device's limits in its own frame, SI units (metres, not the SDK's millimetres).

    ``sources`` says where each value came from: ``"sdk"`` or ``"chai3d"`` (the fallback) or
    ``"default"`` (:data:`DEFAULT_MAX_VELOCITY_M_S`).
    """

    model: str
    max_force_n: float
    max_continuous_force_n: float | None
    max_stiffness_n_per_m: float
    max_damping_n_s_per_m: float
    max_velocity_m_s: float
    workspace_min_m: Vec3
    workspace_max_m: Vec3
    sources: tuple[tuple[str, str], ...] = ()

    @property
    def center_m(self) -> Vec3:
        """Centre [m] of the usable workspace, device frame."""
        lo, hi = self.workspace_min_m, self.workspace_max_m
        return (0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), 0.5 * (lo[2] + hi[2]))

    @classmethod
    def fallback(cls, model: str) -> HdLimits:
        """CHAI3D's limits for ``model`` (the values a device has before the SDK is read)."""
        spec = chai3d_spec(model)
        r = spec.workspace_radius_m
        return cls(
            model=model,
            max_force_n=spec.max_force_n,
            max_continuous_force_n=None,
            max_stiffness_n_per_m=spec.max_stiffness_n_per_m,
            max_damping_n_s_per_m=spec.max_damping_n_s_per_m,
            max_velocity_m_s=DEFAULT_MAX_VELOCITY_M_S,
            workspace_min_m=(-r, -r, -r),
            workspace_max_m=(r, r, r),
            sources=(
                ("max_force_n", "chai3d"),
                ("max_continuous_force_n", "chai3d"),
                ("max_stiffness_n_per_m", "chai3d"),
                ("max_damping_n_s_per_m", "chai3d"),
                ("max_velocity_m_s", "default"),
                ("workspace", "chai3d"),
            ),
        )

    @classmethod
    def from_sdk(
        cls,
        model: str,
        *,
        max_force: float | None,
        max_continuous_force: float | None,
        max_stiffness_n_per_mm: float | None,
        max_damping_n_per_mm_s: float | None,
        velocity_limit_mm_s: float | None,
        usable_workspace_mm: Sequence[float] | None,
    ) -> HdLimits:
        """The limits from what the SDK returned (None: the query failed), in SI units; a value
        that is missing, zero, not finite or implausible falls back to :meth:`fallback`."""
        fb = cls.fallback(model)
        src: dict[str, str] = dict(fb.sources)

        def pick(name: str, value: float | None, factor: float, hi: float, default: float) -> float:
            if value is not None and math.isfinite(value) and 0.0 < value * factor <= hi:
                src[name] = "sdk"
                return value * factor
            return default

        f_max = pick("max_force_n", max_force, 1.0, 100.0, fb.max_force_n)
        k_max = pick(
            "max_stiffness_n_per_m", max_stiffness_n_per_mm, 1e3, 1e5, fb.max_stiffness_n_per_m
        )
        b_max = pick(
            "max_damping_n_s_per_m", max_damping_n_per_mm_s, 1e3, 1e3, fb.max_damping_n_s_per_m
        )
        v_lim = pick(
            "max_velocity_m_s",
            velocity_limit_mm_s,
            1e-3 * VELOCITY_MARGIN,
            10.0,
            fb.max_velocity_m_s,
        )
        cont: float | None = None
        c = max_continuous_force
        if c is not None and math.isfinite(c) and 0.0 < c <= f_max:
            cont = float(c)
            src["max_continuous_force_n"] = "sdk"
        lo, hi = fb.workspace_min_m, fb.workspace_max_m
        w = list(usable_workspace_mm) if usable_workspace_mm is not None else []
        if len(w) == 6 and all(math.isfinite(v) for v in w):
            wlo = (w[0] * 1e-3, w[1] * 1e-3, w[2] * 1e-3)
            whi = (w[3] * 1e-3, w[4] * 1e-3, w[5] * 1e-3)
            if all(0.005 < b - a < 2.0 for a, b in zip(wlo, whi, strict=True)):
                lo, hi = wlo, whi
                src["workspace"] = "sdk"
        return cls(
            model=model,
            max_force_n=f_max,
            max_continuous_force_n=cont,
            max_stiffness_n_per_m=k_max,
            max_damping_n_s_per_m=b_max,
            max_velocity_m_s=v_lim,
            workspace_min_m=lo,
            workspace_max_m=hi,
            sources=tuple(sorted(src.items())),
        )


# -- frames -------------------------------------------------------------------------------------------


def device_to_world(p: Sequence[float], center_w: Vec3, center_d: Vec3, scale: float) -> Vec3:
    """A device-frame point [m] in the world frame: ``center_w + scale * R (p - center_d)``.

    ``R`` maps the device's x (right), y (up), z (toward the user) to the world's x, z, -y.
    """
    dx, dy, dz = p[0] - center_d[0], p[1] - center_d[1], p[2] - center_d[2]
    return (center_w[0] + scale * dx, center_w[1] - scale * dz, center_w[2] + scale * dy)


def device_vector_to_world(v: Sequence[float], scale: float = 1.0) -> Vec3:
    """A device-frame vector in the world frame (``scale * R v``)."""
    return (scale * v[0], -scale * v[2], scale * v[1])


def world_force_to_device(f: Sequence[float]) -> Vec3:
    """A world-frame force [N] in the device frame (``R^T f``; forces are not scaled)."""
    return (f[0], f[2], -f[1])


def world_limits(hd: HdLimits, scale: float, center_w: Vec3) -> DeviceLimits:
    """The limits the servo loop sees: world frame, the workspace scale folded in.

    Stiffness and damping divide by ``scale`` (a world displacement of ``x`` is ``x / scale`` at
    the stylus), velocity and workspace multiply by it, forces are unchanged.
    """
    corners = [  # the rotated box at scale 1, centred on center_w; scaled below
        device_to_world((x, y, z), center_w, hd.center_m, 1.0)
        for x in (hd.workspace_min_m[0], hd.workspace_max_m[0])
        for y in (hd.workspace_min_m[1], hd.workspace_max_m[1])
        for z in (hd.workspace_min_m[2], hd.workspace_max_m[2])
    ]
    lo = (min(c[0] for c in corners), min(c[1] for c in corners), min(c[2] for c in corners))
    hi = (max(c[0] for c in corners), max(c[1] for c in corners), max(c[2] for c in corners))
    return DeviceLimits(
        max_force_n=hd.max_force_n,
        max_continuous_force_n=hd.max_continuous_force_n,
        max_stiffness_n_per_m=hd.max_stiffness_n_per_m,
        max_velocity_m_s=hd.max_velocity_m_s,
        damping_n_s_per_m=0.0,  # the device's own damping: OpenHaptics does not state it
        max_damping_n_s_per_m=hd.max_damping_n_s_per_m,
        workspace_min_m=lo,
        workspace_max_m=hi,
    ).scaled(scale)
