"""Scripted and recorded hand trajectories for the simulated device (DESIGN section 7).

A trajectory is a pure function of time: ``traj(t_s) -> (x, y, z)`` [m], the point the simulated
hand pulls the device handle toward (the hand is a spring-damper, see :mod:`client.devices.sim`).
Scripted trajectories are written relative to an *anchor* point on the object's surface and the
object's *outward* unit normal there, so the same script works for any object and any contact
side. Motions between way-points follow the minimum-jerk profile
``s(u) = 10 u^3 - 15 u^4 + 6 u^5`` (zero velocity and acceleration at both ends), so the hand never
jerks the device.

- :class:`Press`: wait ``delay_s`` at ``standoff_m`` outside the anchor, approach the anchor in
  ``approach_s``, push the hand target ``depth_m`` inside in ``press_s``, hold ``hold_s``, withdraw
  back to the start in ``release_s``, then stay there.
- :class:`Rest`: wait ``delay_s`` at ``standoff_m`` outside, move in ``approach_s`` to a hand target
  ``depth_m`` inside (a light touch on the side), hold for ever.
- :class:`Sweep`: palpation over a curved surface: wait outside the middle of the slide, move
  outside its start point, approach it, press the hand target ``depth_m`` in, hold, slide at
  that depth along the great circle of a sphere (centre and radius) to the end point and back,
  withdraw.
- :class:`Replay`: linear interpolation of a recorded CSV of hand positions (``t_s,x_m,y_m,z_m``),
  holding the first sample before it and the last after it.

How deep the *probe* goes for a given hand-target depth depends on the stiffness it meets: in
steady state the hand spring k_hand and the contact (object in series with the local model)
stiffness k_c share the depth, e_probe = depth * k_hand / (k_hand + k_c).
:func:`hand_depth_for` inverts this.
"""

from __future__ import annotations

import bisect
import csv
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from itertools import accumulate
from pathlib import Path

from haptic_collab.shared.checks import nonneg as _nonneg
from haptic_collab.shared.primitives import unit_vec3, vec3
from haptic_collab.shared.types import Vec3

#: Required CSV columns of a replay file.
REPLAY_COLUMNS = ("t_s", "x_m", "y_m", "z_m")


def min_jerk(u: float) -> float:
    """Minimum-jerk blend s(u) = 10u^3 - 15u^4 + 6u^5 for u clipped to [0, 1]; s(0)=0, s(1)=1."""
    if u <= 0.0:
        return 0.0
    if u >= 1.0:
        return 1.0
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


def hand_depth_for(
    probe_depth_m: float,
    contact_stiffness_n_per_m: float,
    hand_stiffness_n_per_m: float = 300.0,
) -> float:
    """Hand-target depth [m] that settles the probe ``probe_depth_m`` [m] inside the surface.

    Steady state of the hand spring (k_hand) in series with the contact stiffness k_c:
    depth = e_probe * (1 + k_c / k_hand).

    Raises
    ------
    ValueError
        Negative or non-finite depth, or stiffnesses not > 0.
    """
    e = _nonneg("probe_depth_m", probe_depth_m)
    kc, kh = float(contact_stiffness_n_per_m), float(hand_stiffness_n_per_m)
    if not (math.isfinite(kc) and kc > 0 and math.isfinite(kh) and kh > 0):
        raise ValueError("stiffnesses must be finite and > 0 N/m")
    return e * (1.0 + kc / kh)


class _Waypoints:
    """Piecewise minimum-jerk path along the normal: offsets [m] (outward positive) at times [s]."""

    __slots__ = ("anchor", "normal", "times", "offsets")

    def __init__(self, anchor: Vec3, normal: Vec3, times: list[float], offsets: list[float]):
        self.anchor, self.normal, self.times, self.offsets = anchor, normal, times, offsets

    def at(self, t_s: float) -> Vec3:
        times, offs = self.times, self.offsets
        if t_s <= times[0]:
            d = offs[0]
        elif t_s >= times[-1]:
            d = offs[-1]
        else:
            i = bisect.bisect_right(times, t_s) - 1
            t0, t1 = times[i], times[i + 1]
            s = min_jerk((t_s - t0) / (t1 - t0)) if t1 > t0 else 1.0
            d = offs[i] + (offs[i + 1] - offs[i]) * s
        a, n = self.anchor, self.normal
        return (a[0] + d * n[0], a[1] + d * n[1], a[2] + d * n[2])


