"""The parameter classes declare their bounds (pydantic dataclasses, shared.checks): what a user sees.

A bad value is refused with a message naming the class, the field (also when given by position)
and the bound; an int is a float but a bool or a string is not; NaN is refused, inf only where a
field allows it; an unknown keyword is an error, not ignored. The JSON Schema of a class carries
the bounds. The classes are still dataclasses (replace, fields, asdict, equality, hashing, pickle).
"""

from __future__ import annotations

import dataclasses
import math
import pickle
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from pydantic import TypeAdapter, ValidationError

from haptic_collab.client.devices.base import DeviceLimits
from haptic_collab.client.devices.sim import HandParams
from haptic_collab.client.thermal import ThermalParams
from haptic_collab.server.materials import PRESETS, Material
from haptic_collab.server.objects.balloon import BalloonParams
from haptic_collab.shared.checks import describe
from haptic_collab.shared.coupled_loop import UserGains
from haptic_collab.shared.full_loop import Hand, HandBox
from haptic_collab.shared.local_model import LocalModelParams, ThresholdParams
from haptic_collab.shared.local_model_update import LocalModelUpdate, SurfacePatch
from haptic_collab.shared.passivity import PassivityParams
from haptic_collab.shared.primitives import make_plane

PLANE = make_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
BOX = {"workspace_min_m": (-0.1, -0.1, -0.1), "workspace_max_m": (0.1, 0.1, 0.1)}


def limits(**kw: Any) -> DeviceLimits:
    args: dict[str, Any] = {
        "max_force_n": 3.3,
        "max_stiffness_n_per_m": 1000.0,
        "max_velocity_m_s": 1.0,
        "damping_n_s_per_m": 0.0,
        **BOX,
        **kw,
    }
    return DeviceLimits(**args)


BAD: list[tuple[Callable[[], object], str, str, str]] = [
    # (construction, class, field, what pydantic says)
    (lambda: BalloonParams(tension=0.0), "BalloonParams", "tension", "greater than 0"),
    (lambda: BalloonParams(bulk=-1.0), "BalloonParams", "bulk", "greater than or equal to 0"),
    (lambda: BalloonParams(bending=math.nan), "BalloonParams", "bending", "a finite number"),
    (lambda: BalloonParams(sim_period_s=math.inf), "BalloonParams", "sim_period_s", "finite"),
    (lambda: BalloonParams(cache_mb=True), "BalloonParams", "cache_mb", "a valid number"),
    (lambda: BalloonParams(damping="1"), "BalloonParams", "damping", "a valid number"),
    (lambda: Hand(0.0, 1.0, 1.0), "Hand", "mass_kg", "greater than 0"),  # by position
    (lambda: Hand(1.0, 1.0, -1.0), "Hand", "stiffness_n_per_m", "greater than or equal to 0"),
    (lambda: HandBox(mass_kg=(0.0, 1.0)), "HandBox", "mass_kg.0", "greater than 0"),
    (lambda: UserGains(0.0), "UserGains", "k_h", "greater than 0"),
    (lambda: UserGains(1.0, proxy_hold="cubic"), "UserGains", "proxy_hold", "'zoh' or 'foh'"),
    (lambda: LocalModelParams(k_h=-1.0), "LocalModelParams", "k_h", "greater than 0"),
    (lambda: LocalModelParams(k_h=1.0, unilateral=1), "LocalModelParams", "unilateral", "bool"),
    (lambda: ThresholdParams(theta_m=-1e-3), "ThresholdParams", "theta_m", "greater than or"),
    (lambda: ThresholdParams(mode="bogus"), "ThresholdParams", "mode", "'none', 'fixed' or"),
    (
        lambda: LocalModelUpdate(PLANE, 1.0, 0.0, hold_ticks=0),
        "LocalModelUpdate",
        "hold_ticks",
        "1",
    ),
    (
        lambda: LocalModelUpdate(PLANE, 1.0, 0.0, hold_ticks=2.0),
        "LocalModelUpdate",
        "hold_ticks",
        "a valid integer",
    ),  # fmt: skip
    (lambda: LocalModelUpdate(PLANE, 1.0, math.inf), "LocalModelUpdate", "i_gain", "finite"),
    (
        lambda: PassivityParams(max_damping_n_s_per_m=1.0, enabled=1),
        "PassivityParams",
        "enabled",
        "a valid boolean",
    ),  # fmt: skip
    (
        lambda: ThermalParams(7.9, 1.75, release_heat=1.0),
        "ThermalParams",
        "release_heat",
        "less than 1",
    ),  # fmt: skip
    (lambda: HandParams(stiffness_n_per_m=0.0), "HandParams", "stiffness_n_per_m", "greater"),
    (lambda: limits(max_force_n=True), "DeviceLimits", "max_force_n", "a valid number"),
    (lambda: limits(damping_n_s_per_m=math.nan), "DeviceLimits", "damping_n_s_per_m", "finite"),
    (lambda: limits(workspace_min_m=(0.0, 0.0)), "DeviceLimits", "workspace_min_m", "3 numbers"),
    (lambda: Material("x", 0.0, 0.0, 0.0, 2.2e9), "Material", "tension_n_per_m", "greater than 0"),
]


