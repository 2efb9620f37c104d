"""The browser viewer against the real server: HTTP serving, and a live page in Debian's chromium.

The browser tests start the real server in-process (World -> Room -> ServerApp on a free port),
connect two scripted haptic users over real websockets that close the loop through the server
(each renders ``k_h * penetration`` against the patch it last received and reports it back), and
drive /usr/bin/chromium through Playwright. They are skipped, with the reason, when chromium, the
playwright package or web/node_modules/three is missing. Every wait is bounded.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import json
import math
import os
import re
import urllib.request
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from websockets.asyncio.client import ClientConnection, connect

from haptic_collab.shared.protocol import PROTOCOL_VERSION

ROOT = Path(__file__).resolve().parents[2]
WEB = ROOT / "web"
THREE_MODULE = WEB / "node_modules" / "three" / "build" / "three.module.js"
#: The README's screenshot is refreshed only on request: HAPTIC_UPDATE_SCREENSHOT=1 pytest tests/web
SCREENSHOT = ROOT / "docs" / "viewer.png"
UPDATE_SCREENSHOT = os.environ.get("HAPTIC_UPDATE_SCREENSHOT") == "1"
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    # WebGL through SwiftShader, so that the canvas is really drawn headless
    "--use-gl=angle",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
]
VIEW_W, VIEW_H = 1280, 760

SIM_RATE_HZ = 20.0
STATE_RATE_HZ = 40.0
PROBE_SPEED_M_PER_S = 0.02  # how fast a scripted hand moves its probe toward its target
MAX_FORCE_N = 5.0

needs_three = pytest.mark.skipif(
    not THREE_MODULE.is_file(),
    reason="web/node_modules/three is missing: run `make web-install` (npm ci in web/)",
)


def _browser_skip_reason() -> str | None:
    if not CHROMIUM.is_file():
        return "Debian's chromium is not installed at /usr/bin/chromium (`make browser`)"
    if importlib.util.find_spec("playwright") is None:
        return "the playwright Python package is not installed (pip install -e '.[dev]')"
    if not THREE_MODULE.is_file():
        return "web/node_modules/three is missing: run `make web-install` (npm ci in web/)"
    return None


# ----------------------------------------------------------------------------- the real server
def _world(subdivisions: int) -> Any:
    from haptic_collab.server.objects.balloon import Balloon, BalloonParams
    from haptic_collab.server.objects.mesh import default_balloon
    from haptic_collab.server.world import World

    mesh = default_balloon(subdivisions=subdivisions)
    return World(Balloon(mesh, BalloonParams(sim_period_s=1.0 / SIM_RATE_HZ)))


def _fem_world(cache_dir: Path) -> Any:
    """A small FEM solid (162 vertices, r = 5 cm; P2 on the 42-vertex icosphere): its surface
    also moves sideways (DSV1)."""
    import trimesh

    from haptic_collab.server.objects.fem import FemParams, FemSolid
    from haptic_collab.server.world import World

    mesh = trimesh.creation.icosphere(1, 0.05)
    params = FemParams(sim_period_s=1.0 / SIM_RATE_HZ)
    return World(FemSolid(mesh, params, cache_dir=str(cache_dir)))


@contextlib.asynccontextmanager
async def running_server(
    subdivisions: int = 4, port: int = 0, world: Any = None
) -> AsyncIterator[Any]:
    """The real server (World, Room, ServerApp) on 127.0.0.1, a free port unless ``port``; the
    balloon of ``subdivisions`` unless ``world`` is given."""
    from haptic_collab.server.app import ServerApp
    from haptic_collab.server.room import Room

    world = world if world is not None else _world(subdivisions)
    app = ServerApp(Room(world, SIM_RATE_HZ), "127.0.0.1", port)
    await app.start()
    try:
        yield app
    finally:
        await app.stop()


def _get(url: str) -> tuple[int, str, bytes]:
    with urllib.request.urlopen(url, timeout=10) as res:  # loopback only
        return res.status, res.headers.get("Content-Type", ""), res.read()


# ----------------------------------------------------------------------------- scripted users
class ScriptedUser:
    """A haptic user without a device: a probe scripted along the normal of an anchor point.

    ``depth_m`` is how far the probe is inside the *rest* surface along the anchor's inward
    normal (negative: outside); it moves toward ``target_m`` at :data:`PROBE_SPEED_M_PER_S`.
    At :data:`STATE_RATE_HZ` it sends a ``state`` with the force a proportional local model
    renders against the last patch: ``f = k_h * max(e, 0) * n``, ``k_h = 0.5 * k_o_eff``, with
    ``e`` the penetration into the patch primitive. The loop closes through the server. While
    ``silent`` is set it sends nothing but keeps its connection (a stalled client).
    """

    def __init__(self, name: str, anchor: str, depth_m: float) -> None:
        self.name = name
        self.anchor = anchor
        self.depth_m = depth_m
        self.target_m = depth_m
        self.silent = False
        self.force_n = 0.0
        self.patch: dict[str, Any] | None = None
        self.errors: list[dict[str, Any]] = []
        self.welcomed = asyncio.Event()

    def _contact(self, probe: np.ndarray) -> tuple[float, np.ndarray]:
        """Penetration [m] into the last patch's primitive and its outward normal at the probe."""
        assert self.patch is not None
        prim = self.patch["primitive"]
        if prim["kind"] == "sphere":
            d = probe - np.asarray(prim["center"], float)
            dist = float(np.linalg.norm(d))
            return float(prim["radius"]) - dist, d / max(dist, 1e-12)
        n = np.asarray(prim["normal"], float)
        return float((np.asarray(prim["point"], float) - probe) @ n), n

    async def _receive(self, ws: ClientConnection) -> None:
        async for frame in ws:
            if isinstance(frame, bytes):
                continue
            msg = json.loads(frame)
            if msg["type"] == "patch":
                self.patch = msg
            elif msg["type"] == "error":
                self.errors.append(msg)

    async def run(self, port: int, stop: asyncio.Event) -> None:
        """Connect, say hello, then send states until ``stop`` is set."""
        async with connect(f"ws://127.0.0.1:{port}/ws", open_timeout=10) as ws:
            hello = {
                "type": "hello",
                "protocol": PROTOCOL_VERSION,
                "role": "user",
                "name": self.name,
                "device": {"profile": "scripted", "max_force_n": 7.9},
                "servo_rate_hz": 1000.0,
                "local_model": "p",
            }
            await ws.send(json.dumps(hello))
            welcome = json.loads(await asyncio.wait_for(ws.recv(), 10))
            assert welcome["type"] == "welcome", welcome
            obj = welcome["object"]
            point = np.asarray(obj[f"{self.anchor}_m"], float)
            inward = -np.asarray(obj[f"{self.anchor}_normal"], float)
            self.welcomed.set()
            receiver = asyncio.create_task(self._receive(ws))
            loop = asyncio.get_running_loop()
            period = 1.0 / STATE_RATE_HZ
            step = PROBE_SPEED_M_PER_S * period
            t_next = loop.time()
            seq = 0
            try:
                while not stop.is_set() and not receiver.done():
                    self.depth_m += max(-step, min(step, self.target_m - self.depth_m))
                    probe = point + inward * self.depth_m
                    e, n, k_h = 0.0, -inward, 0.0
                    if self.patch is not None:
                        e, n = self._contact(probe)
                        k_h = 0.5 * float(self.patch["k_o_eff"])
                    f = min(k_h * max(e, 0.0), MAX_FORCE_N)
                    self.force_n = f
                    seq += 1
                    state = {
                        "type": "state",
                        "seq": seq,
                        "probe_m": probe.tolist(),
                        "force_n": (f * n).tolist(),
                        "penetration_m": e,
                        "in_contact": e > 0.0,
                        "k_h": k_h,
                        "servo_rate_hz": 1000.0,
                        "rtt_ms": 1.0,
                        "patch_tick": self.patch["tick"] if self.patch else -1,
                    }
                    if not self.silent:
                        await ws.send(json.dumps(state))
                    t_next += period
                    await asyncio.sleep(max(0.0, t_next - loop.time()))
                if stop.is_set():  # leaving on purpose, as a client does: no seat held
                    with contextlib.suppress(Exception):
                        await ws.send(json.dumps({"type": "bye"}))
            finally:
                receiver.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await receiver


