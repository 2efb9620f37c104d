"""The viewer of a named room: the page ``/rooms/NAME/`` watches room NAME, in Debian's chromium.

The real server in this process with two rooms of different objects (the default balloon of 162
vertices, room ``lab`` of 642) and a different simulation rate each; the page must draw the
room its path names. Skipped, with the reason, when chromium, playwright or three.js is missing.
"""

from __future__ import annotations

import pytest

from haptic_collab.server.app import DEFAULT_ROOM, ServerApp
from haptic_collab.server.main import ServerOptions, build_world
from haptic_collab.server.room import Room
from tests.web.test_viewer import _browser_skip_reason, _launch, _watch


def _room(sim_rate_hz: float, subdivisions: int) -> Room:
    opts = ServerOptions(sim_rate_hz=sim_rate_hz, subdivisions=subdivisions)
    return Room(build_world(opts), sim_rate_hz)


@pytest.mark.browser
@pytest.mark.timeout(120)
async def test_the_page_of_a_room_watches_that_room() -> None:
    reason = _browser_skip_reason()
    if reason:
        pytest.skip(reason)
    from playwright.async_api import async_playwright

    app = ServerApp(_room(20.0, 2), "127.0.0.1", 0, rooms={"lab": _room(25.0, 3)})
    await app.start()
    try:
        async with async_playwright() as pw:
            browser = await _launch(pw)
            try:
                page = await browser.new_page()
                problems = _watch(page)
                await page.goto(f"http://127.0.0.1:{app.port}/rooms/lab/")
                await page.wait_for_function(
                    "() => window.viewerState.connected && window.viewerState.frames >= 3",
                    timeout=30_000,
                )
                state = await page.evaluate("() => window.viewerState")
                hint = await page.locator("#client-hint").inner_text()
                watching = {name: len(room.viewers) for name, room in app.rooms().items()}
            finally:
                await browser.close()
        rooms = app.rooms()
        assert state["nVertices"] == len(rooms["lab"].world.vertices) == 642
        assert state["simRateHz"] == 25.0
        assert f"ws://127.0.0.1:{app.port}/rooms/lab/ws" in hint
        assert watching == {DEFAULT_ROOM: 0, "lab": 1}
        assert problems == []
    finally:
        await app.stop()