@pytest.mark.parametrize(
    ("build", "cls", "field", "says"), BAD, ids=[f"{c}.{f}" for _, c, f, _ in BAD]
)
def test_a_bad_value_is_refused_naming_the_class_and_the_field(
    build: Callable[[], object], cls: str, field: str, says: str
) -> None:
    with pytest.raises(ValueError) as err:  # a pydantic ValidationError is a ValueError
        build()
    assert isinstance(err.value, ValidationError)
    first, where, problem = str(err.value).splitlines()[:3]
    assert first.endswith(f"for {cls}")
    assert where == field
    assert says in problem


def test_cross_field_checks_still_say_what_is_wrong() -> None:
    with pytest.raises(
        ValueError, match=r"continuous_force_n must be in \(0, peak_force_n = 7.9\]"
    ):
        ThermalParams(7.9, 9.0)
    with pytest.raises(ValueError, match="workspace_min_m .* must be below workspace_max_m"):
        limits(workspace_min_m=(0.2, 0.0, 0.0))
    with pytest.raises(ValueError, match="i_tot_bar_n must be > 0 for the variable threshold"):
        ThresholdParams(mode="variable", i_tot_bar_n=0.0)
    with pytest.raises(ValueError, match="hand box damping_n_s_per_m must have lo <= hi"):
        HandBox(damping_n_s_per_m=(2.0, 1.0))


def test_an_int_or_a_numpy_number_is_a_float() -> None:
    p = BalloonParams(tension=50, sim_period_s=np.float64(0.02), cache_mb=np.int64(64))
    assert (p.tension, p.sim_period_s, p.cache_mb) == (50.0, 0.02, 64.0)
    assert all(type(v) is float for v in (p.tension, p.sim_period_s, p.cache_mb))
    assert type(Hand(np.float64(0.5), 5, 300).stiffness_n_per_m) is float
    assert LocalModelUpdate(PLANE, np.float64(300.0), 0, hold_ticks=50).k_h == 300.0
    assert type(SurfacePatch.of(PLANE, np.float64(400.0)).k_o) is float


def test_inf_only_where_a_field_allows_it() -> None:
    # a position-only input states no stiffness or speed limit; a limit may be "none"
    spacemouse = limits(
        max_stiffness_n_per_m=math.inf, max_velocity_m_s=math.inf, has_force_output=False
    )
    assert spacemouse.max_stiffness_n_per_m == math.inf
    with pytest.raises(ValueError, match="max_stiffness_n_per_m must be finite for a device with"):
        limits(max_stiffness_n_per_m=math.inf)
    assert PassivityParams(max_damping_n_s_per_m=1.0).max_force_n == math.inf
    assert LocalModelParams(k_h=1.0, integral_limit_n=math.inf).integral_limit_n == math.inf
    # NaN never
    with pytest.raises(ValueError, match="max_force_n\n  Input should be greater than 0"):
        PassivityParams(max_damping_n_s_per_m=1.0, max_force_n=math.nan)
    with pytest.raises(ValueError, match="max_velocity_m_s\n  Input should be greater than 0"):
        limits(max_velocity_m_s=math.nan, has_force_output=False)