@contextlib.asynccontextmanager
async def scripted_users(port: int, *users: ScriptedUser) -> AsyncIterator[None]:
    """Run the users for the duration of the block; re-raise the first failure of any of them."""
    stop = asyncio.Event()
    tasks = [asyncio.create_task(u.run(port, stop)) for u in users]
    try:
        await asyncio.wait_for(asyncio.gather(*(u.welcomed.wait() for u in users)), 10)
        yield
    finally:
        stop.set()
        done = await asyncio.wait_for(asyncio.gather(*tasks, return_exceptions=True), 10)
    for res in done:
        if isinstance(res, BaseException):
            raise res
    for u in users:
        assert not u.errors, f"server refused user {u.name}: {u.errors}"


# ----------------------------------------------------------------------------- fast tests
async def test_http_serves_viewer_page() -> None:
    async with running_server(subdivisions=2) as app:
        base = f"http://127.0.0.1:{app.port}"
        status, ctype, body = await asyncio.to_thread(_get, base + "/")
        assert status == 200
        assert ctype.startswith("text/html")
        html = body.decode()
        assert '<script type="module" src="/viewer.js">' in html
        m = re.search(r'<script type="importmap">(.*?)</script>', html, re.S)
        assert m, "index.html needs an import map for three"
        imports = json.loads(m.group(1))["imports"]
        assert imports["three"] == "/vendor/three/build/three.module.js"
        assert imports["three/addons/"] == "/vendor/three/examples/jsm/"
        for path in ("/viewer.js", "/protocol.js"):
            status, ctype, body = await asyncio.to_thread(_get, base + path)
            assert status == 200 and ctype.startswith("text/javascript"), (path, ctype)
        status, ctype, _ = await asyncio.to_thread(_get, base + "/style.css")
        assert status == 200 and ctype.startswith("text/css")


