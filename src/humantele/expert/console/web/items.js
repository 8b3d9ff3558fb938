// The session's captures and measurements (the daemon's ``items`` message), newest first, so
// the sonographer reviews them before the session ends: each capture's still (a thumbnail,
// the full image on click) and its clip (an MP4 the browser or any player opens), each
// caliper's distance and note's text, with the frame they are on.

const KINDS = { capture: "Capture", caliper: "Caliper", note: "Note" };

export class ItemsList {
  constructor(list, count, key) {
    this.list = list; // <ol>
    this.count = count; // <span>
    this.key = key; // () => the run's key (captured files need it)
    this.items = [];
  }

  fileUrl(name) { return `/captures/${encodeURIComponent(name)}?key=${encodeURIComponent(this.key() || "")}`; }

  set(items) {
    this.items = items;
    const n = { capture: 0, caliper: 0, note: 0 };
    for (const i of items) n[i.kind] = (n[i.kind] || 0) + 1;
    this.count.textContent = items.length
      ? `${n.capture} capture${n.capture === 1 ? "" : "s"}, ${n.caliper} caliper${n.caliper === 1 ? "" : "s"}, ${n.note} note${n.note === 1 ? "" : "s"}`
      : "none yet";
    this.list.replaceChildren(...[...items].reverse().map((i) => this.row(i)));
  }

  row(i) {
    const li = document.createElement("li");
    li.dataset.kind = i.kind;
    const head = document.createElement("span");
    head.className = "what";
    head.textContent = `${i.n}. ${KINDS[i.kind] || i.kind}`;
    const body = document.createElement("span");
    body.className = "detail";
    if (i.kind === "capture") {
      const a = document.createElement("a");
      a.href = this.fileUrl(i.file); a.target = "_blank"; a.rel = "noopener";
      const img = document.createElement("img");
      img.src = a.href; img.alt = `still, frame ${i.seq}`; img.loading = "lazy";
      a.append(img);
      body.append(a, ` frame ${i.seq} `);
      if (i.clip) {
        const c = document.createElement("a");
        c.href = this.fileUrl(i.clip); c.target = "_blank"; c.rel = "noopener";
        c.className = "clip";
        c.textContent = `clip ${Number(i.clip_s || 0).toFixed(1)} s`;
        body.append(c);
      } else if (i.clip_pending) body.append("clip: writing…");
      else if (i.clip_error) body.append("clip failed");
    } else if (i.kind === "caliper") body.textContent = `${Number(i.mm).toFixed(1)} mm, frame ${i.seq}`;
    else body.textContent = `“${i.text}”, frame ${i.seq}`;
    li.append(head, body);
    return li;
  }
}
