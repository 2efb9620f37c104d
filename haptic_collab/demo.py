"""``haptic demo``: the server and two simulated users as separate processes over real websockets.

User A presses into the top of the shared water balloon, holds and releases; user B rests lightly
on its side the whole time. ``--scenario palpation`` (:func:`palpation_setup`): the FEM liver
sphere with a hidden stiff lump under its top (``--inclusion``), A presses in beside the lump,
holds, slides across the top over the lump and back at the same depth and lets go; the report
says how much A's force rose over the lump and whether B felt the sweep
(:func:`haptic_collab.demo_report.palpation_report`). Because every local model is rebuilt from the current global surface,
B's side bulges out while A presses and B feels it: B's force rises. The run says what to open
now and for how long (:func:`opening_lines`), what it shows phase by phase in words, read from
the users' telemetry as they write it (:class:`_Narrator`), then a summary table, whether B felt
A, and at the end a one-line verdict with the viewer it served and the paths of its report, plot
and logs (:func:`closing_lines`); ``--report`` writes JSON, ``--plot`` a PNG.

This module runs the demo: its options, the server's port, the server's and both users' processes
(``python -m haptic_collab.cli``), the viewer and the live progress. A's timeline and what the
run's telemetry says (the hold judgement, how much B feels A, the table and the plot) are
:mod:`haptic_collab.demo_report`'s. The processes' logs and telemetry go to ``--workdir``, or to a
temporary folder deleted after a good run.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
import webbrowser
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from haptic_collab.client.devices.trajectories import Sweep
from haptic_collab.demo_report import (
    B_FORCE_ON_N,
    Timeline,
    build_report,
    palpation_lines,
    palpation_report,
    plot_demo,
    print_summary,
    run_verdict_line,
    timeline,
)
from haptic_collab.server.security import is_loopback
from haptic_collab.server.urls import WILDCARD_HOSTS, local_host, url_host, viewer_urls

#: A direction or point (x, y, z).
FloatVec = tuple[float, float, float]


@dataclass
class DemoOptions:
    """Options of ``haptic demo``."""

    duration_s: float = 20.0
    headless: bool = False
    report: Path | None = None
    plot: Path | None = None
    sim_rate_hz: float = 20.0
    servo_rate_hz: float = 1000.0
    latency_ms: float = 0.0
    jitter_ms: float = 0.0
    loss: float = 0.0
    mesh: str = "balloon"
    port: int = 8765
    host: str = "127.0.0.1"
    local_model: str = "pi"
    workdir: Path | None = None
    seed: int = 0
    stiffness_scale: float = 1.0
    material: str | None = None
    object: str = "balloon"
    mesh_scale: float | None = None
    mesh_size: float | None = None
    mesh_max_edge: float | None = None
    hand_mass_kg: float | None = None
    hand_stiffness_n_per_m: float | None = None
    hand_damping_n_s_per_m: float | None = None
    log_level: str = "info"
    #: Run a do-nothing 1 kHz loop (``bench_servo --minimal-only``) beside the users for the
    #: demo's duration: what this machine's scheduler gives any loop, for the users' servo
    #: timing to be read against (it takes about a third of a core).
    reference_loop: bool = False
    #: ``press`` (A presses the top and holds) or ``palpation`` (the FEM liver with a stiff lump
    #: under the top: A presses in and sweeps across it and back; :func:`palpation_setup`).
    scenario: str = "press"
    #: ``--inclusion`` files and their ``--inclusion-material`` names, passed to the server
    #: (the palpation scenario writes its own lump and twin when none are given).
    inclusions: tuple[str, ...] = ()
    inclusion_materials: tuple[str, ...] = ()

    def hand_args(self) -> list[str]:
        """``haptic client`` flags for the simulated hand values that were given (both users)."""
        out: list[str] = []
        for flag, value in (
            ("--hand-mass", self.hand_mass_kg),
            ("--hand-stiffness", self.hand_stiffness_n_per_m),
            ("--hand-damping", self.hand_damping_n_s_per_m),
        ):
            if value is not None:
                out += [flag, repr(float(value))]
        return out


#: Hosts that mean "every interface" when bound.


def _bind_socket(host: str, port: int) -> socket.socket:
    """A TCP socket bound to (host, port) the way the server's listener binds it.

    The server listens through asyncio's ``create_server``, which sets ``SO_REUSEADDR`` on POSIX:
    a port whose earlier connections linger in TIME_WAIT (a demo run a minute ago) is free for it,
    and must be free here too. A port another process listens on is still refused.

    Raises
    ------
    OSError
        The address cannot be bound.
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    if host not in WILDCARD_HOSTS and ":" not in host:
        with contextlib.suppress(OSError):
            family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0][0]
    s = socket.socket(family, socket.SOCK_STREAM)
    try:
        if os.name == "posix":
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((host, port))
    except OSError:
        s.close()
        raise
    return s


