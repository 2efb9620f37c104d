"""What a client's run is summarised as: the gains it rendered and how they changed, its round
trips, its first contact's wait for gains and its servo timing (``haptic client --summary``).

Pure functions of the session, the link's counters, the servo's status and the telemetry ring.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from haptic_collab.client.link import Link
from haptic_collab.client.recorder import TelemetryRecorder
from haptic_collab.client.servo import ServoStatus
from haptic_collab.client.session import ClientSession, rendered
from haptic_collab.shared.local_model_update import LocalModelUpdate

__all__ = ["ServoReport", "client_summary", "gain_changes"]


class ServoReport(Protocol):
    """What the summary reads of a servo loop (thread or process)."""

    @property
    def overruns(self) -> int:
        """Servo deadlines missed."""
        ...

    def status(self) -> ServoStatus:
        """The servo's status."""
        ...


def gain_changes(updates: list[LocalModelUpdate], limit: int = 200) -> list[dict[str, object]]:
    """The patches at which the rendered gains or their standing changed, first ``limit``.

    Each: the server ``tick``, K_h [N/m], integral gain [N/(m s)], own-force gain C_h [m/N],
    whether verified / a fallback, the loop delay [ticks], K_o_eff and K_o_stiff [N/m], and
    whether it rendered the rest plane (``rest``: felt as K_h itself, its force does not go
    through the simulation) and where the gains came from (``source``,
    :func:`shared.gains.choose.choose`): when a contact rendered what, and why, for reading a
    demo run's haptics after the fact.
    """
    out: list[dict[str, object]] = []
    last: tuple[object, ...] | None = None
    for u in updates:
        surface, choice = rendered(u)
        state = (
            round(u.k_h, 1),
            round(u.i_gain, 1),
            round(u.own_gain, 6),
            choice.verified,
            choice.fallback,
            choice.delay_ticks,
            u.rest_plane,
            choice.source,
        )
        if state == last:
            continue
        last = state
        out.append(
            {
                "tick": surface.tick,
                "k_h": state[0],
                "i_gain": state[1],
                "own_gain": state[2],
                "verified": choice.verified,
                "fallback": choice.fallback,
                "delay_ticks": choice.delay_ticks,
                "k_o": round(surface.k_o, 1),
                "k_o_eff": round(surface.k_o_eff, 1),
                "k_o_stiff": round(surface.k_o_stiff, 1),
                "rest": u.rest_plane,
                "source": choice.source,
            }
        )
        if len(out) >= limit:
            break
    return out


def client_summary(
    head: dict[str, Any],
    session: ClientSession,
    link: Link,
    servo: ServoReport | None,
    recorder: TelemetryRecorder,
    updates: list[LocalModelUpdate],
) -> dict[str, Any]:
    """The summary of a client's run (``haptic client --summary``; JSON-able).

    ``head`` (the user's name, device, profile and local model) comes first; then the link's
    joins and round trips, the gains rendered (first, last, every change: :func:`gain_changes`),
    the first contact's wait for gains, the servo's status and, from the telemetry ring, the
    servo rate [Hz], period percentiles [µs] and largest force [N].
    """
    rtt = np.asarray(session.rtt_all_ms, float)
    choices = [rendered(u)[1] for u in updates]
    out: dict[str, Any] = {
        **head,
        "joins": link.joins,
        "resumes": link.resumes,
        "user_ids": list(link.user_ids),
        "silent_drops": link.silent_drops,
        "patches": session.patches,
        "server_errors": [e.model_dump() for e in session.errors[-10:]],
        "rtt_ms_p50": float(np.percentile(rtt, 50)) if rtt.size else None,
        "rtt_ms_p99": float(np.percentile(rtt, 99)) if rtt.size else None,
        "rtt_ms_samples": [float(x) for x in rtt[-2000:]],
        "delay_ticks_last": choices[-1].delay_ticks if updates else None,
        # patches rendered with a verified plane (the own-response check, shared.gains.own_response),
        # and of those, with the plane of a stiffness it identified other than the K_o reported
        "plane_patches": session.plane_patches,
        "identified_plane_patches": session.identified_plane_patches,
        # patches rendered with their rest plane: the user alone in the room (shared.gains.rest_plane)
        "rest_plane_patches": session.rest_plane_patches,
        "spectral_radius_last": choices[-1].spectral_radius if updates else None,
        "gains_last": None
        if not updates
        else {
            "k_h": updates[-1].k_h,
            "i_gain": updates[-1].i_gain,
            "b_h": updates[-1].b_h,
            "proxy_hold": updates[-1].proxy_hold,
            "felt_stiffness_ratio_1hz": choices[-1].felt_stiffness_ratio_1hz,
        },
        "gain_designs": link.designs,
        "interim_checks": link.checks,
        # from a needed check's request to its verified gains: meanwhile the contact renders
        # conservative unverified gains (client.session)
        "interim_check_wait_ms": [round(w * 1e3, 1) for w in link.check_wait_s],
        "fallback_patches": sum(1 for c in choices if c.fallback),
        "gain_changes": gain_changes(updates),
        "unverified_patches": session.unverified_patches,
        "server_gain_patches": session.server_gain_patches,
        "held_patches": session.held_patches,
        "gains_source": session.gains_source,
        "first_patch_s": session.first_patch_s,
        "first_gains_s": session.first_update_s,
        "first_contact_wait_ms": None
        if session.first_patch_s is None or session.first_update_s is None
        else (session.first_update_s - session.first_patch_s) * 1e3,
        "first_gains": None
        if not updates
        else {
            "k_h": updates[0].k_h,
            "i_gain": updates[0].i_gain,
            "b_h": updates[0].b_h,
            "proxy_hold": updates[0].proxy_hold,
            "fallback": choices[0].fallback,
        },
    }
    if servo is not None:
        status = servo.status().as_dict()
        out["servo"] = status
        out["servo_overruns"] = servo.overruns
    if len(recorder):
        period = recorder.column("period_s")
        period = period[np.isfinite(period) & (period > 0)]
        force = recorder.column("force_n")
        out["servo_rate_hz"] = float(1.0 / np.nanmean(period)) if period.size else None
        out["period_us_p50"] = float(np.percentile(period, 50) * 1e6) if period.size else None
        out["period_us_p99"] = float(np.percentile(period, 99) * 1e6) if period.size else None
        out["max_force_n"] = float(np.nanmax(force)) if force.size else 0.0
    return out
