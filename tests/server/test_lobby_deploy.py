"""The deploy files of "finding a room", read as data (no Docker engine runs here): the
docker-compose services of two room servers and a lobby are valid ``haptic`` commands that fit
together, the services that were there before are unchanged, and the image carries the viewer
and runs as a numeric non-root user.
"""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import Any

import pytest

from haptic_collab.cli import build_parser
from haptic_collab.cli.run import _lobby_backend
from haptic_collab.server.config import load_server_config

yaml = pytest.importorskip("yaml")
ROOT = Path(__file__).resolve().parents[2]


def compose() -> dict[str, Any]:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def command(svc: dict[str, Any]) -> list[str]:
    cmd = svc["command"]
    return cmd if isinstance(cmd, list) else shlex.split(cmd)


def test_two_room_servers_and_a_lobby_that_points_at_them(tmp_path: Path) -> None:
    services = compose()["services"]
    parser = build_parser()
    rooms = {n: services[n] for n in ("room-a", "room-b")}
    lobby_svc = services["lobby"]
    for svc in (*rooms.values(), lobby_svc):
        assert svc["profiles"] == ["rooms"]  # `docker compose up` starts what it did before
        assert svc["image"] == "haptic-collab"
    published = {}
    for name, svc in rooms.items():
        args = parser.parse_args(command(svc))
        assert args.command == "server" and args.host == "0.0.0.0"
        # the servers check room tokens with the secret the lobby signs them with
        assert args.token_secret_file == "/run/secrets/token_secret"
        assert "token_secret" in svc["secrets"]
        (mount,) = svc["configs"]
        assert mount["target"] == args.config
        host_ip, host_port, container_port = svc["ports"][0].split(":")
        assert host_ip == "127.0.0.1" and int(container_port) == args.port
        published[name] = int(host_port)
        assert "snapshots" in svc["volumes"][0]
    # the rooms' configuration makes rooms of any name on demand, a few per server
    cfg = tmp_path / "rooms.toml"
    cfg.write_text(compose()["configs"]["rooms"]["content"])
    keys = load_server_config(cfg)
    assert keys["room_templates"] == {"any": {"prefix": ""}}
    assert 2 <= int(keys["max_rooms"]) <= 16  # type: ignore[call-overload]
    # the lobby reads each server by its service name and gives clients the published port
    args = parser.parse_args(command(lobby_svc))
    assert args.command == "lobby" and args.token_secret_file == "/run/secrets/token_secret"
    assert "token_secret" in lobby_svc["secrets"]
    assert args.status_token_file == "/run/secrets/metrics_token"
    args.status_token_file = str(tmp_path / "metrics_token")  # the secret, here
    (tmp_path / "metrics_token").write_text("t" * 32 + "\n")
    backend = _lobby_backend(args)
    assert backend.status_token == "t" * 32
    assert [s.url for s in backend.servers] == ["http://room-a:8765", "http://room-b:8765"]
    assert [s.bases[0] for s in backend.servers] == [
        f"ws://localhost:{published['room-a']}",
        f"ws://localhost:{published['room-b']}",
    ]
    assert lobby_svc["ports"] == [f"127.0.0.1:{args.port}:{args.port}"]
    assert set(lobby_svc["depends_on"]) == {"room-a", "room-b"}
    assert compose()["secrets"]["token_secret"]["file"]


def test_status_is_read_with_the_metrics_token_the_servers_off_loopback_require() -> None:
    """Every server here listens on 0.0.0.0, so its ``/status`` answers only with its metrics
    token (403 without one configured): the lobby and every healthcheck that reads ``/status``
    send the token the server checks, from a secret the service mounts; the others do not read
    it (a healthcheck that fails keeps the lobby and the users from starting)."""
    services = compose()["services"]
    parser = build_parser()
    lobby = parser.parse_args(command(services["lobby"]))
    for name, svc in services.items():
        args = parser.parse_args(command(svc))
        if args.command != "server":
            continue
        assert args.host == "0.0.0.0"
        check = " ".join(svc["healthcheck"]["test"])
        if "/status" in check:
            assert args.metrics_token_file and args.metrics_token_file in check, name
        if name in ("room-a", "room-b"):  # the lobby reads their /status
            assert args.metrics_token_file == lobby.status_token_file, name
        if args.metrics_token_file:
            secret = args.metrics_token_file.removeprefix("/run/secrets/")
            assert secret in svc["secrets"] and secret in compose()["secrets"], name
    assert "metrics_token" in services["lobby"]["secrets"]


def test_the_services_there_before_still_run_the_same_commands() -> None:
    services = compose()["services"]
    parser = build_parser()
    for name in ("server", "user-a", "user-b"):
        assert "profiles" not in services[name]
        parser.parse_args(command(services[name]))
    user_a = parser.parse_args(command(services["user-a"]))
    assert user_a.url == "ws://server:8765/ws" and user_a.lobby is None


def _stages() -> list[list[tuple[str, str]]]:
    """The Dockerfile's stages, each a list of (INSTRUCTION, arguments)."""
    text = (ROOT / "Dockerfile").read_text().replace("\\\n", " ")
    stages: list[list[tuple[str, str]]] = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            if word.upper() == "FROM":
                stages.append([])
            stages[-1].append((word.upper(), rest.strip()))
    return stages


