"""The ``haptic`` command line as a user meets it: verdicts, JSON, exit codes, one-line errors."""

from __future__ import annotations

import json
import shlex
import socket
from pathlib import Path

import pytest

from haptic_collab.cli import build_parser, main
from tests.support.processes import run

ROOT = Path(__file__).resolve().parents[2]


def test_stability_json_for_the_paper_cases(capsys):
    assert (
        main(["stability", "--k-o", "200", "--k-h", "220", "--json"]) == 0
    )  # exit 0 even if unstable
    out = json.loads(capsys.readouterr().out)
    assert out["stable"] is False and out["analytic_stable"] is False
    assert out["spectral_radius"] == pytest.approx(1.1)
    assert out["poles"] == [[pytest.approx(-1.1), 0.0]]
    assert "eq. 8" in out["condition"]
    assert main(["stability", "--k-o", "300", "--k-h", "100", "--i-gain", "3000", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["stable"] and out["analytic_stable"] and "eq. 15" in out["condition"]
    assert (
        main(
            [
                "stability",
                "--k-o",
                "300",
                "--k-h",
                "100",
                "--i-gain",
                "3000",
                "--damping",
                "1",
                "--json",
            ]
        )
        == 0
    )
    assert "eq. 16" in json.loads(capsys.readouterr().out)["condition"]
    assert main(["stability", "--k-o", "300", "--k-h", "280", "--delay-ticks", "2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["analytic_stable"] is None and out["stable"] and len(out["poles"]) == 3


def test_sampling_the_force_late_in_the_period(capsys):
    args = ["stability", "--k-o", "300", "--k-h", "210", "--i-gain", "4200", "--json"]
    assert main(args) == 0 and json.loads(capsys.readouterr().out)["stable"] is True
    assert main([*args, "--sample-tick", "49"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["stable"] is False and out["analytic_stable"] is None
    assert run("stability", "--k-o", "300", "--k-h", "1", "--sample-tick", "50").returncode == 2


def test_stability_readable_verdict(capsys):
    assert main(["stability", "--k-o", "200", "--k-h", "190"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("STABLE") and "0.9500" in text


@pytest.mark.parametrize("command", ["stability", "gains"])
def test_help_shows_every_default(command, capsys):
    with pytest.raises(SystemExit) as done:
        main([command, "--help"])
    assert done.value.code == 0
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    assert "(default 20.0)" in text and "(default 1000.0)" in text
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    parser = sub.choices[command]
    formatter = parser._get_formatter()
    for action in parser._actions:
        if action.required or action.nargs == 0:  # required values and flags have no default
            continue
        shown = "(default: none)" if action.default is None else f"(default {action.default})"
        assert shown in formatter._expand_help(action), action.option_strings
        assert shown in text, action.option_strings


@pytest.mark.parametrize(
    "args",
    [
        ["stability", "--k-o", "-3", "--k-h", "1"],
        ["stability", "--k-o", "nan", "--k-h", "1"],
        ["stability", "--k-h", "1"],
        ["stability", "--k-o", "300", "--k-h", "100", "--sim-rate", "30"],
        ["stability", "--k-o", "300", "--k-h", "100", "--delay-ticks", "1.5"],
    ],
)
def test_bad_input_exits_2_with_one_clear_line(args):
    res = run(*args)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "error" in lines[0] and "Traceback" not in res.stderr
    assert res.stdout == ""


def test_server_refuses_a_broken_mesh_with_one_line(tmp_path):
    broken = tmp_path / "broken.stl"
    broken.write_bytes(b"\x00garbage that is not a mesh" * 10)
    res = run("server", "--mesh", str(broken), "--port", "0", timeout=60)
    assert res.returncode == 2
    err = [ln for ln in res.stderr.splitlines() if "haptic server: error" in ln]
    assert len(err) == 1 and "broken.stl" in err[0] and "Traceback" not in res.stderr
    open_box = tmp_path / "open.obj"
    open_box.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\n")
    res = run("server", "--mesh", str(open_box), "--port", "0", timeout=60)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "open" in res.stderr or "watertight" in res.stderr


def test_protocol_schema_and_devices(capsys):
    assert main(["protocol", "--schema"]) == 0
    schema = json.loads(capsys.readouterr().out)
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert "version 1" in schema["title"]
    assert set(schema["discriminator"]["mapping"]) == {
        "hello", "state", "ping", "bye", "welcome", "patch", "pong", "error", "room"
    }  # fmt: skip
    assert main(["devices", "--json"]) == 0
    devices = json.loads(capsys.readouterr().out)
    assert {d["profile"] for d in devices if d["kind"] == "sim"} >= {"phantom-desktop", "touch"}


def _spacemouse_attached() -> bool:
    from haptic_collab.client.devices.hid import list_devices

    return any(d["spec"] == "hid:256f:c635" for d in list_devices())


@pytest.mark.parametrize(
    ("spec", "says"),
    [
        ("sim:juggle", "unknown simulated device 'sim:juggle'; use sim:press"),
        ("hid:1234:5678", "no HID profile for 1234:5678"),
        ("hid:256f:c635", "`haptic devices`"),  # a SpaceMouse that is not plugged in
    ],
)
def test_client_with_a_bad_device_exits_2_before_connecting(spec: str, says: str) -> None:
    if spec == "hid:256f:c635" and _spacemouse_attached():
        pytest.skip("a SpaceMouse Compact is attached")
    # a reachable server: a client that got as far as the network would connect to it (and then
    # wait 20 s for a welcome that never comes)
    with socket.create_server(("127.0.0.1", 0)) as srv:
        srv.setblocking(False)
        port = srv.getsockname()[1]
        res = run(
            "client", "--device", spec, "--url", f"ws://127.0.0.1:{port}/ws", "--duration", "30",
            timeout=60,
        )  # fmt: skip
        with pytest.raises(BlockingIOError):
            srv.accept()  # no connection was ever made
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("haptic client: error: "), res.stderr
    assert says in lines[0] and "Traceback" not in res.stderr


def test_compose_services_run_valid_haptic_commands():
    yaml = pytest.importorskip("yaml")
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    parser = build_parser()
    entry = (ROOT / "Dockerfile").read_text()
    assert 'ENTRYPOINT ["haptic"]' in entry
    assert compose["services"]
    for name, svc in compose["services"].items():
        cmd = svc["command"] if isinstance(svc["command"], list) else shlex.split(svc["command"])
        args = parser.parse_args(cmd)  # raises SystemExit on an invalid command
        assert args.command in ("server", "client", "lobby"), name
    latency = compose["services"]["server-latency"]["command"]
    assert (
        latency[latency.index("--latency-ms") + 1] == "100"
        and "latency" in compose["services"]["server-latency"]["profiles"]
    )


@pytest.mark.slow
@pytest.mark.alone  # its verdict needs a quiet machine: run after the others
def test_demo_processes_feel_each_other(tmp_path):
    """`haptic demo`: server and two clients as processes; the report shows coupling and stability."""
    report = tmp_path / "report.json"
    plot = tmp_path / "demo.png"
    temp = tmp_path / "tmp"
    temp.mkdir()
    res = run(
        "demo", "--headless", "--duration", "12", "--port", "0", "--report", str(report), "--plot", str(plot),
        timeout=180, tmpdir=temp,
    )  # fmt: skip
    if res.returncode == 3:  # the demo says the machine was too loaded to judge
        pytest.skip(res.stdout.strip().splitlines()[-1])
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    assert "viewer: http://127.0.0.1:" in res.stdout and "B feels A" in res.stdout
    assert list(temp.iterdir()) == []  # no --workdir: the logs and telemetry are gone
    data = json.loads(report.read_text())
    assert set(data) >= {"users", "coupling", "server", "network"}
    for name in ("A", "B"):
        u = data["users"][name]
        assert set(u) >= {
            "servo_rate_hz",
            "period_us_p99",
            "max_force_n",
            "hold_oscillation_mm",
            "stable",
        }
        assert u["stable"], u
        # the servo loop ran the whole time (a stalled loop shows tens of Hz); how close it keeps
        # to 1 kHz is measured by `haptic bench servo` and the demo's report, not asserted here
        assert u["servo_rate_hz"] > 300.0
    # A really pressed: about 2 N with PI gains; on a loaded machine the measured delay can rule
    # PI out for A's contact, and the verified P coupling gives K_h e alone, about 0.9 N
    assert data["users"]["A"]["max_force_n"] > 0.5
    c = data["coupling"]
    # while A holds, B's side bulges out: the surface under B moves out, B's force rises
    assert c["b_surface_displacement_mm"] > 0.3 and c["b_force_rise_n"] > 0.01, c
    rest = c["rest_window_s"]
    assert rest[0] >= c["b_settled_s"] and rest[1] - rest[0] >= 0.25  # B at rest, settled
    assert rest[1] <= data["timeline_s"]["a_contact"] or rest[0] >= data["timeline_s"]["a_hold_end"]
    assert c["ratio"] == pytest.approx(c["b_force_during_a_press_n"] / c["b_force_at_rest_n"])
    assert data["workdir"] is None
    # the round trip was measured (pings answered), and on loopback it is short
    assert data["server"]["sim_rate_hz"] == 20.0 and 0.0 < data["network"]["rtt_ms_p50"] < 500.0
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and plot.stat().st_size > 20_000


def test_a_failed_demo_keeps_its_logs_and_says_where(tmp_path):
    broken = tmp_path / "broken.stl"
    broken.write_bytes(b"\x00garbage that is not a mesh" * 10)
    temp = tmp_path / "tmp"
    temp.mkdir()
    res = run(
        "demo", "--headless", "--duration", "12", "--port", "0", "--mesh", str(broken),
        timeout=120, tmpdir=temp,
    )  # fmt: skip
    assert res.returncode == 1, res.stdout[-2000:] + res.stderr[-2000:]
    (kept,) = temp.iterdir()
    assert f"logs and telemetry are in {kept}" in res.stderr
    assert "broken.stl" in (kept / "server.log").read_text()


def test_bench_server_prints_one_json_document(capsys, monkeypatch):
    from haptic_collab.bench import world as bench_world

    # the measurements themselves take minutes; what is checked here is what gets printed
    monkeypatch.setattr(bench_world, "bench_world", lambda: {"benchmark": "world_tick"})
    monkeypatch.setattr(bench_world, "bench_viewer_stream", lambda: {"n_vertices": 2562})
    monkeypatch.setattr(bench_world, "bench_gain_advice", lambda: {"users": 8})
    monkeypatch.setattr(bench_world, "bench_room", lambda: {"users": 32})
    monkeypatch.setattr(bench_world, "bench_fem", lambda: {"n_vertices": 642})
    assert main(["bench", "server", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)  # one document: a second copy would not parse
    assert out["viewer_stream"] == {"n_vertices": 2562} and out["gain_advice"] == {"users": 8}
