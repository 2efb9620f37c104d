"""Haptic devices: the :class:`Device` interface, simulated devices and HID devices.

:func:`make_device` builds a device from a short spec string (the ``--device`` option):

==================  ============================================================================
``sim:press``       simulated device whose hand presses on ``anchor`` (:class:`Press`)
``sim:rest``        simulated device whose hand rests lightly on ``anchor`` (:class:`Rest`)
``sim:replay:FILE`` simulated device whose hand replays a CSV ``t_s,x_m,y_m,z_m`` (:class:`Replay`)
``hid:VID:PID``     a real HID device (hex ids): a SpaceMouse, or a device with a JSON profile
==================  ============================================================================

hidapi is only imported when a HID device is opened or listed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from client.devices.base import Device, DeviceLimits, HapticError, Vec3
from client.devices.profiles import (
    SIM_PROFILES,
    HidProfile,
    get_sim_profile,
    load_hid_profile,
    sim_profile_names,
)
from client.devices.sim import HandParams, SimDevice
from client.devices.trajectories import (
    Press,
    Replay,
    ReplayError,
    Rest,
    hand_depth_for,
)
from shared.primitives import unit_vec3, vec3

__all__ = [
    "Device",
    "DeviceLimits",
    "HAND_OPTIONS",
    "HandParams",
    "HapticError",
    "Press",
    "Replay",
    "ReplayError",
    "Rest",
    "SIM_PROFILES",
    "SimDevice",
    "Vec3",
    "hand_depth_for",
    "hand_with_options",
    "list_devices",
    "make_device",
    "parse_hid_ids",
]

#: Distance [m] outside the anchor of a HID device's workspace centre.
HID_STANDOFF_M = 0.02


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


#: ``trajectory_options`` keys that set the simulated hand's own values (:class:`HandParams`
#: field each one sets); the device's mass and damping are added by :class:`SimDevice`.
HAND_OPTIONS: dict[str, str] = {
    "hand_mass_kg": "mass_kg",
    "hand_stiffness_n_per_m": "stiffness_n_per_m",
    "hand_damping_n_s_per_m": "damping_n_s_per_m",
}


def hand_with_options(hand: HandParams | None, options: dict[str, float]) -> HandParams | None:
    """Take the :data:`HAND_OPTIONS` keys out of ``options`` and apply them to ``hand``.

    Parameters
    ----------
    hand : HandParams or None
        The hand to start from (None: the default :class:`HandParams`).
    options : dict
        Trajectory options; the hand keys are removed from it (in place).

    Returns
    -------
    HandParams or None
        ``hand`` unchanged when ``options`` holds no hand key, else a new HandParams.

    Raises
    ------
    ValueError
        A hand value out of range (see :class:`HandParams`).
    """
    values = {HAND_OPTIONS[k]: float(options.pop(k)) for k in list(options) if k in HAND_OPTIONS}
    if not values:
        return hand
    return replace(hand if hand is not None else HandParams(), **values)


def make_device(
    spec: str,
    anchor: Sequence[float],
    normal: Sequence[float],
    profile: str = "phantom-desktop",
    *,
    hand: HandParams | None = None,
    trajectory_options: Mapping[str, float] | None = None,
    servo_rate_hz: float = 1000.0,
    hid_profile: str | Path | HidProfile | None = None,
) -> Device:
    """Build a device (not opened) from a spec string.

    Parameters
    ----------
    spec : str
        ``sim:press``, ``sim:rest``, ``sim:replay:FILE`` or ``hid:VID:PID`` (hex).
    anchor : (3,) float
        Surface point [m] of the object the user works on. Scripted hands press/rest on it; the
        simulated workspace is centred on it; a HID device's workspace is centred
        ``HID_STANDOFF_M`` outside it.
    normal : (3,) float
        Outward surface normal at ``anchor`` (normalized here).
    profile : str
        Simulated device profile (:func:`sim_profile_names`: ``phantom-desktop``, ``touch``).
    hand : HandParams, optional
        The simulated hand (default 300 N/m, 5 N*s/m, 0.45 kg).
    trajectory_options : mapping, optional
        Overrides of the scripted trajectory's keyword arguments, e.g. ``{"delay_s": 2.0,
        "depth_m": 0.025}`` (see :class:`Press` and :class:`Rest` for names and defaults).
        The keys of :data:`HAND_OPTIONS` (``hand_mass_kg``, ``hand_stiffness_n_per_m``,
        ``hand_damping_n_s_per_m``) override the hand's own values instead (``haptic client
        --hand-mass/--hand-stiffness/--hand-damping``), for any ``sim:`` device.
    servo_rate_hz : float
        Servo rate [Hz] the simulation sub-steps against (default 1000).
    hid_profile : str, Path or HidProfile, optional
        Generic HID profile (bundled name, file, or loaded) for a non-SpaceMouse device.

    Returns
    -------
    Device

    Raises
    ------
    ValueError
        Malformed spec, unknown profile, bad trajectory option, bad anchor or normal, or a HID
        device with neither SpaceMouse ids nor a profile.
    ReplayError
        The replay file is missing or malformed (a ValueError).
    """
    a = vec3("anchor", anchor)
    n = unit_vec3("normal", normal)
    kind, _, rest = spec.partition(":")
    if kind == "sim":
        prof = get_sim_profile(profile)
        opts = dict(trajectory_options or {})
        hand = hand_with_options(hand, opts)
        what, _, arg = rest.partition(":")
        traj: Press | Rest | Replay
        try:
            if what == "press" and not arg:
                traj = Press(a, n, **opts)
            elif what == "rest" and not arg:
                traj = Rest(a, n, **opts)
            elif what == "replay" and arg:
                if opts:
                    raise ValueError("sim:replay takes no trajectory options")
                traj = Replay.from_csv(arg)
            else:
                raise ValueError(
                    f"unknown simulated device {spec!r}; use sim:press, sim:rest or sim:replay:FILE"
                )
        except TypeError as exc:
            raise ValueError(f"bad trajectory option for {spec!r}: {exc}") from None
        center = a if not isinstance(traj, Replay) else traj(0.0)
        return SimDevice(
            prof,
            traj,
            hand,
            limits=prof.limits.centered_at(center),
            servo_period_s=1.0 / servo_rate_hz,
        )
    if kind == "hid":
        from client.devices.hid import open_hid_device

        vid, pid = parse_hid_ids(rest)
        hp: HidProfile | None
        if hid_profile is None or isinstance(hid_profile, HidProfile):
            hp = hid_profile
        else:
            hp = load_hid_profile(hid_profile)
        center = (
            a[0] + HID_STANDOFF_M * n[0],
            a[1] + HID_STANDOFF_M * n[1],
            a[2] + HID_STANDOFF_M * n[2],
        )
        return open_hid_device(vid, pid, center, profile=hp)
    raise ValueError(
        f"unknown device spec {spec!r}; use sim:press, sim:rest, sim:replay:FILE or hid:VID:PID"
    )


def list_devices() -> list[dict[str, Any]]:
    """Every device one could use now: attached HID devices, then the simulated profiles.

    Returns
    -------
    list of dict
        HID entries as :func:`client.devices.hid.list_devices` (``kind`` spacemouse,
        profile:NAME or unsupported), then one entry per simulated profile with ``kind`` ``sim``,
        ``spec`` ``sim:press``, ``profile``, ``max_force_n`` and ``max_stiffness_n_per_m``. The
        bundled generic HID profile files are listed by
        :func:`client.devices.profiles.hid_profile_names`.
    """
    from client.devices.hid import list_devices as list_hid

    out = list_hid()
    for name in sim_profile_names():
        lim = SIM_PROFILES[name].limits
        out.append(
            {
                "kind": "sim",
                "spec": "sim:press",
                "profile": name,
                "max_force_n": lim.max_force_n,
                "max_stiffness_n_per_m": lim.max_stiffness_n_per_m,
            }
        )
    return out
