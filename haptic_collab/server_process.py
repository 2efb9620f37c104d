"""``haptic server`` in its own process, the way a user starts it: for the load bench
(:mod:`haptic_collab.bench.load`) and the loopback tests.

:class:`ServerProcess` runs ``python -m haptic_collab.cli server --port PORT`` on loopback, reads
the port from the viewer URL the server prints once it listens, and reads the server's ``/status``,
memory, CPU time and run-queue wait from outside (``/proc``).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import queue
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path
from typing import IO, Any

#: How long a server may take to print its URL [s].
SERVER_START_TIMEOUT_S = 60.0
_PORT_LINE = re.compile(r"viewer: https?://[^\s/]+:(\d+)/")


class ServerProcess:
    """``haptic server --host 127.0.0.1 --port PORT ARGS`` in its own process (``python -m
    haptic_collab.cli``, as a user starts it); ``port`` and ``url`` once it listens.

    Parameters
    ----------
    args : str
        Further ``haptic server`` options.
    port : int
        TCP port; 0 takes any free one.
    log : Path, optional
        File for the server's log (stderr); default a temporary file. :meth:`log_tail` and
        :meth:`warnings` read it either way.

    Raises
    ------
    RuntimeError
        The server exited or did not print its URL within :data:`SERVER_START_TIMEOUT_S`.
    """

    def __init__(self, *args: str, port: int = 0, log: Path | None = None) -> None:
        env = dict(os.environ)
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            env.setdefault(var, "1")
        env["PYTHONUNBUFFERED"] = "1"
        self.log: IO[str] = (
            tempfile.TemporaryFile(mode="w+", prefix="haptic-server-")
            if log is None
            else open(log, "w+")  # noqa: SIM115 (closed in stop)
        )
        cmd = [
            sys.executable, "-m", "haptic_collab.cli", "--log-level", "info",
            "server", "--host", "127.0.0.1", "--port", str(port), *args,
        ]  # fmt: skip
        # its own session and process group: the server's own worker processes (gain designs)
        # are ended with it
        self.proc = subprocess.Popen(
            cmd,
            env=env,
            stdout=subprocess.PIPE,
            stderr=self.log,
            text=True,
            start_new_session=True,
        )
        self._lines: queue.Queue[str | None] = queue.Queue()
        threading.Thread(target=self._drain, daemon=True).start()
        self.port = self._wait_port()
        self.url = f"ws://127.0.0.1:{self.port}/ws"

    def __enter__(self) -> ServerProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _drain(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self._lines.put(line)
        self._lines.put(None)

    def _wait_port(self) -> int:
        deadline = time.monotonic() + SERVER_START_TIMEOUT_S
        while time.monotonic() < deadline:
            try:
                line = self._lines.get(timeout=0.5)
            except queue.Empty:
                continue
            if line is None:
                break
            m = _PORT_LINE.search(line)
            if m:
                return int(m.group(1))
        self.stop()
        raise RuntimeError(f"the server did not start:\n{self.log_tail()}")

    def log_tail(self, n: int = 20) -> str:
        """The last ``n`` lines the server logged (stderr)."""
        self.log.seek(0)
        return "".join(self.log.readlines()[-n:])

    def warnings(self) -> list[str]:
        """Every WARNING, ERROR or CRITICAL line the server logged so far."""
        self.log.seek(0)
        levels = (" WARNING ", " ERROR ", " CRITICAL ")
        return [line.rstrip() for line in self.log if any(x in line for x in levels)]

    def status(self) -> dict[str, Any]:
        """The server's ``/status`` JSON."""
        url = f"http://127.0.0.1:{self.port}/status"
        with urllib.request.urlopen(url, timeout=10) as res:  # loopback only
            out: dict[str, Any] = json.loads(res.read())
        return out

    def rss_mb(self) -> float:
        """Resident memory of the server process [MB] (``VmRSS``, 1 MB = 2**20 bytes)."""
        return _vm_rss_mb(self.proc.pid)

    def cpu_s(self) -> float:
        """User + system CPU time the server process used so far [s]."""
        return _process_cpu_s(self.proc.pid)

    def run_wait_s(self) -> float:
        """Time the server's main thread (its event loop) was ready to run but waited for a CPU
        so far [s] (``/proc/PID/schedstat``; NaN where the kernel does not keep it)."""
        try:
            with open(f"/proc/{self.proc.pid}/schedstat", encoding="ascii") as f:
                return int(f.read().split()[1]) / 1e9
        except (OSError, ValueError, IndexError):
            return math.nan

    def stop(self) -> int | None:
        """End the server as Ctrl-C does (SIGINT: it shuts its workers down), then its group;
        returns its exit status.

        SIGTERM after 10 s, SIGKILL after 5 more; whatever is left of the server's process group
        (a worker orphaned by a server that did not shut down cleanly) gets SIGTERM.
        """
        for sig, wait_s in ((signal.SIGINT, 10.0), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            if self.proc.poll() is not None:
                break
            self.proc.send_signal(sig)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(wait_s)
        with contextlib.suppress(OSError):
            os.killpg(self.proc.pid, signal.SIGTERM)
        self.log.flush()
        return self.proc.returncode


def _vm_rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0  # kB
    return math.nan


def _process_cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat", encoding="ascii") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime
