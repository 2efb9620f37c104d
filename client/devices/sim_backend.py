"""The built-in ``sim`` backend: a simulated device held by a simulated hand (``--device sim:...``).

:class:`SimBackend` (:data:`SIM_BACKEND`, the entry point ``sim``) builds a
:class:`~client.devices.sim.SimDevice` whose hand presses (``sim:press``), rests (``sim:rest``) or
replays a file (``sim:replay:FILE``, :func:`load_replay`), and :func:`hand_with_options` takes the
hand's own values out of the trajectory options (:data:`HAND_OPTIONS`).
"""

from __future__ import annotations

import weakref
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from haptic_collab.client.devices.backends import (
    PLACEHOLDER_ANCHOR,
    PLACEHOLDER_NORMAL,
    DeviceBackend,
    DeviceError,
    DeviceOptions,
)
from haptic_collab.client.devices.base import Device, Vec3
from haptic_collab.client.devices.profiles import SIM_PROFILES, get_sim_profile, sim_profile_names
from haptic_collab.client.devices.sim import HandParams, SimDevice
from haptic_collab.client.devices.trajectories import Press, Replay, ReplayError, Rest

__all__ = [
    "HAND_OPTIONS",
    "RECORD_PROBE_COLUMNS",
    "SIM_BACKEND",
    "SimBackend",
    "hand_with_options",
    "load_replay",
]

#: Probe columns of a ``haptic client --record`` file (:data:`client.recorder.COLUMNS`).
RECORD_PROBE_COLUMNS = ("t_s", "probe_x_m", "probe_y_m", "probe_z_m")


def load_replay(path: str | Path) -> Replay:
    """The hand trajectory of ``sim:replay:FILE``: a ``--record`` file or a ``t_s,x_m,y_m,z_m`` CSV.

    A ``haptic client --record`` CSV (header with ``t_s,probe_x_m,probe_y_m,probe_z_m``) replays
    its recorded probe path, with the time of its first row taken as t = 0 (the replaying
    device's first read); rows whose time does not increase are skipped. Any other CSV must hold
    ``t_s,x_m,y_m,z_m`` (:meth:`Replay.from_csv`, times used as they are). Positions are in the
    world frame [m].

    Parameters
    ----------
    path : str or Path
        The file.

    Returns
    -------
    Replay
        Linear interpolation of the samples, holding the first before and the last after.

    Raises
    ------
    ReplayError
        Missing file, missing columns, a non-numeric or non-finite cell, or no data rows.
    """
    p = Path(path)
    try:
        with p.open(encoding="utf-8") as fh:
            first = ""
            for line in fh:
                if line.strip() and not line.lstrip().startswith("#"):
                    first = line
                    break
    except OSError as exc:
        raise ReplayError(f"cannot open replay file {str(p)!r}: {exc}") from exc
    names = [h.strip() for h in first.strip().split(",")]
    if not all(c in names for c in RECORD_PROBE_COLUMNS):
        return Replay.from_csv(p)
    cols = [names.index(c) for c in RECORD_PROBE_COLUMNS]
    try:
        data = np.loadtxt(p, delimiter=",", skiprows=1, usecols=cols, ndmin=2, comments="#")
    except ValueError as exc:
        raise ReplayError(f"{p}: not a readable --record file: {exc}") from None
    if data.shape[0] == 0:
        raise ReplayError(f"{p}: no data rows")
    if not np.isfinite(data).all():
        bad = int(np.flatnonzero(~np.isfinite(data).all(axis=1))[0])
        raise ReplayError(f"{p}, data row {bad + 1}: non-finite value in {data[bad].tolist()}")
    t = data[:, 0]
    keep = np.ones(t.size, dtype=bool)
    keep[1:] = t[1:] > np.maximum.accumulate(t)[:-1]
    data = data[keep]
    times = tuple((data[:, 0] - data[0, 0]).tolist())
    positions = tuple(map(tuple, data[:, 1:4].tolist()))
    return Replay(times, positions)  # type: ignore[arg-type]


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


def _make_sim(args: str, options: DeviceOptions, a: Vec3, n: Vec3) -> SimDevice:
    """The simulated device ``sim:args`` around anchor ``a`` (outward normal ``n``)."""
    spec = f"sim:{args}" if args else "sim"
    prof = get_sim_profile(options.profile)
    opts = dict(options.trajectory_options)
    hand = hand_with_options(options.hand, opts)
    what, _, arg = args.partition(":")
    traj: Press | Rest | Replay
    try:
        if what == "press" and not arg:
            traj = Press(a, n, **opts)
        elif what == "rest" and not arg:
            traj = Rest(a, n, **opts)
        elif what == "replay" and arg:
            if opts:
                raise ValueError("sim:replay takes no trajectory options")
            traj = load_replay(arg)
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
        servo_period_s=1.0 / options.servo_rate_hz,
    )


class SimBackend(DeviceBackend):
    """``sim:press``, ``sim:rest``, ``sim:replay:FILE``: a simulated device and hand.

    :meth:`open` builds the device around a placeholder anchor (every option is checked, a replay
    file is read); :meth:`place` builds it again around the real anchor, except a replayed hand,
    which is in world coordinates already (the device :meth:`open` returned is used as it is).
    """

    name = "sim"
    description = (
        "a simulated device held by a simulated hand: sim:press, sim:rest or sim:replay:FILE "
        "(--profile NAME)"
    )

    def __init__(self) -> None:
        self._opened: weakref.WeakKeyDictionary[Device, tuple[str, DeviceOptions]] = (
            weakref.WeakKeyDictionary()
        )

    def detect(self) -> list[dict[str, Any]]:
        """One entry per simulated profile (``kind`` ``sim``, ``spec`` ``sim:press``, limits)."""
        out: list[dict[str, Any]] = []
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

    def open(self, args: str, options: DeviceOptions) -> Device:
        dev = _make_sim(args, options, PLACEHOLDER_ANCHOR, PLACEHOLDER_NORMAL)
        self._opened[dev] = (args, options)
        return dev

    def place(self, device: Device, anchor: Vec3, normal: Vec3) -> Device:
        if isinstance(getattr(device, "trajectory", None), Replay):
            return device  # a replayed hand is in world coordinates already
        plan = self._opened.get(device)
        if plan is None:
            raise DeviceError(f"{device.name} was not opened by the sim backend")
        return _make_sim(plan[0], plan[1], anchor, normal)


#: The built-in simulated backend (pyproject.toml registers it as the entry point ``sim``).
SIM_BACKEND = SimBackend()