def _free_port(host: str) -> int:
    """A port the server can listen on at ``host`` (the kernel's pick)."""
    with _bind_socket(host, 0) as s:
        return int(s.getsockname()[1])


def _port_free(host: str, port: int) -> bool:
    """Whether the server could listen on (host, port) now (TIME_WAIT leftovers do not count)."""
    try:
        with _bind_socket(host, port) as s:
            s.listen(1)
    except OSError:
        return False
    return True


def _status(host: str, port: int) -> dict[str, Any] | None:
    try:
        url = f"http://{url_host(local_host(host))}:{port}/status"
        with urllib.request.urlopen(url, timeout=1.0) as r:
            return json.loads(r.read())  # type: ignore[no-any-return]
    except (OSError, ValueError):
        return None


def _status_sample(status: dict[str, Any]) -> dict[str, Any] | None:
    """A polled server status as a sample of the overrun count (when the server reports its
    tick and overruns): this process's clock [s], the tick, the overruns so far."""
    if "tick" not in status or "overruns" not in status:
        return None
    return {
        "t_clock_s": time.perf_counter(),
        "tick": status["tick"],
        "overruns": status["overruns"],
    }


def _has_display() -> bool:
    """Whether a graphical browser can open here (never hand the terminal to a text browser)."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _haptic(*args: str) -> list[str]:
    return [sys.executable, "-m", "haptic_collab.cli", *args]


class DemoVerdictError(RuntimeError):
    """The run finished and its report was written, but not every user was stable.

    ``exit_code`` is the run's exit status (:data:`haptic_collab.demo_report.EXIT_CODES`): 1 when
    a user was unstable or never rendered, 3 when the machine was too loaded to judge; ``report``
    the report dict.
    """

    def __init__(self, message: str, exit_code: int, report: dict[str, Any]) -> None:
        super().__init__(message)
        self.exit_code = exit_code
        self.report = report


def run_demo(opts: DemoOptions) -> dict[str, Any]:
    """Run the demo; return the report dict when every user was stable.

    The processes' logs and telemetry go to ``opts.workdir``, kept; without it, to a temporary
    folder that is deleted after a good run and kept (its path printed) when the run fails or a
    user was not judged stable.

    Raises
    ------
    ValueError
        Bad options (duration shorter than 12 s, port in use).
    DemoVerdictError
        The run finished, its report, plot and summary written, but a user was unstable, never
        rendered, or could not be judged (the machine too loaded); its ``exit_code`` says which.
    RuntimeError
        A process failed (its output is shown).
    """
    if opts.duration_s < 12.0:
        raise ValueError("--duration must be at least 12 s (approach, press, hold, release)")
    if opts.scenario not in SCENARIOS:
        raise ValueError(f"--scenario must be one of {', '.join(SCENARIOS)}, got {opts.scenario!r}")
    if opts.scenario == "palpation":
        if opts.mesh != "balloon" or opts.mesh_scale is not None or opts.mesh_size is not None:
            raise ValueError(
                "--scenario palpation sweeps the default 0.1 m sphere: leave --mesh, "
                "--mesh-scale and --mesh-size out"
            )
        opts = replace(opts, object="fem")
    port = opts.port or _free_port(opts.host)
    if not _port_free(opts.host, port):
        raise ValueError(
            f"port {port} on {opts.host} is in use (pick another with --port, or 0 for any)"
        )
    work = opts.workdir or Path(tempfile.mkdtemp(prefix="haptic-demo-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        report = _run_in(work, port, opts)
    except BaseException:
        print(f"haptic demo: logs and telemetry are in {work}", file=sys.stderr, flush=True)
        raise
    verdict = report["verdict"]
    kept = opts.workdir is not None or verdict["exit_code"] != 0
    if not kept:  # a temporary folder (5-8 MB of telemetry): gone after a good run
        shutil.rmtree(work, ignore_errors=True)
    urls = viewer_urls(opts.host, port)
    for line in closing_lines(report, urls, opts.report, opts.plot, work, kept):
        print(line, flush=True)
    if verdict["exit_code"] != 0:
        failed = ", ".join(f"{n} {v}" for n, v in verdict["users"].items() if v != "stable")
        raise DemoVerdictError(
            f"{verdict['verdict']} ({failed})", int(verdict["exit_code"]), report
        )
    return report


def closing_lines(
    report: dict[str, Any],
    urls: list[str],
    report_path: Path | None,
    plot_path: Path | None,
    work: Path,
    kept: bool,
) -> list[str]:
    """The demo's last lines: the verdict in one line, then the viewer it served and where its
    report, plot, logs and telemetry are (absolute paths, or how to get them when not written).

    Parameters
    ----------
    report : dict
        The run's report (:func:`haptic_collab.demo_report.build_report`).
    urls : list of str
        The viewer URLs the demo served (it has stopped).
    report_path, plot_path : Path or None
        Where ``--report`` and ``--plot`` were written (None: not asked for).
    work : Path
        The folder of the processes' logs and telemetry.
    kept : bool
        Whether ``work`` is still there (a temporary one is deleted after a good run).
    """
    # "viewer: URL" as the server prints it (scripts look for it)
    lines = ["", run_verdict_line(report), f"viewer: {urls[0]} (served while the demo ran)"]
    for label, path, flag in (("report:", report_path, "--report"), ("plot:", plot_path, "--plot")):
        lines.append(
            f"{label:<7} {path.resolve()}"
            if path is not None
            else f"{label:<7} none written (add {flag} FILE)"
        )
    lines.append(
        f"{'logs:':<7} {work.resolve()} (server.log, A.log, B.log; telemetry A.csv, B.csv)"
        if kept
        else f"{'logs:':<7} deleted after a good run (keep them with --workdir DIR)"
    )
    return lines


#: ``--scenario`` choices.
SCENARIOS = ("press", "palpation")

#: The palpation scenario's lump when no ``--inclusion`` is given: diameter and depth of its top
#: under the surface [m], and how many times as stiff as liver. A 10 mm lump 10 mm deep changes
#: K_o under the 15 mm finger pad by about 2 %, below the JND; 30 mm, +19 % (docs/palpation.md).
PALPATION_LUMP = (0.030, 0.010, 10.0)

#: Half the sweep's arc [rad]: A slides from this far on one side of the top to as far on the
#: other, over the lump's twin (-20 degrees) and the lump (+20 degrees); the slide and its 30 mm
#: standoff stay inside the simulated Phantom Desktop's 160 x 120 x 120 mm workspace, centred
#: outside the top (:class:`client.devices.trajectories.Sweep`).
SWEEP_HALF_ANGLE_RAD = math.radians(35.0)

#: The palpating hand's target depth under the surface while it slides [m].
SWEEP_DEPTH_M = 0.010


def palpation_timeline(duration_s: float) -> tuple[Timeline, float]:
    """A's palpation for a run of ``duration_s`` seconds: its :class:`Timeline` (the press, a 2 s
    hold judged as the press scenario's, then the slide out and back and the withdrawal counted
    as the release) and the slide's one-way duration [s]."""
    delay = max(4.0, 0.2 * duration_s)
    approach, press, hold, release = 1.0, 1.5, 2.0, 1.0
    sweep = max(3.0, (0.9 * duration_s - delay - approach - press - hold - release) / 2.0)
    return Timeline(delay, approach, press, hold, 2.0 * sweep + release), sweep