@needs_three
async def test_http_serves_three_and_every_addon_the_viewer_imports() -> None:
    viewer = (WEB / "viewer.js").read_text(encoding="utf-8")
    addons = re.findall(r'from "three/addons/([^"]+)"', viewer)
    assert addons, "viewer.js imports OrbitControls and friends from three/addons/"
    paths = ["/vendor/three/build/three.module.js"]
    paths += [f"/vendor/three/examples/jsm/{a}" for a in addons]
    async with running_server(subdivisions=2) as app:
        for path in paths:
            status, ctype, body = await asyncio.to_thread(
                _get, f"http://127.0.0.1:{app.port}{path}"
            )
            assert status == 200, path
            assert "javascript" in ctype, (path, ctype)
            assert b"export" in body, path


# ----------------------------------------------------------------------------- no browser
def test_viewer_stream_constants_match_the_server() -> None:
    """The STREAM block of viewer.js decodes what server/viewer_stream.py encodes."""
    from haptic_collab.server import viewer_stream as vs

    text = (WEB / "viewer.js").read_text(encoding="utf-8")
    m = re.search(r"export const STREAM = Object\.freeze\(\{(.*?)\}\);", text, re.S)
    assert m, "viewer.js must declare `export const STREAM = Object.freeze({...});`"
    js = dict(re.findall(r'^\s*(\w+): ("?\w+"?),', m.group(1), re.M))
    expected = {
        "NORMALS_MAGIC": f'"{vs.NORMALS_MAGIC.decode()}"',
        "DISPLACEMENT_MAGIC": f'"{vs.DISPLACEMENT_MAGIC.decode()}"',
        "VECTOR_MAGIC": f'"{vs.VECTOR_MAGIC.decode()}"',
        "DSP_HEADER_BYTES": str(vs.DSP_HEADER.size),
        "FLAG_DENSE": str(vs.FLAG_DENSE),
        "FLAG_KEY": str(vs.FLAG_KEY),
        "FLAG_INDEX32": str(vs.FLAG_INDEX32),
        "FLAG_CLAMPED": str(vs.FLAG_CLAMPED),
        "FLAG_PARTIAL": str(vs.FLAG_PARTIAL),
    }
    assert js == expected


# ----------------------------------------------------------------------------- browser tests
_READY = """() => {
  const s = window.viewerState;
  return !!(s && s.connected && s.frames >= 3 && s.renders >= 1 && s.users.A && s.users.B
            && s.users.B.in_contact && s.users.B.force_n_mag > 0);
}"""

