"""The generic HID profile's JSON Schema (``HidProfileModel.model_json_schema()``) is usable as is.

A validator other than pydantic (``jsonschema``) accepts every bundled profile with it and
refuses the mistakes the schema can express, as the loader does.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from haptic_collab.client.devices.profiles import (
    HID_PROFILE_DIR,
    HidProfileModel,
    ProfileError,
    parse_hid_profile,
)

jsonschema = pytest.importorskip("jsonschema")

BUNDLED = sorted(HID_PROFILE_DIR.glob("*.json"))


def validator() -> Any:
    schema = HidProfileModel.model_json_schema()
    cls = jsonschema.validators.validator_for(schema)
    assert cls is jsonschema.Draft202012Validator
    cls.check_schema(schema)  # a valid draft 2020-12 document
    return cls(schema)


def test_there_are_bundled_profiles() -> None:
    assert {p.stem for p in BUNDLED} >= {"example-3dof-force", "example-joystick-rate"}


@pytest.mark.parametrize("path", BUNDLED, ids=lambda p: p.stem)
def test_bundled_profiles_validate_against_the_json_schema(path: Path) -> None:
    data = json.loads(path.read_text(encoding="utf-8"))
    errors = [e.message for e in validator().iter_errors(data)]
    assert errors == []
    parse_hid_profile(data, str(path))  # and the loader agrees


Edit = Callable[[dict[str, Any]], object]


@pytest.mark.parametrize(
    "edit",
    [
        lambda d: d.pop("limits"),
        lambda d: d["input"]["axes"].pop(),
        lambda d: d["input"]["axes"][0].update(type="int24"),
        lambda d: d["input"]["axes"][2].update(scale=0),
        lambda d: d["input"]["axes"][1].update(byte=-1),
        lambda d: d["input"].update(mode="relative"),
        lambda d: d["input"].update(report_id=256),
        lambda d: d.update(vendor_id="0xzz"),
        lambda d: d.update(product_id=0x10000),
        lambda d: d["limits"].update(max_force_n=-1),
        lambda d: d["limits"].update(workspace_size_m=[0.1, 0.1]),
        lambda d: d.update(silence_timeout_s=0),
        lambda d: d.update(name=""),
    ],
)
def test_schema_and_loader_both_refuse_a_broken_profile(edit: Edit) -> None:
    data = json.loads((HID_PROFILE_DIR / "example-3dof-force.json").read_text(encoding="utf-8"))
    edit(data)
    assert not validator().is_valid(data)
    with pytest.raises(ProfileError):
        parse_hid_profile(data, "test.json")
