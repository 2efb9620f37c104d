"""``haptic server --config FILE.toml``: every option from a file, checked, flags still win."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from haptic_collab.cli import build_parser
from haptic_collab.server.config import (
    SERVER_OPTIONS,
    ConfigError,
    apply_server_config,
    load_server_config,
)
from tests.support.helpers import assert_broken_and_missing_toml_refused

EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "server-config.example.toml"

#: ``dest``s of the server subparser that are not options a file can set.
NOT_CONFIGURABLE = {"help", "func", "config"}


def server_parser(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices["server"]


def write(tmp_path: Path, text: str, name: str = "server.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_every_server_option_can_be_set_from_a_file():
    dests = {a.dest for a in server_parser(build_parser())._actions} - NOT_CONFIGURABLE
    assert dests - set(SERVER_OPTIONS) == set()


def test_the_example_file_loads_and_states_the_real_defaults():
    parser = build_parser()
    server = server_parser(parser)
    config = load_server_config(EXAMPLE)
    text = EXAMPLE.read_text()
    for key in SERVER_OPTIONS:  # every option is in the example, set or commented out
        assert re.search(rf"^#? ?{key} = ", text, re.MULTILINE), key
    for key, value in config.items():
        default = parser.get_default(key) if key == "log_level" else server.get_default(key)
        assert value == default, key


def test_a_file_sets_defaults_and_explicit_flags_override_it(tmp_path):
    path = write(
        tmp_path,
        'port = 9001\nsim_rate = 50\nprimitive = "sphere"\nallow_origin = ["https://lab.example"]\n',
    )
    parser = build_parser()
    apply_server_config(server_parser(parser), path)
    args = parser.parse_args(["server", "--port", "9100"])
    assert args.port == 9100  # the flag wins
    assert args.sim_rate == 50.0 and isinstance(args.sim_rate, float)  # the file's value
    assert args.primitive == "sphere"
    assert args.allow_origin == ["https://lab.example"]
    assert args.host == "127.0.0.1"  # untouched default


def test_a_typo_in_a_key_fails_naming_the_key_and_the_file(tmp_path):
    path = write(tmp_path, "sim_rte = 50\n")
    with pytest.raises(ConfigError) as err:
        load_server_config(path)
    msg = str(err.value)
    assert str(path) in msg and "'sim_rte'" in msg and "did you mean 'sim_rate'" in msg


def test_a_dashed_option_name_is_pointed_to_its_underscore_key(tmp_path):
    path = write(tmp_path, '"sim-rate" = 50\n')
    with pytest.raises(ConfigError, match="write 'sim_rate'"):
        load_server_config(path)


@pytest.mark.parametrize(
    "line, words",
    [
        ('port = "8765"', "port must be a whole number"),
        ("port = 8765.0", "port must be a whole number"),
        ("port = 70000", "port must be in 0..65535"),
        ("sim_rate = nan", "sim_rate must be finite"),
        ("sim_rate = -20.0", "sim_rate must be > 0"),
        ("loss = 1.0", r"loss must be in \[0, 1\)"),
        ('insecure = "yes"', "insecure must be true or false"),
        ('primitive = "cube"', "primitive must be one of plane, sphere"),
        ("subdivisions = 9", "subdivisions must be in 0..7"),
        ('allow_origin = "https://a.example"', "allow_origin must be a list of strings"),
        ("stiffness_scale = true", "stiffness_scale must be a number"),
    ],
)
def test_bad_values_are_refused_naming_the_key(tmp_path, line, words):
    path = write(tmp_path, line + "\n")
    with pytest.raises(ConfigError, match=words) as err:
        load_server_config(path)
    assert str(path) in str(err.value)


def test_paths_are_relative_to_the_file_and_names_are_kept(tmp_path):
    folder = tmp_path / "deploy"
    folder.mkdir()
    path = write(
        folder, 'mesh = "ball.stl"\ntls_cert = "/etc/cert.pem"\nmaterial = "soft-tissue"\n'
    )
    config = load_server_config(path)
    assert config["mesh"] == str(folder / "ball.stl")
    assert config["tls_cert"] == "/etc/cert.pem"
    assert config["material"] == "soft-tissue"
    assert load_server_config(write(folder, 'mesh = "balloon"\n', "b.toml"))["mesh"] == "balloon"
    own = load_server_config(write(folder, 'material = "latex.toml"\n', "m.toml"))
    assert own["material"] == str(folder / "latex.toml")


def test_broken_or_missing_files_are_refused_naming_the_file(tmp_path):
    broken = write(tmp_path, "port = = 1\n", name="broken.toml")
    assert_broken_and_missing_toml_refused(load_server_config, ConfigError, broken)


def test_a_key_the_parser_cannot_take_is_refused_before_anything_is_set(tmp_path):
    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, default=8765)
    path = write(tmp_path, 'port = 9000\nmaterial = "water-balloon"\n')
    with pytest.raises(ConfigError, match="no option for 'material'"):
        apply_server_config(parser, path)
    assert parser.parse_args([]).port == 8765
