"""The Node.js reference client (client/js, written from docs/protocol.md) against a real server.

- Two JS users feel each other: A rests lightly on the side of the water balloon, B presses
  into its top; the force A's local model renders rises while B presses (plane and sphere
  primitives).
- Link loss in the middle of a press ramps the JS client's force to zero (a ramp, not a jump)
  and the client rejoins the restarted server and presses again.
- A fatal ``error`` (a token the server refuses) makes the client exit non-zero with the
  server's message; the right token (``HAPTIC_TOKEN``) joins.
- The servo core's own unit tests (``node --test client/js/test/``).

Skipped only when ``node`` is not on PATH. Timing is generous and every comparison is between
windows of the clients' own records, selected by behaviour (in contact, forces not ramped down by
a late patch), so a loaded machine changes how many windows qualify, not the verdict.
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import json
import os
import shutil
import statistics
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from haptic_collab.server.main import ServerOptions, run_server

ROOT = Path(__file__).resolve().parents[2]
JS_DIR = ROOT / "client" / "js"
CLIENT = JS_DIR / "haptic-client.mjs"
NODE = shutil.which("node")
SIM_RATE = 20.0

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        NODE is None, reason="node is not on PATH: the JS reference client needs it"
    ),
]


def _require_node_modules() -> None:
    assert (JS_DIR / "node_modules" / "ws").is_dir(), (
        "client/js/node_modules is missing: run `make js-install` (npm ci in client/js)"
    )


@contextlib.asynccontextmanager
async def serving(port: int = 0, **options: Any) -> AsyncIterator[int]:
    """A real server (the CLI's ``run_server``) on loopback; yields its port, stops on exit."""
    loop = asyncio.get_running_loop()
    ready: asyncio.Future[int] = loop.create_future()
    opts = ServerOptions(host="127.0.0.1", port=port, sim_rate_hz=SIM_RATE, **options)
    task = asyncio.create_task(run_server(opts, on_ready=ready.set_result))
    first: set[asyncio.Future[Any]] = {task, ready}
    done, _ = await asyncio.wait(first, timeout=180, return_when=asyncio.FIRST_COMPLETED)
    if task in done:
        task.result()  # raises what stopped the server
    assert ready in done, "the server did not start within 180 s"
    try:
        yield ready.result()
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


_RUNNING: list[asyncio.subprocess.Process] = []


@pytest.fixture(autouse=True)
def _kill_leftover_clients() -> Any:
    """A test that fails half-way leaves no client running."""
    yield
    while _RUNNING:
        proc = _RUNNING.pop()
        if proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()


class JsUser:
    """One ``node client/js/haptic-client.mjs`` process; ``result()`` waits for its summary."""

    def __init__(
        self, tmp: Path, name: str, port: int, *args: str, env: dict[str, str] | None = None
    ):
        self.name = name
        self.summary_path = tmp / f"{name}.json"
        self.args = [
            str(CLIENT),
            f"--url=ws://127.0.0.1:{port}/ws",
            f"--name={name}",
            f"--summary={self.summary_path}",
            "--quiet",
            *args,
        ]
        self.env = {k: v for k, v in os.environ.items() if k != "HAPTIC_TOKEN"} | (env or {})
        self.proc: asyncio.subprocess.Process | None = None

    async def start(self) -> JsUser:
        assert NODE is not None
        self.proc = await asyncio.create_subprocess_exec(
            NODE,
            *self.args,
            cwd=ROOT,
            env=self.env,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
        )
        _RUNNING.append(self.proc)
        return self

    async def result(self, timeout: float = 120.0) -> tuple[int, dict[str, Any], str]:
        assert self.proc is not None
        try:
            out, err = await asyncio.wait_for(self.proc.communicate(), timeout)
        except TimeoutError:
            self.proc.kill()
            await self.proc.wait()
            raise
        stderr = err.decode(errors="replace")
        assert self.proc.returncode is not None
        summary = json.loads(out) if out.strip() else {}
        return self.proc.returncode, summary, stderr


def windows(summary: dict[str, Any], t0: float, t1: float) -> list[dict[str, Any]]:
    """The summary's force windows inside [t0, t1] (client's clock, s) that are clean contact:
    in contact the whole window and the safety gain at one (no patch came late)."""
    return [
        w
        for w in summary["force_windows"]
        if w["t0_s"] >= t0
        and w["t1_s"] <= t1
        and w["contact_fraction"] == 1.0
        and w["min_safety_gain"] == 1.0
    ]


def median_force(ws: list[dict[str, Any]]) -> float:
    return statistics.median(w["mean_force_n"] for w in ws)


PRESS_AT, PRESS_RAMP, DURATION = 9.0, 1.5, 22.0


@pytest.mark.alone  # B's press: 5.9 N alone, 0.97 N once beside the FEM slow tests on 2 cores
@pytest.mark.parametrize("primitive", ["plane", "sphere"])
async def test_two_js_users_feel_each_other(tmp_path, primitive):
    _require_node_modules()
    async with serving(subdivisions=4, primitive=primitive) as port:
        common = ["--window=0.25", f"--duration={DURATION}"]
        a = JsUser(tmp_path, "A", port, "--on=side", "--rest-depth=0.003", *common)
        b = JsUser(
            tmp_path, "B", port, "--on=top", "--press-depth=0.04",
            f"--press-at={PRESS_AT}", f"--press-ramp={PRESS_RAMP}", *common,
        )  # fmt: skip
        await a.start()
        await b.start()
        (rc_a, sa, err_a), (rc_b, sb, err_b) = await asyncio.gather(a.result(), b.result())
    assert rc_a == 0 and rc_b == 0, (err_a, err_b)
    for s in (sa, sb):
        assert s["joins"] == 1 and s["fatal_error"] is None and not s["errors"], s
        assert s["patches"] > 100, s["patches"]  # ~20 per second once in contact
        # the server sends the primitive asked for; with --primitive sphere it sends a plane
        # where the dented surface is not convex (docs/protocol.md, "The primitives")
        kinds = set(s["patches_by_kind"])
        assert primitive in kinds and kinds <= {primitive, "plane"}, kinds
    # B's press, on A's clock
    shift = sb["clock_origin_unix_s"] - sa["clock_origin_unix_s"]
    press_full = PRESS_AT + PRESS_RAMP
    before = windows(sa, PRESS_AT + shift - 3.5, PRESS_AT + shift - 0.25)
    end = min(DURATION, DURATION + shift) - 0.75  # both still running
    during = windows(sa, press_full + shift + 2.5, end)
    b_during = windows(sb, press_full + 2.5, DURATION - 0.5)
    assert len(before) >= 3 and len(during) >= 3 and len(b_during) >= 3, (
        "too few clean contact windows (link stalls?)",
        sa["force_windows"],
    )
    f_before, f_during = median_force(before), median_force(during)
    f_press = median_force(b_during)
    print(
        f"{primitive}: A rests {f_before:.3f} N -> {f_during:.3f} N while B presses "
        f"{f_press:.2f} N; gains {sa['gains_sources']}, servo {sa['servo']['rate_hz']:.0f} Hz"
    )
    assert f_before > 0.05  # A really rests on the balloon
    assert f_press > 1.0 and f_press > 5 * f_before  # B really presses
    assert f_during >= 1.08 * f_before, (f_before, f_during)  # A feels B's press


async def test_a_js_user_feels_a_python_user_in_the_same_room(tmp_path):
    """One room, two languages: the JS client rests on the side while ``haptic client`` (Python,
    ``sim:press``) presses into the top; the force the JS client renders rises."""
    _require_node_modules()
    async with serving(subdivisions=4) as port:
        # A declares the Python user's device limits (the Phantom Desktop's 10 N*s/m damper):
        # with a damper a coupled contact keeps its own-force compensation (docs/own-force.md)
        a = JsUser(tmp_path, "A", port, "--on=side", "--rest-depth=0.003", "--window=0.25",
                   "--max-damping=10", f"--duration={DURATION}")  # fmt: skip
        await a.start()
        py = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "haptic_collab.cli", "client",
            "--url", f"ws://127.0.0.1:{port}/ws", "--name", "P", "--device", "sim:press",
            "--duration", f"{DURATION - 1.0:g}", "--summary", str(tmp_path / "P.json"),
            "--trajectory", f"delay_s={PRESS_AT - 1.0:g},approach_s=1,press_s={PRESS_RAMP:g},hold_s=30",
            cwd=ROOT, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT,
        )  # fmt: skip
        _RUNNING.append(py)
        (rc_a, sa, err_a), (out_p, _) = await asyncio.gather(
            a.result(), asyncio.wait_for(py.communicate(), 120.0)
        )
    assert rc_a == 0, err_a
    assert py.returncode == 0, out_p.decode(errors="replace")[-3000:]
    sp = json.loads((tmp_path / "P.json").read_text())
    assert sa["joins"] == 1 and sa["fatal_error"] is None and not sa["errors"], sa
    assert sa["patches"] > 100 and sp["patches"] > 100
    assert sp["max_force_n"] > 1.0, {
        k: sp.get(k)
        for k in (
            "max_force_n",
            "first_gains_s",
            "first_patch_s",
            "servo_rate_hz",
            "faults",
            "anchor",
        )
    }  # the Python user really pressed
    # the Python hand reaches full depth about PRESS_AT + PRESS_RAMP after both started
    before = windows(sa, PRESS_AT - 4.0, PRESS_AT - 0.5)
    during = windows(sa, PRESS_AT + PRESS_RAMP + 1.0, DURATION - 1.5)
    assert len(before) >= 3 and len(during) >= 3, sa["force_windows"]
    f_before, f_during = median_force(before), median_force(during)
    # A feels the Python user's press: its force while P holds (the median: the change of gains
    # when the contacts couple costs A a dip of a fraction of a second) rises well above its rest
    # force (measured 0.42 -> 0.57 N). Without a damper declared, a coupled contact's gains
    # cannot keep the compensation and the steady rise is lost in the softer rendering; that
    # case is checked by test_two_js_users_feel_each_other, whose press is 4 cm deep.
    assert f_before > 0.05  # A really rests on the balloon
    assert f_during >= 1.15 * f_before, (f_before, f_during)


