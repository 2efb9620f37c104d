"""The rest plane: what a user alone on the object renders where no verified plane does.

While a user is the only one in the room, the server knows where this user's contact would be
without this user's own push: the object's rest surface, the tangent plane at the contact's
material point (:meth:`server.world.World.tick`), and sends it with the patch (``rest_plane``). Rendered with the object's stiffness, ``F = K_h (x_rest - x) + B_h u`` with
``K_h = min(K_o, K_h,max)``, no integral and no own-force compensation, it is ``static-local``'s
plane of the fidelity benchmark (a local model of the object held at the client, as model-mediated
teleoperation's: Mitra and Niemeyer 2008): felt as a linear object is statically at every
frequency, and stable for any simulation rate and delay because its force does not go through the
simulation: a wall at the servo rate, passive when the device's own damping exceeds ``K_h T / 2 +
|B_h|`` (Colgate and Schenkel 1997; the device's maximum stiffness is its limit for that).

The probe damper B_h is the one of :data:`DAMPER_FRACTIONS` (of the device's damping) whose felt
impedance ``K_h + j w B_h`` is closest over :data:`DAMPER_BAND_HZ` (largest |ln| ratio) to the
object's own as the simulation renders it, ``K_o + B_o (1 - exp(-j w / f_s))`` (eq. 9, B_o the
object damping divided by the simulation period): more the more the object resists a fast push
(:func:`shared.full_loop.object_impedance`; K_o and B_o are all the patch says of the object).
Each is at least :data:`MIN_DAMPER_PER_STIFFNESS_PERIOD` ``K_h T`` (T the servo period), the
sampled spring's energy leak per unit of speed in Colgate and Schenkel's condition: on a spring
0.5 N*s/m at 1000 N/m, felt as ``|1 + j 2 pi 8 Hz B_h / K_h|`` = 1.0003 at 8 Hz. Without it the
light hand's and the lightly damped device's impacts bounced on the plane (hands outside the
design's box; the virtual damper is not a passivity guarantee, Colgate and Schenkel's condition
counts it against the device's damping, but a damped hand on a damped probe settles; measured
with the fidelity benchmark's 1-D simulator, docs/results/).

A press that crossed from the rest plane to the verified planes of a stiffening object and back
every cycle rang (7 Hz, 8 mm), so after a verified plane the rest plane waits :data:`HOLD_BACK_S`
without one in the contact (:class:`client.session.ClientSession`; docs/fidelity.md, "The rest
plane", for what the benchmark measured).

Pure functions: no clock, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from haptic_collab.shared.checks import nonneg, positive
from haptic_collab.shared.full_loop import object_impedance
from haptic_collab.shared.gains.policy import (
    DAMPER_BAND_HZ,
    DAMPER_FRACTIONS,
    MIN_DAMPER_PER_STIFFNESS_PERIOD,
)
from haptic_collab.shared.types import FloatArray


@dataclass(frozen=True, slots=True)
class RestPlaneGains:
    """The rest plane's gains (module docstring).

    Attributes
    ----------
    k_h : float
        Local model stiffness K_h [N/m], ``min(K_o, K_h,max)``.
    b_h : float
        Probe damper B_h [N*s/m], one of :data:`DAMPER_FRACTIONS` times ``B_h,max``, at least
        :data:`MIN_DAMPER_PER_STIFFNESS_PERIOD` ``K_h T`` (up to ``B_h,max``).
    felt_error : float
        Largest |ln| of the felt impedance over the object's over :data:`DAMPER_BAND_HZ` with that
        damper (0: felt as the object).
    """

    k_h: float
    b_h: float
    felt_error: float


def rest_plane_gains(
    k_o: float,
    b_o: float,
    sim_rate_hz: float,
    k_h_max: float,
    b_h_max: float,
    *,
    servo_period_s: float,
) -> RestPlaneGains:
    """The gains of the rest plane for an object of ``k_o`` and ``b_o`` (module docstring).

    Parameters
    ----------
    k_o : float
        Object stiffness at the contact [N/m], > 0 (the patch's K_o).
    b_o : float
        Object damping divided by the simulation period [N/m], >= 0 (eq. 9).
    sim_rate_hz : float
        Simulation rate 1/(N T) [Hz], > 0.
    k_h_max : float
        The device's maximum stiffness [N/m], > 0.
    b_h_max : float
        The largest probe damper the client renders [N*s/m], >= 0.
    servo_period_s : float
        The servo period T [s], > 0.

    Returns
    -------
    RestPlaneGains

    Raises
    ------
    ValueError
        A stiffness or rate not finite and > 0, a damping not finite and >= 0.
    """
    # the object's own values checked here, by name; the device's and the period where batched
    k_h, b_h, err = rest_plane_dampers(
        np.array([positive("k_o", k_o)]), np.array([nonneg("b_o", b_o)]),
        np.array([positive("sim_rate_hz", sim_rate_hz)]), k_h_max, b_h_max,
        servo_period_s=servo_period_s,
    )  # fmt: skip
    return RestPlaneGains(k_h=float(k_h[0]), b_h=float(b_h[0]), felt_error=float(err[0]))


def rest_plane_dampers(
    k_o: FloatArray,
    b_o: FloatArray,
    sim_rate_hz: FloatArray,
    k_h_max: float,
    b_h_max: float,
    *,
    servo_period_s: float,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`rest_plane_gains` over a batch: K_h [N/m], B_h [N*s/m] and the felt error for
    each of the objects ``k_o`` [N/m], ``b_o`` [N/m] at ``sim_rate_hz`` [Hz] (arrays of one
    shape, broadcast; the simulator of the fidelity benchmark renders each patch's rest plane with it, as the client
    does with :func:`rest_plane_gains`).

    Raises
    ------
    ValueError
        As :func:`rest_plane_gains`, for any element.
    """
    k, damping, rate = np.broadcast_arrays(
        *(np.asarray(v, dtype=float) for v in (k_o, b_o, sim_rate_hz))
    )
    if not (np.all(np.isfinite(k) & (k > 0.0)) and np.all(np.isfinite(rate) & (rate > 0.0))):
        raise ValueError("k_o and sim_rate_hz must be finite and > 0")
    if not np.all(np.isfinite(damping) & (damping >= 0.0)):
        raise ValueError("b_o must be finite and >= 0")
    k_h = np.minimum(k, positive("k_h_max", k_h_max))
    b_max = nonneg("b_h_max", b_h_max)
    least = np.minimum(
        MIN_DAMPER_PER_STIFFNESS_PERIOD * k_h * positive("servo_period_s", servo_period_s), b_max
    )
    w = 2.0 * np.pi * np.asarray(DAMPER_BAND_HZ)[(...,) + (None,) * k.ndim]
    obj = np.abs(object_impedance(w / (2.0 * np.pi), k, damping, 1.0 / rate))
    best_err = np.full(k.shape, np.inf)
    best_b = np.zeros(k.shape)
    for frac in DAMPER_FRACTIONS:
        b = np.maximum(frac * b_max, least)
        err = np.max(np.abs(np.log(np.abs(k_h + 1j * w * b) / obj)), axis=0)
        better = err < best_err - 1e-9
        best_err = np.where(better, err, best_err)
        best_b = np.where(better, b, best_b)
    return k_h, best_b, best_err
