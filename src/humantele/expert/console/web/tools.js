// Calipers and annotations on a frozen ultrasound frame, drawn on the overlay canvas.
// Points are image pixels (x right, y down from the image's top-left corner): the overlay
// canvas has the image's size in pixels, and is scaled with it on screen.

export class Marks {
  constructor(canvas, send) {
    this.canvas = canvas;
    this.send = send; // (message) => void, to the daemon
    this.tool = "none"; // "caliper" | "note" | "none"
    this.seq = null; // the frame shown (its marks are drawn)
    this.spacing = null; // [row, col] mm per px of that frame
    this.marks = []; // {kind, seq, a, b?, text?, mm?, n}
    this.start = null; // caliper's first point
    this.hover = null;
    this.count = 0;
    this.visible = false; // marks are drawn on a frozen image only
  }

  // The image pixel under a mouse event on the overlay.
  point(ev) {
    const r = this.canvas.getBoundingClientRect();
    return [
      ((ev.clientX - r.left) / r.width) * this.canvas.width,
      ((ev.clientY - r.top) / r.height) * this.canvas.height,
    ];
  }

  mmBetween(a, b) {
    if (!this.spacing || !(this.spacing[0] > 0)) return null;
    return Math.hypot((b[0] - a[0]) * this.spacing[1], (b[1] - a[1]) * this.spacing[0]);
  }

  setFrame(seq, width, height, spacing) {
    if (this.canvas.width !== width || this.canvas.height !== height) {
      this.canvas.width = width; this.canvas.height = height;
    }
    this.seq = seq;
    this.spacing = spacing;
    this.draw();
  }

  click(p) {
    if (this.tool !== "caliper" || this.seq === null) return null;
    if (!this.start) { this.start = p; this.draw(); return null; }
    const a = this.start;
    this.start = null;
    const mark = { kind: "caliper", seq: this.seq, a, b: p, mm: this.mmBetween(a, p), n: ++this.count };
    this.marks.push(mark);
    this.send({ type: "caliper", seq: this.seq, a, b: p });
    this.draw();
    return mark;
  }

  note(p, text) {
    const mark = { kind: "note", seq: this.seq, a: p, text, n: ++this.count };
    this.marks.push(mark);
    this.send({ type: "annotation", seq: this.seq, at: p, text });
    this.draw();
    return mark;
  }

  confirm(result) { // the daemon's value replaces the page's own for the latest caliper
    for (let i = this.marks.length - 1; i >= 0; i--) {
      const m = this.marks[i];
      if (m.kind === "caliper" && m.seq === result.seq) { m.mm = result.mm; m.confirmed = true; break; }
    }
    this.draw();
  }

  clearFrame() { this.marks = this.marks.filter((m) => m.seq !== this.seq); this.start = null; this.draw(); }
  clearAll() { this.marks = []; this.start = null; this.count = 0; this.draw(); }
  cancel() { this.start = null; this.draw(); }

  draw() {
    const c = this.canvas, g = c.getContext("2d");
    g.clearRect(0, 0, c.width, c.height);
    if (!this.visible) return;
    const scale = c.width / Math.max(1, c.getBoundingClientRect().width || c.width);
    const lw = 1.5 * scale, arm = 7 * scale;
    g.lineWidth = lw;
    g.font = `bold ${Math.round(15 * scale)}px "Liberation Sans", Arial, sans-serif`;
    g.textBaseline = "middle";
    const cross = (p) => {
      g.beginPath();
      g.moveTo(p[0] - arm, p[1]); g.lineTo(p[0] + arm, p[1]);
      g.moveTo(p[0], p[1] - arm); g.lineTo(p[0], p[1] + arm);
      g.stroke();
    };
    const label = (text, p) => {
      const w = g.measureText(text).width + 8 * scale;
      g.fillStyle = "rgba(0,0,0,.7)";
      g.fillRect(p[0], p[1] - 10 * scale, w, 20 * scale);
      g.fillStyle = "#ffe14d";
      g.fillText(text, p[0] + 4 * scale, p[1]);
    };
    g.strokeStyle = "#ffe14d";
    for (const m of this.marks) {
      if (m.seq !== this.seq) continue;
      if (m.kind === "caliper") {
        cross(m.a); cross(m.b);
        g.setLineDash([4 * scale, 4 * scale]);
        g.beginPath(); g.moveTo(...m.a); g.lineTo(...m.b); g.stroke();
        g.setLineDash([]);
        const mm = m.mm === null || m.mm === undefined ? "? mm (no pixel size)" : `${m.mm.toFixed(1)} mm`;
        label(`${m.n}: ${mm}`, [m.b[0] + 10 * scale, m.b[1]]);
      } else {
        g.beginPath(); g.arc(m.a[0], m.a[1], 3 * scale, 0, 2 * Math.PI); g.fillStyle = "#ffe14d"; g.fill();
        label(m.text, [m.a[0] + 8 * scale, m.a[1]]);
      }
    }
    if (this.start) {
      cross(this.start);
      if (this.hover) {
        g.setLineDash([4 * scale, 4 * scale]);
        g.beginPath(); g.moveTo(...this.start); g.lineTo(...this.hover); g.stroke();
        g.setLineDash([]);
        const mm = this.mmBetween(this.start, this.hover);
        if (mm !== null) label(`${mm.toFixed(1)} mm`, [this.hover[0] + 10 * scale, this.hover[1]]);
      }
    }
  }

  list() { return this.marks.map((m) => ({ ...m })); }
}