# Pixels of the WebGL canvas itself (it is transparent where nothing is drawn), in the middle of
# the view area (the part of the window the panels leave free): how many are drawn.
_CANVAS_PIXELS = """() => {
  const c = document.querySelector("#scene canvas");
  const sx = c.width / c.clientWidth;
  const v = document.getElementById("view-area").getBoundingClientRect();
  const x0 = Math.floor((v.left + v.width * 0.35) * sx), x1 = Math.floor((v.left + v.width * 0.65) * sx);
  const y0 = Math.floor((v.top + v.height * 0.35) * sx), y1 = Math.floor((v.top + v.height * 0.65) * sx);
  const cv = document.createElement("canvas");
  cv.width = x1 - x0;
  cv.height = y1 - y0;
  const g = cv.getContext("2d");
  g.drawImage(c, x0, y0, cv.width, cv.height, 0, 0, cv.width, cv.height);
  const d = g.getImageData(0, 0, cv.width, cv.height).data;
  let drawn = 0;
  for (let i = 0; i < d.length; i += 4) if (d[i + 3] >= 16) drawn++;
  return { total: d.length / 4, drawn };
}"""

# Mean colour of the canvas in a 7 x 7 CSS-pixel square around [x, y].
_COLOR_AT = """([x, y]) => {
  const c = document.querySelector("#scene canvas");
  const sx = c.width / c.clientWidth;
  const cv = document.createElement("canvas");
  const n = Math.max(1, Math.round(7 * sx));
  cv.width = cv.height = n;
  const g = cv.getContext("2d");
  g.drawImage(c, Math.round(x * sx) - (n >> 1), Math.round(y * sx) - (n >> 1), n, n, 0, 0, n, n);
  const d = g.getImageData(0, 0, n, n).data;
  const m = [0, 0, 0];
  for (let i = 0; i < d.length; i += 4) for (let k = 0; k < 3; k++) m[k] += d[i + k] / (n * n);
  return m;
}"""

# Bounding boxes [left, top, right, bottom] of the panels and of every user card.
_BOXES = """() => {
  const box = (e) => { const r = e.getBoundingClientRect(); return [r.left, r.top, r.right, r.bottom]; };
  const q = (s) => document.querySelector(s);
  return {
    window: [0, 0, window.innerWidth, window.innerHeight],
    topbar: box(q("#topbar")), users: box(q("#users")), legend: box(q("#legend")),
    colormap: box(q("#colormap")), view: box(q("#view-area")),
    cards: Object.fromEntries([...document.querySelectorAll("#user-list section.user")]
      .map((e) => [e.dataset.userName, box(e)])),
  };
}"""


def _overlap(a: list[float], b: list[float]) -> bool:
    return a[0] < b[2] - 0.5 and b[0] < a[2] - 0.5 and a[1] < b[3] - 0.5 and b[1] < a[3] - 0.5


def _inside(inner: list[float], outer: list[float]) -> bool:
    return (
        inner[0] >= outer[0] - 0.5
        and inner[1] >= outer[1] - 0.5
        and inner[2] <= outer[2] + 0.5
        and inner[3] <= outer[3] + 0.5
    )


async def _viewer_users(page: Any) -> dict[str, dict[str, Any]]:
    users: dict[str, dict[str, Any]] = await page.evaluate("() => window.viewerState.users")
    return users


async def _sample_force(page: Any, name: str, n: int, interval_s: float) -> list[float]:
    out = []
    for _ in range(n):
        out.append(float((await _viewer_users(page))[name]["force_n_mag"]))
        await asyncio.sleep(interval_s)
    return out


def _server_indentation_mm(app: Any, proxy_m: list[float]) -> float:
    """The server's own surface displacement inward [mm] at the vertex nearest ``proxy_m``."""
    world = app.room.world
    v = np.asarray(world.vertices)
    i = int(np.argmin(np.linalg.norm(v - np.asarray(proxy_m), axis=1)))
    w = float((v[i] - world.obj.rest_vertices[i]) @ world.obj.rest_normals[i])
    return -w * 1000.0


async def _launch(pw: Any) -> Any:
    return await pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)


def _watch(page: Any) -> list[str]:
    problems: list[str] = []
    page.on("pageerror", lambda exc: problems.append(f"page error: {exc}"))
    page.on(
        "console",
        lambda m: problems.append(f"console: {m.text}") if m.type == "error" else None,
    )
    return problems


