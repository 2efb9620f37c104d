"""Local geometric models: the plane and the sphere a user's local model is rendered against.

Paper, section 6, Step 1: "the local model is calculated inside the slow simulation loop using the
current surface configuration of the deformable object, as if it was static ... we employ simple
geometric primitives, such as planes and spheres" (after Adachi et al. 1995 and Balaniuk 1999).

The server fits a primitive to the current global surface near each user's probe once per
simulation tick; the client renders it at the servo rate. Everything here is plain Python floats so
that a servo tick (read, compute, write) costs microseconds and allocates almost nothing.

Conventions (SI units):
- ``normal`` is the *outward* unit normal of the object surface.
- penetration ``e`` [m] is the depth of the probe past the surface along the inward normal: positive
  inside the object, negative outside. It is the paper's e = x_h - x_o measured along the normal.
- the proxy [m] is the point of the surface the probe is held against (the paper's x_o).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar, Literal

from haptic_collab.shared.types import Vec3 as Vec3

#: Below this radius [m] a sphere primitive is refused; above ``MAX_RADIUS_M`` a plane is used.
MIN_RADIUS_M = 1e-4
MAX_RADIUS_M = 1e3


def vec3(name: str, value: Sequence[float]) -> Vec3:
    """Validate a 3-vector of finite floats; ``name`` is used in the error message.

    Raises
    ------
    ValueError
        If ``value`` does not have 3 finite entries.
    """
    try:
        x, y, z = (float(v) for v in value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be 3 numbers, got {value!r}") from exc
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return (x, y, z)


def unit_vec3(name: str, value: Sequence[float]) -> Vec3:
    """Validate and normalize a direction (3,).

    Raises
    ------
    ValueError
        Not 3 finite entries, or shorter than 1e-9.
    """
    x, y, z = vec3(name, value)
    length = math.sqrt(x * x + y * y + z * z)
    if length < 1e-9:
        raise ValueError(f"{name} must be a non-zero vector, got {value!r}")
    return (x / length, y / length, z / length)


@dataclass(frozen=True, slots=True)
class Plane:
    """A plane tangent to the surface: ``point`` [m] on it, unit outward ``normal``.

    Build with :func:`make_plane`, which validates and normalizes.
    """

    point: Vec3
    normal: Vec3
    kind: ClassVar[Literal["plane"]] = "plane"

    def penetration(self, x: float, y: float, z: float) -> float:
        """Depth [m] of probe (x, y, z) [m] past the plane along the inward normal."""
        p, n = self.point, self.normal
        return (p[0] - x) * n[0] + (p[1] - y) * n[1] + (p[2] - z) * n[2]

    def contact(self, x: float, y: float, z: float) -> tuple[float, float, float, float]:
        """Penetration [m] and outward unit normal at the probe, in one call: ``(e, nx, ny, nz)``."""
        n = self.normal
        return (self.penetration(x, y, z), n[0], n[1], n[2])

    def proxy(self, x: float, y: float, z: float) -> Vec3:
        """Closest point [m] of the plane to the probe (x, y, z) [m]."""
        e = self.penetration(x, y, z)
        n = self.normal
        return (x + e * n[0], y + e * n[1], z + e * n[2])


@dataclass(frozen=True, slots=True)
class Sphere:
    """A convex sphere fitted to the local curvature: ``center`` [m], ``radius`` [m].

    Build with :func:`make_sphere`, which validates.
    """

    center: Vec3
    radius: float
    kind: ClassVar[Literal["sphere"]] = "sphere"

    def _offset(self, x: float, y: float, z: float) -> tuple[float, float, float, float]:
        c = self.center
        dx, dy, dz = x - c[0], y - c[1], z - c[2]
        d = math.sqrt(dx * dx + dy * dy + dz * dz)
        if d < 1e-12:  # probe at the centre: any direction is as good; take +z
            return (0.0, 0.0, 1.0, 0.0)
        return (dx / d, dy / d, dz / d, d)

    def penetration(self, x: float, y: float, z: float) -> float:
        """Depth [m] of probe (x, y, z) [m] inside the sphere (negative outside)."""
        return self.radius - self._offset(x, y, z)[3]

    def contact(self, x: float, y: float, z: float) -> tuple[float, float, float, float]:
        """Penetration [m] and outward unit normal at the probe: ``(e, nx, ny, nz)``."""
        nx, ny, nz, d = self._offset(x, y, z)
        return (self.radius - d, nx, ny, nz)

    def proxy(self, x: float, y: float, z: float) -> Vec3:
        """Closest point [m] of the sphere surface to the probe (x, y, z) [m]."""
        nx, ny, nz, _ = self._offset(x, y, z)
        c, r = self.center, self.radius
        return (c[0] + r * nx, c[1] + r * ny, c[2] + r * nz)


Primitive = Plane | Sphere


def moved_out(primitive: Primitive, distance_m: float) -> Primitive:
    """``primitive`` moved out along its outward normals by ``distance_m`` [m] (negative: in): a
    plane shifted along its normal, a sphere grown or shrunk (within [:data:`MIN_RADIUS_M`,
    :data:`MAX_RADIUS_M`]). The local model's own-force compensation renders against it
    (:mod:`shared.full_loop`).

    Raises
    ------
    ValueError
        ``distance_m`` not finite.
    """
    d = float(distance_m)
    if not math.isfinite(d):
        raise ValueError(f"distance_m must be finite, got {distance_m!r}")
    if d == 0.0:
        return primitive
    if isinstance(primitive, Plane):
        p, n = primitive.point, primitive.normal
        return Plane(point=(p[0] + d * n[0], p[1] + d * n[1], p[2] + d * n[2]), normal=n)
    r = min(max(primitive.radius + d, MIN_RADIUS_M), MAX_RADIUS_M)
    return Sphere(center=primitive.center, radius=r)


def make_plane(point: Sequence[float], normal: Sequence[float]) -> Plane:
    """Validated plane through ``point`` (3,) [m] with outward ``normal`` (3,) (normalized here).

    Raises
    ------
    ValueError
        Non-finite entries, or a normal shorter than 1e-9.
    """
    return Plane(point=vec3("plane point", point), normal=unit_vec3("plane normal", normal))


def make_sphere(center: Sequence[float], radius: float) -> Sphere:
    """Validated convex sphere, ``center`` (3,) [m], ``radius`` [m].

    Raises
    ------
    ValueError
        Non-finite centre, or a radius outside [MIN_RADIUS_M, MAX_RADIUS_M].
    """
    c = vec3("sphere center", center)
    r = float(radius)
    if not (math.isfinite(r) and MIN_RADIUS_M <= r <= MAX_RADIUS_M):
        raise ValueError(
            f"sphere radius must be in [{MIN_RADIUS_M}, {MAX_RADIUS_M}] m, got {radius!r}"
        )
    return Sphere(center=c, radius=r)