def test_an_unknown_keyword_is_an_error_not_ignored() -> None:
    with pytest.raises(ValueError, match="tensoin\n  Unexpected keyword argument"):
        BalloonParams(tensoin=10.0)  # type: ignore[call-arg]


def test_describe_puts_the_first_problem_on_one_line() -> None:
    with pytest.raises(ValidationError) as err:
        BalloonParams(tension=-1.0)
    assert describe(err.value) == "tension must be > 0, got -1.0"
    with pytest.raises(ValidationError) as err:
        Hand(1.0, math.nan, 0.0)
    assert describe(err.value, {"damping_n_s_per_m": "N*s/m"}) == (
        "damping_n_s_per_m must be finite [N*s/m], got nan"
    )
    with pytest.raises(ValidationError) as err:
        PassivityParams(max_damping_n_s_per_m=1.0, reset_on_release="yes")
    assert describe(err.value) == "reset_on_release must be True or False, got 'yes'"


def test_the_json_schemas_carry_the_bounds() -> None:
    balloon = TypeAdapter(BalloonParams).json_schema()["properties"]
    assert balloon["tension"]["exclusiveMinimum"] == 0
    assert balloon["bending"]["minimum"] == 0
    assert balloon["tension"]["default"] == 50.0
    dev = TypeAdapter(DeviceLimits).json_schema()
    assert dev["properties"]["max_force_n"]["minimum"] == 0
    assert dev["properties"]["max_stiffness_n_per_m"]["exclusiveMinimum"] == 0
    assert dev["properties"]["workspace_min_m"]["minItems"] == 3
    assert dev["additionalProperties"] is False
    assert set(dev["required"]) == {
        "max_force_n",
        "max_stiffness_n_per_m",
        "max_velocity_m_s",
        "damping_n_s_per_m",
        "workspace_min_m",
        "workspace_max_m",
    }
    material = TypeAdapter(Material).json_schema()["properties"]
    assert material["tension_n_per_m"]["exclusiveMinimum"] == 0
    assert material["damping_pa_s_per_m"]["minimum"] == 0
    assert material["name"]["minLength"] == 1
    thermal = TypeAdapter(ThermalParams).json_schema()["properties"]
    assert (thermal["release_heat"]["minimum"], thermal["release_heat"]["exclusiveMaximum"]) == (
        0,
        1,
    )


def test_another_validator_agrees_with_the_schema() -> None:
    jsonschema = pytest.importorskip("jsonschema")
    schema = TypeAdapter(Material).json_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    good = dataclasses.asdict(PRESETS["soft-tissue"])
    assert list(jsonschema.Draft202012Validator(schema).iter_errors(good)) == []
    for bad in ({"tension_n_per_m": 0.0}, {"bulk_modulus_pa": -1.0}, {"name": ""}):
        errors = list(jsonschema.Draft202012Validator(schema).iter_errors({**good, **bad}))
        assert [list(e.path) for e in errors] == [list(bad)]


def test_they_are_still_frozen_dataclasses() -> None:
    p = BalloonParams()
    assert [f.name for f in dataclasses.fields(p)][:3] == ["tension", "bending", "foundation"]
    q = dataclasses.replace(p, damping=2)
    assert q.damping == 2.0 and q != p and dataclasses.replace(q, damping=0.0) == p
    assert hash(dataclasses.replace(q, damping=0.0)) == hash(p)
    assert dataclasses.asdict(p)["tension"] == 50.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.tension = 1.0  # type: ignore[misc]
    with pytest.raises(ValueError, match="tension"):
        dataclasses.replace(p, tension=-1.0)
    for obj in (p, PRESETS["water-balloon"], limits(), Hand(0.5, 5.0, 300.0), HandBox()):
        assert pickle.loads(pickle.dumps(obj)) == obj  # worker processes get them pickled