def _set_path(
    traj: Press | Rest,
    phases: tuple[str, ...],
    offsets: Callable[[float, float], list[float]],
) -> None:
    """Check a frozen :class:`Press` or :class:`Rest` and set its anchor, normal and path.

    The anchor must be 3 finite numbers [m], the normal non-zero (normalized here), ``standoff_m``,
    ``depth_m`` and the durations [s] named in ``phases`` (attributes of ``traj``, in order)
    finite and >= 0. The way-points are at the cumulative sums of those durations, at the offsets
    [m] along the outward normal ``offsets(standoff_m, depth_m)`` (one per phase).

    Raises
    ------
    ValueError
        A value that fails those checks (the first, in the order above).
    """
    a = vec3("anchor", traj.anchor)
    n = unit_vec3("normal", traj.normal)
    so, dp = _nonneg("standoff_m", traj.standoff_m), _nonneg("depth_m", traj.depth_m)
    times = list(accumulate(_nonneg(name, getattr(traj, name)) for name in phases))
    object.__setattr__(traj, "anchor", a)
    object.__setattr__(traj, "normal", n)
    object.__setattr__(traj, "_path", _Waypoints(a, n, times, offsets(so, dp)))


@dataclass(frozen=True)
class Press:
    """Approach, press in, hold, release and withdraw (the pressing user of the demo).

    Parameters
    ----------
    anchor : (3,) float
        Surface point [m] of the object to press on.
    normal : (3,) float
        Outward surface normal at ``anchor`` (normalized here).
    standoff_m : float
        Start and end distance [m] outside the anchor (default 0.03).
    depth_m : float
        Hand-target depth [m] inside the anchor at the bottom of the press (default 0.02: with the
        default 300 N/m hand against a ~300 N/m contact the probe goes in ~10 mm, see
        :func:`hand_depth_for`).
    delay_s, approach_s, press_s, hold_s, release_s : float
        Phase durations [s] (defaults 0.0, 1.0, 1.0, 2.0, 1.0: the press is over at 5 s).

    Raises
    ------
    ValueError
        Non-finite or negative values, or a zero normal.
    """

    anchor: Sequence[float]
    normal: Sequence[float]
    standoff_m: float = 0.03
    depth_m: float = 0.02
    delay_s: float = 0.0
    approach_s: float = 1.0
    press_s: float = 1.0
    hold_s: float = 2.0
    release_s: float = 1.0
    _path: _Waypoints = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        _set_path(
            self,
            ("delay_s", "approach_s", "press_s", "hold_s", "release_s"),
            lambda so, dp: [so, 0.0, -dp, -dp, so],
        )

    @property
    def duration_s(self) -> float:
        """Time [s] at which the hand is back at the start point."""
        return self._path.times[-1]

    def __call__(self, t_s: float) -> Vec3:
        """Hand target (x, y, z) [m] at time ``t_s`` [s]."""
        return self._path.at(t_s)


@dataclass(frozen=True)
class Rest:
    """Touch the object lightly and stay (the resting user who feels the other's push).

    Parameters
    ----------
    anchor : (3,) float
        Surface point [m] to rest on.
    normal : (3,) float
        Outward surface normal at ``anchor`` (normalized here).
    standoff_m : float
        Start distance [m] outside the anchor (default 0.03).
    depth_m : float
        Hand-target depth [m] inside the anchor while resting (default 0.002).
    delay_s, approach_s : float
        Wait before moving and duration of the approach [s] (defaults 0.0 and 1.0).

    Raises
    ------
    ValueError
        Non-finite or negative values, or a zero normal.
    """

    anchor: Sequence[float]
    normal: Sequence[float]
    standoff_m: float = 0.03
    depth_m: float = 0.002
    delay_s: float = 0.0
    approach_s: float = 1.0
    _path: _Waypoints = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        _set_path(self, ("delay_s", "approach_s"), lambda so, dp: [so, -dp])

    def __call__(self, t_s: float) -> Vec3:
        """Hand target (x, y, z) [m] at time ``t_s`` [s]."""
        return self._path.at(t_s)


