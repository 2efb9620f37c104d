"""The ``haptic demo`` report: what the users' telemetry and the server's status say about a run.

Timeline for a run of D seconds (D >= 12): B approaches at once and rests; A waits 0.2 D,
approaches (1 s), presses (1.5 s), holds until 0.75 D, releases (1 s) and withdraws
(:func:`timeline`).

The report's coupling (:func:`coupling_report`) compares the last second of A's hold with a window
where B rests settled (1 s after B's force came on, or once a landing bounce has died out at the
gain design's decay margin: :func:`landing_settled_s`), before A touches, or after A's release when
B's contact came on too late: B's force rise [N] and the outward displacement of the surface under
B [mm]. Each user's whole hold is judged (:func:`judge_user`): how far the probe shook
(:func:`largest_p2p`), how far the felt stiffness stepped (:func:`felt_stiffness_step`, against
the stiffness JND), whether the user ever rendered a model, and whether the machine was too loaded
to judge (:func:`machine_load`); the run's verdict and exit status are :func:`run_verdict`'s. The
servo's missed deadlines are counted (:func:`missed_per_s`); :func:`build_report` assembles the
``--report`` JSON from the run's folder, :func:`print_summary` prints its table, whether B felt A
in plain sentences (:func:`coupling_lines`) and the users' verdicts, :func:`run_verdict_line` the
run's verdict in one line, and :func:`plot_demo` draws the ``--plot`` PNG. The palpation
scenario's own figures (A's force over the lump and beside it, B's force during A's sweep) are
:func:`palpation_report`'s, in words :func:`palpation_lines`. The processes that make the telemetry are run by
:mod:`haptic_collab.demo`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from haptic_collab.client.devices.trajectories import Rest, Sweep
from haptic_collab.shared.gains.policy import DESIGN_OVER_REST, MIN_DECAY_RATE_PER_S

#: A hold is stable when the probe's largest peak to peak over its whole hold, each second after
#: its straight-line trend (:func:`largest_p2p`), stays below this [mm] (and :func:`hold_shake_mm`,
#: the penetration's, in the loopback test).
STABLE_P2P_MM = 1.0
#: After a change of gains the hold's equilibrium moves (a stiffer coupling holds the probe nearer
#: the proxy) for about this long [s]: the client's gain transfer (0.25 s) and the hand settling.
GAIN_SETTLE_S = 0.5
#: A change of K_h smaller than this share is not a change of gains for the hold judgement: a
#: table design is rendered scaled to the reported K_o (GainDesign.at), so a K_o that drifts
#: inside its cell moves K_h a little every patch, with the equilibrium staying put.
GAIN_CHANGE_SHARE = 0.02
#: B's resting samples count when B's coupling holds B's hand as it does while A holds: its
#: steady compliance (:func:`steady_coupling_compliance`) within this share of 1/K_h (the K_h B
#: renders while A holds) of the hold's. At rest a P local model adds 1/K_h in series with the
#: object and own-force compensation takes C_h back (docs/own-force.md); B's P designs on the
#: balloon all have C_h K_h = 1, so a design replaced by another (the coupled class's, 146 N/m,
#: for the uncoupled 176 N/m, 17 % apart) leaves B's resting force where it was (0.281 N under
#: both, measured in six demos), while a quarter-K_o fallback without compensation (4/K_o more)
#: stays out. Without compensation the rule is the K_h within about 15 % it replaced (and, like
#: it, lets a resting force differ by up to about that share: the compliances that occur are 0,
#: 1/K_h and 4/K_o, far apart).
REST_COUPLING_SHARE = 0.15
#: An integral carrying force holds the probe theta inside the proxy: B's rest counts only with
#: the threshold B has while A holds, within this [m] (theta is a setting, 0.5-3 mm, never near).
REST_THETA_M = 1e-5
#: B's contact counts as settled this long after its force came on [s] (the PI local model's
#: integral takes about 1 s to reach B's resting force).
B_SETTLE_S = 1.0
#: After A's release the surface and B's integral relax for about this long [s].
RELEASE_SETTLE_S = 2.0
#: B's force is "on" above this [N].
B_FORCE_ON_N = 0.01
#: B feels A when B's force changes by at least this share of its resting force while A holds
#: (the force JND, about 7-10 %: Jones 1989; Pang, Tan and Durlach 1991) ...
FEEL_FORCE_SHARE = 0.10
#: ... the surface under B moves by at least this [mm], and the force follows the surface (up
#: when it bulges out toward B's hand, down when it is drawn in): on a balloon the water pushes
#: B's side out; on other shapes the membrane near A's dent may draw B's side in instead.
FEEL_DISPLACEMENT_MM = 0.1
#: The shortest window B's resting force and position are averaged over [s].
MIN_REST_WINDOW_S = 0.25
#: How long after A touches B's lowest force is looked for [s] (A's press takes 1.5 s). When the
#: contacts couple, a client without checked gains for the new coupling renders a conservative
#: fallback for the 0.15-0.3 s of a check: B's resting force fell from 0.28 to 0.07-0.11 N then,
#: just as A arrived, where it should only rise.
ARRIVAL_WINDOW_S = 1.0
#: B's resting samples count only with the coupling B renders while A holds
#: (:data:`REST_COUPLING_SHARE`), and this long after B's gains last changed [s] (a gain change's
#: transfer ramp, 0.25 s, and the slow loop's settling): B resting with a quarter-K_o fallback (its
#: delay had risen) dents the surface less, and compared with the hold under its designed gains
#: that read as B's side barely moving (0.14-0.30 mm against 0.65). (Named apart from
#: :data:`GAIN_SETTLE_S`, which it had overwritten: the hold judgement left out 0.3 s after a
#: change of gains, not the 0.5 s stated.)
REST_GAIN_SETTLE_S = 0.3


@dataclass(frozen=True)
class Timeline:
    """A's scripted press, in seconds from the start of A's client (its clock's zero; shifted
    by :func:`script_start_s` once the run is over, as A's script starts at its servo's first
    tick)."""

    delay_s: float
    approach_s: float
    press_s: float
    hold_s: float
    release_s: float

    @property
    def contact_s(self) -> float:
        """When A's hand reaches the surface."""
        return self.delay_s + self.approach_s

    @property
    def hold_end_s(self) -> float:
        """When A's hold ends (the release begins)."""
        return self.delay_s + self.approach_s + self.press_s + self.hold_s

    def options(self) -> str:
        """``--trajectory`` value for A's client."""
        return (
            f"delay_s={self.delay_s:g},approach_s={self.approach_s:g},press_s={self.press_s:g},"
            f"hold_s={self.hold_s:g},release_s={self.release_s:g}"
        )


def script_start_s(csv_path: Path) -> float:
    """When A's scripted hand started, on A's clock [s]: the ``t_s`` of the first telemetry row.

    A scripted device starts its trajectory at the servo's first read
    (:meth:`client.devices.sim.SimDevice.read`), and the servo starts once the client has joined
    and loaded its gains: 0.5-3 s into A's clock on a loaded machine. The demo's timeline (the
    judged hold, B's windows, the plot) is in trajectory time, so it is shifted by this. 0.0
    when A wrote no row (the report then says A never rendered).
    """
    import csv

    try:
        with open(csv_path, newline="") as f:
            reader = csv.reader(f)
            header = next(reader)
            row = next(reader)
        t = float(row[header.index("t_s")])
    except (OSError, StopIteration, ValueError, IndexError):
        return 0.0
    return t if math.isfinite(t) and t > 0.0 else 0.0


def timeline(duration_s: float) -> Timeline:
    """A's press for a run of ``duration_s`` seconds (module docstring)."""
    # B's forces come on once its first gains are checked (a few hundred ms after its first patch;
    # before interim checks, 1-2.5 s): A waits at least 4 s, so the "before" window sees B resting
    delay = max(4.0, 0.2 * duration_s)
    approach, press, release = 1.0, 1.5, 1.0
    hold = max(2.0, 0.75 * duration_s - delay - approach - press)
    return Timeline(delay, approach, press, hold, release)


class RunSettings(Protocol):
    """What :func:`build_report` reads of the run's options (a
    :class:`haptic_collab.demo.DemoOptions`).

    Attributes
    ----------
    sim_rate_hz : float
        The server's simulation rate [Hz].
    stiffness_scale : float
        The factor every stiffness term of the object is multiplied by.
    latency_ms, jitter_ms : float
        The server's injected one-way latency and its jitter [ms].
    loss : float
        The server's injected loss of state frames, a share in [0, 1).
    duration_s : float
        The run's length [s].
    """

    sim_rate_hz: float
    stiffness_scale: float
    latency_ms: float
    jitter_ms: float
    loss: float
    duration_s: float


def _load(work: Path, name: str) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    summary = json.loads((work / f"{name}.json").read_text())
    with open(work / f"{name}.csv") as f:
        header = f.readline().strip().split(",")
    data = np.loadtxt(work / f"{name}.csv", delimiter=",", skiprows=1, ndmin=2)
    if data.shape[1] != len(header):  # a header and no rows: the user's servo never ticked
        data = np.zeros((0, len(header)))
    cols = {h: data[:, i] for i, h in enumerate(header)}
    return cols, summary


def _window(cols: dict[str, np.ndarray], t0: float, t1: float) -> np.ndarray:
    t = cols["t_s"]
    return (t >= t0) & (t < t1)


