"""tools/coupled_pair_check.py: the shipped designs of two coupled users on their coupled loop.

What a user would notice: on the bowl at 2 ticks of delay, a resting user who kept the gains of
its uncoupled contact when the other's press coupled them would ring (spectral radius above 1);
the coupling class's own design is what keeps it steady. On the torus the same pairing meets the
margin, which is why a check of the pair as rendered (not done: docs/coupled-users.md) could spare
the resting user its felt step there.
"""

from __future__ import annotations

from tools.coupled_pair_check import CASES, check


def _case(prefix: str) -> tuple[float, float, float]:
    (value,) = (v for k, v in CASES.items() if k.startswith(prefix))
    return value


def test_on_the_bowl_a_resting_user_keeping_its_uncoupled_gains_would_ring() -> None:
    out = check(*_case("bowl"), delay_ticks=2, mode="pi")
    pairs = out["pairs"]
    assert isinstance(pairs, dict)
    assert pairs["A coupled, B coupled"]["meets_margin"]
    assert pairs["A coupled, B uncoupled"]["margin_radius"] > 1.0  # unstable
    assert pairs["A uncoupled, B uncoupled"]["margin_radius"] > 1.0


def test_on_the_torus_the_pair_would_hold_with_only_the_arriving_user_coupled() -> None:
    out = check(*_case("torus"), delay_ticks=2, mode="pi")
    pairs = out["pairs"]
    assert isinstance(pairs, dict)
    assert pairs["A coupled, B coupled"]["meets_margin"]
    assert pairs["A coupled, B uncoupled"]["meets_margin"]
    assert not pairs["A uncoupled, B uncoupled"]["meets_margin"]
