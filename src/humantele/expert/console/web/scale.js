// The ultrasound's depth scale, beside the image: depth in cm from depth 0 (the skin under
// the centre of the probe's face), a label every 1, 2 or 5 cm as the image's size on screen
// allows, each at its depth's row (the image's own ticks, when it has them, are beside it).
// From the frame header's pixel spacing (mm per image row) and the image row of depth 0;
// hidden when either is unknown. Its canvas sits in a gutter right of the image, as tall as
// the image on screen.

const MIN_LABEL_GAP_PX = 16; // screen px between two labels, at least

export class DepthScale {
  constructor(canvas) {
    this.canvas = canvas;
    this.geometry = null; // {mmPerRow, depth0Row, rows} of the image shown
    this.key = "";
    this.labels = []; // [cm, screen y] of the labels drawn (for tests)
  }

  // The image shown: mm per row, the row of depth 0 (NaN: unknown), its height in rows.
  set(mmPerRow, depth0Row, rows) {
    const known = mmPerRow > 0 && Number.isFinite(depth0Row) && rows > 0;
    this.geometry = known ? { mmPerRow, depth0Row, rows } : null;
    this.draw();
  }

  draw() {
    const c = this.canvas, g = this.geometry;
    c.hidden = !g;
    if (!g) { this.labels = []; return; }
    const dpr = window.devicePixelRatio || 1;
    const cssW = c.clientWidth, cssH = c.clientHeight;
    if (!cssW || !cssH) return;
    const key = [g.mmPerRow, g.depth0Row, g.rows, cssW, cssH, dpr].join();
    if (key === this.key) return;
    this.key = key;
    c.width = Math.round(cssW * dpr); c.height = Math.round(cssH * dpr);
    const ctx = c.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, cssW, cssH);
    const pxPerRow = cssH / g.rows;
    const pxPerCm = (10 / g.mmPerRow) * pxPerRow;
    const every = [1, 2, 5, 10].find((k) => k * pxPerCm >= MIN_LABEL_GAP_PX) || 10;
    ctx.fillStyle = "#c3cad2";
    ctx.font = '11px "Liberation Sans", Arial, sans-serif';
    ctx.textBaseline = "middle";
    this.labels = [];
    for (let cm = 0; ; cm += every) {
      const y = (g.depth0Row + 0.5) * pxPerRow + cm * pxPerCm; // row centres
      if (y > cssH - 6) break;
      if (y < 6) continue;
      ctx.fillText(cm === 0 ? "0 cm" : String(cm), 3, y);
      this.labels.push([cm, y]);
    }
  }
}