@contextlib.asynccontextmanager
async def viewer_page(
    *users: ScriptedUser,
    subdivisions: int = 4,
    viewport: tuple[int, int] = (VIEW_W, VIEW_H),
    world: Any = None,
) -> AsyncIterator[tuple[Any, Any, list[str]]]:
    """``(app, page, problems)``: the real server (the balloon, or ``world``) with ``users``
    connected, and its viewer page in chromium (``viewport`` width, height [px]) ready;
    ``problems`` collects the page's errors.

    Skips the test, with the reason, when chromium, playwright or three.js is missing.
    """
    reason = _browser_skip_reason()
    if reason:
        pytest.skip(reason)
    from playwright.async_api import async_playwright

    async with (
        running_server(subdivisions, world=world) as app,
        scripted_users(app.port, *users),
        async_playwright() as pw,
    ):
        browser = await _launch(pw)
        try:
            page = await browser.new_page(viewport={"width": viewport[0], "height": viewport[1]})
            problems = _watch(page)
            await page.goto(f"http://127.0.0.1:{app.port}/", wait_until="domcontentloaded")
            await page.wait_for_function(_READY, timeout=30_000)
            yield app, page, problems
        finally:
            await browser.close()


@pytest.mark.browser
@pytest.mark.timeout(120)
async def test_viewer_shows_the_dent_users_and_coupled_force() -> None:
    """A presses the top: the viewer colours the dent, shows A's indentation as the server has
    it, keeps A's arrow and the dent in view, and the force it shows for B (on the side) rises."""
    a = ScriptedUser("A", "top", depth_m=-0.005)  # hovering 5 mm above the top
    b = ScriptedUser("B", "side", depth_m=0.002)  # resting 2 mm inside the side
    async with viewer_page(a, b) as (app, page, problems):
        # header and connection indicator (a loaded machine may show "late" for a moment)
        await page.wait_for_function(
            "() => document.getElementById('conn').className === 'conn connected'",
            timeout=10_000,
        )
        # the rate is filled in by the first room summary, which may come after the connection
        await page.wait_for_function(
            f"() => document.getElementById('s-rate').textContent === '{SIM_RATE_HZ:.0f}'",
            timeout=10_000,
        )

        # B at rest, A not touching yet: B's force settles and the surface stream goes quiet
        await asyncio.sleep(1.5)
        before = await _sample_force(page, "B", n=5, interval_s=0.1)
        baseline = sum(before) / len(before)
        assert baseline > 0.0
        users = await _viewer_users(page)
        assert users["A"]["force_n_mag"] == 0.0 and users["A"]["penetration_mm"] < 0.0
        card_a = page.locator('#user-list section.user[data-user-name="A"]')
        await page.wait_for_timeout(300)
        assert await card_a.locator(".indent-value").inner_text() == "not in contact"
        assert await card_a.locator('[data-k="penetration_mm"]').inner_text() == (
            "not in contact"
        )  # not a negative depth
        # once B's contact has settled nothing moves: the surface stream is about a header a
        # tick (float32 frames were 31 kB a tick here, 600 kB/s)
        await page.wait_for_function("() => window.viewerState.bytesPerS < 5000", timeout=15_000)

        # A presses 15 mm into the top: the water pushes the side out into B's probe
        a.target_m = 0.015
        peak = baseline
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 15.0
        while loop.time() < deadline:
            users = await _viewer_users(page)
            peak = max(peak, float(users["B"]["force_n_mag"]))
            if peak >= 1.15 * baseline and users["A"]["penetration_mm"] > 5.0:
                break
            await asyncio.sleep(0.1)
        users = await _viewer_users(page)
        assert peak >= 1.10 * baseline, (
            f"B's force shown by the viewer went {baseline:.3f} -> {peak:.3f} N "
            f"while A pressed (expected a rise of at least 10 %)"
        )
        assert users["A"]["in_contact"] and users["A"]["force_n_mag"] > 0.3, users["A"]
        assert users["A"]["penetration_mm"] > 1.0, users["A"]
        assert users["B"]["k_o"] > 0 and users["B"]["k_o_eff"] > 0 and users["B"]["k_h"] > 0

        # A holds still: the indentation shown is the server's surface displacement there
        while a.depth_m != a.target_m and loop.time() < deadline:
            await asyncio.sleep(0.1)
        # the dent settles after A's probe stops (slower on a loaded machine): the viewer shows
        # the server's indentation once both stand still
        settle = loop.time() + 10.0
        while True:
            await asyncio.sleep(1.0)
            users = await _viewer_users(page)
            shown = users["A"]["indentation_mm"]
            assert shown is not None and shown >= 0.0
            truth = _server_indentation_mm(app, users["A"]["proxy_m"])
            if (truth > 2.0 and abs(shown - truth) < 0.3) or loop.time() > settle:
                break
        assert truth > 2.0 and abs(shown - truth) < 0.3, (shown, truth)
        await page.wait_for_timeout(300)
        text = await card_a.locator(".indent-value").inner_text()
        assert abs(float(text.replace("mm", "")) - shown) < 0.05, (text, shown)

        # both users have a panel showing their force, in the colour of their name
        cards = page.locator("#user-list section.user")
        assert await cards.count() == 2
        for name in ("A", "B"):
            card = page.locator(f'#user-list section.user[data-user-name="{name}"]')
            assert await card.locator(".name").inner_text() == name
            shown_f = float(await card.locator(".force-value").inner_text())
            assert math.isfinite(shown_f) and shown_f > 0.0
            assert "scripted" in await card.locator(".device").inner_text()
            color = await card.evaluate("e => e.style.getPropertyValue('--c')")
            assert color == users[name]["color"]
        assert users["A"]["color"] != users["B"]["color"]

        # the colour legend is there in mm and covers the dent (read in one go with the state:
        # the scale may change between two reads while the dent settles)
        state, legend = await page.evaluate(
            "() => [window.viewerState, document.getElementById('cm-in').textContent]"
        )
        scale = state["colorScale"]
        assert await page.locator("#colormap").is_visible()
        assert legend == f"−{scale['range_mm']:g} mm", legend
        # A's indentation of that same state: the dent may still be relaxing since `shown` was
        # read (on a loaded machine it moved 0.9 mm in the seconds between), and the surface
        # frames and the room summaries arrive apart (up to a tick's motion between them)
        now = state["users"]["A"]["indentation_mm"]
        assert scale["max_in_mm"] >= now - 0.2 and scale["range_mm"] >= scale["max_in_mm"]

        # the camera shows the dent from outside, and the force arrows stay in view
        dent = state["dent"]
        assert dent is not None and dent["depth_mm"] >= now - 0.2
        assert dent["in_view"] and dent["facing"] > 0.2, dent
        for name, arrow in state["arrows"].items():
            assert arrow["in_view"] or not arrow["visible"], (name, arrow)
        assert state["arrows"]["A"]["visible"]
        # pushed in is warm on the legend: the dent is drawn in warm colours
        r, _, blue = await page.evaluate(_COLOR_AT, dent["px"])
        assert r > blue + 40, (r, blue)

        # the balloon is drawn, in the middle of the view area
        pixels = await page.evaluate(_CANVAS_PIXELS)
        assert pixels["drawn"] >= 0.9 * pixels["total"], pixels
        # its surface came as normal displacements (DSP1), never the dearer vectors (DSV1)
        assert state["frames"] > 0 and state["vectorFrames"] == 0, state

        png = await page.screenshot(type="png")
        if UPDATE_SCREENSHOT:
            SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
            SCREENSHOT.write_bytes(png)
        assert not problems, problems


