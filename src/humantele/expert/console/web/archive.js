// The exam and the hospital's archive ([expert.archive]): the patient entered before the first
// capture (or picked from the worklist), and what has reached the archive. Its own panel and
// its own requests (/archive/..., the console's key in a header; the patient's identity only
// in request and response bodies, never in an address). Absent when the archive is off.
// "Archive scan" beside the scan controls: the whole scan as one multi-frame image, the scan in
// progress at its end or the last one ended now (POST /archive/scan).
const KEY_STORE = "humantele-console-key";
const POLL_MS = 1000;

function key() {
  const m = /(?:^#|&)key=([^&]+)/.exec(location.hash);
  return m ? decodeURIComponent(m[1]) : sessionStorage.getItem(KEY_STORE);
}

async function call(method, path, body) {
  const headers = { "X-Console-Key": key() || "" };
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const r = await fetch(path, { method, headers, cache: "no-store",
    body: body === undefined ? undefined : JSON.stringify(body) });
  let data = null;
  try { data = await r.json(); } catch { data = null; }
  return { status: r.status, data };
}

function el(tag, attrs = {}, ...kids) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "text") e.textContent = v; else e.setAttribute(k, v);
  }
  for (const k of kids) e.append(k);
  return e;
}

const FIELDS = [
  ["patient_id", "Patient ID", "text", 64], ["family_name", "Family name", "text", 64],
  ["given_name", "Given name", "text", 64], ["birth_date", "Birth date", "date", 10],
  ["accession_number", "Accession no.", "text", 16],
];

function buildPanel() {
  const panel = el("section", { id: "archive-panel", class: "panel" },
    el("div", { class: "label" }, el("span", { class: "name", text: "Exam and archive" }),
      el("span", { id: "archive-status", class: "info", text: "–" })));
  const form = el("form", { id: "exam-form", autocomplete: "off" });
  for (const [name, label, type, max] of FIELDS) {
    form.append(el("label", {}, el("span", { text: label }),
      el("input", { name, type, maxlength: String(max), ...(name === "patient_id" ? { required: "" } : {}) })));
  }
  const sex = el("select", { name: "sex" });
  for (const [v, t] of [["", "sex: unknown"], ["F", "F"], ["M", "M"], ["O", "O"]]) {
    sex.append(el("option", { value: v, text: t }));
  }
  form.append(el("label", {}, el("span", { text: "Sex" }), sex));
  form.append(el("button", { type: "submit", id: "exam-start", text: "Start exam" }),
    el("button", { type: "button", id: "worklist-ask", text: "Worklist", hidden: "" }));
  panel.append(
    el("p", { id: "exam-need", class: "result", "data-ok": "false",
      text: "Enter the patient before the first capture (the archive files the images under them)" }),
    form,
    el("div", { id: "exam-on", hidden: "" }, el("span", { id: "exam-patient", class: "mono" }),
      el("button", { type: "button", id: "exam-end", text: "End exam" })),
    el("ol", { id: "worklist", hidden: "" }),
    el("p", { id: "archive-last", class: "result" }),
    el("ul", { id: "archive-refused" }));
  const side = document.getElementById("side");
  side.insertBefore(panel, document.getElementById("items-panel"));
  const scanButton = el("button", { type: "button", id: "archive-scan", class: "big", disabled: "",
    title: "Send the whole scan to the archive as one multi-frame image", text: "Archive scan" });
  document.getElementById("clutch").after(scanButton);
  return panel;
}

// The "Archive scan" button from the status: enabled once a scan has frames (and a patient).
function showScan(s) {
  const b = document.getElementById("archive-scan");
  const k = s.scan_archive;
  let text = "Archive scan", can = false, why = "no scan yet";
  if (k && k.outcome === "queued") {
    text = `Scan ${k.scan} archived`; why = `queued for the archive: ${k.frames} frames`;
  } else if (k && k.outcome === "building") {
    text = `Archiving scan ${k.scan}…`; why = "making its image";
  } else if (k && k.running && (k.wanted || k.auto)) {
    text = `Scan ${k.scan}: archived at its end`; why = `${k.frames} frames kept so far`;
  } else if (k) {
    text = `Archive scan ${k.scan}`;
    can = k.running ? k.frames > 0 : k.frames >= 2;
    why = can ? `${k.frames} frames over ${k.seconds} s (${k.fps} a second)${k.running ? ", sent when the scan stops" : ""}`
      : "no frames kept of it (frames are kept while the console is open)";
  }
  if (!s.exam) { can = false; why = "enter the patient first"; }
  if (b.textContent !== text) b.textContent = text;
  b.disabled = !can;
  b.title = why;
}

