"""The product's own client in the drawn loop (haptic_collab/research/drawn_loop.py): what a hand
of the box notices on conditions of the declared set, and ``haptic bench drawn``."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace

import pytest

from haptic_collab.research.drawn_loop import run
from haptic_collab.shared.declared_set import DrawnCondition, DrawnHand, DrawnObject

pytestmark = pytest.mark.slow

#: Condition 5 of seed 11 (docs/stability.md): three PI users, 76 % coupled, on an object half
#: as stiff as the 131 N/m reported, 50 Hz, 63 ms each way; the two partners press and let go
#: while this user holds. With the passivity controller's damper fed to the object it rang
#: 8.7 mm peak to peak; the product's client holds still.
SOFT_THREE = DrawnCondition(
    seed=11,
    index=5,
    k_o=131.1,
    sim_rate_hz=50.0,
    one_way_delay_s=0.063,
    jitter_s=0.0125,
    users=3,
    coupling=0.76,
    obj=DrawnObject("spring", 0.52),
    force_n=1.2,
)
HAND = DrawnHand(0.12, 6.05, 137.6)


def test_three_pi_users_on_a_soft_object_hold_still_after_the_partners_let_go():
    for phase in (0.05, 0.45):
        r = run(SOFT_THREE, HAND, mode="pi", phase=phase)
        assert not r.runaway
        assert r.stable, r
        assert r.force_hold_n > 0.5  # the user is pressing, not resting off the object
        assert r.passivity_dissipated_mj > 0.0  # with the controller on, as the client runs PI


def test_a_user_alone_renders_the_rest_plane_and_holds_still_on_every_family():
    for obj in (
        DrawnObject("two-mass", 0.98, 45.8, 0.14, 0.036, 0.3),
        DrawnObject("hunt-crossley", 1.39, exponent=1.3, hc_lambda_s_per_m=0.5),
        DrawnObject("creep", 0.69, 0.6, creep_time_s=2.0),
    ):
        cond = replace(SOFT_THREE, users=1, coupling=0.0, obj=obj, k_o=300.0)
        r = run(cond, DrawnHand(0.6, 2.0, 1000.0), mode="p", phase=0.45)
        assert r.stable, (obj.family, r)
        assert set(r.sources) == {"rest"}


def test_haptic_bench_drawn_prints_its_seed_and_the_shares():
    out = subprocess.run(
        [sys.executable, "-m", "haptic_collab.cli", "bench", "drawn", "--seed", "4",
         "--conditions", "1", "--hands", "1", "--workers", "1", "--json"],
        capture_output=True, text=True, timeout=900, check=True,
    )  # fmt: skip
    assert "drawn: seed 4" in out.stderr
    doc = json.loads(out.stdout)
    assert doc["seed"] == 4 and len(doc["conditions"]) == 1
    assert set(doc["summary"]) == {
        "p_one_user", "p_several_users", "pi_one_user", "pi_several_users",
    }  # fmt: skip
    row = doc["conditions"][0]
    assert len(row["p"]["runs"]) == 2 and len(row["pi"]["runs"]) == 2  # both phases