def hold_shake_mm(
    t: np.ndarray,
    x: np.ndarray,
    k_h: np.ndarray,
    window: tuple[float, float],
    settle_s: float = GAIN_SETTLE_S,
) -> float:
    """How much a held probe shakes: peak to peak [mm] of ``x`` [m] after its trend.

    A hold is judged in ``window`` (t0, t1) [s] on the telemetry's clock ``t`` [s]. A change of
    K_h (``k_h`` [N/m], one per sample) by more than :data:`GAIN_CHANGE_SHARE` moves the hold's
    equilibrium: the ``settle_s`` after each change are left out, and each stretch between changes is judged apart, after its own
    straight-line trend (a slow creep, such as the probe sinking while the PI integral stops at
    the device's continuous force, is not a shake). Stretches under 0.1 s are not judged.

    Returns
    -------
    float
        The largest peak to peak [mm] of a stretch; NaN if no stretch could be judged.
    """
    t = np.asarray(t, float)
    x = np.asarray(x, float)
    k_h = np.asarray(k_h, float)
    judged = (t >= window[0]) & (t < window[1]) & np.isfinite(x)
    changes = t[1:][np.abs(np.diff(k_h)) > GAIN_CHANGE_SHARE * np.abs(k_h[:-1])]
    for ts in changes:
        judged &= ~((t >= ts) & (t < ts + settle_s))
    # stretches: runs of judged samples not separated by a change of gains
    stretch = np.searchsorted(changes, t, side="right")
    worst = float("nan")
    for k in np.unique(stretch[judged]):
        m = judged & (stretch == k)
        tk, xk = t[m], x[m]
        if tk.size < 3 or tk[-1] - tk[0] < 0.1:
            continue
        shake = xk - np.polyval(np.polyfit(tk, xk, 1), tk)
        p2p = float(np.ptp(shake) * 1000.0)
        worst = p2p if not np.isfinite(worst) else max(worst, p2p)
    return worst


def missed_per_s(
    t_s: np.ndarray, period_s: np.ndarray, servo_rate_hz: float, skip_s: float = 1.0
) -> float:
    """Servo deadlines missed per second after the first ``skip_s`` [s] of the recording: a
    period of k > 1.5 servo periods skipped round(k) - 1 deadlines (the scheduler's late
    tolerance, :class:`client.scheduler.DeadlineLoop`)."""
    if t_s.size < 2:
        return float("nan")
    keep = (t_s > t_s[0] + skip_s) & np.isfinite(period_s)
    span = float(t_s[keep][-1] - t_s[keep][0]) if keep.sum() > 1 else 0.0
    if span <= 0.0:
        return float("nan")
    k = period_s[keep] * servo_rate_hz
    return float(np.sum(np.where(k > 1.5, np.round(k) - 1.0, 0.0)) / span)


# --------------------------------------------------------------------------- the hold's verdict
#: The stiffness JND [share]: two stiffnesses further apart than this ratio less one are told
#: apart by a hand. The project's one value, shared.gains.policy.DESIGN_OVER_REST = ln(1.1)
#: (docs/fidelity.md), read back as a share (0.10).
STIFFNESS_JND = math.expm1(DESIGN_OVER_REST)
#: A's hold is judged from this long after its press ends [s] (the hand settling on the surface).
HOLD_SETTLE_S = 0.5
#: The probe's and the force's peak to peak are taken over windows this long [s], each after its
#: own straight-line trend (a slow creep, such as the probe sinking while the device's force is
#: held at its continuous limit, is not a shake), :data:`SHAKE_HOP_S` apart.
SHAKE_WINDOW_S = 0.5
#: See :data:`SHAKE_WINDOW_S` [s].
SHAKE_HOP_S = 0.125
#: The felt stiffness is summarised (lowest, highest) over blocks this long [s]: one simulation
#: tick at 20 Hz, at most one patch's gains.
FELT_BLOCK_S = 0.05
#: A felt-stiffness step is the largest ratio between two blocks at most this far apart [s]: a
#: change a still hand feels as a step, not a drift over seconds.
FELT_STEP_WINDOW_S = 0.5
#: Too loaded to judge: the server overran more than this share of its ticks during the hold ...
LOADED_OVERRUN_SHARE = 0.10
#: ... or the user's servo missed more than this many deadlines per second during it (5 % at
#: 1 kHz) ...
LOADED_MISSED_PER_S = 50.0
#: ... or the user's round trip's median exceeded the injected one (twice the latency and the
#: jitter) by more than this [ms] (the processes' event loops starved) ...
LOADED_RTT_EXTRA_MS = 50.0
#: ... or no gain design finished in the user's run and it rendered fallback gains for at least
#: this share of its patches (the design worker starved: the run never showed the designed gains).
LOADED_FALLBACK_SHARE = 0.9
#: ... or the link fell silent and the servo ramped the forces to zero for safety in the hold or
#: this long [s] before it (the hand then falls into the object and is pushed back: a shake
#: that the stall made, not the loop).
LINK_LOST_BEFORE_HOLD_S = 1.0

#: The verdicts, worst first (:func:`run_verdict`).
VERDICTS = ("never rendered", "unstable", "could not judge", "stable")
#: ``haptic demo``'s exit status per verdict: 1 when a user is unstable or never rendered (the
#: demo did not work), 3 when no user failed but one could not be judged (the machine was too
#: loaded: run it again on a quieter one), 0 when every user was stable. (2 is a usage error.)
EXIT_CODES = {"never rendered": 1, "unstable": 1, "could not judge": 3, "stable": 0}
#: What each exit status means, as the demo's last line says it.
EXIT_MEANING = {
    0: "every user stable",
    1: "a user unstable or never rendered",
    3: "the machine was too loaded to judge; run it again on a quieter machine",
}


def largest_p2p(
    t: np.ndarray,
    x: np.ndarray,
    mask: np.ndarray,
    window_s: float = SHAKE_WINDOW_S,
    hop_s: float = SHAKE_HOP_S,
) -> tuple[float, float | None]:
    """The largest peak to peak of ``x`` over any window of the masked samples, after its trend.

    Windows of ``window_s`` [s] start every ``hop_s`` [s] from the first masked sample; each is
    judged after its own straight-line fit, so a slow creep is not a peak to peak. Windows with
    fewer than 3 samples or spanning under half ``window_s`` are not judged.

    Parameters
    ----------
    t : (m,) array
        Sample times [s].
    x : (m,) array
        The signal (any unit; the result is in that unit).
    mask : (m,) bool array
        The samples judged (non-finite ``x`` are left out too).

    Returns
    -------
    (float, float or None)
        The largest peak to peak (NaN if no window was judged) and the start of its window [s].
    """
    keep = mask & np.isfinite(x)
    tk, xk = t[keep], x[keep]
    worst, at = float("nan"), None
    if tk.size < 3:
        return worst, at
    starts = np.arange(tk[0], max(tk[-1] - 0.5 * window_s, tk[0]) + 1e-9, hop_s)
    for t0 in starts:
        i0, i1 = np.searchsorted(tk, [t0, t0 + window_s])
        tw, xw = tk[i0:i1], xk[i0:i1]
        if tw.size < 3 or tw[-1] - tw[0] < 0.5 * window_s:
            continue
        p2p = float(np.ptp(xw - np.polyval(np.polyfit(tw - tw[0], xw, 1), tw - tw[0])))
        if not p2p <= worst:  # the first, or a larger one
            worst, at = p2p, float(t0)
    return worst, at


def contact_normal(cols: dict[str, np.ndarray], mask: np.ndarray) -> np.ndarray | None:
    """The contact's outward unit normal: the mean direction of the force on the hand over the
    masked samples (the force pushes the hand out of the surface); None without force there."""
    f = np.stack([cols["force_x_n"], cols["force_y_n"], cols["force_z_n"]], axis=1)[mask]
    mean = np.nanmean(f, axis=0) if f.size else np.zeros(3)
    norm = float(np.linalg.norm(mean)) if np.all(np.isfinite(mean)) else 0.0
    return mean / norm if norm > 1e-9 else None


def landing_settled_s(b: dict[str, np.ndarray], onset_s: float) -> tuple[float, float | None]:
    """When B's landing has settled [s, ``b``'s clock], and how far it bounced [mm] (None: no
    probe or force columns to measure it).

    A heavy hand held loosely bounces as it lands on a soft solid, and its landing sets the solid
    ringing (the liver ball rocks at 1.6-2.4 Hz): the solid coupled directly at 1 kHz, with no
    delay and no local model, bounces such a hand by more than 1 mm for most of a second too
    (``tools/landing_reference.py``, docs/palpation.md). A transient that dies out is not an
    instability; the gain design's own test of one is its decay rate
    (:data:`shared.gains.policy.MIN_DECAY_RATE_PER_S`). So B counts as settled
    :data:`B_SETTLE_S` after its force came on or, when the probe's largest peak to peak ``p``
    in that first second (:func:`largest_p2p` along the contact normal) is
    :data:`STABLE_P2P_MM` or more, once a bounce of ``p`` decaying at that rate from the end of
    its window would be under it: ``t_p + SHAKE_WINDOW_S + ln(p / STABLE_P2P_MM) /
    MIN_DECAY_RATE_PER_S``. A shake that decays more slowly than the margin, or not at all, is
    still :data:`STABLE_P2P_MM` or more when B's rest is judged.
    """
    settled = onset_s + B_SETTLE_S
    need = ("probe_x_m", "probe_y_m", "probe_z_m", "force_x_n", "force_y_n", "force_z_n")
    if not all(k in b for k in need):
        return settled, None
    first = _window(b, onset_s, settled)
    normal = contact_normal(b, first & (b["in_contact"] > 0))
    if normal is None:
        return settled, None
    probe = np.stack([b["probe_x_m"], b["probe_y_m"], b["probe_z_m"]], axis=1) @ normal
    p2p, at = largest_p2p(b["t_s"], probe, first)
    if not np.isfinite(p2p) or at is None:
        return settled, None
    p2p_mm = p2p * 1000.0
    if p2p_mm >= STABLE_P2P_MM:
        decays_by = at + SHAKE_WINDOW_S + math.log(p2p_mm / STABLE_P2P_MM) / MIN_DECAY_RATE_PER_S
        settled = max(settled, decays_by)
    return settled, p2p_mm