@pytest.mark.browser
@pytest.mark.timeout(120)
async def test_layout_at_900_px_shows_every_card_and_colours_follow_names() -> None:
    """At 900 x 700 nothing overlaps and three users' cards are all visible; a user who leaves
    and comes back keeps its colour; a free user reads "not in contact"."""
    a = ScriptedUser("A", "top", depth_m=0.002)
    b = ScriptedUser("B", "side", depth_m=0.002)
    async with viewer_page(a, b, subdivisions=3, viewport=(900, 700)) as (app, page, problems):
        three = "() => Object.keys(window.viewerState.users).length === 3"
        async with scripted_users(app.port, ScriptedUser("C", "side", depth_m=-0.02)):
            await page.wait_for_function(three, timeout=10_000)
            await page.wait_for_timeout(400)  # the panels refresh every 100 ms
            boxes = await page.evaluate(_BOXES)
            colors = {n: u["color"] for n, u in (await _viewer_users(page)).items()}
            card_c = page.locator('#user-list section.user[data-user-name="C"]')
            assert await card_c.locator(".indent-value").inner_text() == "not in contact"
        for name in ("topbar", "users", "legend", "colormap", "view"):
            assert _inside(boxes[name], boxes["window"]), (name, boxes[name])
        assert not _overlap(boxes["topbar"], boxes["users"]), boxes
        assert not _overlap(boxes["topbar"], boxes["view"]), boxes
        assert not _overlap(boxes["users"], boxes["legend"]), boxes
        assert not _overlap(boxes["users"], boxes["view"]), boxes
        assert sorted(boxes["cards"]) == ["A", "B", "C"]
        for name, card in boxes["cards"].items():
            assert _inside(card, boxes["users"]), (name, card, boxes["users"])
        assert len(set(colors.values())) == 3, colors

        # C leaves; C comes back (a new connection, a new user id): the same colour
        await page.wait_for_function(
            "() => Object.keys(window.viewerState.users).length === 2", timeout=10_000
        )
        async with scripted_users(app.port, ScriptedUser("C", "top", depth_m=-0.02)):
            await page.wait_for_function(three, timeout=10_000)
            again = (await _viewer_users(page))["C"]["color"]
        assert again == colors["C"]
        assert not problems, problems


