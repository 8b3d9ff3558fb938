"""Scenario helpers for the headset page (inside the namespace): hold the picture still and
take it with and without each drawn object, with the camera and poses it was drawn from."""

from __future__ import annotations

from typing import Any

from playwright.async_api import Page

OBJECTS = ("virtual", "ghost", "outline")
ALL_DRAWN = (*OBJECTS, "arrow", "label")


async def next_frames(ctx: Any, page: Page, n: int = 3) -> None:
    """Wait until the page has drawn ``n`` more frames."""
    start = await page.evaluate("headset.frames")
    await ctx.until(page, f"headset.frames >= {start + n}")


async def capture(
    ctx: Any, page: Page, prefix: str, alone: tuple[str, ...] = (), when: str = "true"
) -> dict[str, Any]:
    """Freeze the page as soon as ``when`` (JavaScript on ``h``, the HUD) holds (checked and
    frozen in one step); screenshots ``<prefix>`` (as a user sees it), and of the 3D view
    alone ``<prefix>_all`` and ``<prefix>_no_<object>``; with ``alone``, also
    ``<prefix>_none`` (nothing drawn but the room) and ``<prefix>_only_<object>`` for each
    object in it (drawn with nothing in front of it: in a live session the see-through ghost
    is in front of the virtual probe, or behind it, as the novice's hand happens to be); the
    camera, the poses drawn (the feed's objects) and each object's matrixWorld."""
    freeze = (
        f"(() => {{ const h = headset.hud(); if (!({when})) return false;"
        " headset.freeze(true); return true; })()"
    )
    await ctx.until(page, freeze, 60)
    await next_frames(ctx, page)
    seen = await ctx.still_shot(page, prefix)
    await page.evaluate("headset.showHud(false)")
    await next_frames(ctx, page)
    out: dict[str, Any] = {
        "camera": await page.evaluate("headset.camera()"),
        "virtual": await page.evaluate("headset.state.virtual"),
        "probe": await page.evaluate("headset.state.probe"),
        "model": await page.evaluate("headset.state.model"),
        "hud": await page.evaluate("headset.hud()"),
        "colour": await page.evaluate("headset.colour()"),
        "matrix": {n: await page.evaluate(f"headset.matrixWorld('{n}')") for n in OBJECTS},
        "visible": {n: await page.evaluate(f"headset.visible('{n}')") for n in OBJECTS},
        "shots": {"seen": seen, "all": await ctx.still_shot(page, f"{prefix}_all")},
    }
    for name in OBJECTS:
        await page.evaluate(f"headset.show('{name}', false)")
        await next_frames(ctx, page)
        out["shots"][name] = await ctx.still_shot(page, f"{prefix}_no_{name}")
        await page.evaluate(f"headset.show('{name}', true)")
    if alone:
        await _show(page, ALL_DRAWN, False)
        await next_frames(ctx, page)
        out["shots"]["none"] = await ctx.still_shot(page, f"{prefix}_none")
        for name in alone:
            await _show(page, [name], True)
            await next_frames(ctx, page)
            out["shots"][f"only_{name}"] = await ctx.still_shot(page, f"{prefix}_only_{name}")
            await _show(page, [name], False)
        await _show(page, ALL_DRAWN, True)
    await page.evaluate("headset.showHud(true)")
    await page.evaluate("headset.freeze(false)")
    await next_frames(ctx, page)
    return out


async def _show(page: Page, names, on: bool) -> None:
    for name in names:
        await page.evaluate(f"headset.show('{name}', {'true' if on else 'false'})")


# Bad input from a page: run in the page, against the feed at `url` (same origin).
BAD_INPUT_JS = """async (url) => {
  const ws = new WebSocket(url);
  await new Promise((ok, fail) => { ws.onopen = ok; ws.onerror = fail; });
  for (const m of ['garbage', '[1,2]', '{"type":"hello"}',
                   '{"type":"drawn","pose_id":-4,"draw_to_send_ms":1}']) ws.send(m);
  ws.send(new Uint8Array([0, 1, 2]));
  for (let i = 0; i < 300; i++) ws.send('{"type":"drawn","pose_id":1,"draw_to_send_ms":0}');
  await new Promise((ok) => setTimeout(ok, 300));
  const closed = new Promise((ok) => { ws.onclose = (e) => ok(e.code); });
  ws.send('x'.repeat(5000));
  return await closed;
}"""

# A page of another site opening the feed: the browser sends that site's Origin, which the
# feed refuses. (A page under the headset page's CSP could not even try.)
CROSS_ORIGIN_JS = """(url) => new Promise((ok) => {
  const ws = new WebSocket(url);
  ws.onopen = () => ok('opened');
  ws.onerror = () => ok('refused');
})"""