def rest_plane_k_h(summary: dict[str, Any]) -> np.ndarray:
    """The K_h [N/m] of every rest-plane rendering in the client summary's ``gain_changes``
    (rounded there to 0.1 N/m)."""
    return np.array(
        [float(g.get("k_h") or 0.0) for g in summary.get("gain_changes") or [] if g.get("rest")]
    )


def felt_stiffness(
    cols: dict[str, np.ndarray],
    mask: np.ndarray,
    k_o: float,
    block_s: float = FELT_BLOCK_S,
    rest_k_h: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The stiffness a still hand feels through the rendered coupling, per block of ``block_s``.

    At rest a coupling adds the compliance c in series with the object's 1/K_o
    (:func:`steady_coupling_compliance`: ``1/K_h - C_h`` for a P coupling or an integral at 0,
    ``-C_h`` for an integral carrying force), so the hand feels K_f = 1 / (c + 1/K_o): K_o
    itself under a design with C_h K_h = 1, K_o/5 under a quarter-K_o fallback without
    compensation. K_h, I, C_h and the integral are each sample's rendered ones; K_o is the
    object's at the contact (:func:`object_stiffness`). It is computed from the gains rather
    than from the measured force and depth: the recorded own-force offset is the server's
    sampled force times C_h, which steps at every patch (0.2 mm on a resting hand) and at once
    at a change of gains while the rendered proxy ramps, so a measured depth per newton read
    25 % steps on holds whose force and probe did not move. What the rendering's lags do to the
    hand shows in the probe's peak to peak (:func:`largest_p2p`). Samples count where masked,
    in contact with a model (K_h > 0), at full force (no engage or release ramp) and without
    a fault; K_f is capped at 10 K_o (a coupling stiffer than the object, c < -0.9/K_o). A
    sample rendered against the rest plane (a user alone; ``rest_k_h``, :func:`rest_plane_k_h`:
    its K_h within the summary's rounding, no integral, no compensation) is felt as K_h itself:
    its force does not go through the simulation, so the object's compliance is not in series.

    Parameters
    ----------
    cols : dict of (m,) arrays
        The user's telemetry (``t_s``, ``k_h_n_per_m``, ``in_contact`` and, when recorded,
        ``i_gain_n_per_m_s``, ``integral_n``, ``own_gain_m_per_n``, ``force_scale``, ``fault``).
    mask : (m,) bool array
        The samples judged.
    k_o : float
        The object's stiffness at the contact [N/m].

    Returns
    -------
    (t, low, high) : (n,) arrays
        Each block's start [s] and its lowest and highest felt stiffness [N/m] (blocks without
        a counted sample are left out).
    """
    t = cols["t_s"]
    kh = cols["k_h_n_per_m"]
    ok = mask & (cols["in_contact"] > 0) & (kh > 0.0)
    if "force_scale" in cols:
        ok &= cols["force_scale"] >= 0.999
    if "fault" in cols:
        ok &= cols["fault"] == 0
    if not ok.any() or not k_o > 0.0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    c = steady_coupling_compliance(
        kh[ok],
        cols.get("i_gain_n_per_m_s", np.zeros_like(t))[ok],
        cols["own_gain_m_per_n"][ok] if "own_gain_m_per_n" in cols else None,
        cols["integral_n"][ok] if "integral_n" in cols else None,
    )
    k_f = 1.0 / np.maximum(c + 1.0 / k_o, 0.1 / k_o)
    if rest_k_h is not None and rest_k_h.size:
        own = cols["own_gain_m_per_n"][ok] if "own_gain_m_per_n" in cols else np.zeros(ok.sum())
        ig = cols.get("i_gain_n_per_m_s", np.zeros_like(t))[ok]
        near = np.min(np.abs(kh[ok][:, None] - rest_k_h[None, :]), axis=1) <= 0.051
        rest = near & (own == 0.0) & (ig == 0.0)
        k_f = np.where(rest, kh[ok], k_f)
    block = np.floor((t[ok] - t[ok][0]) / block_s).astype(np.int64)
    edges = np.r_[0, np.nonzero(np.diff(block))[0] + 1]
    return (
        t[ok][0] + block_s * block[edges],
        np.minimum.reduceat(k_f, edges),
        np.maximum.reduceat(k_f, edges),
    )


def felt_stiffness_step(
    t_b: np.ndarray, low: np.ndarray, high: np.ndarray, window_s: float = FELT_STEP_WINDOW_S
) -> dict[str, float] | None:
    """The largest step of the felt stiffness: the largest ratio of the highest to the lowest
    felt stiffness [N/m] within ``window_s`` [s] (:func:`felt_stiffness`'s (n,) block starts
    [s], lows and highs).

    Returns
    -------
    dict or None
        ``ratio`` (high / low, >= 1), ``low_n_per_m``, ``high_n_per_m``, ``step_n_per_m``
        (high - low) and ``at_s`` (the window's first block); None without a block.
    """
    if t_b.size == 0:
        return None
    best: dict[str, float] | None = None
    for i in range(t_b.size):
        j1 = max(int(np.searchsorted(t_b, t_b[i] + window_s, side="right")), i + 1)
        lo, hi = float(np.min(low[i:j1])), float(np.max(high[i:j1]))
        if best is None or hi / lo > best["ratio"]:
            best = {
                "ratio": hi / lo,
                "low_n_per_m": lo,
                "high_n_per_m": hi,
                "step_n_per_m": hi - lo,
                "at_s": float(t_b[i]),
            }
    return best


def object_stiffness(summary: dict[str, Any]) -> float | None:
    """The object's stiffness at the user's contact [N/m]: the median K_o of the patches at
    which the user's gains changed (the client summary's ``gain_changes``); None without any.

    K_o is the contact's own stiffness, the inverse of its diagonal compliance: what a press
    meets while every other user's force stays as it is, and what the rest plane renders once
    the user is alone. A contact coupled to another user's also reports K_o_eff, the stiffness
    of the mode in which both press together, which is lower (146 against 181 N/m for the
    palpation demo's resting user while the other pressed on the top). Judged against K_o_eff,
    a compensated design felt as the contact's own stiffness read as a step of x1.16-1.18 when
    the partner left and the rest plane of 181 N/m rendered. Summaries written before ``k_o``
    was recorded give K_o_eff."""
    changes = summary.get("gain_changes") or []
    k = [float(g.get("k_o") or g["k_o_eff"]) for g in changes if g.get("k_o") or g.get("k_o_eff")]
    return float(np.median(k)) if k else None


def server_overrun_share(
    samples: list[dict[str, float]] | None, status: dict[str, Any], window: tuple[float, float]
) -> tuple[float | None, str]:
    """The share of the server's ticks that overran in ``window`` [s, A's clock].

    ``samples`` are the server's status polled during the run (``t_s`` on A's clock, ``tick``,
    ``overruns``): the counts at the last sample at or before the window's start and the first
    at or after its end are differenced. Without two such samples, the final ``status``'s
    totals (which count the start-up's too). Returns (share or None, which of the two).
    """
    pts = sorted(
        (s for s in samples or [] if s.get("tick") is not None and s.get("overruns") is not None),
        key=lambda s: s["t_s"],
    )
    before = [s for s in pts if s["t_s"] <= window[0]]
    after = [s for s in pts if s["t_s"] >= window[1]]
    if before and after and after[0]["tick"] > before[-1]["tick"]:
        d_over = after[0]["overruns"] - before[-1]["overruns"]
        return d_over / (after[0]["tick"] - before[-1]["tick"]), "during the hold"
    tick, over = status.get("tick"), status.get("overruns")
    if tick and over is not None:
        return over / tick, "over the whole run"
    return None, "not measured"


def delay_rise_in_hold(
    summary: dict[str, Any],
    hold: list[tuple[float, float]],
    tick_times: tuple[np.ndarray, np.ndarray] | None,
) -> tuple[int, float] | None:
    """Whether the user's measured delay rose and unchecked fallback gains were rendered in its
    hold: (the delay [simulation ticks], the fallback's K_h [N/m]) of the first such gains, or
    None.

    The client summary's ``gain_changes`` say, per change of the rendered gains, the server
    tick, K_h, whether the gains were checked (``verified``) or a ``fallback``, and the loop
    delay the client measured (``delay_ticks``). A delay above the run's lowest, on the demo's
    loopback link whose injected latency does not change, is the machine's load (the event loops
    late to answer), and gains unchecked for it are the quarter-K_o fallback the client renders
    until a check for the new delay arrives: a hand feels them as the object going soft. Each
    change holds until the next; ``tick_times`` ((k,) server ticks, (k,) times [s, A's clock],
    from the server's polled status) place them in time; without it every change of the run
    counts.
    """
    changes = [g for g in summary.get("gain_changes") or [] if g.get("tick") is not None]
    delays = [int(g.get("delay_ticks") or 0) for g in changes]
    if not changes:
        return None
    if tick_times is not None and tick_times[0].size >= 2:
        starts = np.interp([float(g["tick"]) for g in changes], *tick_times)
        ends = np.r_[starts[1:], np.inf]
    else:
        starts = np.full(len(changes), -np.inf)
        ends = np.full(len(changes), np.inf)
    lowest = min(delays)
    for g, d, t0, t1 in zip(changes, delays, starts, ends, strict=True):
        in_hold = any(t0 < h1 and t1 > h0 for h0, h1 in hold)
        unchecked = g.get("fallback") and not g.get("verified", True)
        if in_hold and unchecked and d > lowest:
            return d, float(g.get("k_h") or 0.0)
    return None


def link_lost_in_hold(
    cols: dict[str, np.ndarray], summary: dict[str, Any], hold: list[tuple[float, float]]
) -> float:
    """How long [s] the servo's forces were ramped below full in the hold (or in the
    :data:`LINK_LOST_BEFORE_HOLD_S` before it) because the link fell silent, or 0.

    The telemetry's ``force_scale`` says a safety ramp ran; the summary's ``servo.counts`` say
    why over the run. The ramp counts as the link's only when the run had link losses and no
    velocity-limit or device-fault ramps (an oscillating probe can trip the velocity limit: that
    ramp must not excuse an unstable loop).
    """
    counts = (summary.get("servo") or {}).get("counts") or {}
    if not counts.get("link_lost") or counts.get("velocity_limit") or counts.get("device_fault"):
        return 0.0
    if "force_scale" not in cols or not hold or cols["t_s"].size < 2:
        return 0.0
    w = _window(cols, hold[0][0] - LINK_LOST_BEFORE_HOLD_S, hold[-1][1])
    ramped = w & (cols["force_scale"] < 0.999)
    return float(ramped.sum()) * float(np.median(np.diff(cols["t_s"])))


def machine_load(
    summary: dict[str, Any],
    missed_in_hold_per_s: float,
    overrun_share: float | None,
    injected_rtt_ms: float,
    delay_rise: tuple[int, float] | None = None,
    link_lost_s: float = 0.0,
) -> list[str]:
    """Why the machine was too loaded to judge this user's hold, in plain words ([] if not).

    Any of: the server overran more than :data:`LOADED_OVERRUN_SHARE` of its ticks during the
    hold; the user's servo missed more than :data:`LOADED_MISSED_PER_S` deadlines per second in
    it; the user's median round trip exceeded ``injected_rtt_ms`` by more than
    :data:`LOADED_RTT_EXTRA_MS`; no gain design finished and at least
    :data:`LOADED_FALLBACK_SHARE` of the patches were rendered with fallback gains; the user's
    measured delay rose and it rendered unchecked fallback gains in its hold (``delay_rise``,
    :func:`delay_rise_in_hold`); the link fell silent and the forces ramped down for safety in
    or just before the hold (``link_lost_s`` [s], :func:`link_lost_in_hold`).
    """
    out: list[str] = []
    if overrun_share is not None and overrun_share > LOADED_OVERRUN_SHARE:
        out.append(f"the server overran {overrun_share:.0%} of its ticks")
    if np.isfinite(missed_in_hold_per_s) and missed_in_hold_per_s > LOADED_MISSED_PER_S:
        out.append(f"the servo missed {missed_in_hold_per_s:.0f} deadlines per second")
    rtt = summary.get("rtt_ms_p50")
    if rtt is not None and rtt > injected_rtt_ms + LOADED_RTT_EXTRA_MS:
        out.append(f"the round trip took {rtt:.0f} ms (median; {injected_rtt_ms:.0f} ms injected)")
    patches = int(summary.get("patches") or 0)
    fallback = int(summary.get("fallback_patches") or 0)
    if not summary.get("gain_designs") and patches and fallback >= LOADED_FALLBACK_SHARE * patches:
        out.append(f"no gain design finished (fallback gains for {fallback} of {patches} patches)")
    if delay_rise is not None:
        out.append(
            f"its measured delay rose to {delay_rise[0]} simulation "
            f"tick{'' if delay_rise[0] == 1 else 's'} and it rendered unchecked fallback gains "
            f"({delay_rise[1]:.0f} N/m) in its hold"
        )
    if link_lost_s > 0.0:
        out.append(
            f"the link fell silent (a stalled server or network) and its forces were ramped "
            f"down for safety for {link_lost_s:.2f} s in or just before its hold"
        )
    return out


def hold_window(
    name: str, tl: Timeline, cols: dict[str, np.ndarray], settled_s: float | None
) -> list[tuple[float, float]]:
    """The user's hold phase: its stretches (t0, t1) [s, A's clock].

    A's: from :data:`HOLD_SETTLE_S` after its press to its release. B rests the whole run, and
    A's press and release move the surface under B by design (the coupling): B's hold is its
    rest while A is still, in up to three stretches: from B's settled contact (``settled_s``;
    without it B's hold begins at A's hold) to A's contact, A's hold, and from
    :data:`RELEASE_SETTLE_S` after A's release to 0.2 s before B's last sample.
    """
    a_hold = (tl.contact_s + tl.press_s + HOLD_SETTLE_S, tl.hold_end_s)
    if name == "A":
        return [a_hold]
    end = float(cols["t_s"][-1]) - 0.2 if cols["t_s"].size else tl.hold_end_s
    spans = [
        (tl.contact_s if settled_s is None else settled_s, tl.contact_s),
        a_hold,
        (tl.hold_end_s + tl.release_s + RELEASE_SETTLE_S, end),
    ]
    starts_after = -np.inf if settled_s is None else settled_s
    spans = [(max(t0, starts_after), t1) for t0, t1 in spans]
    return [(t0, t1) for t0, t1 in spans if t1 - t0 > 0.1]


def judge_user(
    cols: dict[str, np.ndarray],
    summary: dict[str, Any],
    hold: list[tuple[float, float]],
    load: list[str],
) -> dict[str, Any]:
    """The verdict on one user's hold (``hold``: its stretches (t0, t1) [s] on the telemetry's
    clock, :func:`hold_window`; each judged apart, the worst reported).

    - ``never rendered``: no local model arrived (no sample with K_h > 0), none during the hold,
      or the user never touched the object during it: the user felt nothing, loaded machine or
      not (its load is named among the reasons).
    - ``could not judge``: the machine was too loaded (``load``, :func:`machine_load`, not
      empty); what was measured is still reported.
    - ``unstable``: over the whole hold the probe (along the contact normal) shook
      :data:`STABLE_P2P_MM` or more peak to peak (:func:`largest_p2p`), the felt stiffness
      stepped by more than the stiffness JND (:func:`felt_stiffness_step`), or a fault occurred.
    - ``stable``: none of those.

    Returns
    -------
    dict
        ``verdict``, ``verdict_reasons`` (plain words), ``hold_window_s``,
        ``hold_oscillation_mm`` and ``hold_oscillation_at_s`` (the probe), ``hold_force_p2p_n``,
        ``felt_stiffness`` (:func:`felt_stiffness_step`'s dict with ``k_o_n_per_m`` and
        ``jnd``, or None), ``model_share_of_hold`` and ``contact_share_of_hold``.
    """
    t = cols["t_s"]
    w = np.zeros(t.shape, bool)
    for span in hold:
        w |= _window(cols, *span)
    kh = cols.get("k_h_n_per_m", np.zeros_like(t))
    model = kh > 0.0
    contact = w & model & (cols["in_contact"] > 0)
    n_hold = max(int(w.sum()), 1)
    out: dict[str, Any] = {
        "hold_window_s": [[t0, t1] for t0, t1 in hold],
        "hold_oscillation_mm": None,
        "hold_oscillation_at_s": None,
        "hold_force_p2p_n": None,
        "felt_stiffness": None,
        "model_share_of_hold": float((w & model).sum() / n_hold),
        "contact_share_of_hold": float(contact.sum() / n_hold),
        "force_limited_share_of_hold": float(np.sum(w & (cols["force_limited"] > 0)) / n_hold)
        if "force_limited" in cols
        else None,
    }
    reasons: list[str] = []
    if not model.any():
        reasons.append(
            f"no local model arrived ({int(summary.get('patches') or 0)} patches): "
            "it rendered no force"
        )
    elif not (w & model).any():
        reasons.append("no local model during its hold")
    elif not contact.any():
        reasons.append("it never touched the object during its hold")
    if reasons:  # a load explains it, but the user still felt nothing: the demo did not work
        if load:
            reasons.append("the machine was loaded: " + ", ".join(load))
        return {**out, "verdict": "never rendered", "verdict_reasons": reasons}
    normal = contact_normal(cols, contact)
    if normal is not None:
        probe = np.stack([cols["probe_x_m"], cols["probe_y_m"], cols["probe_z_m"]], axis=1)
        p2p, at = _worst_p2p(cols, probe @ normal, hold)
        out["hold_oscillation_mm"] = p2p * 1000.0 if np.isfinite(p2p) else None
        out["hold_oscillation_at_s"] = at
    f_p2p, _ = _worst_p2p(cols, cols["force_n"], hold)
    out["hold_force_p2p_n"] = f_p2p if np.isfinite(f_p2p) else None
    k_o = object_stiffness(summary)
    if k_o is not None:
        step = felt_stiffness_step(*felt_stiffness(cols, w, k_o, rest_k_h=rest_plane_k_h(summary)))
        if step is not None:
            out["felt_stiffness"] = {**step, "k_o_n_per_m": k_o, "jnd": STIFFNESS_JND}
    shake = out["hold_oscillation_mm"]
    if shake is not None and shake >= STABLE_P2P_MM:
        reasons.append(
            f"the probe shook {shake:.2f} mm peak to peak (in the {SHAKE_WINDOW_S:g} s from "
            f"{out['hold_oscillation_at_s']:.1f} s; under {STABLE_P2P_MM:g} mm is steady)"
        )
    felt = out["felt_stiffness"]
    if felt is not None and felt["ratio"] > 1.0 + STIFFNESS_JND:
        reasons.append(
            f"the felt stiffness stepped x{felt['ratio']:.2f} ({felt['low_n_per_m']:.0f} <-> "
            f"{felt['high_n_per_m']:.0f} N/m, within {FELT_STEP_WINDOW_S:g} s from "
            f"{felt['at_s']:.1f} s; a hand tells {STIFFNESS_JND:.0%} apart)"
        )
    faults = int(np.nansum(cols["fault"][w])) if "fault" in cols else 0
    if faults:
        reasons.append(f"{faults} servo ticks with a fault")
    if shake is None and felt is None:
        reasons.append("nothing of the hold could be measured")
    if load:
        measured = "; measured anyway: " + ("; ".join(reasons) if reasons else "a steady hold")
        return {
            **out,
            "verdict": "could not judge",
            "verdict_reasons": ["machine too loaded: " + ", ".join(load) + measured],
        }
    if reasons:
        return {**out, "verdict": "unstable", "verdict_reasons": reasons}
    return {**out, "verdict": "stable", "verdict_reasons": []}


def _worst_p2p(
    cols: dict[str, np.ndarray], x: np.ndarray, hold: list[tuple[float, float]]
) -> tuple[float, float | None]:
    """:func:`largest_p2p` of ``x`` in each stretch of ``hold`` apart: the largest, and where."""
    worst, at = float("nan"), None
    for span in hold:
        p2p, t0 = largest_p2p(cols["t_s"], x, _window(cols, *span))
        if np.isfinite(p2p) and not p2p <= worst:
            worst, at = p2p, t0
    return worst, at


def run_verdict(users: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The run's verdict from its users' (``verdict`` each): the worst of them
    (:data:`VERDICTS`) and its exit status (:data:`EXIT_CODES`)."""
    worst = min((u["verdict"] for u in users.values()), key=VERDICTS.index, default="stable")
    return {
        "verdict": worst,
        "exit_code": EXIT_CODES[worst],
        "users": {name: u["verdict"] for name, u in users.items()},
    }


