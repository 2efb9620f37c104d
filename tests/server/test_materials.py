"""Materials: cited presets feel as documented, TOML materials are checked strictly."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh

from haptic_collab.server.materials import (
    LIVER_YOUNG_PA,
    PRESETS,
    WATER_BULK_MODULUS_PA,
    Material,
    MaterialError,
    disc_load_compliance,
    halfspace_patch_stiffness,
    load_material,
    material_to_params,
    top_side_stiffness,
)
from haptic_collab.server.objects.balloon import Balloon, BalloonParams
from haptic_collab.server.objects.mesh import default_balloon
from tests.support.helpers import assert_broken_and_missing_toml_refused

#: K_o [N/m] (top, side) on the default mesh as docs/materials.md lists them.
DOCUMENTED_K_O = {
    "water-balloon": (186.3, 179.2),
    "silicone-ball": (308.4, 271.0),
    "soft-tissue": (135.9, 135.9),
}

TOP = np.array([0.0, 0.0, 0.1])
SIDE = np.array([0.1, 0.0, 0.0])


@pytest.fixture(scope="module")
def mesh() -> trimesh.Trimesh:
    return default_balloon()


@pytest.fixture(scope="module")
def balloons(mesh: trimesh.Trimesh) -> dict[str, Balloon]:
    return {
        name: Balloon(mesh, material_to_params(m, BalloonParams(), volume_m3=float(mesh.volume)))
        for name, m in PRESETS.items()
    }


def write(tmp_path: Path, text: str, name: str = "mine.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


GOOD_TOML = """\
source = "measured on our bench"
tension_n_per_m = 80
bending_n_m = 7.8e-10
foundation_n_per_m3 = 0.0
bulk_modulus_pa = 2.2e9
"""


# ------------------------------------------------------------------------------------ presets
def test_presets_are_the_three_documented_ones():
    assert set(PRESETS) == set(DOCUMENTED_K_O)
    for name, material in PRESETS.items():
        assert material.name == name
        assert material.source  # every preset says where its numbers come from


@pytest.mark.parametrize("name", sorted(DOCUMENTED_K_O))
def test_each_preset_has_its_documented_k_o_at_top_and_side(balloons, name):
    k_top, k_side = top_side_stiffness(balloons[name])
    # renderable by a desktop device and inside the local-model design's range
    assert 30.0 <= k_side <= k_top <= 3000.0, (k_top, k_side)
    want_top, want_side = DOCUMENTED_K_O[name]
    assert k_top == pytest.approx(want_top, rel=0.02)
    assert k_side == pytest.approx(want_side, rel=0.02)


def test_top_side_stiffness_measures_where_the_readme_does(balloons):
    b = balloons["silicone-ball"]
    by_points = b.contact_stiffness([b.patch_key(TOP), b.patch_key(SIDE)])
    assert top_side_stiffness(b) == pytest.approx(tuple(by_points))


def test_silicone_ball_feels_like_todays_default_balloon(balloons, mesh):
    default = top_side_stiffness(Balloon(mesh, BalloonParams()))
    assert top_side_stiffness(balloons["silicone-ball"]) == pytest.approx(default, rel=0.01)


def test_latex_film_bends_orders_of_magnitude_more_easily_than_the_silicone_shell():
    latex, silicone = PRESETS["water-balloon"], PRESETS["silicone-ball"]
    assert silicone.bending_n_m / latex.bending_n_m > 1e6
    # Laplace: the film's tension is that of a few kPa of overpressure in a 0.1 m balloon
    overpressure = 2.0 * latex.tension_n_per_m / 0.1
    assert 1e3 < overpressure < 5e3
    assert latex.foundation_n_per_m3 == 0.0  # nothing but tension and water holds the film


def test_water_couples_the_balloons_but_tissue_answers_locally(balloons):
    def coupling(b: Balloon) -> float:
        c = b.contact_compliance([b.patch_key(TOP), b.patch_key(SIDE)])
        return float(-c[0, 1] / c[1, 1])  # pushing the top moves the side out

    assert coupling(balloons["water-balloon"]) > 0.05
    assert coupling(balloons["silicone-ball"]) > 0.10
    assert abs(coupling(balloons["soft-tissue"])) < 0.03


def test_soft_tissue_matches_the_indentation_stiffness_of_liver(balloons):
    target = halfspace_patch_stiffness(LIVER_YOUNG_PA, BalloonParams().patch_radius_m)
    assert target == pytest.approx(1.672 * LIVER_YOUNG_PA * 0.015, rel=1e-3)
    k_top, k_side = top_side_stiffness(balloons["soft-tissue"])
    assert k_top == pytest.approx(target, rel=0.05)
    assert k_side == pytest.approx(target, rel=0.05)


def test_halfspace_quadrature_reproduces_the_uniform_disc_closed_form():
    # uniform pressure on a disc: mean displacement 16 (1 - nu^2) F / (3 pi^2 E a)
    c = disc_load_compliance(lambda r: np.ones_like(r))
    assert c == pytest.approx(16.0 / (3.0 * math.pi**2), rel=1e-4)


def test_pushing_the_water_balloon_in_raises_its_pressure(balloons):
    b = balloons["water-balloon"]
    b.reset()
    b.step([b.patch_key(TOP)], [2.0])
    dv = b.volume_change_m3
    pressure_rise = -b.params.bulk * dv  # dp = -kappa a^T w
    b.reset()
    assert dv < 0.0
    assert pressure_rise > 0.0


# ------------------------------------------------------------------------- params conversion
def test_material_to_params_turns_the_bulk_modulus_into_the_water_term(mesh):
    base = BalloonParams(sim_period_s=0.01, patch_radius_m=0.02)
    params = material_to_params(PRESETS["water-balloon"], base, volume_m3=float(mesh.volume))
    assert params.bulk == pytest.approx(WATER_BULK_MODULUS_PA / float(mesh.volume))
    assert params.bulk == pytest.approx(5.26e11, rel=0.01)
    assert params.tension == PRESETS["water-balloon"].tension_n_per_m
    assert (params.sim_period_s, params.patch_radius_m) == (0.01, 0.02)  # numerics kept
    with pytest.raises(ValueError, match="volume_m3"):
        material_to_params(PRESETS["water-balloon"], base, volume_m3=0.0)


def test_a_materials_damping_reaches_the_balloon(mesh):
    damped = replace(PRESETS["silicone-ball"], damping_pa_s_per_m=200.0)
    params = material_to_params(damped, BalloonParams(), volume_m3=float(mesh.volume))
    assert params.damping == 200.0


# ------------------------------------------------------------------------------------ loading
def test_presets_load_by_name():
    assert load_material("soft-tissue") is PRESETS["soft-tissue"]


def test_unknown_preset_names_the_presets():
    with pytest.raises(MaterialError, match="water-balloon") as err:
        load_material("water-baloon")
    assert "did you mean 'water-balloon'" in str(err.value)


def test_a_toml_material_loads_with_its_file_name(tmp_path):
    path = write(tmp_path, GOOD_TOML)
    m = load_material(str(path))
    assert m.name == "mine"
    assert m.tension_n_per_m == 80.0 and isinstance(m.tension_n_per_m, float)
    assert m.damping_pa_s_per_m == 0.0
    assert m.source == "measured on our bench"


def test_a_typo_in_a_key_fails_naming_the_key_and_the_file(tmp_path):
    path = write(tmp_path, GOOD_TOML.replace("tension_n_per_m", "tenson_n_per_m"))
    with pytest.raises(MaterialError) as err:
        load_material(path)
    msg = str(err.value)
    assert str(path) in msg and "'tenson_n_per_m'" in msg and "'tension_n_per_m'" in msg


def test_a_missing_key_fails_naming_the_key_and_the_file(tmp_path):
    text = "\n".join(line for line in GOOD_TOML.splitlines() if "bulk_modulus" not in line)
    path = write(tmp_path, text)
    with pytest.raises(MaterialError, match="missing required key 'bulk_modulus_pa'") as err:
        load_material(path)
    assert str(path) in str(err.value)


@pytest.mark.parametrize(
    "line, words",
    [
        ("bending_n_m = nan", "finite"),
        ("bending_n_m = inf", "finite"),
        ("bending_n_m = -1e-6", ">= 0"),
        ('bending_n_m = "1e-6"', "must be a number"),
        ("bending_n_m = true", "must be a number"),
    ],
)
def test_bad_values_are_refused_naming_the_key(tmp_path, line, words):
    path = write(tmp_path, GOOD_TOML.replace("bending_n_m = 7.8e-10", line))
    with pytest.raises(MaterialError, match=words) as err:
        load_material(path)
    assert "bending_n_m" in str(err.value) and str(path) in str(err.value)


def test_zero_tension_is_refused(tmp_path):
    path = write(tmp_path, GOOD_TOML.replace("tension_n_per_m = 80", "tension_n_per_m = 0"))
    with pytest.raises(MaterialError, match="tension_n_per_m must be > 0"):
        load_material(path)


def test_broken_toml_and_missing_files_are_refused_naming_the_file(tmp_path):
    broken = write(tmp_path, "tension_n_per_m = = 3\n", name="broken.toml")
    assert_broken_and_missing_toml_refused(load_material, MaterialError, broken)


def test_material_constructor_checks_its_fields():
    # a pydantic ValidationError (a ValueError) naming the field; the loader says it as a
    # one-line MaterialError with the file and the unit (test_bad_values_are_refused_naming_the_key)
    with pytest.raises(ValueError, match=r"foundation_n_per_m3\n  Input should be a finite number"):
        Material("x", 10.0, 0.0, float("nan"), 2.2e9)
    with pytest.raises(ValueError, match=r"name\n  String should have at least 1 character"):
        Material("", 10.0, 0.0, 0.0, 2.2e9)
    with pytest.raises(ValueError, match=r"name\n  Value error, must be a non-empty string"):
        Material("  ", 10.0, 0.0, 0.0, 2.2e9)


def test_the_example_in_the_docs_is_a_valid_material(tmp_path):
    docs = Path(__file__).resolve().parents[2] / "docs" / "materials.md"
    block = docs.read_text().split("```toml\n", 1)[1].split("```", 1)[0]
    m = load_material(write(tmp_path, block, name="my-balloon.toml"))
    assert m.name == "my-balloon" and m.tension_n_per_m == 95.0


# ---- the FEM solid's presets (server/solid_materials.py) against docs/materials.md ----

DOCS = Path(__file__).resolve().parents[2] / "docs" / "materials.md"


def _docs_block(begin: str, end: str) -> str:
    text = DOCS.read_text()
    return text.split(begin, 1)[1].split(end, 1)[0].strip()


def test_the_solid_presets_table_in_the_docs_is_what_the_module_holds():
    from haptic_collab.server.solid_materials import SOLID_PRESETS, preset_table

    block = _docs_block("<!-- SOLID-PRESETS:BEGIN -->", "<!-- SOLID-PRESETS:END -->")
    assert block == preset_table(), "regenerate: python -m haptic_collab.server.solid_materials"
    for name in SOLID_PRESETS:  # every preset listed, with a source for each number
        assert f"| `{name}` |" in block


def test_ecoflex_is_its_small_strain_modulus_not_the_data_sheets_secant():
    from haptic_collab.server.solid_materials import (
        ECOFLEX_0030_100_MODULUS_PA,
        SOLID_PRESETS,
    )

    e = SOLID_PRESETS["ecoflex-0030"].young_pa
    # an incompressible neo-Hookean bar of this E, stretched to twice its length, carries the
    # data sheet's 100 % modulus (10 psi = 68.9 kPa) as its nominal stress
    lam = 2.0
    nominal = e / 3.0 * (lam - lam**-2)
    assert nominal == pytest.approx(68.9e3, rel=2e-3)
    assert nominal == pytest.approx(ECOFLEX_0030_100_MODULUS_PA, rel=2e-3)
    assert e == pytest.approx(118e3, rel=5e-3)  # the docs' number


def test_neo_hookean_secant_refuses_what_has_no_modulus():
    from haptic_collab.server.solid_materials import neo_hookean_young_from_secant

    for stress, stretch in ((0.0, 2.0), (1e3, 1.0), (1e3, math.nan), (-1.0, 2.0)):
        with pytest.raises(ValueError):
            neo_hookean_young_from_secant(stress, stretch)


def test_liver_is_the_mean_of_its_cohort_in_both_objects_and_the_docs():
    from haptic_collab.server import solid_materials

    assert solid_materials.SOLID_PRESETS["liver"].young_pa == LIVER_YOUNG_PA == 5.5e3
    for text in (DOCS.read_text(), solid_materials.__doc__ or ""):
        assert "is the upper normal value" not in text
        assert "Roulot" in text and "5.49" in text  # the cohort's mean, cited


def test_the_damping_loss_factors_the_docs_quote_follow_from_beta():
    from haptic_collab.server.solid_materials import SOLID_PRESETS

    docs = DOCS.read_text()
    beta = SOLID_PRESETS["liver"].rayleigh_beta_s
    for hz, quoted in ((1.0, "0.06 at 1 Hz"), (3.8, "0.24 at 3.8 Hz"), (10.0, "0.63 at 10 Hz")):
        assert quoted in docs
        assert f"{2 * math.pi * hz * beta:.2f}" == quoted.split()[0]
