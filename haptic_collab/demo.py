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
import re
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
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

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
    script_start_s,
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
    #: ``--gravity`` [m/s^2]: the FEM solid sags under its own weight at start (0: weightless);
    #: passed to the server, refused with the balloon (:func:`check_gravity`).
    gravity_m_s2: float = 0.0

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
    check_gravity(opts)
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


#: How long the demo waits for its server to listen [s]: a FEM solid's start-up (volume mesh,
#: factor and modes) is 15-30 s for the default sphere on a quiet 2-core machine and several
#: times that under load (docs/fem.md, "Cost of the quadratic elements"); the largest stress
#: shape's first start-up is about 230 s quiet (docs/fem.md, "Linear tetrahedra with averaged
#: nodal pressure"; its modes are cached for the next).
SERVER_START_TIMEOUT_S = 600.0

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

#: How far from the sphere's centre the hand waits outside the slide's ends at most [m]: the
#: 0.1 m ball's radius and the sweep's 30 mm standoff. A larger sphere (the flatter top of a
#: sagged ball, 116 mm) gets a shorter standoff, at least :data:`SWEEP_MIN_STANDOFF_M`, so that
#: the hand's start stays inside the simulated Phantom Desktop's 160 mm wide workspace.
SWEEP_REACH_M = 0.13
#: The shortest standoff outside the slide's ends [m].
SWEEP_MIN_STANDOFF_M = 0.015


#: The palpation scenario's run length when none is given [s]: A's slide then takes 7.75 s each
#: way (about 16 mm/s). In a 20 s run it takes 4.25 s (29 mm/s), the proxy trails the hand
#: further, and A felt the default lump +4 % (not felt) where 30 s runs gave +12-13 %
#: (docs/palpation.md).
PALPATION_DURATION_S = 30.0

#: The press scenario's run length when none is given [s].
PRESS_DURATION_S = 20.0


def default_duration(scenario: str) -> float:
    """The run length [s] of ``haptic demo --scenario SCENARIO`` without ``--duration``."""
    return PALPATION_DURATION_S if scenario == "palpation" else PRESS_DURATION_S


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
    sweep = write_sweep(work, tl, sweep_s)
    over = tuple(float(v) for v in lump_direction(LUMP_ANGLE_RAD, 1.0))
    beside = tuple(float(v) for v in lump_direction(LUMP_ANGLE_RAD, -1.0))
    return tl, sweep, flags, (over, beside)  # type: ignore[return-value]