def palpation_setup(
    work: Path, opts: DemoOptions
) -> tuple[Timeline, Sweep, list[str], tuple[FloatVec, FloatVec]]:
    """What the palpation scenario needs, written into ``work``.

    The lump (``--inclusion`` files as given, or :data:`PALPATION_LUMP` and its twin of liver
    written as ``lump.stl`` and ``twin.stl``: :func:`haptic_collab.research.palpation.
    lump_and_twin`), A's sweep (:class:`client.devices.trajectories.Sweep` over the default
    sphere, written as ``sweep.csv`` at 200 Hz for ``sim:replay``).

    Returns
    -------
    (timeline, sweep, server flags, (direction over the lump, direction beside it))
    """
    from haptic_collab.research.palpation import LUMP_ANGLE_RAD, lump_and_twin, lump_direction
    from haptic_collab.server.solid_materials import SOLID_PRESETS

    tl, sweep_s = palpation_timeline(opts.duration_s)
    files, materials = list(opts.inclusions), list(opts.inclusion_materials)
    if not files:
        diameter, depth, factor = PALPATION_LUMP
        liver = SOLID_PRESETS["liver"]
        stiff = replace(liver, name=f"liver*{factor:g}", young_pa=liver.young_pa * factor)
        for inc in lump_and_twin(diameter, depth, stiff, liver):
            path = work / f"{inc.where}.stl"
            inc.mesh.export(path)
            files.append(str(path))
            materials.append(inc.material.name)
    flags: list[str] = []
    for f, m in zip(files, materials, strict=True):
        flags += ["--inclusion", f, "--inclusion-material", m]
    sweep = Sweep(
        centre=(0.0, 0.0, 0.0),
        radius_m=0.1,
        start=tuple(lump_direction(SWEEP_HALF_ANGLE_RAD, -1.0)),
        end=tuple(lump_direction(SWEEP_HALF_ANGLE_RAD, 1.0)),
        depth_m=SWEEP_DEPTH_M,
        delay_s=tl.delay_s,
        approach_s=tl.approach_s,
        press_s=tl.press_s,
        hold_s=tl.hold_s,
        sweep_s=sweep_s,
        release_s=tl.release_s - 2.0 * sweep_s,
    )
    with open(work / "sweep.csv", "w") as fh:
        fh.write("t_s,x_m,y_m,z_m\n")
        for i in range(int((sweep.duration_s + 1.0) * 200) + 1):
            x, y, z = sweep(i / 200.0)
            fh.write(f"{i / 200.0:.3f},{x:.6f},{y:.6f},{z:.6f}\n")
    over = tuple(float(v) for v in lump_direction(LUMP_ANGLE_RAD, 1.0))
    beside = tuple(float(v) for v in lump_direction(LUMP_ANGLE_RAD, -1.0))
    return tl, sweep, flags, (over, beside)  # type: ignore[return-value]