def test_the_image_carries_the_viewer_and_runs_non_root() -> None:
    build, final = _stages()[0], _stages()[-1]
    runs = [rest for word, rest in build if word == "RUN"]
    npm = next(i for i, r in enumerate(runs) if "cd web" in r and "npm ci" in r)
    wheel = next(i for i, r in enumerate(runs) if "pip wheel" in r)
    assert npm < wheel  # three.js is in web/ when the wheel is built
    assert ("COPY", "web ./web") in build
    # the wheel carries the viewer's page and the three.js it loads
    import tomllib

    data = tomllib.loads((ROOT / "pyproject.toml").read_text())
    files = data["tool"]["setuptools"]["package-data"]["haptic_collab"]
    assert "web/index.html" in files
    assert "web/node_modules/three/build/three.module.js" in files
    assert any("pip install" in r and ".whl" in r for w, r in final if w == "RUN")
    user = [rest for word, rest in final if word == "USER"][-1].split(":")[0]
    assert user.isdigit() and int(user) != 0
    exposed = {int(p) for w, r in final if w == "EXPOSE" for p in r.split()}
    assert {8765, build_parser().parse_args(["lobby", "--token-secret-file", "x"]).port} <= exposed
    entry = [rest for word, rest in final if word == "ENTRYPOINT"]
    assert entry == ['["haptic"]']


def test_the_lobby_and_client_commands_say_what_is_missing(tmp_path: Path, capsys) -> None:
    from haptic_collab.cli import main

    secret = tmp_path / "secret"
    secret.write_text("x" * 48)
    assert main(["lobby", "--token-secret-file", str(secret)]) == 2
    assert "--server URL" in capsys.readouterr().err
    both = ["--server", "http://127.0.0.1:1", "--agones-allocator", "http://127.0.0.1:2"]
    assert main(["lobby", "--token-secret-file", str(secret), *both]) == 2
    assert "one of the two" in capsys.readouterr().err
    short = tmp_path / "short"
    short.write_text("x")
    assert main(["lobby", "--token-secret-file", str(short), "--server", "http://h:1"]) == 2
    assert "at least 32 bytes" in capsys.readouterr().err
    off = ["--host", "0.0.0.0", "--server", "http://h:1"]
    assert main(["lobby", "--token-secret-file", str(secret), *off]) == 2
    assert "--token-file" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["lobby", "--token-secret-file", str(secret), "--server", "ftp://h"])
    assert "http(s)://HOST:PORT" in capsys.readouterr().err
    one = ["--token-secret-file", str(secret), "--server", "http://h:1"]
    assert main(["lobby", *one, "--trusted-proxy", "lb.example"]) == 2
    assert "address or a network such as 10.0.0.0/8, got 'lb.example'" in capsys.readouterr().err
    assert main(["lobby", *one, "--peer", "http://a:8780"]) == 2
    assert "--peer-self URL (this one) go together" in capsys.readouterr().err
    peers = ["--peer", "http://a:8780", "--peer", "http://b:8780", "--peer-self", "http://c:8780"]
    assert main(["lobby", *one, *peers]) == 2
    assert "is not among its peers" in capsys.readouterr().err
    bad = tmp_path / "metrics-token"
    bad.write_text("short")
    assert main(["lobby", *one, "--metrics-token-file", str(bad)]) == 2
    assert "the metrics token file must hold one token" in capsys.readouterr().err
    assert main(["lobby", *one, "--status-token-file", str(bad)]) == 2
    assert "the metrics token file must hold one token" in capsys.readouterr().err
    assert main(["lobby", *one, "--status-token-file", str(tmp_path / "none")]) == 2
    assert "cannot read the metrics token file" in capsys.readouterr().err
    agones = ["--token-secret-file", str(secret), "--agones-allocator", "http://h:2"]
    assert main(["lobby", *agones, "--status-token-file", str(bad)]) == 2
    assert "--status-token-file is for the local room servers" in capsys.readouterr().err
    assert main(["client", "--lobby", "http://127.0.0.1:1"]) == 2
    assert "--room NAME go together" in capsys.readouterr().err
    assert main(["client", "--lobby", "http://h:1", "--room", "a", "--url", "ws://h/ws"]) == 2
    assert "not both" in capsys.readouterr().err


async def test_the_room_servers_healthcheck_passes_against_a_server_off_loopback(
    tmp_path: Path,
) -> None:
    """room-a's healthcheck, run as Docker runs it, against a server listening on 0.0.0.0 with
    a metrics token (as in its container; the request goes to 127.0.0.1): it passes, and fails
    without the token (what kept the lobby from starting). Only the port and the secret's path
    differ from the compose file."""
    import asyncio
    import subprocess
    import sys

    from tests.server.test_rooms_need_a_token import token_server

    svc = compose()["services"]["room-a"]
    kind, *test = svc["healthcheck"]["test"]
    assert kind == "CMD" and test[:2] == ["python", "-c"]
    code = test[2]
    token = "h" * 32
    secret = tmp_path / "metrics_token"
    secret.write_text(token + "\n")
    async with token_server(tmp_path / "s", host="0.0.0.0", metrics_token=token) as port:
        here = code.replace("127.0.0.1:8765", f"127.0.0.1:{port}").replace(
            "/run/secrets/metrics_token", str(secret)
        )
        assert here != code and "/status" in here

        def run(src: str) -> int:
            return subprocess.run(
                [sys.executable, "-c", src], capture_output=True, timeout=60
            ).returncode

        assert await asyncio.to_thread(run, here) == 0
        bare = f"import urllib.request; urllib.request.urlopen('http://127.0.0.1:{port}/status')"
        assert await asyncio.to_thread(run, bare) != 0  # 401: the check before this change
