"""What `--help` tells a newcomer (issue 61, item 7): where to start, every device backend, and
what the options a first run needs mean."""

from __future__ import annotations

import io
from contextlib import redirect_stdout

import pytest

from haptic_collab.cli import build_parser


def _help(*argv: str) -> str:
    out = io.StringIO()
    with redirect_stdout(out), pytest.raises(SystemExit):
        build_parser().parse_args([*argv, "--help"])
    return " ".join(out.getvalue().split())  # argparse's wrapping aside


def test_the_top_help_says_where_to_start_and_lists_the_runtime_commands_first():
    text = _help()
    assert "Start with `haptic demo`" in text
    start = text.index("{demo")
    listed = text[start + 1 : text.index("}", start)].split(",")
    assert listed[:3] == ["demo", "server", "client"]


def test_the_clients_help_names_every_backend_and_explains_url_and_local_model():
    text = _help("client")
    for backend in ("sim:press", "hid:VID:PID", "openhaptics", "forcedimension", "haply"):
        assert backend in text, backend
    assert "`haptic devices` lists what is here" in text
    assert "--url URL the server's websocket URL" in text
    assert "--local-model {p,pi} the local model" in text and "default pi" in text


def test_the_servers_host_says_its_default_and_what_another_address_needs():
    text = _help("server")
    assert "--host HOST address to listen on (default 127.0.0.1: this machine only" in text


def test_each_benchmark_is_a_subcommand_with_only_its_own_options():
    text = _help("bench")
    for name in ("server", "servo", "gains", "fidelity", "load", "rooms", "all"):
        assert name in text
    load = _help("bench", "load")
    assert "--users" in load and "--jitter-us" not in load
    fidelity = _help("bench", "fidelity")
    assert "--jitter-us" in fidelity and "--users" not in fidelity
    assert "--users" not in _help("bench", "server")