def _run_in(work: Path, port: int, opts: DemoOptions) -> dict[str, Any]:
    """Run the processes with their logs and telemetry in ``work``; report, plot, summary."""
    tl = timeline(opts.duration_s)
    palpation: tuple[Sweep, tuple[FloatVec, FloatVec]] | None = None
    a_device, a_extra = "sim:press", ["--trajectory", tl.options()]
    inclusion_flags: list[str] = []
    for file, material in zip(opts.inclusions, opts.inclusion_materials, strict=True):
        inclusion_flags += ["--inclusion", file, "--inclusion-material", material]
    if opts.scenario == "palpation":
        tl, sweep, inclusion_flags, where = palpation_setup(work, opts)
        palpation = (sweep, where)
        a_device, a_extra = f"sim:replay:{work / 'sweep.csv'}", []
    urls = viewer_urls(opts.host, port)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    server_cmd = _haptic(
        "--log-level", opts.log_level,
        "server", "--host", opts.host, "--port", str(port), "--mesh", opts.mesh,
        "--sim-rate", f"{opts.sim_rate_hz:g}", "--latency-ms", f"{opts.latency_ms:g}",
        "--jitter-ms", f"{opts.jitter_ms:g}", "--loss", f"{opts.loss:g}", "--seed", str(opts.seed),
        "--stiffness-scale", repr(float(opts.stiffness_scale)),
    )  # fmt: skip
    if opts.material is not None:
        server_cmd += ["--material", opts.material]
    if opts.object != "balloon":
        server_cmd += ["--object", opts.object]
    if opts.mesh_scale is not None:
        server_cmd += ["--mesh-scale", repr(float(opts.mesh_scale))]
    if opts.mesh_size is not None:
        server_cmd += ["--mesh-size", repr(float(opts.mesh_size))]
    if opts.mesh_max_edge is not None:
        server_cmd += ["--mesh-max-edge", repr(float(opts.mesh_max_edge))]
    server_cmd += inclusion_flags
    hint = ""
    if not is_loopback(local_host(opts.host)) or opts.host in WILDCARD_HOSTS:
        # reachable from the network: the demo's users and viewers need a token (docs/security.md)
        token = secrets.token_urlsafe(18)
        env["HAPTIC_TOKEN"] = token
        server_cmd += ["--token", token]
        hint = f"#token={token}"
    logs = {k: open(work / f"{k}.log", "w") for k in ("server", "A", "B")}  # noqa: SIM115
    procs: dict[str, subprocess.Popen[bytes]] = {}
    reference: subprocess.Popen[bytes] | None = None
    reference_stats: dict[str, Any] | None = None
    status_samples: list[dict[str, Any]] = []
    try:
        procs["server"] = subprocess.Popen(
            server_cmd, stdout=logs["server"], stderr=subprocess.STDOUT, env=env
        )
        t0 = time.monotonic()
        while _status(opts.host, port) is None:
            if procs["server"].poll() is not None:
                raise RuntimeError(
                    "the server exited:\n" + (work / "server.log").read_text()[-2000:]
                )
            if time.monotonic() - t0 > 60.0:
                raise RuntimeError("the server did not come up within 60 s")
            time.sleep(0.1)
        opened = False
        if not opts.headless and _has_display():
            with contextlib.suppress(Exception):
                opened = bool(webbrowser.open(urls[0] + hint))
        for line in opening_lines(
            [u + hint for u in urls], tl, opts.duration_s, opened, opts.scenario
        ):
            print(line, flush=True)
        ws = f"ws://{url_host(local_host(opts.host))}:{port}/ws"
        common = [
            "--url", ws, "--servo-rate", f"{opts.servo_rate_hz:g}", "--local-model", opts.local_model,
            "--duration", f"{opts.duration_s:g}", *opts.hand_args(),
        ]  # fmt: skip
        for name, device, extra in (
            # B rests on the side a press on the top moves most (server.room), whoever joins first
            ("B", "sim:rest", ["--anchor", "side:1"]),
            ("A", a_device, a_extra),
        ):
            procs[name] = subprocess.Popen(
                _haptic(
                    "--log-level",
                    opts.log_level,
                    "client",
                    "--name",
                    name,
                    "--device",
                    device,
                    *common,
                    *extra,
                    "--record",
                    str(work / f"{name}.csv"),
                    "--summary",
                    str(work / f"{name}.json"),
                ),  # fmt: skip
                stdout=logs[name],
                stderr=subprocess.STDOUT,
                env=env,
            )
        if opts.reference_loop:
            reference = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "haptic_collab.bench.servo",
                    "--minimal-only",
                    "--duration",
                    f"{opts.duration_s:g}",
                    "--rate",
                    f"{opts.servo_rate_hz:g}",
                ],  # fmt: skip
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                env=env,
            )
        status_samples = _progress(opts, procs, port, tl, work)
        for name in ("A", "B"):
            rc = procs[name].wait(timeout=60.0)
            if rc != 0:
                raise RuntimeError(
                    f"client {name} failed (exit {rc}):\n"
                    + (work / f"{name}.log").read_text()[-3000:]
                )
        server_status = _status(opts.host, port) or {}
        if (sample := _status_sample(server_status)) is not None:
            status_samples.append(sample)
        if reference is not None:
            out, _ = reference.communicate(timeout=opts.duration_s + 30.0)
            with contextlib.suppress(ValueError):
                reference_stats = json.loads(out)
    finally:
        if reference is not None and reference.poll() is None:
            reference.kill()
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs.values():
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=5.0)
            if p.poll() is None:
                p.kill()
        for f in logs.values():
            f.close()
    report = build_report(work, tl, server_status, opts, status_samples)
    if reference_stats is not None:
        report["reference_loop"] = {
            k: reference_stats.get(k)
            for k in ("rate_hz", "period_p99_us", "period_max_us", "missed_per_s", "realtime")
        }
        ref_p99 = reference_stats.get("period_p99_us")
        for u in report["users"].values():
            p99 = u.get("period_us_p99")
            u["period_p99_vs_reference"] = p99 / ref_p99 if p99 and ref_p99 else None
    if palpation is not None:
        sweep, (over, beside) = palpation
        report["palpation"] = palpation_report(work, sweep, over, beside)
    report["workdir"] = str(work) if opts.workdir is not None else None  # a temp one is deleted
    if opts.report:
        opts.report.parent.mkdir(parents=True, exist_ok=True)
        opts.report.write_text(json.dumps(report, indent=2))
    if opts.plot:
        plot_demo(work, tl, opts.plot)
    print_summary(report)
    if "palpation" in report:
        for line in palpation_lines(report["palpation"]):
            print(line)
    return report


