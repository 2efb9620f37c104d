"""The server bounds every reported force by its own geometry (DESIGN section 7b).

A user reports the force its device rendered (Step 3 of the paper's algorithm) and the simulation
applies its opposite to the shared object, so a client that lies about its force could push
everyone's hands. The server knows what that user's local model *could* have rendered: the
primitives it sent in its last patches, the probe the user reports with the force (both from the
same servo tick), and the gains the user reports. The local model (eq. 12, ``shared.local_model``)
renders along the primitive's outward normal at the probe

    f = K_h * e + s,    0 <= s <= F_I    (anti-windup bound of the integral, F_I)

with e the penetration; the integral s is fed with the penetration (less a threshold), so it
grows by at most I * dt * e over dt, and with an integral a contact is kept while the probe stays
within s / K_o outside the surface (the recovery band). The server keeps its own upper bound s_max
of the integral and allows, along the normal n of the primitive the probe penetrates most,

    in contact (e > -(s_max / K_o + e_tol)):
        s_max <- min(F_I, s_max + min(I, c_I * K_o) * dt * max(e, 0))
        f_max  = min(K_h, c_K * K_o) * max(e + e_tol, 0) + s_max
    out of contact:
        s_max <- max(0, s_max - F_I * dt / release_s)        (the client ramps it down)
        f_max  = s_max

With own-force compensation (:mod:`shared.full_loop`) the client renders against the primitive
moved out by C_h F_s, F_s the force the server applied from this user for that patch (sent in the
patch as ``own_force_n``), so e above is the compensated penetration ``e + C_h' F_s`` with the
reported C_h believed up to ``C_h' = min(C_h, max(1 / K, 1 / K_o + c_C / K))``, ``K = min(K_h,
c_K K_o)`` (the product's C_h K_h = 1 always passes). At a fixed contact the surface sits F_s / K_o
in from where this user's own push found it, so the allowance grows with F_s at most by the
factor ``max(1 - K / K_o, c_C)`` < 1 per tick: however a client lies, its force stays within
``max(K_o, K / (1 - c_C)) (x_rest + e_tol)`` (plus the integral term), at most ``c_K K_o (x_rest +
e_tol) / (1 - c_C)``, x_rest its probe's depth past the surface as it was without its own push.

(the integral is fed with e - theta, and the threshold theta, 1 mm by default, absorbs the
penetration tolerance, so the integral bound grows with e alone: at the surface it does not grow),
where e is the largest penetration over the primitives of the last few patches (a client renders a
patch up to a simulation period or two late: that is the tolerance for latency), e_tol a
penetration tolerance (encoder quantization, the plane versus the true surface), c_K and c_I
factors that keep a client from claiming gains above what any stable design for that K_o would
choose (the designs in docs/gains-table.json have K_h / K_o <= 1 and I / K_o < 70 1/s; the
design never goes above K_h = 2 K_o), and F_I
the integral's anti-windup bound, the device's declared maximum force. A force is accepted
unchanged when it is within ``force_tol_n`` of that bound and within a cone of half-angle
``cone_deg`` around n; otherwise it is replaced by its normal component clipped to [0, f_max]
along n, and the clamp is reported with its reason.

Nothing here reads a clock or allocates beyond a few floats.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from haptic_collab.shared.primitives import Plane, Sphere
from haptic_collab.shared.types import Vec3

ClampReason = Literal["out_of_contact", "wrong_direction", "too_large"]


@dataclass(frozen=True)
class ForceBoundParams:
    """Tolerances of the force bound (SI units).

    Attributes
    ----------
    penetration_tol_m : float
        e_tol [m]: the penetration the server may underestimate (quantization, fitted plane).
    force_tol_n : float
        Force [N] a report may exceed the bound by, and the smallest force ever refused: below
        what one user feels of another through the object (coupling is 12-14 %, DESIGN section 5).
    stiffness_factor : float
        c_K: a reported K_h is believed up to c_K * K_o (stable designs stay below K_o).
    integral_factor_per_s : float
        c_I [1/s]: a reported I is believed up to c_I * K_o.
    compensation_factor : float
        c_C, < 1: a reported own-force compensation C_h is believed up to
        ``1 / K_o + c_C / min(K_h, c_K K_o)`` (module docstring).
    max_dt_s : float
        Longest interval [s] one update integrates over (after a silence the bound does not jump).
    cone_deg : float
        Half-angle [deg] of the cone around the normal a force must lie in (the normal turns
        between successive patches).
    release_s : float
        Out of contact the allowance falls linearly to zero over this [s] (the client's integral
        release ramp, 0.1 s, with margin).
    history_patches : int
        How many of the latest patches' primitives the probe is checked against (latency).
    """

    penetration_tol_m: float = 0.001
    force_tol_n: float = 0.5
    stiffness_factor: float = 2.0
    integral_factor_per_s: float = 100.0
    compensation_factor: float = 0.8
    max_dt_s: float = 0.25
    cone_deg: float = 30.0
    release_s: float = 0.25
    history_patches: int = 3


@dataclass(frozen=True)
class BoundedForce:
    """The force the server applies and why it differs from the report (if it does).

    Attributes
    ----------
    force_n : (3,) tuple of float
        Force [N] to apply (as reported when ``reason`` is None).
    limit_n : float
        f_max [N], the largest force the user's local model could render here.
    integral_bound_n : float
        s_max [N], the server's bound on the user's integral force (pass it to the next call).
    reason : str or None
        ``out_of_contact``, ``wrong_direction`` or ``too_large``; None when unchanged.
    excess_n : float
        How much the report exceeded the clamped force [N] (norm of the difference).
    """

    force_n: Vec3
    limit_n: float
    integral_bound_n: float = 0.0
    reason: ClampReason | None = None
    excess_n: float = 0.0


def bound_force(
    force_n: Sequence[float],
    probe_m: Sequence[float],
    contacts: Sequence[tuple[Plane | Sphere, float, float]],
    *,
    k_h: float,
    i_gain: float,
    own_gain: float = 0.0,
    integral_limit_n: float,
    integral_bound_n: float = 0.0,
    dt_s: float = 0.0,
    params: ForceBoundParams | None = None,
) -> BoundedForce:
    """Bound a reported force by what the user's local model could render (module docstring).

    Parameters
    ----------
    force_n : (3,) float
        Reported force on the user [N] (outward).
    probe_m : (3,) float
        Reported probe position [m], sampled in the same servo tick as the force.
    contacts : sequence of (primitive, k_o, own_force_n)
        Primitives of the user's latest patches with their K_o [N/m] and the force F_s [N] the
        server had applied from this user for each; empty before any patch.
    k_h : float
        Reported proportional gain K_h [N/m].
    own_gain : float
        Reported own-force compensation C_h [m/N] (0: none).
    i_gain : float
        Reported integral weight I [N/(m*s)]; 0 means no integral force.
    integral_limit_n : float
        F_I, the integral's anti-windup bound [N] (the device's declared maximum force).
    integral_bound_n : float
        s_max [N] from the previous call (0 for a new user).
    dt_s : float
        Time since the previous call [s].
    params : ForceBoundParams
        Tolerances.

    Returns
    -------
    BoundedForce
    """
    p = params or ForceBoundParams()
    fx, fy, fz = (float(c) for c in force_n)
    x, y, z = (float(c) for c in probe_m)
    e, n, k_o = -math.inf, (0.0, 0.0, 0.0), 0.0
    k_h_eff = max(k_h, 0.0)
    c_h = max(own_gain, 0.0) if math.isfinite(own_gain) else 0.0
    for prim, ko, f_s in contacts:
        ko = float(ko)
        ei, nx, ny, nz = prim.contact(x, y, z)
        if c_h > 0.0 and ko > 0.0:
            stiff = min(k_h_eff, p.stiffness_factor * ko)
            cap = (
                max(1.0 / stiff, 1.0 / ko + p.compensation_factor / stiff)
                if stiff > 0.0
                else 1.0 / ko
            )
            ei += min(c_h, cap) * max(float(f_s), 0.0)
        if ei > e:
            e, n = ei, (nx, ny, nz)
        k_o = max(k_o, ko)
    f_i = max(0.0, integral_limit_n)
    dt = min(max(dt_s, 0.0), p.max_dt_s)
    s_max = min(max(integral_bound_n, 0.0), f_i)
    touching = contacts and k_o > 0.0 and e > -(s_max / k_o + p.penetration_tol_m)
    if touching:
        depth = max(e + p.penetration_tol_m, 0.0)
        i_eff = min(max(i_gain, 0.0), p.integral_factor_per_s * k_o)
        s_max = min(f_i, s_max + i_eff * dt * max(e, 0.0))
        limit = min(max(k_h, 0.0), p.stiffness_factor * k_o) * depth + s_max
    else:  # out of contact: the integral is ramped down over release_s, not dropped
        s_max = max(0.0, s_max - f_i * dt / p.release_s) if p.release_s > 0.0 else 0.0
        limit = s_max
    f_norm = math.sqrt(fx * fx + fy * fy + fz * fz)
    f_n = fx * n[0] + fy * n[1] + fz * n[2]
    tx, ty, tz = fx - f_n * n[0], fy - f_n * n[1], fz - f_n * n[2]
    f_t = math.sqrt(tx * tx + ty * ty + tz * tz)
    tol = p.force_tol_n
    reason: ClampReason | None = None
    if f_norm <= tol:
        return BoundedForce((fx, fy, fz), limit, s_max)
    if f_n < -tol or f_t > tol + math.tan(math.radians(p.cone_deg)) * abs(f_n):
        reason = "wrong_direction"
    elif f_n > limit + tol:
        reason = "too_large" if touching else "out_of_contact"
    if reason is None:
        return BoundedForce((fx, fy, fz), limit, s_max)
    mag = min(max(f_n, 0.0), limit)
    out = (mag * n[0], mag * n[1], mag * n[2])
    excess = math.sqrt((fx - out[0]) ** 2 + (fy - out[1]) ** 2 + (fz - out[2]) ** 2)
    return BoundedForce(out, limit, s_max, reason, excess)