_STALE = """(name) => {
  const u = window.viewerState.users[name], a = window.viewerState.arrows[name];
  return !!(u && u.stale && a && !a.visible);
}"""
_LIVE = """(name) => {
  const u = window.viewerState.users[name], a = window.viewerState.arrows[name];
  return !!(u && !u.stale && u.force_n_mag > 0 && a && a.visible);
}"""

#: A user's card in the panel reads live: not marked stale, and a force above zero shown.
_CARD_LIVE = """(name) => {
  const card = document.querySelector(`#user-list section.user[data-user-name="${name}"]`);
  if (!card || card.classList.contains("stale")) return false;
  const badge = card.querySelector(".badge"), force = card.querySelector(".force-value");
  return badge.textContent.toLowerCase() !== "stale" && parseFloat(force.textContent) > 0;
}"""


@pytest.mark.browser
@pytest.mark.timeout(120)
async def test_a_silent_user_is_shown_stale_with_no_force() -> None:
    """B rests on the side, then stops sending states but stays connected: the viewer marks B
    stale on its card and draws no arrow for it, while A, resting just as still on the top, keeps
    its force and arrow. When B sends again it is live again."""
    a = ScriptedUser("A", "top", depth_m=0.002)
    b = ScriptedUser("B", "side", depth_m=0.002)
    async with viewer_page(a, b, subdivisions=3) as (app, page, problems):
        for name in ("A", "B"):
            await page.wait_for_function(_LIVE, arg=name, timeout=10_000)
        card_b = page.locator('#user-list section.user[data-user-name="B"]')
        # the panels refresh every 100 ms; a scripted user in this test's own busy process may
        # be late a moment (CI once read B's card stale 300 ms after B was live)
        await page.wait_for_function(_CARD_LIVE, arg="B", timeout=5_000)

        # B's client stalls: its last force is no longer shown, in the scene or on its card
        b.silent = True
        await page.wait_for_function(_STALE, arg="B", timeout=5_000)
        await page.wait_for_timeout(300)
        assert (await card_b.locator(".badge").inner_text()).lower() == "stale"
        assert "stale" in (await card_b.get_attribute("class") or "").split()
        assert await card_b.locator(".force-value").inner_text() == "–"
        # A holds just as still, but it is still sending: it keeps its force and arrow (a
        # scripted user in this test's own busy process may be late a moment: it is live again
        # within a few seconds, while B stays stale)
        await asyncio.sleep(1.0)
        await page.wait_for_function(_LIVE, arg="A", timeout=5_000)
        users = await _viewer_users(page)
        assert not users["A"]["stale"] and users["A"]["force_n_mag"] > 0.0, users["A"]
        assert users["B"]["stale"], users["B"]
        await page.wait_for_function(_CARD_LIVE, arg="A", timeout=5_000)

        # B sends again: live again, with its arrow
        b.silent = False
        await page.wait_for_function(_LIVE, arg="B", timeout=10_000)
        await page.wait_for_function(_CARD_LIVE, arg="B", timeout=5_000)
        assert not problems, problems


