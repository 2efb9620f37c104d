"""The FEM solid's modes, kept on disk (server/objects/mode_cache.py).

What a user would notice: a server started again on the same solid comes up without solving its
modes again and behaves exactly as before; a damaged or stale file is never used; a change of
material solves anew; the folder does not grow without bound.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import trimesh

from haptic_collab.server.objects import mode_cache
from haptic_collab.server.objects.fem import FemParams, FemSolid

SIM_PERIOD_S = 0.05


def ball() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=2, radius=0.05)


def build(folder: Path, **changes: object) -> FemSolid:
    params = FemParams(**{"sim_period_s": SIM_PERIOD_S, **changes})  # type: ignore[arg-type]
    return FemSolid(ball(), params, cache_dir=str(folder))


def pressed(solid: FemSolid) -> np.ndarray:
    """The surface after 5 ticks of a 0.5 N push on the top and 5 after its release."""
    top = solid.patch_key(solid.rest_vertices[int(np.argmax(solid.rest_vertices[:, 2]))])
    for _ in range(5):
        solid.step([top], [0.5])
    for _ in range(5):
        solid.step([], [])
    return np.array(solid.vertices, copy=True)


def mode_files(folder: Path) -> list[Path]:
    return sorted(folder.glob("modes-*.npz"))


def test_a_solid_built_again_loads_its_modes_and_moves_the_same(tmp_path):
    first = build(tmp_path)
    assert not first.modes_cached
    assert len(mode_files(tmp_path)) == 1
    again = build(tmp_path)
    assert again.modes_cached
    assert len(again.natural_frequencies_hz) > 0
    np.testing.assert_array_equal(again.natural_frequencies_hz, first.natural_frequencies_hz)
    np.testing.assert_array_equal(pressed(again), pressed(first))


def test_another_material_or_rate_solves_its_own_modes(tmp_path):
    build(tmp_path)
    assert not build(tmp_path, young_pa=11e3).modes_cached
    assert not build(tmp_path, sim_period_s=0.02).modes_cached  # another settle frequency
    assert len(mode_files(tmp_path)) == 3


@pytest.mark.parametrize("damage", ["scaled", "shifted", "truncated", "not_ascending"])
def test_a_damaged_file_is_refused_and_the_modes_solved_again(tmp_path, caplog, damage):
    first = build(tmp_path)
    (path,) = mode_files(tmp_path)
    with np.load(path) as data:
        omega2, phi = np.array(data["omega2"]), np.array(data["phi"])
    if damage == "scaled":  # one mode 1 % off: not mass-normalised
        phi[:, 3] *= 1.01
        np.savez(path, omega2=omega2, phi=phi)
    elif damage == "shifted":  # frequencies 0.05 % off their shapes'
        np.savez(path, omega2=omega2 * 1.001, phi=phi)
    elif damage == "not_ascending":
        np.savez(path, omega2=omega2[::-1], phi=phi[:, ::-1])
    else:
        path.write_bytes(path.read_bytes()[:1000])
    with caplog.at_level(logging.WARNING):
        again = build(tmp_path)
    assert not again.modes_cached
    assert "cached FEM modes" in caplog.text and "refused" in caplog.text
    np.testing.assert_allclose(
        again.natural_frequencies_hz, first.natural_frequencies_hz, rtol=1e-9
    )
    assert build(tmp_path).modes_cached  # the good modes were written back


def test_the_folder_keeps_the_most_recently_used_files_within_its_budget(tmp_path):
    for name, size in (("modes-old.npz", 400_000), ("modes-mid.npz", 400_000)):
        (tmp_path / name).write_bytes(b"x" * size)
    newest = tmp_path / "modes-new.npz"
    newest.write_bytes(b"x" * 400_000)
    old, mid = tmp_path / "modes-old.npz", tmp_path / "modes-mid.npz"
    import os

    os.utime(old, (1_000, 1_000))
    os.utime(mid, (2_000, 2_000))
    mode_cache.prune(tmp_path, keep=newest, budget_mb=0.9)
    assert not old.exists() and mid.exists() and newest.exists()
    mode_cache.prune(tmp_path, keep=newest, budget_mb=0.1)
    assert newest.exists() and not mid.exists()  # the file just written stays


def test_an_unwritable_folder_costs_only_the_next_start(tmp_path):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the cache folder would be")
    solid = build(blocker)  # the volume mesh and the modes cannot be kept: the solid still works
    assert not solid.modes_cached and len(solid.natural_frequencies_hz) > 0