#: How often the demo polls the server's status while the users run [s].
_POLL_S = 0.5


#: About how long the users take to start and join [s] (2-5 s measured on a busy 2-core machine).
JOIN_S = 4.0


def opening_lines(
    urls: list[str], tl: Timeline, duration_s: float, opened: bool, scenario: str = "press"
) -> list[str]:
    """What the demo says once its server is up: what to open now and for how long, and what
    will happen (A's timeline in seconds from A's start; the users need a few seconds to join;
    ``scenario`` as ``--scenario``)."""
    # the users run duration_s once they have joined, which takes a few seconds
    lines = [f"open {urls[0]} now: the demo is live for about {duration_s + JOIN_S:.0f} s"]
    lines += [f"  (or {u})" for u in urls[1:]]
    if opened:
        lines.append("  (opened in your browser)")
    if scenario == "palpation":
        lines.append(
            f"What happens: users A and B join; B rests on the liver's side; after "
            f"{tl.delay_s:.0f} s A presses into the top beside a hidden stiff lump, holds, then "
            f"slides across the top over the lump and back and lets go at "
            f"{tl.hold_end_s + tl.release_s:.0f} s. Over the lump A's force rises at the same "
            "depth; B feels A's sweep through the liver."
        )
        return lines
    lines.append(
        f"What happens: users A and B join; B rests on the balloon's side; after {tl.delay_s:.0f} s "
        f"A moves onto the top, presses in for {tl.press_s:g} s, holds until "
        f"{tl.hold_end_s:.0f} s and lets go. While A presses, B's side bulges out and B's force "
        "rises: B feels A."
    )
    return lines


