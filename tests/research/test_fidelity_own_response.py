"""The benchmark's simulator runs the client's own-response check: its batch bookkeeping
(haptic_collab.research.fidelity_1d._verified_plane_gains) gives the verdicts and the
stiffness identified that shared.gains.own_response.OwnResponse gives the client, patch by patch."""

from __future__ import annotations

import numpy as np

from haptic_collab.research.fidelity_1d import _PLANE_CELLS, _verified_plane_gains
from haptic_collab.shared.gains.own_response import (
    OwnResponse,
    empty_deformation,
    empty_jumps,
    empty_sums,
)

K_O = 300.0
RATE_HZ = 20.0


class _EveryCellHasAPlane:
    """A plane table with every cell (the check's verdicts are what is compared here)."""

    ratio = 1.1

    def has_cell(self, k: np.ndarray) -> np.ndarray:
        return np.ones(len(k), dtype=bool)

    def gains_and_hold(self, k: np.ndarray):
        return k, 0.0 * k, 0.0 * k, 1.0 / k, np.zeros(len(k), dtype=bool)


def _patches() -> list[tuple[int, float, float]]:
    """(tick, this user's force [N], surface depth [m]): three presses up and down on a spring
    20 % softer than reported, a tenth of the patches late by 6 ticks (stalls), the contact
    ending between presses; then a hold at 1 N and a jump to 2 N with the surface moving out."""
    rng = np.random.default_rng(1)
    out, tick = [], 0
    for _ in range(3):
        for f in np.concatenate([np.linspace(0.1, 3.0, 20), np.linspace(3.0, 0.1, 20)]):
            out.append((tick, float(f), f / (0.8 * K_O) + rng.normal(0.0, 2e-5)))
            tick += 1 if rng.random() > 0.1 else 7
        out.append((tick, 0.0, 0.0))  # the contact ends
        tick += 3
    for f in [1.0] * 30 + [2.0] * 30:
        out.append((tick, f, f / K_O - (0.0011 if f > 1.5 else 0.0)))
        tick += 1
    return out


def test_the_simulator_identifies_as_the_client_does_patch_by_patch() -> None:
    verdicts, ratios = _agree(_patches())
    # and there was something to agree on: the softer spring identified, the jump refused
    assert any(abs(r - 0.8) < 0.04 and ok for (r, _), (ok, _) in zip(ratios, verdicts, strict=True))
    assert not (verdicts[-1][0] and abs(ratios[-1][0] - 1.0) > 0.05)


def _agree(
    patches: list[tuple[int, float, float]],
) -> tuple[list[tuple[bool, bool]], list[tuple[float, float]]]:
    """Feed ``patches`` to the simulator's bookkeeping and to the client's check; they agree
    patch by patch: the verdicts and the stiffness identified (returned, client's first)."""
    state = {
        "sums": empty_sums((1,)),
        "deform": empty_deformation((1,)),
        "seq_last": np.full(1, -1),
        "ok": np.zeros(1, dtype=bool),
        "ref": np.ones(1),
        "start": np.full(1, -1),
        "jumps": empty_jumps((1,)),
        "since": np.full((1, _PLANE_CELLS), -1),
    }
    gains = (np.zeros(1),) * 4 + (np.zeros(1, dtype=bool),)
    client, last_tick = OwnResponse(), None
    verdicts, ratios = [], []
    for tick, f, x in patches:
        _verified_plane_gains(
            np.ones(1, dtype=bool), gains, _EveryCellHasAPlane(), np.array([K_O]),
            delay_s=np.zeros(1), seq=np.array([tick]),
            surface=np.array([x]),
            force=np.array([f]), sim_rate_hz=np.array([RATE_HZ]), **state,
        )  # fmt: skip
        if f <= 0.0:  # the client starts over when the contact ends
            client.reset()
            last_tick = None
            continue
        dt = 0.0 if last_tick is None else (tick - last_tick) / RATE_HZ
        last_tick = tick
        got = client.update(dt_s=dt, surface_m=x, force_n=f, k_o=K_O)
        verdicts.append((got, state["ok"][0]))
        ratios.append((client.identified_ratio, state["ref"][0]))
    assert all(a == b for a, b in verdicts)
    assert np.allclose([a for a, _ in ratios], [b for _, b in ratios], rtol=1e-12, atol=0.0)
    return verdicts, ratios