def _user_report(
    cols: dict[str, np.ndarray],
    summary: dict[str, Any],
    hold: list[tuple[float, float]],
    overrun_share: float | None,
    injected_rtt_ms: float,
    tick_times: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict[str, Any]:
    """One user's part of the report: servo timing, gains, and the verdict on its ``hold``
    (:func:`hold_window`'s stretches; ``tick_times``: :func:`delay_rise_in_hold`'s)."""
    rate_set = float(summary.get("servo_rate_hz_set") or 1000.0)
    whole = _window(cols, hold[0][0], hold[-1][1]) if hold else np.zeros(cols["t_s"].shape, bool)
    missed_hold = (
        missed_per_s(cols["t_s"][whole], cols["period_s"][whole], rate_set, skip_s=0.0)
        if whole.sum() > 1
        else float("nan")
    )
    w = np.zeros(cols["t_s"].shape, bool)
    for span in hold:
        w |= _window(cols, *span)
    delay_rise = delay_rise_in_hold(summary, hold, tick_times)
    load = machine_load(
        summary,
        missed_hold,
        overrun_share,
        injected_rtt_ms,
        delay_rise,
        link_lost_in_hold(cols, summary, hold),
    )
    judged = judge_user(cols, summary, hold, load)
    force = cols["force_n"]
    return {
        "verdict": judged["verdict"],
        "verdict_reasons": judged["verdict_reasons"],
        "stable": judged["verdict"] == "stable",
        "servo_rate_hz": summary.get("servo_rate_hz"),
        "period_us_p99": summary.get("period_us_p99"),
        "max_force_n": float(np.nanmax(force)) if force.size else 0.0,
        **{k: v for k, v in judged.items() if not k.startswith("verdict")},
        "mean_force_during_hold_n": float(np.nanmean(force[w])) if w.any() else None,
        "machine_load": load,
        "servo_overruns": summary.get("servo_overruns"),
        "servo_missed_per_s": missed_per_s(cols["t_s"], cols["period_s"], rate_set),
        "servo_missed_per_s_in_hold": missed_hold if np.isfinite(missed_hold) else None,
        "servo_host": summary.get("servo_host"),
        "servo_realtime": summary.get("servo_realtime"),
        "rtt_ms_p50": summary.get("rtt_ms_p50"),
        "patches": summary.get("patches"),
        "fallback_patches": summary.get("fallback_patches"),
        "gain_designs": summary.get("gain_designs"),
        "delay_ticks_last": summary.get("delay_ticks_last"),
        "plane_patches": summary.get("plane_patches"),
        "identified_plane_patches": summary.get("identified_plane_patches"),
        "rest_plane_patches": summary.get("rest_plane_patches"),
    }


def build_report(
    work: Path,
    tl: Timeline,
    server_status: dict[str, Any],
    opts: RunSettings,
    status_samples: list[dict[str, float]] | None = None,
) -> dict[str, Any]:
    """The ``--report`` JSON from the clients' telemetry and summaries and the server's status.

    ``status_samples``: the server's status polled during the run (``t_clock_s``,
    ``time.perf_counter()`` at the poll [s], the clock of the clients' ``clock_origin_s``;
    ``tick``, ``overruns``), for its overruns during each user's hold
    (:func:`server_overrun_share`).
    """
    a, a_sum = _load(work, "A")
    b, b_sum = _load(work, "B")
    # B's telemetry on A's clock (both clocks are CLOCK_MONOTONIC with a per-process origin)
    shift = b_sum["clock_origin_s"] - a_sum["clock_origin_s"]
    b = dict(b)
    b["t_s"] = b["t_s"] + shift
    hold = (tl.hold_end_s - 1.0, tl.hold_end_s)
    rtts = np.array(a_sum.get("rtt_ms_samples", []) + b_sum.get("rtt_ms_samples", []), float)
    coupling = coupling_report(b, tl, hold, b_approach_end_s=shift + _REST_APPROACH_S)
    samples = [
        {**s, "t_s": s["t_clock_s"] - a_sum["clock_origin_s"]}
        for s in status_samples or []
        if "t_clock_s" in s
    ]
    injected_rtt_ms = 2.0 * (opts.latency_ms + opts.jitter_ms)
    polled = sorted((float(s["tick"]), float(s["t_s"])) for s in samples if "tick" in s)
    tick_times = (
        (np.array([k for k, _ in polled]), np.array([t for _, t in polled]))
        if len(polled) >= 2
        else None
    )
    users: dict[str, dict[str, Any]] = {}
    holds: dict[str, Any] = {}
    for name, cols, summary in (("A", a, a_sum), ("B", b, b_sum)):
        window = hold_window(name, tl, cols, coupling["b_settled_s"])
        whole = (window[0][0], window[-1][1]) if window else (tl.contact_s, tl.hold_end_s)
        share, share_is = server_overrun_share(samples, server_status, whole)
        holds[name] = {"share": share, "is": share_is}
        users[name] = _user_report(cols, summary, window, share, injected_rtt_ms, tick_times)
        users[name]["server_overrun_share_in_hold"] = share
    return {
        "verdict": run_verdict(users),
        "users": users,
        "coupling": coupling,
        "server": {
            "sim_rate_hz": opts.sim_rate_hz,
            "stiffness_scale": opts.stiffness_scale,
            "tick_ms_p50": server_status.get("tick_ms_p50"),
            "tick_ms_p99": server_status.get("tick_ms_p99"),
            "overruns": server_status.get("overruns"),
            "ticks": server_status.get("tick"),
            "overrun_share_in_hold_measured": holds["A"]["is"],
        },
        "network": {
            "rtt_ms_p50": float(np.percentile(rtts, 50)) if rtts.size else None,
            "rtt_ms_p99": float(np.percentile(rtts, 99)) if rtts.size else None,
            "latency_ms": opts.latency_ms,
            "jitter_ms": opts.jitter_ms,
            "loss": opts.loss,
        },
        "timeline_s": {
            "b_settled": coupling["b_settled_s"],
            "a_contact": tl.contact_s,
            "a_hold_end": tl.hold_end_s,
            "duration": opts.duration_s,
        },
    }


#: When B's hand reaches the side [s from B's start]: the sim:rest approach (it starts at once).
_REST_APPROACH_S = Rest((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)).approach_s


def _rest_window(
    b: dict[str, np.ndarray], tl: Timeline, settled_s: float, usable: np.ndarray | None = None
) -> tuple[str, tuple[float, float]] | None:
    """Where B rests undisturbed: (which, (t0, t1)) on A's clock, or None if nowhere.

    Before A touches, from B's settled contact on; if that is too short (B's contact came on
    late), from :data:`RELEASE_SETTLE_S` after A's release to B's last samples. With ``usable``
    (a mask of B's samples), a window counts only from its first usable sample on and only if
    its usable samples span :data:`MIN_REST_WINDOW_S`.
    """
    end = float(b["t_s"][-1]) - 0.2 if b["t_s"].size else -np.inf
    windows = [
        ("before A's press", (settled_s, tl.contact_s - 0.1)),
        (
            "after A's release",
            (max(settled_s, tl.hold_end_s + tl.release_s + RELEASE_SETTLE_S), end),
        ),
    ]
    for which, (t0, t1) in windows:
        if usable is not None:
            ts = b["t_s"][_window(b, t0, t1) & usable]
            if ts.size == 0:
                continue
            t0 = max(t0, float(ts[0]))
        if t1 - t0 >= MIN_REST_WINDOW_S:
            return which, (t0, t1)
    return None


def steady_coupling_compliance(
    k_h: np.ndarray,
    i_gain: np.ndarray,
    own_gain: np.ndarray | None,
    integral_n: np.ndarray | None = None,
) -> np.ndarray:
    """The compliance [m/N] B's coupling adds in series with the object and the hand at rest.

    A P local model holds the probe F/K_h inside the proxy; an integral (I > 0) that holds a force
    (``integral_n`` > 0) drives that to the threshold theta whatever K_h (:mod:`shared.local_model`:
    an offset, compared apart); own-force compensation moves the proxy out by C_h F
    (docs/own-force.md). So at rest: ``1/K_h - C_h`` (P, or an integral at 0) or ``-C_h`` (an
    integral holding force), and a resting hand's force depends on the gains only through it and
    theta (0 for the P designs B renders on the balloon, which all have C_h K_h = 1; an integral at
    its limit is taken as holding force). Shapes: (m,) arrays in, (m,) out; K_h <= 0 (no patch
    yet) gives inf.
    """
    with np.errstate(divide="ignore"):
        p_part = np.where(k_h > 0.0, 1.0 / np.where(k_h > 0.0, k_h, 1.0), np.inf)
    c = np.where(_integral_holds(i_gain, integral_n), 0.0, p_part)
    return c - (0.0 if own_gain is None else own_gain)


def _integral_holds(i_gain: np.ndarray, integral_n: np.ndarray | None) -> np.ndarray:
    """Samples whose integral carries force (I > 0 and, with the column, a positive integral)."""
    holds = i_gain > 0.0
    return holds if integral_n is None else holds & (integral_n > 0.0)


def _stepped(x: np.ndarray) -> np.ndarray:
    """Samples where ``x`` changed by more than :data:`GAIN_CHANGE_SHARE` from the one before."""
    prev = np.concatenate([x[:1], x[:-1]])
    with np.errstate(invalid="ignore"):
        return np.abs(x - prev) > GAIN_CHANGE_SHARE * np.maximum(np.abs(prev), 1e-12)


#: How long the client carries a change of gains over [s] (``client.app.GAIN_TRANSFER_S``,
#: docs/physics.md "Gain changes"; a test keeps the two equal).
GAIN_TRANSFER_S = 0.25


def in_gain_transfer(cols: dict[str, np.ndarray], span_s: float = GAIN_TRANSFER_S) -> np.ndarray:
    """(m,) bool: the samples within ``span_s`` [s] after the rendered K_h, I or own-force gain
    C_h changed (by more than :data:`GAIN_CHANGE_SHARE`), while the client carries the change
    over without a force step.

    Meanwhile the rendered proxy moves from the old gains' place to the new ones' (0.25 s), while
    the recorded own-force offset C_h F_s steps at once: their difference is not the object's
    surface. On the palpation demo's resting user a change from K_h 121 to 48 N/m (offsets 2.9
    and 7.6 mm) 0.05 s into A's 1 s hold read as the surface moving 0.05 mm in, where it moved
    0.5 mm out."""
    t = cols["t_s"]
    kh = cols.get("k_h_n_per_m")
    if kh is None:
        return np.zeros(t.shape, bool)
    stepped = _stepped(kh) | _stepped(cols.get("i_gain_n_per_m_s", np.zeros_like(kh)))
    if "own_gain_m_per_n" in cols:
        stepped |= _stepped(cols["own_gain_m_per_n"])
    last = np.maximum.accumulate(np.where(stepped, t, -np.inf))
    return t - last < span_s


def _same_coupling(b: dict[str, np.ndarray], hold_mask: np.ndarray) -> np.ndarray | None:
    """B's samples whose coupling holds B's hand as it does while A holds, :data:`REST_GAIN_SETTLE_S`
    after B's gains last changed; None without K_h telemetry or hold samples.

    The same: the integral carrying force or not as in most of the hold, with the same threshold
    theta when it does (within :data:`REST_THETA_M`), and the steady compliance
    (:func:`steady_coupling_compliance`) within :data:`REST_COUPLING_SHARE` / K_h of the hold's
    (medians). A change: K_h, I or C_h by more than :data:`GAIN_CHANGE_SHARE`, or to a coupling
    that differs. Telemetry without ``own_gain_m_per_n`` (recorded before it was kept) is taken
    as uncompensated.
    """
    kh = b.get("k_h_n_per_m")
    if kh is None or not hold_mask.any():
        return None
    ig = b.get("i_gain_n_per_m_s", np.zeros_like(kh))
    own = b.get("own_gain_m_per_n")
    holds = _integral_holds(ig, b.get("integral_n"))
    c = steady_coupling_compliance(kh, ig, own, b.get("integral_n"))
    k_hold = float(np.median(kh[hold_mask]))
    c_hold = float(np.median(c[hold_mask]))
    holds_hold = bool(np.mean(holds[hold_mask]) >= 0.5)
    with np.errstate(invalid="ignore"):
        same = (np.abs(c - c_hold) <= REST_COUPLING_SHARE / max(k_hold, 1.0)) & (
            holds == holds_hold
        )
    theta = b.get("theta_m")
    if holds_hold and theta is not None:
        th_hold = float(np.median(theta[hold_mask]))
        same &= np.abs(theta - th_hold) <= REST_THETA_M
    stepped = _stepped(kh) | _stepped(ig) | (_stepped(own) if own is not None else False)
    last_other = np.maximum.accumulate(np.where(same & ~stepped, -np.inf, b["t_s"]))
    return same & (b["t_s"] - last_other >= REST_GAIN_SETTLE_S)


def coupling_report(
    b: dict[str, np.ndarray],
    tl: Timeline,
    hold: tuple[float, float],
    b_approach_end_s: float,
) -> dict[str, Any]:
    """How much B feels A's press, as physical quantities.

    ``b_force_rise_n``: B's force while A holds minus B's resting force [N].
    ``b_feels_a``: that change is at least :data:`FEEL_FORCE_SHARE` of the resting force, the
    surface under B moved at least :data:`FEEL_DISPLACEMENT_MM`, and the force followed the
    surface (rose as it bulged out, fell as it was drawn in); None when not measured.
    ``b_surface_displacement_mm``: how far the surface under B (B's proxy) moves outward, along
    B's force, while A holds [mm]. Both compare the ``hold`` window with a window where B rests,
    settled (``b_settled_s``, :func:`landing_settled_s`: :data:`B_SETTLE_S` after B's force came
    on after B's approach, later if B's landing bounced; ``b_landing_p2p_mm``: how far), before
    A touches (or, failing that, after A's release: ``baseline`` says which). While A holds, samples where
    B is out of contact count too (force 0): a side drawn in by A's press can leave B's finger.
    ``b_force_lowest_as_a_arrives_n``: B's lowest force in the :data:`ARRIVAL_WINDOW_S` after A
    touches, and ``b_force_dip_as_a_arrives_n`` how far that is below
    ``b_force_before_a_arrives_n``, B's force in the half second before [N] (only when B had
    settled by then; about 0 when B feels only A's push). ``ratio`` is B's force while
    A holds over B's resting force: it depends on how hard B leans in (its hand depth beyond the
    threshold θ), not on the object; the two above are the coupling.

    Parameters
    ----------
    b : dict of (m,) arrays
        B's telemetry, times on A's clock.
    tl : Timeline
        A's press.
    hold : (t0, t1)
        The end of A's hold [s, A's clock].
    b_approach_end_s : float
        When B's hand reaches the side [s, A's clock].
    """
    on = (b["in_contact"] > 0) & (b["force_n"] > B_FORCE_ON_N) & (b["t_s"] >= b_approach_end_s)
    onset = float(b["t_s"][np.argmax(on)]) if on.any() else None
    settled_at, landing_mm = (None, None) if onset is None else landing_settled_s(b, onset)
    out: dict[str, Any] = {
        "b_force_rise_n": None,
        "b_surface_displacement_mm": None,
        "b_feels_a": None,
        "b_force_at_rest_n": None,
        "b_force_during_a_press_n": None,
        "ratio": None,
        "ratio_is": "B's force while A holds / B's force at rest; set by how hard B rests (its "
        "hand depth beyond the threshold theta), not by the object",
        "baseline": None,
        "rest_window_s": None,
        "hold_window_s": [hold[0], hold[1]],
        "b_force_before_a_arrives_n": None,
        "b_force_lowest_as_a_arrives_n": None,
        "b_force_dip_as_a_arrives_n": None,
        "b_settled_s": settled_at,
        "b_landing_p2p_mm": landing_mm,
    }
    # samples with B in contact at full force (no ramp in or out, no fault)
    steady = b.get("force_scale", np.ones_like(b["t_s"])) >= 0.999
    full = (b["in_contact"] > 0) & steady
    # while A holds, also the samples where the surface drew away from B's finger (B's force
    # fell to nothing: the strongest change B can feel; the proxy is still the surface)
    w_hold = _window(b, *hold) & steady
    # as A arrives: B's force just before, against its lowest in the second after
    w_pre = _window(b, tl.contact_s - 0.5, tl.contact_s - 0.05) & full
    w_arrive = _window(b, tl.contact_s, tl.contact_s + ARRIVAL_WINDOW_S)
    if (
        settled_at is not None
        and settled_at <= tl.contact_s - 0.5
        and w_pre.any()
        and w_arrive.any()
    ):
        before = float(np.nanmean(b["force_n"][w_pre]))
        lowest = float(np.nanmin(b["force_n"][w_arrive]))
        out.update(
            b_force_before_a_arrives_n=before,
            b_force_lowest_as_a_arrives_n=lowest,
            b_force_dip_as_a_arrives_n=before - lowest,
        )
    usable = _same_coupling(b, w_hold)
    found = None if settled_at is None else _rest_window(b, tl, settled_at, usable)
    if found is None or not w_hold.any():
        return out
    baseline, rest = found
    w_rest = _window(b, *rest) & full
    if usable is not None:
        w_rest &= usable
    if not w_rest.any():
        return out
    fvec = np.stack([b["force_x_n"], b["force_y_n"], b["force_z_n"]], axis=1)[w_rest]
    outward = np.nanmean(fvec, axis=0)  # the force on B's hand points out of the surface
    outward = outward / np.linalg.norm(outward)
    # the object's surface: the rendered proxy, less any own-force compensation offset, where no
    # change of gains is being carried over (:func:`in_gain_transfer`)
    proxy = np.stack([b["proxy_x_m"], b["proxy_y_m"], b["proxy_z_m"]], axis=1) @ outward
    proxy = proxy - b.get("own_offset_m", np.zeros_like(proxy))
    settled = ~in_gain_transfer(b)
    s_hold = w_hold & settled if (w_hold & settled).any() else w_hold
    s_rest = w_rest & settled if (w_rest & settled).any() else w_rest
    f_rest = float(np.nanmean(b["force_n"][w_rest]))
    f_hold = float(np.nanmean(b["force_n"][w_hold]))
    moved_mm = float((np.nanmean(proxy[s_hold]) - np.nanmean(proxy[s_rest])) * 1000.0)
    rise = f_hold - f_rest
    out.update(
        b_force_rise_n=rise,
        b_surface_displacement_mm=moved_mm,
        b_feels_a=bool(
            abs(rise) >= FEEL_FORCE_SHARE * f_rest
            and abs(moved_mm) >= FEEL_DISPLACEMENT_MM
            and rise * moved_mm > 0.0
        ),
        b_force_at_rest_n=f_rest,
        b_force_during_a_press_n=f_hold,
        ratio=f_hold / f_rest if f_rest > 1e-9 else None,
        baseline=baseline,
        rest_window_s=[rest[0], rest[1]],
        b_k_h_at_rest_n_per_m=float(np.nanmedian(b["k_h_n_per_m"][w_rest]))
        if "k_h_n_per_m" in b
        else None,
        b_k_h_during_a_press_n_per_m=float(np.nanmedian(b["k_h_n_per_m"][w_hold]))
        if "k_h_n_per_m" in b
        else None,
    )
    return out


def verdict_line(name: str, u: dict[str, Any]) -> str:
    """One user's verdict in plain words (the last lines ``haptic demo`` prints)."""
    verdict = u.get("verdict", "stable" if u.get("stable") else "unstable")
    reasons = "; ".join(u.get("verdict_reasons") or [])
    if verdict == "stable":
        spans = u.get("hold_window_s") or []
        held = sum(t1 - t0 for t0, t1 in spans)
        shake = u.get("hold_oscillation_mm")
        felt = u.get("felt_stiffness")
        parts = [f"over its {held:.1f} s hold"]
        if shake is not None:
            parts.append(f"the probe stayed within {shake:.2f} mm peak to peak")
        if felt is not None:
            parts.append(
                f"the felt stiffness within x{felt['ratio']:.2f} "
                f"({felt['low_n_per_m']:.0f}-{felt['high_n_per_m']:.0f} N/m; "
                f"a hand tells {felt['jnd']:.0%} apart)"
            )
        line = f"{name}: stable: " + ", ".join(parts)
        if felt is not None and felt["high_n_per_m"] * (1.0 + felt["jnd"]) < felt["k_o_n_per_m"]:
            line += (
                f"; softer than the object throughout ({felt['k_o_n_per_m']:.0f} N/m): "
                "conservative gains"
            )
        return line
    return f"{name}: {verdict.upper()}: {reasons}"


def print_summary(report: dict[str, Any]) -> None:
    """A readable table of the report, ending with each user's verdict in plain words."""
    print()
    print(
        f"{'user':<6}{'servo Hz':>10}{'p99 us':>9}{'missed/s':>10}{'max N':>8}"
        f"{'hold p2p mm':>13}{'felt step':>11}  verdict"
    )
    for name, u in report["users"].items():
        rate = u["servo_rate_hz"] or float("nan")
        p99 = u["period_us_p99"] or float("nan")
        missed = u.get("servo_missed_per_s")
        missed = float("nan") if missed is None else missed
        shake = u.get("hold_oscillation_mm")
        felt = u.get("felt_stiffness")
        shake_s = "-" if shake is None else f"{shake:.3f}"
        felt_s = "-" if felt is None else f"x{felt['ratio']:.2f}"
        print(
            f"{name:<6}{rate:>10.1f}{p99:>9.0f}{missed:>10.2f}{u['max_force_n']:>8.2f}"
            f"{shake_s:>13}{felt_s:>11}  {u.get('verdict', '?')}"
        )
    ref = report.get("reference_loop")
    if ref:
        print(
            f"{'ref':<6}{ref.get('rate_hz') or float('nan'):>10.1f}"
            f"{ref.get('period_p99_us') or float('nan'):>9.0f}"
            f"{ref.get('missed_per_s') or 0.0:>10.2f}  (a do-nothing loop beside the users)"
        )
    for line in coupling_lines(report["coupling"]):
        print(line)
    s, n = report["server"], report["network"]
    print(
        f"server: {s['sim_rate_hz']:g} Hz, a tick took {s['tick_ms_p50'] or 0:.2f} ms "
        f"(p99 {s['tick_ms_p99'] or 0:.2f} ms), {s['overruns'] or 0} overran; network round trip "
        f"{n['rtt_ms_p50'] or 0:.1f} ms (p99 {n['rtt_ms_p99'] or 0:.1f} ms)"
    )
    for name, u in report["users"].items():
        print(verdict_line(name, u))


def coupling_lines(c: dict[str, Any]) -> list[str]:
    """Whether B felt A's press, in plain sentences (the :func:`coupling_report` dict ``c``).

    What a newcomer reads: did B feel A, how far the side under B moved [mm] and how B's force
    changed [N]; where B's resting force was measured; and whether B's force dipped as A arrived
    (B should only feel a rise).
    """
    landing = c.get("b_landing_p2p_mm")
    bounce = (
        [
            f"  (B's hand bounced {landing:.1f} mm peak to peak as it landed, as a hand does on "
            f"a soft solid its landing sets ringing; B counts as settled from "
            f"{c['b_settled_s']:.1f} s on A's clock, when a bounce decaying at the gain design's "
            f"margin, {MIN_DECAY_RATE_PER_S:g}/s, is under {STABLE_P2P_MM:g} mm.)"
        ]
        if landing is not None and landing >= STABLE_P2P_MM and c.get("b_settled_s") is not None
        else []
    )
    if c["b_force_rise_n"] is None:
        return [
            "B feels A's press: not measured (B's contact never settled outside A's press, so "
            "there is no resting force to compare with).",
            *bounce,
        ]
    w = c["rest_window_s"]
    rest, hold = c["b_force_at_rest_n"], c["b_force_during_a_press_n"]
    rise, moved = c["b_force_rise_n"], c["b_surface_displacement_mm"]
    share = f" ({rise / rest:+.0%})" if rest > 1e-9 else ""
    way = "outward" if moved >= 0.0 else "inward"
    rises = "rose" if rise >= 0.0 else "fell"
    answer = "yes" if c.get("b_feels_a") else "no"
    lines = [
        f"B feels A's press: {answer}. While A held, the side under B moved "
        f"{abs(moved):.2f} mm {way} and B's force {rises} from {rest:.3f} N to {hold:.3f} N"
        f"{share}; a hand notices about {FEEL_FORCE_SHARE:.0%}.",
        f"  (B's force at rest was measured {c['baseline']}, {w[0]:.1f}-{w[1]:.1f} s on A's "
        "clock.)",
        *bounce,
    ]
    lowest = c.get("b_force_lowest_as_a_arrives_n")
    if lowest is not None:
        before, dip = c["b_force_before_a_arrives_n"], c["b_force_dip_as_a_arrives_n"]
        if dip > FEEL_FORCE_SHARE * before:
            lines.append(
                f"  As A arrived, B's force dipped from {before:.3f} N to {lowest:.3f} N for a "
                f"moment ({dip:.3f} N less); it should only have risen."
            )
        else:
            lines.append(
                f"  As A arrived, B's force held: {before:.3f} N just before, never below "
                f"{lowest:.3f} N in the second after."
            )
    return lines


def run_verdict_line(report: dict[str, Any]) -> str:
    """The run's verdict in one line: the verdict, each user's, whether B felt A, the exit status.

    The verdict and its exit status are :func:`run_verdict`'s (in ``report["verdict"]``); this
    only says them.
    """
    v = report["verdict"]
    code = int(v["exit_code"])
    who = ", ".join(
        f"{name} {'could not be judged' if verdict == 'could not judge' else verdict}"
        for name, verdict in v["users"].items()
    )
    feels = report.get("coupling", {}).get("b_feels_a")
    felt = (
        "B felt A's press"
        if feels
        else "B's feeling of A was not measured"
        if feels is None
        else "B did not feel A's press"
    )
    return f"verdict: {v['verdict']} ({who}; {felt}; exit status {code}: {EXIT_MEANING[code]})"


def plot_demo(work: Path, tl: Timeline, path: Path, subject: str = "water balloon") -> None:
    """PNG of both users' probe, proxy and force over time (A's press and B's response);
    ``subject`` names the object in the title (``haptic_collab.demo.object_title``: e.g.
    ``FEM liver, gravity 9.81 m/s^2`` for a solid sagged under its own weight)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from haptic_collab.client.recorder import plot_probe_proxy

    a, a_sum = _load(work, "A")
    b, b_sum = _load(work, "B")
    shift = b_sum["clock_origin_s"] - a_sum["clock_origin_s"]
    fig, axes = plt.subplots(3, 1, figsize=(11, 9), sharex=True)
    for ax, cols, name, dt in (
        (axes[0], a, "A (presses the top)", 0.0),
        (axes[1], b, "B (rests on the side)", shift),
    ):
        plot_probe_proxy(ax, cols, dt)
        ax.set_title(f"user {name}")
    axes[2].plot(a["t_s"], a["force_n"], label="A", color="tab:purple")
    axes[2].plot(b["t_s"] + shift, b["force_n"], label="B", color="tab:green")
    axes[2].set_ylabel("force on the user [N]")
    axes[2].set_xlabel("time [s] (A's clock)")
    axes[2].grid(alpha=0.3)
    axes[2].legend(loc="upper left")
    for ax in axes:
        ax.axvspan(tl.contact_s, tl.hold_end_s, color="0.9", zorder=0)
    axes[0].text(tl.contact_s + 0.1, axes[0].get_ylim()[1] * 0.9, "A presses and holds", va="top")
    fig.suptitle(f"Two users on a shared {subject}: B feels A's press")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ----------------------------------------------------------------------------------- palpation
#: Half-width [rad] of the stretch of A's sweep that counts as over the lump (or beside it): 5
#: degrees, 8.7 mm on the 0.1 m sphere, about the finger pad's radius.
PALPATION_WINDOW_RAD = math.radians(5.0)


def _angle_to(points: np.ndarray, direction: Sequence[float]) -> np.ndarray:
    """The angle [rad] between each point (P, 3) [m], seen from the origin, and ``direction``."""
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    r = np.linalg.norm(points, axis=1)
    cos = np.clip(points @ d / np.where(r > 0.0, r, 1.0), -1.0, 1.0)
    return np.arccos(cos)


def palpation_report(
    work: Path,
    sweep: Sweep,
    over: Sequence[float],
    beside: Sequence[float],
) -> dict[str, Any]:
    """What A felt sweeping over the lump, and what B felt of it (``haptic demo --scenario
    palpation``).

    A's samples in contact during the slide (out and back: ``sweep.slide_s``) whose probe, seen
    from the sphere's centre, is within :data:`PALPATION_WINDOW_RAD` of ``over`` (the lump) or of
    ``beside`` (its twin, the mirror point): the mean force [N]; the probe's *indentation*, its
    depth under the rest sphere (``sweep.radius_m`` about ``sweep.centre``) [mm]; and their
    ratio, the stiffness A feels there [N/m]. ``rise`` is the felt stiffness over the lump over
    the one beside it less 1: how much more force the same indentation takes over the lump (the
    solid is linear, F = K_o d); ``felt`` whether it exceeds the stiffness JND
    (:data:`STIFFNESS_JND`). ``force_rise_at_hand_depth`` is the mean force's rise at the hand's
    same target depth: the hand's own compliance in series makes it about half the stiffness's
    (docs/palpation.md). ``penetration_mm`` is the probe's depth behind its proxy. B: its force [N] before A touched (median) and its range (5th to
    95th percentile) while A slid: B feels the sweep when that range exceeds
    :data:`FEEL_FORCE_SHARE` of its resting force.

    Returns
    -------
    dict
        ``a_over``, ``a_beside`` (``force_n``, ``indentation_mm``, ``stiffness_n_per_m``,
        ``penetration_mm``, ``samples``; None where A never passed), ``rise``, ``felt``,
        ``force_rise_at_hand_depth``, ``b_rest_force_n``, ``b_force_range_in_sweep_n``,
        ``b_felt_sweep``.
    """
    a, a_sum = _load(work, "A")
    b, b_sum = _load(work, "B")
    t0, t1 = sweep.slide_s
    sliding = (a["t_s"] >= t0) & (a["t_s"] <= t1) & (a["in_contact"] > 0)
    probe = np.stack([a["probe_x_m"], a["probe_y_m"], a["probe_z_m"]], axis=1)
    probe = probe - np.asarray(sweep.centre, dtype=float)
    indentation = float(sweep.radius_m) - np.linalg.norm(probe, axis=1)

    def near(direction: Sequence[float]) -> dict[str, Any] | None:
        m = sliding & (_angle_to(probe, direction) < PALPATION_WINDOW_RAD)
        if not m.any():
            return None
        f, d = float(np.mean(a["force_n"][m])), float(np.mean(indentation[m]))
        return {
            "force_n": f,
            "indentation_mm": d * 1e3,
            "stiffness_n_per_m": f / d if d > 0.0 else None,
            "penetration_mm": float(np.mean(a["penetration_m"][m])) * 1e3,
            "samples": int(m.sum()),
        }

    a_over, a_beside = near(over), near(beside)
    rise = force_rise = None
    if a_over is not None and a_beside is not None:
        if a_over["stiffness_n_per_m"] and a_beside["stiffness_n_per_m"]:
            rise = a_over["stiffness_n_per_m"] / a_beside["stiffness_n_per_m"] - 1.0
        if a_beside["force_n"] > 0.0:
            force_rise = a_over["force_n"] / a_beside["force_n"] - 1.0
    shift = b_sum["clock_origin_s"] - a_sum["clock_origin_s"]
    tb = b["t_s"] + shift
    before = (tb < sweep.delay_s) & (b["in_contact"] > 0)
    during = (tb >= t0) & (tb <= t1) & (b["in_contact"] > 0)
    b_rest = float(np.median(b["force_n"][before])) if before.any() else None
    b_range = (
        float(np.percentile(b["force_n"][during], 95) - np.percentile(b["force_n"][during], 5))
        if during.any()
        else None
    )
    return {
        "over_direction": [float(v) for v in over],
        "beside_direction": [float(v) for v in beside],
        "window_deg": math.degrees(PALPATION_WINDOW_RAD),
        "hand_depth_mm": sweep.depth_m * 1e3,
        "slide_s": [t0, t1],
        "a_over": a_over,
        "a_beside": a_beside,
        "rise": rise,
        "felt": None if rise is None else bool(rise > STIFFNESS_JND),
        "force_rise_at_hand_depth": force_rise,
        "b_rest_force_n": b_rest,
        "b_force_range_in_sweep_n": b_range,
        "b_felt_sweep": (
            None
            if b_rest is None or b_range is None
            else bool(b_range > FEEL_FORCE_SHARE * max(b_rest, B_FORCE_ON_N))
        ),
    }


def palpation_lines(p: dict[str, Any]) -> list[str]:
    """The palpation scenario's result in plain sentences (the :func:`palpation_report` dict)."""
    over, beside = p.get("a_over"), p.get("a_beside")
    if over is None or beside is None or p.get("rise") is None:
        return ["palpation: A's sweep never passed both over the lump and beside it in contact"]
    felt = "felt it" if p["felt"] else "did not feel it (under the stiffness JND)"
    lines = [
        f"palpation: A felt {over['stiffness_n_per_m']:.0f} N/m over the lump and "
        f"{beside['stiffness_n_per_m']:.0f} N/m beside it (force per depth under the surface, "
        f"{over['indentation_mm']:.1f} and {beside['indentation_mm']:.1f} mm): "
        f"{100.0 * p['rise']:+.0f} %, A {felt}."
    ]
    if p.get("force_rise_at_hand_depth") is not None:
        lines.append(
            f"At the same hand depth that is {over['force_n']:.2f} N against "
            f"{beside['force_n']:.2f} N ({100.0 * p['force_rise_at_hand_depth']:+.0f} %): the "
            "hand's own give takes up part of it."
        )
    if p.get("b_force_range_in_sweep_n") is not None and p.get("b_rest_force_n") is not None:
        lines.append(
            f"B's force moved over {p['b_force_range_in_sweep_n']:.3f} N while A swept "
            f"(resting {p['b_rest_force_n']:.3f} N): B "
            f"{'felt' if p['b_felt_sweep'] else 'did not feel'} A's sweep."
        )
    return lines
