"""The product's gains for a FEM contact, checked on the solid's own slow modes.

``python tools/modal_loop_check.py [--at side|top] [--delays 0 1 2] [--modes 20] [--direct]
[--json FILE]``
builds the default FEM solid (``haptic server --object fem``: the liver sphere), reads K_o and
B_o at the contact as the server reports them, designs the product's gains for that contact as
``haptic gains --local-model p`` does (own-force compensation, the simulated Phantom Desktop's
limits; the shipped tables hold the same designs), and judges them twice at each delay: on the
loop the design checks (:func:`shared.full_loop.monodromy`, the object as eq. 9's K_o and B_o)
and on the same loop closed over the contact's modes (:func:`shared.modal_loop.modal_monodromy`,
the ``--modes`` of largest dynamic response, the rest static:
:meth:`shared.modal_loop.ContactModes.reduced`). It prints, and writes with ``--json``, the
slowest decay rate [1/s] per hand of the design's box (:func:`shared.coupled_loop.
verification_hands`) and for the demo's heavy, loosely held hand with the device's mass and
damping, beside the design's margin and the solid's own slowest decay; with ``--direct``, each
hand held on the solid itself at 1 kHz through a finger pad, with no product between
(:func:`shared.modal_loop.direct_decay_rates`): what the rates are to be judged against. Each
row also gives what the server recommends instead since the modal guard
(:func:`shared.gains.modal_guard.guard`, as :meth:`server.gains.GainAdvisor.guard_modes` runs it:
the table's design for the key the server makes, on the server's
:data:`shared.gains.policy.MODAL_CHECK_MODES`) and its rates the same two ways (on ``--modes``),
and on the solid's modes over the box's whole lattice of hands
(:meth:`shared.full_loop.HandBox.hands`, as the guard checks). Not a test: the measurement behind
docs/fem.md and docs/palpation.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

POINTS = {"side": ((0.1, 0.0, 0.0), (1.0, 0.0, 0.0)), "top": ((0.0, 0.0, 0.1), (0.0, 0.0, 1.0))}


def direct(at: str, hands: list[Any], pad: tuple[float, float]) -> list[float]:
    """The slowest decay rate [1/s] of each hand held on the solid itself (no product between):
    :func:`shared.modal_loop.direct_decay_rates` on the same solid stepped every millisecond."""
    from haptic_collab.server.objects.fem import FemParams, FemSolid, sphere_for_solid
    from haptic_collab.server.solid_materials import SOLID_PRESETS, solid_to_params
    from haptic_collab.shared.modal_loop import direct_decay_rates

    params = solid_to_params(SOLID_PRESETS["liver"], FemParams(sim_period_s=1e-3))
    mesh, element = sphere_for_solid(4)
    solid = FemSolid(mesh, replace(params, element=element))
    point, normal = POINTS[at]
    modes = solid.contact_modes(solid.patch_key(point, normal=normal))
    rates = direct_decay_rates(
        hands=hands, modes=modes, pad_stiffness_n_per_m=pad[0], pad_damping_n_s_per_m=pad[1],
        period_s=1e-3,
    )  # fmt: skip
    return [float(r) for r in rates]


def check(
    at: str, delays: list[int], mode_count: int, pad: tuple[float, float] | None = None
) -> dict[str, Any]:
    """The module docstring's measurement at contact ``at``."""
    from haptic_collab.cli.design import _profile_design
    from haptic_collab.client.devices.profiles import get_sim_profile
    from haptic_collab.research.harness_3d import PROFILE
    from haptic_collab.server.objects.fem import FemParams, FemSolid, sphere_for_solid
    from haptic_collab.server.solid_materials import SOLID_PRESETS, solid_to_params
    from haptic_collab.shared.coupled_loop import verification_hands
    from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX, Hand, monodromy
    from haptic_collab.shared.gains.key import make_gain_key
    from haptic_collab.shared.gains.modal_guard import ModalCase, guard
    from haptic_collab.shared.gains.policy import (
        K_O_GRID_RATIO,
        MIN_DECAY_RATE_PER_S,
        MODAL_CHECK_MODES,
    )
    from haptic_collab.shared.gains.table import GainTable
    from haptic_collab.shared.modal_loop import decay_rate_per_s, decay_rates, modal_decay_rates

    params = solid_to_params(SOLID_PRESETS["liver"], FemParams())
    mesh, element = sphere_for_solid(4)
    solid = FemSolid(mesh, replace(params, element=element))
    point, normal = POINTS[at]
    key = solid.patch_key(point, normal=normal)
    k_o = float(solid.contact_stiffness([key])[0])
    b_o = float(solid.contact_damping([key])[0])
    full = solid.contact_modes(key)
    modes = full.reduced(mode_count)
    period = params.sim_period_s
    alone = decay_rate_per_s(float(np.abs(np.linalg.eigvals(full.a)).max()), period)
    prof = get_sim_profile(PROFILE)
    heavy = Hand(
        mass_kg=0.6 + prof.mass_kg,
        damping_n_s_per_m=2.0 + prof.limits.damping_n_s_per_m,
        stiffness_n_per_m=20.0,
    )
    hands = [*verification_hands(DEFAULT_HAND_BOX), heavy]
    names = [
        f"{h.mass_kg:g} kg, {h.damping_n_s_per_m:g} N*s/m, {h.stiffness_n_per_m:g} N/m"
        for h in hands
    ]
    rows = []
    for d in delays:
        design = _profile_design(PROFILE, k_o, paper=False, b_o=b_o, delay_ticks=d, mode="p")
        gains = {
            "k_h": design.k_h, "b_h": design.b_h, "own_gain": design.own_gain,
            "proxy_hold": design.proxy_hold,
        }  # fmt: skip
        m9 = monodromy(hand=hands, k_o=k_o, b_o=b_o, delay_ticks=d, **gains)
        eq9 = decay_rates(m9).tolist()
        modal = modal_decay_rates(hands=hands, modes=modes, delay_ticks=d, **gains)
        key_d = make_gain_key(
            servo_rate_hz=1000.0, sim_rate_hz=1.0 / period, delay_ticks=d, mode="p",
            margin=0.15, k_h_max=prof.limits.max_stiffness_n_per_m,
            b_h_max=prof.limits.max_damping_n_s_per_m, b_o=b_o, stiff_ratio=1.0,
        )  # fmt: skip
        cell = GainTable(DEFAULT_HAND_BOX, K_O_GRID_RATIO).cell(k_o)
        server_modes = full.reduced(MODAL_CHECK_MODES)  # as the server checks
        verdict = guard(
            ModalCase(key, key_d, cell, design, server_modes), K_O_GRID_RATIO, DEFAULT_HAND_BOX
        )
        guarded: dict[str, Any] = {
            "bar_per_s": verdict.bar_per_s,
            "designed_rate_screen_hands_per_s": verdict.designed_rate_per_s,
            "found": verdict.design is not None,
        }
        if verdict.design is not None:
            g2 = {
                "k_h": verdict.design.k_h, "b_h": verdict.design.b_h,
                "own_gain": verdict.design.own_gain, "proxy_hold": verdict.design.proxy_hold,
            }  # fmt: skip
            eq9_g = decay_rates(monodromy(hand=hands, k_o=k_o, b_o=b_o, delay_ticks=d, **g2))
            modal_g = modal_decay_rates(hands=hands, modes=modes, delay_ticks=d, **g2)
            lattice = modal_decay_rates(
                hands=DEFAULT_HAND_BOX.hands(), modes=modes, delay_ticks=d, **g2
            )
            guarded.update(
                gains={**g2, "k_h_scale": verdict.scale},
                modal_slowest_full_lattice=float(lattice.min()),
                eq9_slowest_in_box=float(eq9_g[:-1].min()),
                modal_slowest_in_box=float(modal_g[:-1].min()),
                heavy_loose_hand={"eq9": float(eq9_g[-1]), "modal": float(modal_g[-1])},
            )
        rows.append(
            {
                "delay_ticks": d,
                "design": {**gains, "worst_spectral_radius": design.worst_spectral_radius},
                "eq9_decay_per_s": dict(zip(names, eq9, strict=True)),
                "modal_decay_per_s": dict(zip(names, modal.tolist(), strict=True)),
                "eq9_slowest_in_box": min(eq9[:-1]),
                "modal_slowest_in_box": float(modal[:-1].min()),
                "heavy_loose_hand": {"eq9": eq9[-1], "modal": float(modal[-1])},
                "guarded": guarded,
            }
        )
    reference = None if pad is None else dict(zip(names, direct(at, hands, pad), strict=True))
    return {
        "at": at,
        "direct_decay_per_s": reference,
        "direct_pad": None
        if pad is None
        else {"stiffness_n_per_m": pad[0], "damping_n_s_per_m": pad[1]},
        "k_o_n_per_m": k_o,
        "b_o_n_per_m": b_o,
        "modes_stepped": full.mode_count,
        "modes_in_check": modes.mode_count,
        "lowest_modes_hz": [float(f) for f in solid.natural_frequencies_hz[:4]],
        "first_mode_static_share": float(np.max(np.abs(full.static_shares())) / full.c_static),
        "solid_alone_slowest_decay_per_s": alone,
        "design_margin_per_s": MIN_DECAY_RATE_PER_S,
        "rows": rows,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--at", choices=sorted(POINTS), default="side")
    ap.add_argument("--delays", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--modes", type=int, default=20, help="modes kept in the check")
    ap.add_argument(
        "--direct", action="store_true",
        help="also each hand on the solid itself (1 kHz, the pad below; a minute more)",
    )  # fmt: skip
    ap.add_argument("--pad-stiffness", type=float, default=1000.0, help="[N/m]")
    ap.add_argument("--pad-damping", type=float, default=5.0, help="[N*s/m]")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    pad = (args.pad_stiffness, args.pad_damping) if args.direct else None
    out = check(args.at, args.delays, args.modes, pad)
    out["how"] = "tools/modal_loop_check.py " + " ".join(sys.argv[1:] if argv is None else argv)
    print(
        f"{args.at}: K_o {out['k_o_n_per_m']:.1f} N/m, B_o {out['b_o_n_per_m']:.1f} N/m; the "
        f"solid alone decays at {out['solid_alone_slowest_decay_per_s']:.2f}/s; the design's "
        f"margin {out['design_margin_per_s']:g}/s"
    )
    for r in out["rows"]:
        g = r["design"]
        print(
            f"  {r['delay_ticks']} ticks: K_h {g['k_h']:.1f} N/m, B_h {g['b_h']:.2f} N*s/m, "
            f"C_h K_h {g['own_gain'] * g['k_h']:.2f}, {g['proxy_hold']}: slowest in the box "
            f"eq. 9 {r['eq9_slowest_in_box']:.2f}/s, the solid's modes "
            f"{r['modal_slowest_in_box']:.2f}/s; heavy loose hand {r['heavy_loose_hand']['eq9']:.2f}"
            f" -> {r['heavy_loose_hand']['modal']:.2f}/s"
        )
        gd = r["guarded"]
        if gd.get("gains"):
            g = gd["gains"]
            print(
                f"    the server recommends: K_h {g['k_h']:.1f} N/m (x{g['k_h_scale']:.2f}), B_h "
                f"{g['b_h']:.2f} N*s/m, {g['proxy_hold']}: eq. 9 {gd['eq9_slowest_in_box']:.2f}/s, "
                f"the solid's modes {gd['modal_slowest_in_box']:.2f}/s (bar {gd['bar_per_s']:.2f}/s)"
                f"; heavy loose hand {gd['heavy_loose_hand']['modal']:.2f}/s"
            )
        else:
            print(f"    no gains keep the bar ({gd['bar_per_s']:.2f}/s): the design renders")
    if out["direct_decay_per_s"] is not None:
        slowest = min(out["direct_decay_per_s"].items(), key=lambda kv: kv[1])
        print(f"  on the solid itself: slowest {slowest[1]:.2f}/s ({slowest[0]})")
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