def load_record(path: Path) -> dict[str, list[float]]:
    with path.open() as f:
        rows = list(csv.DictReader(f))
    return {k: [float(r[k]) for r in rows] for k in rows[0]}


async def test_js_client_ramps_to_zero_on_link_loss_and_rejoins(tmp_path):
    _require_node_modules()
    record = tmp_path / "A.csv"
    async with serving(subdivisions=3) as port:
        user = JsUser(
            tmp_path, "A", port, "--on=top", "--press-depth=0.02", "--press-at=1.5",
            "--duration=16", f"--record={record}",
        )  # fmt: skip
        await user.start()
        await asyncio.sleep(6.0)  # A is pressing and holding
        t_loss = time.time()
    # the server is gone in the middle of the press; it comes back 1.5 s later on the same port
    await asyncio.sleep(1.5)
    async with serving(port=port, subdivisions=3):
        rc, summary, err = await user.result()
    assert rc == 0, err
    cols = load_record(record)
    t_loss -= summary["clock_origin_unix_s"]  # on the client's clock
    t, f = cols["t_s"], cols["force_n"]

    def select(t0: float, t1: float) -> list[float]:
        return [fi for ti, fi in zip(t, f, strict=True) if t0 < ti < t1]

    f_pressing = statistics.mean(select(t_loss - 1.0, t_loss))
    assert f_pressing > 0.3  # A was really pressing
    # no patch for 0.25 s, then a 50 ms ramp: zero well before the server is back
    assert max(select(t_loss + 0.25 + 0.05 + 0.25, t_loss + 1.4)) == 0.0
    # a ramp, not a jump: from 90 % of the pressing force to zero takes about the ramp's 50 ms
    # (a jump: one tick). The ramp runs on elapsed time, so only a servo stall nearly as long as
    # the ramp itself could shorten it.
    near = [(ti, fi) for ti, fi in zip(t, f, strict=True) if t_loss - 0.5 < ti < t_loss + 1.4]
    t_zero = next(ti for ti, fi in near if fi == 0.0)
    t_full = max(ti for ti, fi in near if ti < t_zero and fi >= 0.9 * f_pressing)
    print(f"link loss: {f_pressing:.2f} N ramped to zero in {1e3 * (t_zero - t_full):.0f} ms")
    assert t_zero - t_full >= 0.03, (t_full, t_zero)
    assert summary["joins"] >= 2 and summary["link_losses"] >= 1  # rejoined the new server
    assert statistics.mean(select(t_loss + 6.0, 15.5)) > 0.3  # and presses again


async def test_js_client_fatal_error_exits_non_zero_and_token_joins(tmp_path):
    _require_node_modules()
    if "token" not in ServerOptions.__dataclass_fields__:
        pytest.skip("this server has no tokens (haptic server --token) yet")
    token = "js-client-test-token"
    async with serving(subdivisions=2, token=token) as port:
        refused = await JsUser(tmp_path, "nobody", port, "--duration=20").start()
        rc, summary, err = await refused.result(timeout=60)
        assert rc == 1, (rc, err)
        assert "fatal error from the server" in err and "token" in err
        assert summary["fatal_error"]["code"] and summary["joins"] == 0
        admitted = await JsUser(
            tmp_path, "A", port, "--duration=3", env={"HAPTIC_TOKEN": token}
        ).start()
        rc, summary, err = await admitted.result(timeout=60)
    assert rc == 0, err
    assert summary["joins"] == 1 and summary["patches"] > 10 and summary["fatal_error"] is None


def test_js_servo_core_unit_tests():
    assert NODE is not None
    import subprocess

    res = subprocess.run(
        [NODE, "--test", str(JS_DIR / "test")], capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
    assert "# fail 0" in res.stdout
