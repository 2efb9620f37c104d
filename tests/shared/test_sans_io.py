"""shared/ is sans-I/O: no module imports a clock, a socket, a thread, an event loop or a plot.

DESIGN's rule ("shared/ never touches sockets, threads or clocks; time is passed in"), checked on
the source (type-checking imports included) so that a new import cannot slip in. Whoever needs a
wall time (a design's ``design_ms``) measures it outside (``haptic_collab.client.workers.timed``); the
figures are drawn by ``haptic_collab.research.plots`` (matplotlib sets process-wide state).
"""

from __future__ import annotations

import ast
from pathlib import Path

SHARED_DIR = Path(__file__).resolve().parents[2] / "shared"
FORBIDDEN = {
    "time",
    "socket",
    "threading",
    "asyncio",
    "concurrent",
    "multiprocessing",
    "selectors",
    "websockets",
    "matplotlib",
}


def test_shared_imports_no_clock_socket_thread_event_loop_or_plotting() -> None:
    offenders = []
    for path in sorted(SHARED_DIR.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            else:
                continue
            for name in names:
                if name.split(".")[0] in FORBIDDEN:
                    offenders.append(f"{path.name}:{node.lineno} imports {name}")
    assert offenders == []