def _last_row(path: Path) -> dict[str, float] | None:
    """The last complete row of a telemetry CSV that a client is still writing, by column name
    (the client appends rows every 0.2 s); None when it has none yet or cannot be read."""
    try:
        with open(path, "rb") as f:
            header = f.readline().decode().strip().split(",")
            f.seek(0, os.SEEK_END)
            end = f.tell()
            f.seek(max(0, end - 8192))
            tail = f.read().decode(errors="replace")
    except OSError:
        return None
    complete = tail.split("\n")[:-1]  # the text after the last newline may be half a row
    for line in reversed(complete):
        values = line.strip().split(",")
        if len(values) == len(header) and values[0] != header[0]:
            try:
                return dict(zip(header, map(float, values), strict=True))
            except ValueError:
                return None
    return None


class _Narrator:
    """Says what the demo is showing now, in words: who has joined, and A's phase with both
    users' forces, read from the users' telemetry as they write it (A's own clock, so the phase
    is A's real one, not the demo's guess)."""

    def __init__(self, tl: Timeline, duration_s: float, sweeps: bool = False) -> None:
        self.tl = tl
        self.duration_s = duration_s
        #: A slides across the top after its hold (the palpation scenario): the first part of
        #: the timeline's release is the slide out and back, its last second the withdrawal.
        self.sweeps = sweeps
        #: B's latest force while A was still away [N] (B's resting force, for comparison).
        self.b_rest_n: float | None = None
        #: Both users have joined (the server counted two once).
        self.joined = False

    def phase(
        self, users: int | None, a: dict[str, float] | None, b: dict[str, float] | None
    ) -> tuple[str, str]:
        """(which phase, what it shows in words). ``users``: users joined per the server (None:
        unknown); ``a``, ``b``: the users' latest telemetry rows (None: none yet)."""
        if users is not None and users >= 2:
            self.joined = True
        if not self.joined and a is None:
            if not users:
                return "joining", "waiting for A and B to join (their processes are starting)"
            return "joining", f"waiting for A and B to join ({users} of 2 joined)"
        if a is None:
            return "starting", "A and B joined; A's hand is starting"
        tl, t = self.tl, a["t_s"]
        b_on = b is not None and b["in_contact"] > 0 and b["force_n"] > B_FORCE_ON_N
        fb = b["force_n"] if b is not None else 0.0
        if t < tl.contact_s and b_on:
            self.b_rest_n = fb
        b_touches = b is not None and b["in_contact"] > 0
        b_rests = (
            f"B rests on the side with {fb:.2f} N"
            if b_on
            else "B touches the side, no force yet"
            if b_touches
            else "B is off the side"
            if self.b_rest_n is not None
            else "B moves onto the side"
        )
        rest = f" ({self.b_rest_n:.2f} N at rest)" if self.b_rest_n is not None else ""
        fa = a["force_n"]
        if t < tl.delay_s:
            return f"waiting B {'on' if b_on else 'off'}", (
                f"{b_rests}; A waits above the top (A touches it in {tl.contact_s - t:.0f} s)"
            )
        if t < tl.contact_s:
            return "approach", f"A moves down onto the top; {b_rests}"
        if t < tl.contact_s + tl.press_s:
            return "press", (
                f"A presses into the top with {fa:.2f} N: the dent grows and B's side bulges "
                f"out; B feels {fb:.2f} N{rest}"
            )
        if t < tl.hold_end_s:
            return "hold", f"A holds still, pressing with {fa:.2f} N; B feels {fb:.2f} N{rest}"
        if self.sweeps and t < tl.hold_end_s + tl.release_s - 1.0:
            return "sweep", (
                f"A slides across the top at the same depth, over the hidden lump and back, "
                f"pressing {fa:.2f} N; B feels {fb:.2f} N{rest}"
            )
        if t < tl.hold_end_s + tl.release_s:
            return "release", f"A lets go ({fa:.2f} N); B feels {fb:.2f} N{rest}"
        left = self.duration_s - t
        if left < 0.5:
            return "ending", "the users are finishing; then the report"
        return "after", (
            f"A has let go and the balloon settles; {b_rests} (the run ends in {left:.0f} s)"
        )