let panel = null, exam = undefined;

function showExam(p) {
  exam = p;
  panel.querySelector("#exam-form").hidden = !!p;
  panel.querySelector("#exam-need").hidden = !!p;
  panel.querySelector("#exam-on").hidden = !p;
  panel.querySelector("#exam-patient").textContent = p
    ? `${p.family_name}${p.given_name ? ", " + p.given_name : ""} (${p.patient_id})${p.accession_number ? " acc. " + p.accession_number : ""}`
    : "";
}

async function loadExam() {
  const r = await call("GET", "/archive/exam");
  if (r.status === 200) showExam(r.data.patient);
}

function showStatus(s) {
  const st = panel.querySelector("#archive-status");
  st.textContent = s.text;
  st.dataset.level = s.unreachable ? "bad" : s.refused ? "warn" : s.archived === s.total ? "ok" : "warn";
  panel.querySelector("#archive-last").textContent = s.last || "";
  const ul = panel.querySelector("#archive-refused");
  ul.replaceChildren(...(s.refused_items || []).map((i) =>
    el("li", { text: `refused: object ${i.n} (${i.kind}): ${i.reason}` })));
  panel.querySelector("#worklist-ask").hidden = s.identity !== "worklist";
  if (s.exam !== !!exam) loadExam();
  showScan(s);
}

async function poll() {
  let r;
  try { r = await call("GET", "/archive/status"); } catch { r = { status: 0 }; }
  if (r.status === 200 && r.data && r.data.enabled === false) { // the archive is off
    if (panel) panel.hidden = true;
    return;
  }
  if (r.status === 200) {
    if (!panel) { panel = buildPanel(); wire(); await loadExam(); }
    panel.hidden = false;
    showStatus(r.data);
    window.humanteleArchive = r.data; // (for the browser tests)
  }
  setTimeout(poll, POLL_MS);
}

function wire() {
  document.getElementById("archive-scan").addEventListener("click", async () => {
    const r = await call("POST", "/archive/scan");
    const text = r.status === 200 ? r.data.text : `not archived: ${r.data?.error || r.status}`;
    panel.querySelector("#archive-last").textContent = text;
    const out = document.getElementById("control-result");
    out.dataset.ok = String(r.status === 200);
    out.dataset.state = r.status === 200 ? "ok" : "failed";
    out.textContent = `Archive scan: ${text}`;
  });
  panel.querySelector("#exam-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const data = Object.fromEntries(new FormData(ev.target).entries());
    if (!data.birth_date) data.birth_date = null;
    const r = await call("POST", "/archive/exam", data);
    panel.querySelector("#archive-last").textContent = r.status === 200 ? "exam started" : `not started: ${r.data?.error || r.status}`;
    if (r.status === 200) { ev.target.reset(); await loadExam(); }
  });
  panel.querySelector("#exam-end").addEventListener("click", async () => {
    await call("DELETE", "/archive/exam");
    showExam(null);
  });
  panel.querySelector("#worklist-ask").addEventListener("click", async () => {
    const ol = panel.querySelector("#worklist");
    ol.hidden = false;
    ol.replaceChildren(el("li", { text: "asking the worklist…" }));
    const r = await call("GET", "/archive/worklist");
    if (r.status !== 200) { ol.replaceChildren(el("li", { text: `worklist: ${r.data?.error || r.status}` })); return; }
    ol.replaceChildren(...r.data.items.map((i) => {
      const b = el("button", { type: "button", text: `${i.scheduled} ${i.patient.family_name}, ${i.patient.given_name} (${i.patient.patient_id}) ${i.description}` });
      b.addEventListener("click", async () => {
        const s = await call("POST", "/archive/exam", i.patient);
        if (s.status === 200) { ol.hidden = true; await loadExam(); }
      });
      return el("li", {}, b);
    }));
  });
}

poll();
