"""Two coupled users' gains as the shipped tables give them, verified on their coupled loop.

The product designs each user of a coupled group alone, over its whole modal range
(:mod:`shared.gains.coupled_design`: stable whatever the other users render, a rigid partner
included). This tool asks how much that costs where a contact's coupling class rises under a
resting user: for the contacts the stress meshes' demo measured (docs/real-objects.md), it
rebuilds the two users' compliance from their K_o_eff and K_o_stiff, takes each user's shipped
design for its uncoupled key and for its coupled one, and verifies every pairing on the coupled
loop (:func:`shared.coupled_loop.verify_coupled`: every user takes each of the 10 verification
hands of the box and, by default, the sampling ticks 0, N/2 and N - 1, all combinations, with the
K_o margin), as the product's coupled-loop tests do; ``--all-ticks`` takes every one of the N
sampling ticks per user (about 15 s a pairing).

Usage: ``.venv/bin/python tools/coupled_pair_check.py [--all-ticks] [--out FILE]`` (JSON on
stdout or to FILE).
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path

import haptic_collab.cli.blas_threads  # noqa: F401  (first: one BLAS thread, before numpy)
from haptic_collab.client.gain_store import preload
from haptic_collab.shared.coupled_compliance import compliance_matrix
from haptic_collab.shared.coupled_loop import UserGains, verification_hands, verify_coupled
from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX
from haptic_collab.shared.gains.choose import static_felt_stiffness
from haptic_collab.shared.gains.key import make_gain_key, stiff_ratio_class
from haptic_collab.shared.gains.table import GainTable

#: name: (A's K_o [N/m], B's K_o [N/m], K_o_stiff / K_o_eff), as the demo's patches reported
#: them while A pressed (docs/real-objects.md; 2026-11-27 runs, both users' numbers agree).
CASES = {
    "torus (A on top, B resting on the side)": (472.7, 1202.9, 2003.6 / 859.4),
    "bowl (A on the rim's inside, B resting)": (306.1, 281.4, 1178.2 / 175.9),
}


def _key(stiff_ratio: float, delay_ticks: int, mode: str):
    return make_gain_key(
        servo_rate_hz=1000.0, sim_rate_hz=20.0, delay_ticks=delay_ticks, mode=mode,  # type: ignore[arg-type]
        margin=0.15, k_h_max=1000.0, b_h_max=10.0, b_o=0.0, stiff_ratio=stiff_ratio,
    )  # fmt: skip


@functools.cache
def _shipped() -> GainTable:
    table = GainTable()
    preload(table, cache=False)
    return table


def check(
    k_a: float, k_b: float, ratio: float, delay_ticks: int, mode: str, *, all_ticks: bool = False
) -> dict[str, object]:
    """Every pairing of A's and B's uncoupled and coupled designs (Phantom Desktop's shipped
    table) on the coupled loop of two contacts of stiffness ``k_a``, ``k_b`` [N/m] whose modal
    stiffness ratio is ``ratio`` (``all_ticks``: every sampling tick per user)."""
    rho = (ratio - 1.0) / (ratio + 1.0)  # 2 contacts: K_o_stiff / K_o_eff = (1 + r) / (1 - r)
    compliance = compliance_matrix([k_a, k_b], rho)
    table = _shipped()
    cls = stiff_ratio_class(1.0, ratio)
    users = {}
    for name, k in (("A", k_a), ("B", k_b)):
        for coupled in (False, True):
            k_eff = k / (1.0 + rho) if coupled else k
            d = table.lookup(_key(cls if coupled else 1.0, delay_ticks, mode), k_eff)
            assert d is not None, (name, coupled)
            users[(name, coupled)] = (d, k_eff)
    out: dict[str, object] = {
        "k_o_n_per_m": {"A": k_a, "B": k_b},
        "k_o_stiff_over_k_o_eff": ratio,
        "class": cls,
        "delay_ticks": delay_ticks,
        "mode": mode,
        "designs": {
            f"{n} {'coupled' if c else 'uncoupled'}": {
                "k_h": d.k_h,
                "i_gain": d.i_gain,
                "b_h": d.b_h,
                "c_h_k_h": d.own_gain * d.k_h,
                "proxy_hold": d.proxy_hold,
                "felt_1hz_over_k_o": d.felt_stiffness_ratio_1hz,
                "static_felt_n_per_m": static_felt_stiffness(d.k_h, d.i_gain, d.own_gain, k_eff),
            }
            for (n, c), (d, k_eff) in users.items()
        },
        "pairs": {},
    }
    for a_coupled in (False, True):
        for b_coupled in (False, True):
            ga, gb = users[("A", a_coupled)][0], users[("B", b_coupled)][0]
            v = verify_coupled(
                compliance, (UserGains.from_design(ga), UserGains.from_design(gb)),
                delay_ticks=delay_ticks, margin=0.15, hands=verification_hands(DEFAULT_HAND_BOX),
                sample_ticks=range(50) if all_ticks else None,  # N = 1 kHz / 20 Hz
            )  # fmt: skip
            name = f"A {'coupled' if a_coupled else 'uncoupled'}, B {'coupled' if b_coupled else 'uncoupled'}"
            out["pairs"][name] = {  # type: ignore[index]
                "meets_margin": bool(v.meets_margin),
                "margin_radius": float(v.margin_radius),
            }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path)
    ap.add_argument("--all-ticks", action="store_true", help="every sampling tick per user")
    args = ap.parse_args(argv)
    rows = [
        {"case": name, **check(k_a, k_b, ratio, d, mode, all_ticks=args.all_ticks)}
        for name, (k_a, k_b, ratio) in CASES.items()
        for d in (0, 2)
        for mode in ("p", "pi")
    ]
    command = "tools/coupled_pair_check.py" + (" --all-ticks" if args.all_ticks else "")
    text = json.dumps({"command": command, "rows": rows}, indent=1)
    if args.out:
        args.out.write_text(text + "\n")
    else:
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
