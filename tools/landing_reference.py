"""What a resting hand's landing does on the FEM solid itself: the reference for a demo's bounce.

``python tools/landing_reference.py [--hand-mass KG --hand-damping NS --hand-stiffness NM]
[--demo-csv WORK/B.csv] [--json FILE]`` lands the demo's resting user B (``sim:rest``: the hand
target from 30 mm outside the side of the liver ball to 2 mm inside it in 1 s,
:class:`client.devices.trajectories.Rest`; the simulated Phantom Desktop's mass and damping added
to the hand's, as :class:`client.devices.sim.SimDevice` moves them) on the default FEM solid
(``haptic server --object fem``: the 642-vertex liver sphere, P2/P0, the liver preset) coupled
directly at 1 kHz: the solid stepped every millisecond (every mode moving), the finger pad a
punch on a spring (``--pad-stiffness``, ``--pad-damping``) whose force is solved each tick with
the solid's own one-tick response (:meth:`server.objects.fem.FemSolid.checkpoint`), no delay, no
local model, no gains. That is the object and the hand alone: what a user's hand would do on
such a ball, which the product's rendering is compared with.

It prints, and writes with ``--json``, the probe's peak to peak along the contact normal in each
half second after the landing (after each window's straight-line trend, as the demo report
judges a hold: :data:`haptic_collab.demo_report.SHAKE_WINDOW_S`), when the report's rule counts
B as settled (:func:`haptic_collab.demo_report.landing_settled_s`) and the largest peak to peak
after that; with ``--demo-csv`` the same figures from a demo's telemetry (B's ``B.csv`` in the
demo's ``--workdir``) side by side. Not a test: the measurement behind docs/palpation.md.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

HALVES = 12  # half seconds after the landing reported


def _p2p_after_landing(t: np.ndarray, x: np.ndarray, t_land: float) -> list[float]:
    """Peak to peak [mm] of ``x`` [m] in each half second after ``t_land``, after its trend."""
    out = []
    for i in range(HALVES):
        w = (t >= t_land + 0.5 * i) & (t < t_land + 0.5 * (i + 1))
        if w.sum() < 3:
            break
        tw, xw = t[w] - t[w][0], x[w]
        out.append(float(np.ptp(xw - np.polyval(np.polyfit(tw, xw, 1), tw))) * 1000.0)
    return out


def _judged(t: np.ndarray, x: np.ndarray, cols: dict[str, np.ndarray], t_land: float) -> dict:
    """When the demo report counts this landing settled, and the largest shake after it."""
    from haptic_collab.demo_report import STABLE_P2P_MM, landing_settled_s, largest_p2p

    settled, bounced = landing_settled_s(cols, t_land)
    after, _ = largest_p2p(t, x, (t >= settled) & (t < t_land + 0.5 * HALVES))
    before, _ = largest_p2p(t, x, (t >= t_land + 1.0) & (t < t_land + 0.5 * HALVES))
    return {
        "landing_p2p_mm": bounced,
        "settled_after_landing_s": settled - t_land,
        "largest_p2p_after_settled_mm": after * 1000.0,
        "largest_p2p_from_1_s_mm": before * 1000.0,
        "steady_from_settled": bool(after * 1000.0 < STABLE_P2P_MM),
    }


def reference(args: argparse.Namespace) -> dict[str, Any]:
    """Land the hand on the solid at 1 kHz (module docstring)."""
    from haptic_collab.client.devices.profiles import get_sim_profile
    from haptic_collab.client.devices.trajectories import Rest
    from haptic_collab.research.harness_3d import PROFILE
    from haptic_collab.server.objects.fem import FemParams, FemSolid, sphere_for_solid
    from haptic_collab.server.solid_materials import SOLID_PRESETS, solid_to_params

    period = 1e-3
    params = solid_to_params(SOLID_PRESETS["liver"], FemParams(sim_period_s=period))
    mesh, element = sphere_for_solid(4)
    solid = FemSolid(mesh, replace(params, element=element))
    anchor, normal = np.array([0.1, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])
    key = solid.patch_key(anchor, normal=normal)
    patch = solid.patch(key)
    idx, w, n = patch.indices, patch.weights, patch.normal
    k_o = float(solid.contact_stiffness([key])[0])
    b_o = float(solid.contact_damping([key])[0])
    c_tick = 1.0 / (k_o + b_o)  # the surface's give in one tick under a held push [m/N]

    def surface() -> float:
        return float(w @ (solid.vertices[idx] @ n))

    prof = get_sim_profile(PROFILE)
    mass = args.hand_mass + prof.mass_kg
    k_hand, b_hand, b_dev = args.hand_stiffness, args.hand_damping, prof.limits.damping_n_s_per_m
    rest = Rest(tuple(anchor), tuple(normal))
    rest_at = surface()
    x = float(np.asarray(rest(0.0)) @ normal)
    v = 0.0
    sub = 10  # the hand's own integration steps a tick
    rows = []
    for tick in range(round(args.duration / period)):
        t = tick * period
        mark = solid.checkpoint()
        solid.step([key], [0.0])
        free = surface()  # where the surface would be after this tick with no push
        solid.rewind(mark)
        # the pad spring's force equals the push that leaves the surface there
        f = max(0.0, (args.pad_stiffness * (free - x) - args.pad_damping * v))
        f /= 1.0 + args.pad_stiffness * c_tick
        solid.step([key], [f])
        # the simulated hand: a spring-damper to its target's position and velocity, the
        # device's damping to ground (client.devices.sim.SimDevice)
        target = float(np.asarray(rest(t)) @ normal)
        v_target = (float(np.asarray(rest(t + period)) @ normal) - target) / period
        h = period / sub
        for _ in range(sub):
            a = k_hand * (target - x) + b_hand * (v_target - v) - b_dev * v + f
            v += a / mass * h
            x += v * h
        rows.append((t, x, surface(), f))
    t, xs, ss, fs = np.array(rows).T
    t_land = float(t[np.argmax(fs > 0.0)])
    cols = _cols(t, xs * normal[0], fs * normal[0], fs > 0.0)
    return {
        "k_o_n_per_m": k_o,
        "b_o_one_ms_n_per_m": b_o,
        "rest_surface_m": rest_at,
        "landing_s": t_land,
        "landing_speed_m_s": _speed_at(t, xs, t_land),
        "probe_p2p_mm_each_half_second": _p2p_after_landing(t, xs, t_land),
        "surface_p2p_mm_each_half_second": _p2p_after_landing(t, ss, t_land),
        "force_n_last_second": float(np.mean(fs[t >= t[-1] - 1.0])),
        **_judged(t, xs, cols, t_land),
    }


def _speed_at(t: np.ndarray, x: np.ndarray, t_land: float) -> float:
    i = int(np.searchsorted(t, t_land))
    j = max(i - 10, 0)
    return float(abs(x[i] - x[j]) / max(t[i] - t[j], 1e-9))


def _cols(t: np.ndarray, px: np.ndarray, fx: np.ndarray, contact: np.ndarray) -> dict:
    zero = np.zeros_like(t)
    return {
        "t_s": t, "probe_x_m": px, "probe_y_m": zero, "probe_z_m": zero,
        "force_x_n": fx, "force_y_n": zero, "force_z_n": zero, "force_n": np.abs(fx),
        "in_contact": contact.astype(float),
    }  # fmt: skip


def from_demo(csv_path: Path) -> dict[str, Any]:
    """The same figures from a demo's B telemetry (its clock; the landing: B's first force)."""
    from haptic_collab.demo_report import contact_normal

    header = csv_path.read_text().split("\n", 1)[0].strip().split(",")
    data = np.loadtxt(csv_path, delimiter=",", skiprows=1, ndmin=2)
    cols = {h: data[:, i] for i, h in enumerate(header)}
    t = cols["t_s"]
    on = (cols["in_contact"] > 0) & (cols["force_n"] > 0.0)
    t_land = float(t[np.argmax(on)])
    normal = contact_normal(cols, on)
    if normal is None:
        raise SystemExit(f"{csv_path}: no force, no landing")
    x = np.stack([cols["probe_x_m"], cols["probe_y_m"], cols["probe_z_m"]], axis=1) @ normal
    return {
        "csv": str(csv_path),
        "landing_s": t_land - float(t[0]),
        "landing_speed_m_s": _speed_at(t, x, t_land),
        "probe_p2p_mm_each_half_second": _p2p_after_landing(t, x, t_land),
        **_judged(t, x, cols, t_land),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hand-mass", type=float, default=0.6, help="[kg] (the box's heaviest)")
    ap.add_argument("--hand-damping", type=float, default=2.0, help="[N*s/m] (the box's least)")
    ap.add_argument("--hand-stiffness", type=float, default=20.0, help="[N/m] (the loosest)")
    ap.add_argument("--pad-stiffness", type=float, default=1000.0, help="[N/m]")
    ap.add_argument("--pad-damping", type=float, default=5.0, help="[N*s/m]")
    ap.add_argument("--duration", type=float, default=7.0, help="[s]")
    ap.add_argument("--demo-csv", type=Path, default=None, help="a demo's B.csv to set beside")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    out: dict[str, Any] = {
        "how": "tools/landing_reference.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "hand": {
            "mass_kg": args.hand_mass, "damping_n_s_per_m": args.hand_damping,
            "stiffness_n_per_m": args.hand_stiffness,
        },
        "pad": {"stiffness_n_per_m": args.pad_stiffness, "damping_n_s_per_m": args.pad_damping},
        "reference_1khz_no_delay": reference(args),
    }  # fmt: skip
    if args.demo_csv is not None:
        out["demo"] = from_demo(args.demo_csv)
    for name in ("reference_1khz_no_delay", "demo"):
        if name in out:
            r = out[name]
            halves = " ".join(f"{p:.2f}" for p in r["probe_p2p_mm_each_half_second"])
            print(
                f"{name}: landing at {r['landing_speed_m_s'] * 1000:.0f} mm/s; probe p2p [mm] "
                f"each 0.5 s after: {halves}; settled {r['settled_after_landing_s']:.2f} s "
                f"after landing, largest p2p after {r['largest_p2p_after_settled_mm']:.2f} mm "
                f"(from 1 s: {r['largest_p2p_from_1_s_mm']:.2f} mm)"
            )
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0 if math.isfinite(out["reference_1khz_no_delay"]["k_o_n_per_m"]) else 1


if __name__ == "__main__":
    sys.exit(main())
