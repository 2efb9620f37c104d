"""The integration threshold theta the client's PI local model renders with (paper eq. 17-18),
chosen for the device's encoder and servo period.

Pure functions and constants; no I/O.
"""

from __future__ import annotations

from typing import Literal

from haptic_collab.shared.local_model import ThresholdParams, encoder_speed_bound

__all__ = [
    "THETA_DIRECTION_FILTER_S",
    "THETA_ENCODER_MARGIN",
    "THETA_ENCODER_NOISE_COUNTS",
    "THETA_EXIT_SPEED_M_S",
    "threshold_for",
]

#: Filter time constant [s] on the probe's depth rate that decides eq. 18's branch: 20 ms, an
#: 8 Hz corner, above the 1-5 Hz of a hand deliberately leaving an object.
THETA_DIRECTION_FILTER_S = 0.02

#: Encoder counts the quantization noise of a still probe may span (a position between two
#: counts plus a little tremor); eq. 18's deadband is set 20 % above what that can make of the
#: filtered speed (:func:`shared.local_model.encoder_speed_bound`; the bound is reached only by
#: the worst pattern, a long plateau then a drop of all the counts in one tick).
THETA_ENCODER_NOISE_COUNTS = 3.0
THETA_ENCODER_MARGIN = 1.2

#: Slowest outward probe speed [m/s] taken as the user leaving (eq. 18's exiting branch), unless
#: the encoder needs more. Measured with the simulated hand and the hand box's extremes holding a
#: press on 300 and 1000 N/m objects and nudged: below about 7 mm/s the hand's own ringing after
#: a nudge reaches the exiting branch now and then (0.5-0.7 mm peak to peak with 5 mm/s); from
#: 7.5 mm/s on the hold stays below 0.5 mm for every hand tried. A deliberate exit is faster
#: (tens of mm/s).
THETA_EXIT_SPEED_M_S = 0.01


def threshold_for(
    mode: Literal["auto", "fixed", "variable"],
    local_model: Literal["p", "pi"],
    theta_m: float,
    encoder_resolution_m: float,
    servo_period_s: float = 1e-3,
) -> ThresholdParams:
    """The integration threshold theta (eq. 17 or 18) the client renders with.

    ``auto`` is eq. 18 (variable) for a PI local model and eq. 17 (fixed) otherwise (a P model
    has no integral: theta does nothing). Eq. 18: theta_1 = theta_m / 2 while pressing in or
    holding, up to theta_2 = 3 theta_m while leaving (reached at 1 N of integral force). The
    branch is a memoryless function of the probe's own speed along the normal (never the proxy's
    jumps), low-pass filtered over :data:`THETA_DIRECTION_FILTER_S`: leaving while the filtered
    outward speed exceeds the deadband ``max(1.2 R q / (T + tau), THETA_EXIT_SPEED_M_S)``, R =
    :data:`THETA_ENCODER_NOISE_COUNTS` counts of the device's encoder q [m] (quantization noise
    cannot reach it, :func:`shared.local_model.encoder_speed_bound`; 3.9 mm/s for a 23 um
    encoder, 9.4 mm/s for 55 um), and at least the speed of a deliberate exit.

    Parameters
    ----------
    mode : {"auto", "fixed", "variable"}
    local_model : {"p", "pi"}
    theta_m : float
        theta_bar [m] of eq. 17 (and the scale of eq. 18's thresholds), >= 0.
    encoder_resolution_m : float
        The device's position quantum [m], >= 0 (0: unknown or none).
    servo_period_s : float
        Servo period T [s].

    Raises
    ------
    ValueError
        Out-of-range values.
    """
    variable = mode == "variable" or (mode == "auto" and local_model == "pi")
    if not variable:
        return ThresholdParams(mode="fixed", theta_m=theta_m)
    tau = THETA_DIRECTION_FILTER_S
    noise = THETA_ENCODER_MARGIN * encoder_speed_bound(
        encoder_resolution_m, THETA_ENCODER_NOISE_COUNTS, tau, servo_period_s
    )
    return ThresholdParams(
        mode="variable",
        theta_m=theta_m,
        theta_1_m=0.5 * theta_m,
        theta_2_m=3.0 * theta_m,
        i_tot_bar_n=1.0,
        direction_deadband_m=THETA_ENCODER_NOISE_COUNTS * encoder_resolution_m,
        direction_deadband_m_s=max(noise, THETA_EXIT_SPEED_M_S),
        direction_filter_s=tau,
    )