def _server_words(st: dict[str, Any]) -> str:
    """The server's figures in a few words (``?`` for what it did not report)."""
    if not st:
        return "server: no answer"
    return (
        f"server: tick {st.get('tick', '?')}, {st.get('tick_ms_p50', 0) or 0:.1f} ms a tick, "
        f"{st.get('overruns', '?')} overran"
    )


def _progress(
    opts: DemoOptions,
    procs: dict[str, subprocess.Popen[bytes]],
    port: int,
    tl: Timeline,
    work: Path,
) -> list[dict[str, Any]]:
    """Say what the demo shows, in words, when it changes and every 2 s while the users run;
    return the server's status polled every :data:`_POLL_S` (``t_clock_s``,
    ``time.perf_counter()`` at the poll [s], the clock of the clients' ``clock_origin_s``;
    ``tick``, ``overruns``): the report's server overruns during each user's hold."""
    t0 = time.monotonic()
    last = -1.0
    polled = -1.0
    said = ""
    samples: list[dict[str, Any]] = []
    st: dict[str, Any] = {}
    narrator = _Narrator(tl, opts.duration_s, sweeps=opts.scenario == "palpation")
    while any(procs[n].poll() is None for n in ("A", "B")):
        t = time.monotonic() - t0
        if t - polled >= _POLL_S:
            polled = t
            st = _status(opts.host, port) or {}
            if (sample := _status_sample(st)) is not None:
                samples.append(sample)
            users = st.get("users")
            which, words = narrator.phase(
                users if isinstance(users, int) else None,
                _last_row(work / "A.csv"),
                _last_row(work / "B.csv"),
            )
            if which != said or t - last >= 2.0:  # a new phase at once, else every 2 s
                said, last = which, t
                print(f"  t={t:5.1f} s  {words}   [{_server_words(st)}]", flush=True)
        time.sleep(0.1)
    return samples
