// The force plot: the contact force along the beam (N, > 0 pressing into the patient) the
// follower's probe measures and the one rendered to the sonographer's stylus, the last
// `seconds`, on one canvas. Samples taken while the data is stale are gaps.

const GAP_MS = 500;

export class ForcePlot {
  constructor(canvas, seconds = 10) {
    this.canvas = canvas;
    this.seconds = seconds;
    this.samples = []; // [t_ms (page clock), measured N | null, rendered N | null]
    this.draws = 0;
  }

  add(tMs, measured, rendered) {
    this.samples.push([tMs, measured, rendered]);
    const cut = tMs - this.seconds * 1000 - 500;
    while (this.samples.length && this.samples[0][0] < cut) this.samples.shift();
  }

  draw(nowMs) {
    const c = this.canvas;
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(50, Math.round(c.clientWidth * dpr));
    const h = Math.max(50, Math.round(c.clientHeight * dpr));
    if (c.width !== w || c.height !== h) { c.width = w; c.height = h; }
    const g = c.getContext("2d");
    g.clearRect(0, 0, w, h);
    const padL = 34 * dpr, padB = 16 * dpr, padT = 6 * dpr, padR = 6 * dpr;
    let top = 5, low = 0;
    for (const [, m, r] of this.samples) {
      top = Math.max(top, m ?? 0, r ?? 0);
      low = Math.min(low, m ?? 0, r ?? 0);
    }
    top = Math.ceil(top * 1.15 / 5) * 5;
    const step = top <= 10 ? 2 : top <= 25 ? 5 : 10;
    const bottom = low < 0 ? -Math.ceil((-low * 1.15) / step) * step : 0; // pulling: below 0
    const x = (t) => padL + (w - padL - padR) * (1 - (nowMs - t) / (this.seconds * 1000));
    const y = (v) => h - padB - (h - padB - padT) * ((v - bottom) / (top - bottom));
    g.font = `${11 * dpr}px "Liberation Sans", Arial, sans-serif`;
    g.fillStyle = "#7d8793";
    g.strokeStyle = "#262c34";
    g.lineWidth = 1;
    for (let v = bottom; v <= top; v += step) {
      g.strokeStyle = v === 0 ? "#3a424c" : "#262c34";
      g.beginPath(); g.moveTo(padL, y(v)); g.lineTo(w - padR, y(v)); g.stroke();
      g.fillText(`${v} N`, 2 * dpr, y(v) + 4 * dpr);
    }
    for (let s = 0; s <= this.seconds; s += 2) {
      const xs = x(nowMs - s * 1000);
      g.fillText(s === 0 ? "now" : `-${s} s`, xs - (s === 0 ? 22 : 12) * dpr, h - 3 * dpr);
    }
    g.save();
    g.beginPath(); g.rect(padL, 0, w - padL - padR, h); g.clip();
    g.lineWidth = 2 * dpr;
    for (const [i, colour] of [[2, "#4cc9f0"], [1, "#ff9f43"]]) {
      g.strokeStyle = colour;
      g.beginPath();
      let pen = false, tPrev = -Infinity;
      for (const s of this.samples) {
        const v = s[i];
        if (s[0] - tPrev > GAP_MS) pen = false; // no samples for a while: a gap, not a line
        tPrev = s[0];
        if (v === null || v === undefined) { pen = false; continue; }
        if (pen) g.lineTo(x(s[0]), y(v)); else g.moveTo(x(s[0]), y(v));
        pen = true;
      }
      g.stroke();
    }
    g.restore();
    this.draws += 1;
  }
}
