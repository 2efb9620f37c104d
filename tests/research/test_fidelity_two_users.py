"""The two-user 1-D grid (docs/fidelity.md, "The two-user 1-D grid"): a user held still by a
loose, heavy hand while another user presses and lets go, with the product's design rendering
(no rest plane is sent with two users)."""

from __future__ import annotations

import numpy as np
import pytest

from haptic_collab.bench.fidelity import DEVICE, GRID_HANDS, _design_cell, _gain_key
from haptic_collab.research.fidelity_1d import simulate
from haptic_collab.research.fidelity_cases import (
    OTHER_USER,
    PRESS,
    SPRING_SOFTER,
    TRAJECTORIES,
    Cell,
)
from haptic_collab.research.fidelity_metrics import STABLE_HOLD_P2P_M, cell_metrics
from haptic_collab.research.fidelity_schemes import TableCell, rendering_for
from haptic_collab.shared.full_loop import DEFAULT_HAND_BOX
from haptic_collab.shared.gains.table import GainTable

#: A condition of issue 58's finding: 100 N/m reported, 50 Hz, 100 ms each way, local-p.
K_O, RATE_HZ, DELAY_MS = 100.0, 50.0, 100.0


@pytest.mark.slow  # a cell's design and 48 hand-in-the-loop runs: make test-slow
def test_a_spring_softer_than_reported_holds_still_after_the_other_user_lets_go() -> None:
    # the spring is 20 % softer than the K_o reported. With another user the product renders
    # its design (alone it renders the rest plane). Designed only down to 0.85 K_o, the box's
    # fifth corner (0.6 kg, 2 N*s/m, 20 N/m) rang 0.557 mm peak to peak a second after the other
    # user let go (at the stale end of the sampling phase), where a probe on the spring itself
    # with that hand rings 0.2 mm. The design is now checked down to K_o / 1.25 wherever that
    # costs less than a stiffness JND (shared.gains.design.softest_k_o), as it does here
    key = _gain_key("p", RATE_HZ, DELAY_MS, DEVICE)
    design = _design_cell(key, K_O)
    assert design.k_o_range[0] < 0.85 * K_O  # this cell's design took the soft end
    table = GainTable(DEFAULT_HAND_BOX)
    cells = (TableCell.from_design(table.cell(K_O), design, table.grid_ratio),)
    r = rendering_for(
        "local-p", sim_rate_hz=RATE_HZ, device=DEVICE, design=design.at(K_O), table=cells,
        rest_plane=False,
    )  # fmt: skip
    hands = GRID_HANDS[:8]  # the box's corners
    runs = []
    for tr in TRAJECTORIES:
        cs = [
            Cell(r, K_O, RATE_HZ, DELAY_MS, h, tr, SPRING_SOFTER, stale_sample=st, other=OTHER_USER)
            for h in hands
            for st in (False, True)
        ]
        runs.append((tr, cs, cell_metrics(simulate(cs, device=DEVICE), cs)))
    for tr, cs, ms in runs:
        for c, m in zip(cs, ms, strict=True):
            assert m.stable, (tr.name, c.hand, c.stale_sample, m.hold_p2p_mm)
    # the fifth corner on the press, the stale phase: the ring the other user's release set off
    # has died down to under the benchmark's 0.5 mm by the hold window
    press = next(ms for tr, _cs, ms in runs if tr == PRESS)
    i = 4 * 2 + 1  # hand 4 (the fifth corner), stale
    assert press[i].hold_p2p_mm < 1e3 * STABLE_HOLD_P2P_M
    assert np.isfinite(press[i].hold_p2p_mm)