def write_sweep(
    work: Path,
    tl: Timeline,
    sweep_s: float,
    centre: FloatVec = (0.0, 0.0, 0.0),
    radius_m: float = 0.1,
) -> Sweep:
    """A's palpating sweep over the top of the sphere (``centre`` [m], ``radius_m`` [m]), written
    as ``work/sweep.csv`` (``t_s, x_m, y_m, z_m`` at 200 Hz, for ``sim:replay``).

    The default sphere is the unloaded liver ball; under ``--gravity`` the demo passes the
    sphere fitted to the rest surface the server reports (:func:`fit_top_sphere`), so that the
    hand slides :data:`SWEEP_DEPTH_M` inside the sagged top, not 10 mm above it. The hand
    waits :data:`SWEEP_REACH_M` from the centre (30 mm outside the default sphere), never less
    than :data:`SWEEP_MIN_STANDOFF_M` outside the surface.

    Parameters
    ----------
    work : Path
        The run's folder.
    tl : Timeline
        A's palpation timeline (:func:`palpation_timeline`).
    sweep_s : float
        The slide's one-way duration [s].
    centre : (3,) float
        The sphere's centre [m].
    radius_m : float
        Its radius [m].

    Returns
    -------
    Sweep
        The trajectory written.
    """
    from haptic_collab.research.palpation import lump_direction

    standoff = min(0.03, max(SWEEP_MIN_STANDOFF_M, SWEEP_REACH_M - radius_m))
    sweep = Sweep(
        centre=centre,
        radius_m=radius_m,
        standoff_m=standoff,
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
    return sweep


#: The cap of the rest surface a sagged top's sphere is fitted to: the vertices within this
#: angle of +z from the object's centre [rad], the sweep's 35 degrees and a finger pad more.
FIT_CAP_RAD = math.radians(45.0)


def fit_top_sphere(
    vertices: npt.ArrayLike, centre: Sequence[float], cap_rad: float = FIT_CAP_RAD
) -> tuple[FloatVec, float]:
    """The sphere (centre [m], radius [m]) closest to the top cap of a surface, by linear least
    squares (``|v|^2 = 2 c . v + r^2 - |c|^2``).

    The palpating hand slides at a fixed depth under a sphere (:class:`Sweep`); on a ball sagged
    under its own weight the top is about 20 mm lower and a little flatter than the mesh's sphere,
    and this is the sphere of the surface the server reports.

    Parameters
    ----------
    vertices : (n, 3) float
        The rest surface [m] (the server's ``VTX1`` frame).
    centre : (3,) float
        The object's centre [m] (the welcome's ``center_m``): the cap is the vertices within
        ``cap_rad`` of +z seen from it.
    cap_rad : float
        Half-angle of the cap [rad].

    Returns
    -------
    ((3,) float, float)
        The fitted centre [m] and radius [m].

    Raises
    ------
    RuntimeError
        Fewer than 10 vertices in the cap, or a fit that is not finite.
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    rel = v - np.asarray(centre, dtype=np.float64)
    length = np.linalg.norm(rel, axis=1)
    cap = v[(length > 0.0) & (rel[:, 2] > math.cos(cap_rad) * length)]
    if len(cap) < 10:
        raise RuntimeError(f"the object's top has {len(cap)} vertices: no sphere to sweep over")
    a = np.column_stack([2.0 * cap, np.ones(len(cap))])
    sol = np.linalg.lstsq(a, np.einsum("ij,ij->i", cap, cap), rcond=None)[0]
    c = sol[:3]
    r2 = float(sol[3] + c @ c)
    if not (np.all(np.isfinite(c)) and math.isfinite(r2) and r2 > 0.0):
        raise RuntimeError("the object's top fits no sphere")
    return (float(c[0]), float(c[1]), float(c[2])), math.sqrt(r2)


def rest_surface(
    host: str, port: int, token: str | None = None, timeout_s: float = 30.0
) -> tuple[dict[str, Any], npt.NDArray[np.float64]]:
    """The object as the running server reports it: its welcome's object info and its rest
    surface, read once as a viewer (hello, welcome, then the ``VTX1`` frame of rest positions).

    With ``--gravity`` the rest surface is the sagged one (docs/fem.md, "Gravity"): the scripted
    users must work on it, not on the mesh.

    Parameters
    ----------
    host, port :
        The demo's server.
    token : str or None
        The access token when the server asks for one.
    timeout_s : float
        How long to wait for the frames [s].

    Returns
    -------
    (dict, (n, 3) float64)
        The ``object`` of the welcome (:class:`shared.protocol.ObjectInfo` as JSON: ``top_m``,
        ``center_m``, ... [m]) and the rest vertices [m].

    Raises
    ------
    RuntimeError
        The server sent no welcome or no rest surface in time.
    """
    from websockets.sync.client import connect

    from haptic_collab.shared.protocol import (
        PROTOCOL_VERSION,
        VERTICES_MAGIC,
        Hello,
        decode_binary,
        encode,
    )

    ws = f"ws://{url_host(local_host(host))}:{port}/ws"
    info: dict[str, Any] | None = None
    deadline = time.monotonic() + timeout_s
    try:
        with connect(ws, open_timeout=timeout_s, max_size=None) as conn:
            conn.send(
                encode(Hello(protocol=PROTOCOL_VERSION, role="viewer", name="demo", token=token))
            )
            while (left := deadline - time.monotonic()) > 0.0:
                msg = conn.recv(timeout=left)
                if isinstance(msg, str):
                    body = json.loads(msg)
                    if body.get("type") == "welcome":
                        info = body["object"]
                    elif body.get("type") == "error":
                        raise RuntimeError(f"the server refused the demo's look: {body}")
                elif msg[:4] == VERTICES_MAGIC and info is not None:
                    _, _, rest = decode_binary(msg)
                    return info, np.asarray(rest, dtype=np.float64)
    except (OSError, TimeoutError, ValueError) as exc:
        raise RuntimeError(f"could not read the object's rest surface from {ws}: {exc}") from exc
    raise RuntimeError(f"the server at {ws} sent no rest surface within {timeout_s:g} s")


def check_gravity(opts: DemoOptions) -> None:
    """``--gravity``: finite, in [0, ``GRAVITY_MAX_M_S2``] m/s^2 (100), and only with an FEM
    object (``--object fem`` or the palpation scenario), as the server checks it.

    Raises
    ------
    ValueError
        Out of range, or given (> 0) with the balloon, which has no weight model.
    """
    from haptic_collab.cli.run import GRAVITY_MAX_M_S2

    g = float(opts.gravity_m_s2)
    if not (math.isfinite(g) and 0.0 <= g <= GRAVITY_MAX_M_S2):
        raise ValueError(
            f"--gravity must be in [0, {GRAVITY_MAX_M_S2:g}] m/s^2 (9.81 on Earth), got {g:g}"
        )
    if g > 0.0 and opts.object != "fem" and opts.scenario != "palpation":
        raise ValueError(
            "--gravity needs --object fem or --scenario palpation (the balloon has no weight model)"
        )


def object_title(opts: DemoOptions) -> str:
    """The object in a few words, for the plot's title and the summary: ``water balloon``, or
    the FEM solid's material, with ``gravity G m/s^2`` when it sagged under its own weight
    (e.g. ``FEM liver, gravity 9.81 m/s^2``)."""
    fem = opts.object == "fem" or opts.scenario == "palpation"
    if not fem:
        return "water balloon" if opts.material is None else f"balloon ({opts.material})"
    material = Path(opts.material).stem if opts.material is not None else "liver"
    words = f"FEM {material}"
    if opts.gravity_m_s2 > 0.0:
        words += f", gravity {opts.gravity_m_s2:g} m/s^2"
    return words


#: The server's log line that says how far the FEM solid sagged (server.main).
_SAG_LOG = re.compile(r"sagged under its own weight \(g ([0-9.eE+-]+) m/s\^2\), ([0-9.]+) mm")


def logged_sag_mm(server_log: str) -> float | None:
    """How far the solid sagged under its own weight [mm], as its server logged it (None: not
    logged, no gravity)."""
    m = _SAG_LOG.search(server_log)
    return float(m.group(2)) if m else None


def server_command(opts: DemoOptions, port: int) -> list[str]:
    """The demo's ``haptic server`` command for ``opts`` on ``port`` (without the palpation
    lump's ``--inclusion`` flags or a token): the object, its mesh and material, the rates, the
    injected link and, for an FEM object, ``--gravity`` (never for the balloon:
    :func:`check_gravity`)."""
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
    fem = opts.object == "fem" or opts.scenario == "palpation"
    if opts.gravity_m_s2 > 0.0 and fem:  # it sags at start
        server_cmd += ["--gravity", repr(float(opts.gravity_m_s2))]
    return server_cmd


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
        palpation_sweep_s = palpation_timeline(opts.duration_s)[1]
        a_device, a_extra = f"sim:replay:{work / 'sweep.csv'}", []
    urls = viewer_urls(opts.host, port)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    server_cmd = server_command(opts, port)
    server_cmd += inclusion_flags
    hint = ""
    token: str | None = None
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
        told = False
        while _status(opts.host, port) is None:
            if procs["server"].poll() is not None:
                raise RuntimeError(
                    "the server exited:\n" + (work / "server.log").read_text()[-2000:]
                )
            waited = time.monotonic() - t0
            if waited > SERVER_START_TIMEOUT_S:
                raise RuntimeError(
                    f"the server did not come up within {SERVER_START_TIMEOUT_S:g} s "
                    f"(its log: {work / 'server.log'})"
                )
            if not told and waited > 3.0:
                told = True
                print(
                    "the server is building the FEM solid (its volume mesh, factor and modes: "
                    "15-30 s on a quiet machine) ..."
                    if opts.object == "fem" or opts.scenario == "palpation"
                    else "waiting for the server to start ...",
                    flush=True,
                )
            time.sleep(0.1)
        if palpation is not None and opts.gravity_m_s2 > 0.0:
            # the sweep slides over the sagged top the server reports, not the mesh's sphere
            info, rest = rest_surface(opts.host, port, token)
            centre, radius = fit_top_sphere(rest, info["center_m"])
            sweep = write_sweep(work, tl, palpation_sweep_s, centre, radius)
            palpation = (sweep, palpation[1])
        opened = False
        if not opts.headless and _has_display():
            with contextlib.suppress(Exception):
                opened = bool(webbrowser.open(urls[0] + hint))
        subject = "balloon" if opts.object == "balloon" else object_title(opts)
        for line in opening_lines(
            [u + hint for u in urls], tl, opts.duration_s, opened, opts.scenario, subject
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
    # A's script starts at its servo's first tick, 0.5-3 s into A's clock under load: the hold
    # is judged, B's windows are set and the plot is drawn where A's hand really was
    a_start_s = script_start_s(work / "A.csv")
    tl = replace(tl, delay_s=tl.delay_s + a_start_s)
    if palpation is not None:
        moved = replace(palpation[0], delay_s=palpation[0].delay_s + a_start_s)
        palpation = (moved, palpation[1])
    report = build_report(work, tl, server_status, opts, status_samples)
    report["a_script_start_s"] = a_start_s
    if reference_stats is not None:
        report["reference_loop"] = {
            k: reference_stats.get(k)
            for k in ("rate_hz", "period_p99_us", "period_max_us", "missed_per_s", "realtime")
        }
        ref_p99 = reference_stats.get("period_p99_us")
        for u in report["users"].values():
            p99 = u.get("period_us_p99")
            u["period_p99_vs_reference"] = p99 / ref_p99 if p99 and ref_p99 else None
    report["object"] = _object_report(opts, work)
    if palpation is not None:
        sweep, (over, beside) = palpation
        report["palpation"] = palpation_report(work, sweep, over, beside)
        report["palpation"]["sphere"] = {
            "centre_m": list(sweep.centre),
            "radius_m": sweep.radius_m,
            "from": "the server's rest surface" if opts.gravity_m_s2 > 0.0 else "the mesh",
        }
    report["workdir"] = str(work) if opts.workdir is not None else None  # a temp one is deleted
    if opts.report:
        opts.report.parent.mkdir(parents=True, exist_ok=True)
        opts.report.write_text(json.dumps(report, indent=2))
    if opts.plot:
        sag = report["object"]["sag_mm"]
        subject = report["object"]["title"] + (f" (sagged {sag:.1f} mm)" if sag else "")
        plot_demo(work, tl, opts.plot, subject)
    print(object_line(report["object"]))
    print_summary(report)
    if "palpation" in report:
        for line in palpation_lines(report["palpation"]):
            print(line)
    return report


def _object_report(opts: DemoOptions, work: Path) -> dict[str, Any]:
    """The report's ``object``: what the users touched.

    ``title`` (:func:`object_title`), ``object``, ``material``, ``gravity_m_s2``, ``sag_mm`` (how
    far the solid sagged under its own weight, from the server's log; None without gravity) and
    ``a_anchor_m``, ``b_anchor_m``: the surface points [m] the scripted hands worked on, as the
    server reported them in each user's welcome (on the sagged surface under ``--gravity``).
    """
    anchors: dict[str, Any] = {}
    for name in ("A", "B"):
        with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
            anchors[name] = json.loads((work / f"{name}.json").read_text())["anchor"]["point_m"]
    sag: float | None = None
    if opts.gravity_m_s2 > 0.0:
        with contextlib.suppress(OSError):
            sag = logged_sag_mm((work / "server.log").read_text(errors="replace"))
    fem = opts.object == "fem" or opts.scenario == "palpation"
    return {
        "title": object_title(opts),
        "object": "fem" if fem else opts.object,
        "material": opts.material or ("liver" if fem else "water-balloon"),
        "gravity_m_s2": float(opts.gravity_m_s2),
        "sag_mm": sag,
        "a_anchor_m": anchors.get("A"),
        "b_anchor_m": anchors.get("B"),
    }


def object_line(obj: dict[str, Any]) -> str:
    """The summary's first line: the object the users touched, and under gravity how far it
    sagged and where A's hand met its sagged top (the report's ``object``)."""
    line = f"object: {obj['title']}"
    if obj["gravity_m_s2"] > 0.0:
        sag = obj.get("sag_mm")
        line += (
            f"; it sagged {sag:.1f} mm under its own weight before anyone touched it"
            if sag is not None
            else "; it sagged under its own weight before anyone touched it"
        )
        a = obj.get("a_anchor_m")
        if a is not None:
            line += f" (A's top anchor, as the server reported it: z = {1e3 * a[2]:.1f} mm)"
    return line


#: How often the demo polls the server's status while the users run [s].
_POLL_S = 0.5


#: About how long the users take to start and join [s] (2-5 s measured on a busy 2-core machine).
JOIN_S = 4.0


def opening_lines(
    urls: list[str],
    tl: Timeline,
    duration_s: float,
    opened: bool,
    scenario: str = "press",
    subject: str = "balloon",
) -> list[str]:
    """What the demo says once its server is up: what to open now and for how long, and what
    will happen (A's timeline in seconds from A's start; the users need a few seconds to join;
    ``scenario`` as ``--scenario``; ``subject`` what the press scenario's users touch, e.g.
    ``balloon`` or ``FEM liver, gravity 9.81 m/s^2``)."""
    # the users run duration_s once they have joined, which takes a few seconds
    lines = [f"open {urls[0]} now: the demo is live for about {duration_s + JOIN_S:.0f} s"]
    lines += [f"  (or {u})" for u in urls[1:]]
    if opened:
        lines.append("  (opened in your browser)")
    sagged = f" (the {subject}: it has sagged under its own weight)" if "gravity" in subject else ""
    if scenario == "palpation":
        lines.append(
            f"What happens: users A and B join; B rests on the liver's side{sagged}; after "
            f"{tl.delay_s:.0f} s A presses into the top beside a hidden stiff lump, holds, then "
            f"slides across the top over the lump and back and lets go at "
            f"{tl.hold_end_s + tl.release_s:.0f} s. Over the lump A's force rises at the same "
            "depth; B feels A's sweep through the liver."
        )
        return lines
    what = "balloon" if subject == "balloon" else "object"
    lines.append(
        f"What happens: users A and B join; B rests on the {what}'s side{sagged}; after "
        f"{tl.delay_s:.0f} s "
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

    def __init__(
        self, tl: Timeline, duration_s: float, sweeps: bool = False, subject: str = "balloon"
    ) -> None:
        self.tl = tl
        #: What the users touch, in the closing phase's words ("the balloon settles").
        self.subject = subject
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
            f"A has let go and the {self.subject} settles; {b_rests} (the run ends in {left:.0f} s)"
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
    fem = opts.object == "fem" or opts.scenario == "palpation"
    narrator = _Narrator(
        tl,
        opts.duration_s,
        sweeps=opts.scenario == "palpation",
        subject="solid" if fem else "balloon",
    )
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