@dataclass(frozen=True)
class Sweep:
    """Press in, then slide across the surface at that depth and back: a palpating hand.

    The surface is taken as a sphere (``centre``, ``radius_m``) along the slide, so the hand
    target stays ``depth_m`` inside it all the way (a straight chord would dig deeper in the
    middle: 6 mm on a 20 degree half-arc of a 0.1 m ball). The slide follows the great circle
    from ``start`` to ``end`` (unit directions from the centre), minimum-jerk in angle, then back.

    The hand waits outside the *middle* of the slide and moves outside its start point in the
    last ``move_s`` of ``delay_s``: a simulated device's workspace is centred on its first
    position (:class:`client.devices.sim.SimDevice`), and a Phantom Desktop's is 160 mm wide,
    less than an 80 degree slide on a 0.1 m ball with a 30 mm standoff at one end (measured
    2026-11-27: a sweep that started at one end stopped at the workspace's far wall).

    Parameters
    ----------
    centre : (3,) float
        The sphere's centre [m].
    radius_m : float
        Its radius [m] (> 0).
    start, end : (3,) float
        Directions from the centre to the slide's ends (normalized here; not opposite).
    standoff_m : float
        Distance [m] outside the start point at the beginning and the end (default 0.03).
    depth_m : float
        Hand-target depth [m] inside the surface while sliding (default 0.01).
    delay_s, approach_s, press_s, hold_s, sweep_s, release_s : float
        Phase durations [s]: wait (and move), approach the start point, press in, hold still,
        slide to the end (and as long back), withdraw (defaults 1, 1, 1.5, 2, 4, 1).
    move_s : float
        The last part of ``delay_s`` [s] in which the hand moves from outside the middle to
        outside the start point (default 1; at most ``delay_s``).

    Raises
    ------
    ValueError
        Non-finite or negative values, a radius not > 0, zero or opposite directions, a
        depth not less than the radius, or ``move_s`` longer than ``delay_s``.
    """

    centre: Sequence[float]
    radius_m: float
    start: Sequence[float]
    end: Sequence[float]
    standoff_m: float = 0.03
    depth_m: float = 0.01
    delay_s: float = 1.0
    approach_s: float = 1.0
    press_s: float = 1.5
    hold_s: float = 2.0
    sweep_s: float = 4.0
    release_s: float = 1.0
    move_s: float = 1.0
    _times: tuple[float, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        c = vec3("centre", self.centre)
        a, b = unit_vec3("start", self.start), unit_vec3("end", self.end)
        r = _nonneg("radius_m", self.radius_m)
        if r <= 0.0:
            raise ValueError(f"radius_m must be > 0, got {self.radius_m!r}")
        _nonneg("standoff_m", self.standoff_m)
        if not _nonneg("depth_m", self.depth_m) < r:
            raise ValueError(f"depth_m must be less than radius_m, got {self.depth_m!r}")
        cos = sum(x * y for x, y in zip(a, b, strict=True))
        if cos <= -1.0 + 1e-9:
            raise ValueError("start and end must not be opposite (the great circle is not one)")
        if _nonneg("move_s", self.move_s) > _nonneg("delay_s", self.delay_s):
            raise ValueError(f"move_s must be at most delay_s, got {self.move_s!r}")
        phases = ("delay_s", "approach_s", "press_s", "hold_s", "sweep_s", "sweep_s", "release_s")
        times = tuple(accumulate(_nonneg(name, getattr(self, name)) for name in phases))
        object.__setattr__(self, "centre", c)
        object.__setattr__(self, "start", a)
        object.__setattr__(self, "end", b)
        object.__setattr__(self, "_times", times)

    @property
    def duration_s(self) -> float:
        """Time [s] at which the hand is back outside the start point."""
        return self._times[-1]

    @property
    def slide_s(self) -> tuple[float, float]:
        """(start, end) [s] of the slide out and back."""
        return self._times[3], self._times[5]

    def direction(self, s: float) -> Vec3:
        """The unit direction a share ``s`` in [0, 1] of the way from ``start`` to ``end`` along
        the great circle (spherical linear interpolation)."""
        a, b = self.start, self.end
        cos = max(-1.0, min(1.0, sum(x * y for x, y in zip(a, b, strict=True))))
        angle = math.acos(cos)
        if angle < 1e-9:
            return (a[0], a[1], a[2])
        wa, wb = (
            math.sin((1.0 - s) * angle) / math.sin(angle),
            math.sin(s * angle) / math.sin(angle),
        )
        return (wa * a[0] + wb * b[0], wa * a[1] + wb * b[1], wa * a[2] + wb * b[2])

    def __call__(self, t_s: float) -> Vec3:
        """Hand target (x, y, z) [m] at time ``t_s`` [s]."""
        t0, t_contact, t_in, t_slide, t_end, t_back, t_out = self._times
        so, dp = self.standoff_m, self.depth_m

        def blend(t: float, ta: float, tb: float) -> float:
            return min_jerk((t - ta) / (tb - ta)) if tb > ta else float(t >= tb)

        if t_s < t0:  # outside the middle, then over to outside the start point
            s, off = 0.5 * (1.0 - blend(t_s, t0 - self.move_s, t0)), so
        elif t_s < t_slide:
            s = 0.0
            if t_s < t_contact:
                off = so + (0.0 - so) * blend(t_s, t0, t_contact)
            else:
                off = -dp * blend(t_s, t_contact, t_in)
        elif t_s < t_back:
            off = -dp
            s = blend(t_s, t_slide, t_end) if t_s < t_end else 1.0 - blend(t_s, t_end, t_back)
        else:
            s = 0.0
            off = -dp + (so + dp) * blend(t_s, t_back, t_out)
        d = self.direction(s)
        c, r = self.centre, self.radius_m + off
        return (c[0] + r * d[0], c[1] + r * d[1], c[2] + r * d[2])


class ReplayError(ValueError):
    """A replay CSV is missing, malformed, or has non-increasing times."""


@dataclass(frozen=True)
class Replay:
    """Hand positions replayed from samples, linearly interpolated.

    Parameters
    ----------
    times_s : (m,) float
        Sample times [s], strictly increasing, m >= 1.
    positions_m : (m, 3) float
        Hand positions [m] in the world frame.

    Raises
    ------
    ReplayError
        Empty, mismatched, non-finite or non-increasing samples.
    """

    times_s: tuple[float, ...]
    positions_m: tuple[Vec3, ...]

    def __post_init__(self) -> None:
        t = tuple(float(v) for v in self.times_s)
        p = tuple(self.positions_m)
        if not t or len(t) != len(p):
            raise ReplayError("replay needs at least one sample and as many times as positions")
        if not all(math.isfinite(v) for v in t):
            raise ReplayError("replay times must be finite")
        if any(b <= a for a, b in zip(t, t[1:], strict=False)):
            raise ReplayError("replay times must be strictly increasing")
        try:
            pos = tuple(vec3(f"position {i}", q) for i, q in enumerate(p))
        except ValueError as exc:
            raise ReplayError(str(exc)) from exc
        object.__setattr__(self, "times_s", t)
        object.__setattr__(self, "positions_m", pos)

    @classmethod
    def from_csv(cls, path: str | Path) -> Replay:
        """Read a CSV with a header containing ``t_s,x_m,y_m,z_m`` (other columns are ignored).

        Raises
        ------
        ReplayError
            Missing file, missing columns, a non-numeric or non-finite cell (with its line number),
            no data rows, or non-increasing times.
        """
        p = Path(path)
        try:
            fh = p.open(newline="", encoding="utf-8")
        except OSError as exc:
            raise ReplayError(f"cannot open replay file {str(p)!r}: {exc}") from exc
        with fh:
            reader = csv.reader(line for line in fh if not line.lstrip().startswith("#"))
            header = next(reader, None)
            if header is None:
                raise ReplayError(f"{p}: empty file, expected a header {','.join(REPLAY_COLUMNS)}")
            names = [h.strip() for h in header]
            missing = [c for c in REPLAY_COLUMNS if c not in names]
            if missing:
                raise ReplayError(
                    f"{p}: header {names} lacks column(s) {missing}; "
                    f"expected {','.join(REPLAY_COLUMNS)}"
                )
            idx = [names.index(c) for c in REPLAY_COLUMNS]
            times: list[float] = []
            positions: list[Vec3] = []
            for row in reader:
                if not row or all(not c.strip() for c in row):
                    continue
                line = reader.line_num
                try:
                    t, x, y, z = (float(row[i]) for i in idx)
                except (IndexError, ValueError):
                    raise ReplayError(
                        f"{p}, row {line}: expected numbers in {REPLAY_COLUMNS}, got {row}"
                    ) from None
                if not all(math.isfinite(v) for v in (t, x, y, z)):
                    raise ReplayError(f"{p}, row {line}: non-finite value in {row}")
                if times and t <= times[-1]:
                    raise ReplayError(f"{p}, row {line}: time {t} s is not after {times[-1]} s")
                times.append(t)
                positions.append((x, y, z))
        if not times:
            raise ReplayError(f"{p}: no data rows")
        return cls(tuple(times), tuple(positions))

    @property
    def duration_s(self) -> float:
        """Time [s] of the last sample."""
        return self.times_s[-1]

    def __call__(self, t_s: float) -> Vec3:
        """Hand target (x, y, z) [m] at ``t_s`` [s], interpolated; clamped to the recorded span."""
        ts, ps = self.times_s, self.positions_m
        if t_s <= ts[0]:
            return ps[0]
        if t_s >= ts[-1]:
            return ps[-1]
        i = bisect.bisect_right(ts, t_s) - 1
        u = (t_s - ts[i]) / (ts[i + 1] - ts[i])
        a, b = ps[i], ps[i + 1]
        return (a[0] + (b[0] - a[0]) * u, a[1] + (b[1] - a[1]) * u, a[2] + (b[2] - a[2]) * u)