#: What the viewer draws may differ from the server's surface per axis: one quantum (1 um, the
#: half-quantum rounding and a tick of residual creep) plus float32 rounding of the positions.
DRAWN_TOL_M = 1.0e-6 + 1.0e-7


@pytest.mark.browser
@pytest.mark.timeout(120)
async def test_viewer_draws_a_solid_moving_sideways_where_the_server_has_it(tmp_path: Path) -> None:
    """On the FEM solid, whose surface also slides sideways, A presses the top: every vertex is
    drawn where the server has it, within a quantum per axis, including the vertices that moved a
    millimetre or more off their rest normals (drawn along the normals they would be that far
    off)."""
    a = ScriptedUser("A", "top", depth_m=-0.003)  # hovering 3 mm above the top
    b = ScriptedUser("B", "side", depth_m=0.002)
    world = _fem_world(tmp_path)
    async with viewer_page(a, b, subdivisions=2, world=world) as (app, page, problems):
        a.target_m = 0.012  # 12 mm into the top
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 30.0
        while a.depth_m != a.target_m and loop.time() < deadline:
            await asyncio.sleep(0.1)
        obj = app.room.world.obj
        rest, normals = np.asarray(obj.rest_vertices), np.asarray(obj.rest_normals)
        every = list(range(len(rest)))
        err, sideways = math.inf, 0.0
        while loop.time() < deadline:  # until the pressed solid settles under the held probe
            server = np.array(app.room.world.vertices)
            drawn = np.array(await page.evaluate("(i) => window.viewerPositions(i)", every))
            d = server - rest
            along = np.einsum("ij,ij->i", d, normals)[:, None] * normals
            sideways = float(np.max(np.linalg.norm(d - along, axis=1)))
            err = float(np.max(np.abs(drawn - server)))
            if err <= DRAWN_TOL_M and sideways > 1e-3:  # drawn where it is, and pressed in
                break
            await asyncio.sleep(0.1)
        assert sideways > 1e-3, f"the press moved vertices only {sideways * 1e3:.3f} mm sideways"
        assert err <= DRAWN_TOL_M, f"drawn {err * 1e6:.1f} um from the server's surface"
        state = await page.evaluate("() => window.viewerState")
        # all of it came as vectors (DSV1): the keyframe and every frame after it
        assert state["frames"] > 0, state
        assert state["vectorFrames"] == state["frames"] + state["keyframes"], state
        assert state["users"]["A"]["in_contact"] and state["colorScale"]["max_in_mm"] > 2.0
        assert not problems, problems


@pytest.mark.browser
@pytest.mark.timeout(90)
async def test_viewer_reconnects_after_server_restart() -> None:
    """The socket closes (server restarted on the same port): the page reconnects by itself."""
    reason = _browser_skip_reason()
    if reason:
        pytest.skip(reason)
    from playwright.async_api import async_playwright

    async with async_playwright() as pw:
        browser = await _launch(pw)
        try:
            page = await browser.new_page(viewport={"width": VIEW_W, "height": VIEW_H})
            async with running_server(subdivisions=2) as app:
                port = app.port
                await page.goto(f"http://127.0.0.1:{port}/", wait_until="domcontentloaded")
                await page.wait_for_function(
                    "() => window.viewerState && window.viewerState.connected"
                    " && window.viewerState.frames > 0",
                    timeout=30_000,
                )
            await page.wait_for_function("() => !window.viewerState.connected", timeout=10_000)
            assert await page.locator("#conn").get_attribute("class") == "conn reconnecting"
            async with running_server(subdivisions=2, port=port):
                await page.wait_for_function(
                    "() => window.viewerState.connected && window.viewerState.reconnects >= 1",
                    timeout=20_000,
                )
                frames = await page.evaluate("() => window.viewerState.frames")
                await page.wait_for_function(
                    f"() => window.viewerState.frames > {frames}", timeout=10_000
                )
                # "late" until the new server's first room summary is in, then connected
                await page.wait_for_function(
                    "() => document.getElementById('conn').className === 'conn connected'",
                    timeout=10_000,
                )
        finally:
            await browser.close()
