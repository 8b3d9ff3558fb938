"""What the console scenarios read from the console page (scenarios/console_*.py)."""

from __future__ import annotations

# Mean level of a canvas's pixels (every 97th) and a hash of them and of the top-left 64 x 32
# px (the frame counter the sources stamp: it changes with every frame, even a dark one).
PIXELS_JS = """(id) => {
  const c = document.getElementById(id), g = c.getContext('2d');
  const d = g.getImageData(0, 0, c.width, c.height).data;
  let sum = 0, hash = 0, n = 0;
  for (let i = 0; i < d.length; i += 4 * 97) {
    sum += d[i] + d[i + 1] + d[i + 2]; n += 3; hash = (hash * 31 + d[i]) | 0;
  }
  const p = g.getImageData(0, 0, 64, 32).data;
  for (let i = 0; i < p.length; i += 4) hash = (hash * 31 + p[i]) | 0;
  return { mean: sum / n, hash, w: c.width, h: c.height };
}"""

_OVERLAY_JS = """() => {
  const c = document.getElementById('us-marks'), r = c.getBoundingClientRect();
  return [r.left, r.top, r.width, r.height, c.width, c.height];
}"""


async def pixels(page, canvas: str) -> dict:
    return await page.evaluate(PIXELS_JS, canvas)


async def image_point(page, x: float, y: float) -> tuple[float, float]:
    """Page (CSS px) coordinates of ultrasound image pixel (x, y), through the overlay."""
    r = await page.evaluate(_OVERLAY_JS)
    return r[0] + x * r[2] / r[4], r[1] + y * r[3] / r[5]


async def result(ctx, page, of: str, n: int, timeout: float = 20.0) -> dict:
    """The page's ``n``-th result of a tool (``caliper``, ``annotation``, ``capture``)."""
    js = (f"(() => {{ const r = consoleApp.results.filter(x => x.of === '{of}');"
          f" return r.length >= {n} ? r[r.length - 1] : null; }})()")  # fmt: skip
    return await ctx.until(page, js, timeout)


async def scroll_cine(ctx, page, index: int) -> int:
    """Move the cine slider to ``index``; the frame number shown once it is drawn."""
    await page.evaluate(
        f"(() => {{ const s = document.getElementById('cine'); s.value = '{index}';"
        " s.dispatchEvent(new Event('input')); })()"
    )
    seq = await page.evaluate(f"consoleApp.cine[{index}][0]")
    await ctx.until(page, f"consoleApp.shown.cine && consoleApp.shown.seq === {seq}", 10)
    return seq


async def measure(ctx, page, a: tuple[float, float], b: tuple[float, float]) -> dict:
    """A caliper from image pixel ``a`` to ``b`` on the frame shown (caliper tool on): the
    daemon's mm, the page's points, and the mm the asked points and the page's points give."""
    import math

    shown = await page.evaluate("consoleApp.shown")
    n = len(await page.evaluate("consoleApp.results.filter(x => x.of === 'caliper')"))
    for p in (a, b):
        x, y = await image_point(page, *p)
        await page.mouse.click(x, y)
    cal = await result(ctx, page, "caliper", n + 1)
    mark = (await page.evaluate("consoleApp.marks.list()"))[-1]
    row, col = shown["spacing"]

    def mm(p, q):
        return math.hypot((q[0] - p[0]) * col, (q[1] - p[1]) * row)

    return {
        "server_mm": cal["mm"],
        "seq": cal["seq"],
        "spacing": [row, col],
        "asked_mm": mm(a, b),
        "page_mm": mm(mark["a"], mark["b"]),
        "label": mark.get("mm"),
    }


async def use_frozen_tools(
    ctx,
    page,
    min_frames: int,
    cine_index,
    caliper: tuple[tuple[float, float], tuple[float, float]],
    note_at: tuple[float, float],
    note: str,
    shot: str,
) -> dict:
    """Freeze, scroll the cine to ``cine_index(n)`` of its ``n`` (> ``min_frames``) frames,
    measure a caliper between two points and place an annotation at ``note_at`` (fractions of
    the image's width and height), capture; a screenshot ``shot``; live again. What the page
    showed and the daemon answered: ``cine`` (frames, seq shown, its time label),
    ``caliper`` (see :func:`measure`), ``annotation``, ``capture`` (the results)."""
    out: dict = {}
    await page.click("#freeze")
    await ctx.until(page, f"consoleApp.cine.length > {min_frames}", 15)
    n = await page.evaluate("consoleApp.cine.length")
    seq = await scroll_cine(ctx, page, cine_index(n))
    out["cine"] = {"frames": n, "seq": seq, "label": await page.text_content("#cine-time")}
    shown = await page.evaluate("consoleApp.shown")
    w, h = shown["width"], shown["height"]
    await page.click("#tool-caliper")
    (ax, ay), (bx, by) = caliper
    out["caliper"] = await measure(ctx, page, (ax * w, ay * h), (bx * w, by * h))
    await page.click("#tool-note")
    x, y = await image_point(page, note_at[0] * w, note_at[1] * h)
    await page.mouse.click(x, y)
    await page.keyboard.type(note)
    await page.keyboard.press("Enter")
    out["annotation"] = await result(ctx, page, "annotation", 1)
    await page.click("#capture")
    out["capture"] = await result(ctx, page, "capture", 1)
    await ctx.shot(page, shot)
    # Live again (a DOM click: playwright's scroll-into-view step once hung for 30 s on a
    # loaded machine).
    await page.evaluate("document.getElementById('freeze').click()")
    await ctx.until(page, "!consoleApp.frozen", 5)
    return out
