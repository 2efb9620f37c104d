"""The viewer's "show lump": a FEM solid's inclusion is hidden until the user asks for it.

The real server runs in this process around a small FEM solid (r = 5 cm) of liver with a lump
ten times as stiff at its centre; chromium (Debian's, through Playwright, as in
``test_viewer.py``) opens the viewer. The lump is hidden at first (palpation is blind): the
checkbox is off, its text says "hidden" and the canvas at the lump's place shows the object's
own colour. Ticking it draws the lump there (red: stiffer) and says what it is; unticking hides
it again. ``?lump=1`` shows it from the start, and an object without inclusions has no
checkbox. Skipped, with the reason, when chromium, playwright or three.js is missing.
"""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from tests.web.test_viewer import (
    _COLOR_AT,
    SIM_RATE_HZ,
    VIEW_H,
    VIEW_W,
    _browser_skip_reason,
    _launch,
    _watch,
    running_server,
)


def _lump_world(cache_dir: Path) -> Any:
    """The FEM solid of test_viewer.py (162 vertices, r = 5 cm) with a lump of 2 cm radius at
    its centre, ten times as stiff as the liver around it."""
    import trimesh

    from haptic_collab.server.objects.fem import FemParams, FemSolid
    from haptic_collab.server.objects.inclusions import (
        Inclusion,
        element_materials,
        inclusion_material,
        volume_with_inclusions,
    )
    from haptic_collab.server.solid_materials import SOLID_PRESETS
    from haptic_collab.server.world import World

    mesh = trimesh.creation.icosphere(2, 0.05)
    lump = trimesh.creation.icosphere(1, 0.02)  # 42 vertices: the P2 solid stays small
    inc = [Inclusion(lump, inclusion_material("liver*10"), "lump.stl")]
    volume = volume_with_inclusions(mesh, inc, cache_dir=cache_dir)
    materials = element_materials(*volume, SOLID_PRESETS["liver"], inc)
    params = FemParams(sim_period_s=1.0 / SIM_RATE_HZ)
    return World(FemSolid(mesh, params, volume=volume, materials=materials))


_DRAWN = """() => {
  const s = window.viewerState;
  return !!(s && s.connected && s.keyframes >= 1 && s.renders >= 1 && s.lumps.count >= 1
            && s.lumps.items[0].px);
}"""


@contextlib.asynccontextmanager
async def page_of(world: Any, query: str = "") -> AsyncIterator[tuple[Any, list[str]]]:
    """The viewer page of a server around ``world`` (``query`` after ``/``) and its problems."""
    reason = _browser_skip_reason()
    if reason:
        pytest.skip(reason)
    from playwright.async_api import async_playwright

    async with running_server(world=world) as app, async_playwright() as pw:
        browser = await _launch(pw)
        try:
            page = await browser.new_page(viewport={"width": VIEW_W, "height": VIEW_H})
            problems = _watch(page)
            await page.goto(f"http://127.0.0.1:{app.port}/{query}", wait_until="domcontentloaded")
            yield page, problems
        finally:
            await browser.close()


async def _lumps(page: Any) -> dict[str, Any]:
    lumps: dict[str, Any] = await page.evaluate("() => window.viewerState.lumps")
    return lumps


async def _shown_is(page: Any, shown: bool) -> None:
    """Wait until the viewer says the lump is ``shown`` and has drawn it so."""
    flag = "true" if shown else "false"
    renders = await page.evaluate("() => window.viewerState.renders")
    await page.wait_for_function(
        f"() => window.viewerState.lumps.shown === {flag}"
        f" && window.viewerState.renders > {renders}",
        timeout=10_000,
    )


@pytest.mark.browser
@pytest.mark.timeout(180)
async def test_the_lump_is_hidden_until_the_user_shows_it_and_hides_again(tmp_path: Path) -> None:
    async with page_of(_lump_world(tmp_path)) as (page, problems):
        await page.wait_for_function(_DRAWN, timeout=60_000)
        lumps = await _lumps(page)
        assert lumps["count"] == 1 and lumps["of"] == 1 and lumps["rejected"] == 0
        (item,) = lumps["items"]
        assert (item["name"], item["material"]) == ("lump.stl", "liver*10")
        assert item["young_ratio"] == pytest.approx(10.0) and item["in_view"]
        toggle, box, info = (page.locator(s) for s in ("#lump-toggle", "#show-lump", "#lump-info"))

        # hidden by default: palpation is blind
        assert not lumps["shown"]
        assert await toggle.is_visible() and not await box.is_checked()
        assert await info.inner_text() == "hidden"
        await page.wait_for_timeout(300)
        hidden = await page.evaluate(_COLOR_AT, item["px"])

        # shown: drawn red (stiffer) where it is, and the viewer says what it is
        await box.check()
        await _shown_is(page, True)
        shown = await page.evaluate(_COLOR_AT, item["px"])
        assert shown[0] > hidden[0] + 40 and shown[0] > shown[2] + 40, (hidden, shown)
        assert await info.inner_text() == "lump.stl · liver*10 · 10× as stiff"

        # hidden again: the object's own colour is back
        await box.uncheck()
        await _shown_is(page, False)
        again = await page.evaluate(_COLOR_AT, item["px"])
        assert max(abs(a - b) for a, b in zip(again, hidden, strict=True)) < 12, (hidden, again)
        assert await info.inner_text() == "hidden"
        assert not problems, problems


@pytest.mark.slow  # two browser runs; the lump's toggle is checked in make test
@pytest.mark.browser
@pytest.mark.timeout(180)
async def test_lump_1_shows_it_from_the_start_and_a_balloon_has_no_checkbox(
    tmp_path: Path,
) -> None:
    async with page_of(_lump_world(tmp_path), "?lump=1") as (page, problems):
        await page.wait_for_function(_DRAWN, timeout=60_000)
        assert (await _lumps(page))["shown"]
        assert await page.locator("#show-lump").is_checked()
        assert "10× as stiff" in await page.locator("#lump-info").inner_text()
        assert not problems, problems
    async with page_of(None, "?lump=1") as (page, problems):  # the balloon: no inclusions
        await page.wait_for_function(
            "() => window.viewerState.keyframes >= 1 && window.viewerState.renders >= 1",
            timeout=30_000,
        )
        lumps = await _lumps(page)
        assert lumps["count"] == 0 and lumps["of"] == 0
        assert not await page.locator("#lump-toggle").is_visible()
        assert not problems, problems
