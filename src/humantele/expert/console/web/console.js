// The sonographer's console: the ultrasound image large, the follower's view, the force,
// the session at a glance. One WebSocket to the expert daemon (same origin, /ws): binary
// messages are video frames (32-byte header + JPEG, or + the encoded frame as the expert
// received it, which WebCodecs decodes here: the hello's "transport"), text messages JSON
// (see the daemon's humantele.expert.console.messages). Nothing stale is shown as live: each panel greys out
// when its data is older than the daemon's stale_after_ms (ages from capture and state times
// mapped onto this page's clock by the heartbeat, status.js); a daemon slow to answer is
// "slow (N ms)" while its socket is open, lost only when it closes; every click says what
// became of it.

import { readCounter } from "./counter.js";
import { ForcePlot } from "./plot.js";
import { DepthScale } from "./scale.js";
import { Marks } from "./tools.js";
import { Clicks, Heartbeat } from "./status.js";
import { ItemsList } from "./items.js";

const $ = (id) => document.getElementById(id);
const TRACKS = ["us", "pov"];
const FORCE_BAR_MAX_N = 20;
const SCALE_GUTTER_PX = 30; // right of the ultrasound image: its depth scale
const COUNTER_PX = [64, 32]; // the frame counter's patch, top left of a frame (image px)

const plot = new ForcePlot($("plot"), 10);
const depthScale = new DepthScale($("us-scale"));

const app = {
  ws: null,
  hello: null,
  state: null,
  stateAt: -Infinity, // performance.now() of the last state message
  frames: { us: 0, pov: 0 }, // frames drawn
  lastFrame: { us: null, pov: null }, // {seq, at (page ms), width, height, spacing}
  frozen: false,
  cine: [], // [[seq, t rel. newest (s)], ...]
  shown: null, // the ultrasound frame on screen: {seq, width, height, spacing, cine}
  pendingCine: null,
  cineInFlight: false,
  results: [],
  closedReason: null,
  rxToDraw: [], // ms from a frame's arrival at the page to its draw call (last 500)
  counters: { us: null, pov: null }, // the counter read from each track's last drawn frame
};
window.consoleApp = app;
app.plot = plot;
app.depthScale = depthScale;
const hb = new Heartbeat(send);
const clicks = new Clicks(send, showClick, () => (hb.health(performance.now()).level === "behind"
  ? "this page reads the expert daemon's answers late (the browser is behind)" : "the expert daemon is slow"));
const itemsList = new ItemsList($("items"), $("items-count"), () => sessionStorage.getItem(KEY_STORE));
app.heartbeat = hb;
app.clicks = clicks;
app.items = itemsList;
app.drawn = { us: [], pov: [] }; // [page ms, frames drawn] samples, for the drawn frame rate

// --- the connection -------------------------------------------------------------------------

// The run's key: the address the expert prints carries it in its fragment (#key=..., which the
// browser never sends in a request); the page keeps it for this tab, takes it out of the
// address bar, and passes it on the WebSocket. Refused (4401): said on the page, no retry.
const KEY_STORE = "humantele-console-key";
const CLOSE_UNAUTHORIZED = 4401, CLOSE_THROTTLED = 4429;

function consoleKey() {
  const m = /(?:^#|&)key=([^&]+)/.exec(location.hash);
  if (m) {
    sessionStorage.setItem(KEY_STORE, decodeURIComponent(m[1]));
    history.replaceState(null, "", location.pathname + location.search);
  }
  return sessionStorage.getItem(KEY_STORE);
}

function connect() {
  const key = consoleKey();
  if (!key) {
    app.closedReason = "this page has no key: open the address the expert printed (it ends in #key=…)";
    return;
  }
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  // ?transport=jpeg|webcodecs in the page's address asks the daemon for that one (A/B)
  const asked = new URLSearchParams(location.search).get("transport");
  const extra = asked ? `&transport=${encodeURIComponent(asked)}` : "";
  const ws = new WebSocket(`${scheme}://${location.host}/ws?key=${encodeURIComponent(key)}${extra}`);
  ws.binaryType = "arraybuffer";
  app.ws = ws;
  ws.onopen = () => hb.opened(performance.now());
  ws.onmessage = (ev) => {
    hb.heard(performance.now());
    if (typeof ev.data === "string") onText(JSON.parse(ev.data)); else onFrame(ev.data);
  };
  ws.onclose = (ev) => {
    app.ws = null;
    hb.closed();
    clicks.closed();
    app.closedReason = ev.reason || null;
    if (ev.code === CLOSE_UNAUTHORIZED) { sessionStorage.removeItem(KEY_STORE); return; }
    setTimeout(connect, ev.code === CLOSE_THROTTLED ? 30000 : 1000);
  };
  ws.onerror = () => {};
}

function send(msg) {
  if (app.ws && app.ws.readyState === WebSocket.OPEN) { app.ws.send(JSON.stringify(msg)); return true; }
  return false;
}

function onText(m) {
  if (m.type === "state") { app.state = m; app.stateAt = performance.now(); hb.saw(m.t, app.stateAt); renderState(); }
  else if (m.type === "pong") hb.pong(m, performance.now());
  else if (m.type === "items") itemsList.set(m.items);
  else if (m.type === "hello") onHello(m);
  else if (m.type === "cine") onCineIndex(m);
  else if (m.type === "result") onResult(m);
}

function onHello(m) {
  app.hello = m;
  app.transport = m.transport || "jpeg";
  resetVideo();
  const sim = m.video === "sim";
  document.body.dataset.video = m.video;
  document.querySelector("#us-panel .name").textContent = sim ? "Ultrasound: SIMULATED" : "Ultrasound";
  document.querySelector("#pov-panel .name").textContent = sim ? "Follower's view: SIMULATED" : "Follower's view";
  for (const t of TRACKS) $(`${t}-sim`).hidden = !sim;
  if (m.video === "none") for (const t of TRACKS) $(`${t}-stale`).querySelector("b").textContent = "No video on this console";
  const clipS = Number(m.clip_seconds || 0);
  $("clip-label").hidden = !(clipS > 0);
  $("clip-s").textContent = String(clipS);
}

// --- video ----------------------------------------------------------------------------------

function parseHeader(buf) {
  const v = new DataView(buf);
  return {
    version: v.getUint8(0), track: TRACKS[v.getUint8(1)], cine: (v.getUint8(2) & 1) === 1,
    encoded: (v.getUint8(2) & 2) === 2, keyframe: (v.getUint8(2) & 4) === 4,
    h264: (v.getUint8(2) & 8) === 8,
    seq: v.getUint32(4, true), tCapture: v.getFloat64(8, true),
    spacing: [v.getFloat32(16, true), v.getFloat32(20, true)],
    width: v.getUint16(24, true), height: v.getUint16(26, true),
    depth0: v.getFloat32(28, true), // the image row of depth 0 (NaN: unknown)
  };
}

const decoding = { us: false, pov: false, cine: false };
const waiting = { us: null, pov: null, cine: null };

function onFrame(buf) {
  const h = parseHeader(buf);
  h.rx = performance.now();
  if (h.version !== 2 || !h.track) return;
  if (h.encoded) { onEncoded(h, buf); return; }
  const lane = h.cine ? "cine" : h.track;
  if (decoding[lane]) { waiting[lane] = { buf, h }; return; } // latest wins while one decodes
  decode(lane, buf, h);
}

async function decode(lane, buf, h) {
  decoding[lane] = true;
  try {
    const bitmap = await createImageBitmap(new Blob([new Uint8Array(buf, 32)], { type: "image/jpeg" }));
    if (lane === "cine" || !(lane === "us" && app.frozen)) draw(h, bitmap);
    else app.lastFrame.us = { seq: h.seq, at: performance.now(), ...h }; // frozen: not drawn
    bitmap.close();
  } catch (e) {
    console.warn("frame not decoded", e);
  }
  decoding[lane] = false;
  const next = waiting[lane];
  waiting[lane] = null;
  if (next) decode(lane, next.buf, next.h);
}

// --- WebCodecs: the encoded frames the expert received, decoded here ------------------------

// A decoder per track, fed in order from a keyframe on; a decoder that fails or falls behind
// is dropped and the daemon asked for a keyframe (the next one starts a new decoder).
const MAX_DECODE_QUEUE = 16; // (0.8 s of US): beyond, start again at a keyframe
const decoders = { us: null, pov: null };
const needKey = { us: true, pov: true };
const headers = { us: new Map(), pov: new Map() }; // chunk timestamp (the seq) -> header
app.decoded = { us: 0, pov: 0 }; // frames WebCodecs gave back

function resetVideo() {
  for (const t of TRACKS) {
    if (decoders[t] && decoders[t].state !== "closed") decoders[t].close();
    decoders[t] = null; needKey[t] = true; headers[t].clear();
  }
}

function restart(track, why) {
  if (decoders[track] && decoders[track].state !== "closed") decoders[track].close();
  decoders[track] = null; needKey[track] = true; headers[track].clear();
  console.warn(`${track}: decoder restarts at a keyframe (${why})`);
  send({ type: "keyframe", track });
}

function decoderFor(track, h264) {
  if (decoders[track]) return decoders[track];
  const d = new VideoDecoder({
    output: (frame) => onDecoded(track, frame),
    error: (e) => { if (decoders[track] === d) restart(track, e.message); },
  });
  // Software decoding: a GPU decoder's round trips (through Chromium's GPU process, itself
  // in software on a machine without one) decoded a frame in seconds.
  d.configure({ codec: h264 ? "avc1.42E01F" : "vp8", optimizeForLatency: true,
                hardwareAcceleration: "prefer-software" });
  decoders[track] = d;
  return d;
}

function onEncoded(h, buf) {
  const track = h.track;
  if (needKey[track] && !h.keyframe) return;
  if (typeof VideoDecoder === "undefined") { app.closedReason = "this browser has no WebCodecs"; return; }
  let d = decoderFor(track, h.h264);
  if (d.decodeQueueSize > MAX_DECODE_QUEUE) {
    restart(track, "fell behind");
    if (!h.keyframe) return;
    d = decoderFor(track, h.h264);
  }
  needKey[track] = false;
  h.rx = performance.now();
  headers[track].set(h.seq, h);
  d.decode(new EncodedVideoChunk({ type: h.keyframe ? "key" : "delta", timestamp: h.seq,
                                   data: new Uint8Array(buf, 32) }));
}

// Behind (more frames waiting to decode), a frame is drawn only if none was for
// DRAW_AT_LEAST_MS: the newest is what the sonographer needs, and drawing is work.
const DRAW_AT_LEAST_MS = 100;
const drawnAt = { us: -Infinity, pov: -Infinity };

function onDecoded(track, frame) {
  const map = headers[track], h = map.get(frame.timestamp);
  for (const k of map.keys()) { if (k <= frame.timestamp) map.delete(k); else break; }
  app.decoded[track] += 1;
  try {
    if (!h) return;
    const d = decoders[track], now = performance.now();
    if (track === "us" && app.frozen) app.lastFrame.us = { ...h, at: now };
    else if (!d || d.decodeQueueSize === 0 || now - drawnAt[track] >= DRAW_AT_LEAST_MS) {
      drawnAt[track] = now;
      draw(h, frame);
    }
  } finally {
    frame.close();
  }
}

function draw(h, bitmap) {
  const canvas = $(h.track);
  if (canvas.width !== h.width || canvas.height !== h.height) {
    canvas.width = h.width; canvas.height = h.height; fit();
  }
  const t0 = performance.now();
  // A CPU canvas: drawing a decoded frame is a copy, with no GPU upload and read-back (on a
  // software GPU, as in the headless tests, a GPU canvas halved the frame rate).
  const g = canvas.getContext("2d", { willReadFrequently: true });
  g.drawImage(bitmap, 0, 0);
  if (h.rx !== undefined) app.rxToDraw.push(t0 - h.rx);
  if (app.rxToDraw.length > 500) app.rxToDraw.shift();
  if (!h.cine) {
    app.frames[h.track] += 1;
    // The frame as drawn: its counter, read back from the canvas (glass-to-glass latency).
    const counter = readCounter(g);
    app.counters[h.track] = counter;
    setHidden($(`${h.track}-counter`), counter === null);
    app.lastFrame[h.track] = { ...h, at: t0 };
    if (h.seq !== null) {
      send({ type: "drawn", track: h.track, seq: h.seq, counter, draw_to_send_ms: performance.now() - t0 });
    }
  }
  if (h.track === "us") {
    const spacing = h.spacing[0] > 0 ? h.spacing : null;
    app.shown = { seq: h.seq, width: h.width, height: h.height, spacing, cine: h.cine };
    marks.setFrame(h.seq, h.width, h.height, spacing);
    depthScale.set(spacing ? spacing[0] : 0, h.depth0, h.height);
    if (h.cine) showCineTime(h.seq);
  }
}

// Canvases fill their box keeping the image's aspect ratio (the ultrasound leaves a gutter
// on its right for the depth scale); the marks overlay and the scale follow.
function fit() {
  for (const id of TRACKS) {
    const canvas = $(id), box = canvas.parentElement;
    const gutter = id === "us" ? SCALE_GUTTER_PX : 0;
    const bw = box.clientWidth - gutter, bh = box.clientHeight;
    if (bw <= 0 || !bh) continue;
    const s = Math.min(bw / canvas.width, bh / canvas.height);
    canvas.style.width = `${Math.floor(canvas.width * s)}px`;
    canvas.style.height = `${Math.floor(canvas.height * s)}px`;
    canvas.style.marginRight = `${gutter}px`;
    // The frame counter is read from the canvas, and covered on screen: a flickering patch
    // is nothing a sonographer should have to look at.
    const mask = $(`${id}-counter`);
    mask.style.left = `${canvas.offsetLeft}px`; mask.style.top = `${canvas.offsetTop}px`;
    mask.style.width = `${Math.ceil(COUNTER_PX[0] * s)}px`;
    mask.style.height = `${Math.ceil(COUNTER_PX[1] * s)}px`;
    if (id === "us") {
      const left = `${canvas.offsetLeft}px`, top = `${canvas.offsetTop}px`;
      const o = $("us-marks");
      o.style.width = canvas.style.width; o.style.height = canvas.style.height;
      o.style.left = left; o.style.top = top;
      const sc = $("us-scale");
      sc.style.left = `${canvas.offsetLeft + canvas.offsetWidth}px`; sc.style.top = top;
      sc.style.width = `${gutter}px`; sc.style.height = canvas.style.height;
      marks.draw();
      depthScale.draw();
    }
  }
}
window.addEventListener("resize", fit);
const boxWatch = new ResizeObserver(() => fit());
for (const id of TRACKS) boxWatch.observe($(`${id}-box`));

// --- freeze and cine ------------------------------------------------------------------------

function setFrozen(on) {
  if (clicks.click("freeze", { type: "freeze", on }) === null) return;
  app.frozen = on;
  marks.visible = on;
  $("us-marks").hidden = !on; // the marks layer exists on a frozen image only
  document.body.dataset.frozen = String(on);
  $("freeze").textContent = on ? "Live" : "Freeze";
  $("freeze").dataset.frozen = String(on);
  $("frozen-tag").hidden = !on;
  for (const id of ["tool-caliper", "tool-note", "clear"]) $(id).disabled = !on;
  $("cine").disabled = !on;
  if (!on) {
    setTool("none");
    marks.clearAll();
    app.cine = [];
    $("cine").max = "0"; $("cine").value = "0";
    $("cine-time").textContent = "live";
  }
}

function onCineIndex(m) {
  app.cine = m.frames;
  const slider = $("cine");
  slider.max = String(Math.max(0, m.frames.length - 1));
  const shown = app.shown ? m.frames.findIndex((f) => f[0] === app.shown.seq) : -1;
  slider.value = String(shown >= 0 ? shown : m.frames.length - 1);
  if (shown < 0 && m.frames.length) requestCine(m.frames[m.frames.length - 1][0]);
  else if (app.shown) showCineTime(app.shown.seq);
}

function requestCine(seq) {
  if (app.cineInFlight) { app.pendingCine = seq; return; }
  app.cineInFlight = true;
  send({ type: "cine", seq });
}

function showCineTime(seq) {
  app.cineInFlight = false;
  if (app.pendingCine !== null && app.pendingCine !== seq) {
    const s = app.pendingCine; app.pendingCine = null; requestCine(s);
  }
  const f = app.cine.find((e) => e[0] === seq);
  if (f) $("cine-time").textContent = `${f[1].toFixed(2)} s`;
}

$("freeze").onclick = () => setFrozen(!app.frozen);
$("cine").oninput = (ev) => {
  const f = app.cine[Number(ev.target.value)];
  if (f) requestCine(f[0]);
};

// --- calipers, annotations, capture ---------------------------------------------------------

const marks = new Marks($("us-marks"), (msg) => clicks.click(msg.type, msg));
app.marks = marks;

function setTool(tool) {
  marks.tool = tool;
  marks.cancel();
  $("us-box").dataset.tool = tool;
  $("tool-caliper").setAttribute("aria-pressed", String(tool === "caliper"));
  $("tool-note").setAttribute("aria-pressed", String(tool === "note"));
  $("note-input").hidden = true;
}
setTool("none");

$("tool-caliper").onclick = () => setTool(marks.tool === "caliper" ? "none" : "caliper");
$("tool-note").onclick = () => setTool(marks.tool === "note" ? "none" : "note");
$("clear").onclick = () => marks.clearFrame();
$("capture").onclick = () => capture();

function capture() {
  const f = app.frozen ? app.shown : app.lastFrame.us;
  if (!f) { showResult({ of: "capture", ok: false, detail: "no ultrasound frame to capture" }); return; }
  const clip = app.hello && app.hello.clip_seconds > 0 && $("clip").checked ? app.hello.clip_seconds : 0;
  clicks.click("capture", { type: "capture", seq: f.seq, clip_s: clip });
}

let notePoint = null;
$("us-marks").addEventListener("click", (ev) => {
  if (!app.frozen) return;
  const p = marks.point(ev);
  if (marks.tool === "caliper") marks.click(p);
  else if (marks.tool === "note") {
    notePoint = p;
    const input = $("note-input"), box = $("us-box").getBoundingClientRect();
    input.style.left = `${Math.min(ev.clientX - box.left, box.width - 230)}px`;
    input.style.top = `${ev.clientY - box.top + 8}px`;
    input.value = "";
    input.hidden = false;
    input.focus();
  }
});
$("us-marks").addEventListener("mousemove", (ev) => {
  if (marks.start) { marks.hover = marks.point(ev); marks.draw(); }
});
$("note-input").addEventListener("keydown", (ev) => {
  ev.stopPropagation();
  if (ev.key === "Enter") {
    const text = ev.target.value.trim();
    if (text && notePoint) marks.note(notePoint, text);
    ev.target.hidden = true;
  } else if (ev.key === "Escape") ev.target.hidden = true;
});

function onResult(m) {
  if (m.id !== undefined) clicks.answered(m);
  if (m.of === "caliper" && m.ok) marks.confirm(m);
  showResult(m);
  app.results.push(m);
}

const NAMES = { caliper: "Caliper", annotation: "Annotation", capture: "Capture", cine: "Cine",
  clip: "Clip", freeze: "Freeze", scan: "Scan", clutch: "Clutch" };

function showResult(m) {
  showClick({ of: m.of, state: m.ok ? "ok" : "failed", detail: m.detail });
}

// What became of a click (sent, answered, refused, late, not sent), beside its buttons.
function showClick(m) {
  const el = $(m.of === "scan" || m.of === "clutch" ? "control-result" : "tool-result");
  el.dataset.ok = String(m.state !== "failed");
  el.dataset.state = m.state;
  const name = m.of === "capture" && m.state === "ok" ? "Captured" : NAMES[m.of] || m.of;
  el.textContent = `${name}: ${m.detail}`;
  app.shownClicks = (app.shownClicks || []).concat([{ ...m, text: el.textContent }]).slice(-50);
}

document.addEventListener("keydown", (ev) => {
  if (ev.target instanceof HTMLInputElement && ev.target.type === "text") return;
  const k = ev.key.toLowerCase();
  if (k === "f") setFrozen(!app.frozen);
  else if (k === "c" && app.frozen) setTool(marks.tool === "caliper" ? "none" : "caliper");
  else if (k === "a" && app.frozen) setTool(marks.tool === "note" ? "none" : "note");
  else if (k === "s") capture();
  else if (k === "escape") setTool("none");
  else if ((k === "arrowleft" || k === "arrowright") && app.frozen) {
    const s = $("cine"), v = Number(s.value) + (k === "arrowleft" ? -1 : 1);
    if (v >= 0 && v <= Number(s.max)) { s.value = String(v); s.dispatchEvent(new Event("input")); }
  }
});

// --- scan and clutch ------------------------------------------------------------------------

// The button does what it says (its label is the state the sonographer saw when clicking).
$("scan").onclick = () => clicks.click("scan", { type: "scan", action: $("scan").dataset.scanning === "true" ? "stop" : "start" });
$("clutch").onclick = () => {
  const on = $("clutch").getAttribute("aria-pressed") !== "true";
  if (clicks.click("clutch", { type: "clutch", on }) !== null) $("clutch").setAttribute("aria-pressed", String(on));
};

// --- the session at a glance ----------------------------------------------------------------

// DOM writes only when a value changes: each write costs the page a style and layout pass
// (and, on a software GPU, a repaint), which at display rate slowed the video.
function setText(el, text) { if (el.textContent !== text) el.textContent = text; }
function setData(el, key, value) { if (el.dataset[key] !== value) el.dataset[key] = value; }
function setHidden(el, hidden) { if (el.hidden !== hidden) el.hidden = hidden; }

const fmt = (v, digits = 1, unit = "") => (v === null || v === undefined ? "–" : `${Number(v).toFixed(digits)}${unit}`);

function chip(id, level, text) {
  const el = $(id);
  setData(el, "level", level);
  setText(el.querySelector(".v"), text);
}

function renderState() {
  const s = app.state;
  if (!s || s.error) return;
  const link = s.link || {};
  const connected = link.state === "connected";
  chip("chip-link", !connected ? "bad" : link.stale ? "warn" : "ok",
    !connected ? (link.state || "unknown")
      : link.pose_age_ms == null ? "connected · no pose yet"
      : link.stale ? `pose lost (${fmt(link.pose_age_ms / 1000, 1, " s")})`
      : `connected · ${fmt(link.pose_age_ms, 0, " ms")}`);
  const cal = s.calibration || {};
  chip("chip-cal", cal.state === "calibrated" ? "ok" : cal.state === "calibrating" ? "warn" : "off",
    cal.state === "calibrating" ? `press ${cal.landmark || "…"}` : cal.state || "–");
  const al = s.alignment;
  const alLevel = !al || link.stale ? "off" : al.mm <= 5 && al.deg <= 5 ? "ok" : al.mm <= 15 && al.deg <= 15 ? "warn" : "bad";
  chip("chip-align", alLevel, !al || link.stale ? "–" : `${fmt(al.mm)} mm · ${fmt(al.deg)}°`);
  const servo = s.servo || {};
  chip("chip-servo", !servo.alive ? "bad" : servo.fault ? "bad" : "ok",
    !servo.alive ? "servo stopped" : servo.fault ? `FAULT: ${servo.fault}` : `${fmt(servo.rate_hz, 0, " Hz")}`);
  const rec = s.recording || {};
  chip("chip-rec", rec.error ? "bad" : rec.on ? "rec" : "off", rec.error ? "FAILED" : rec.on ? "recording" : "off");
  chip("chip-scan", s.scan ? "ok" : "off", s.scan ? `scan ${s.scan}` : "none");
  setText($("scan"), s.scan ? `Stop scan ${s.scan}` : "Start scan");
  setData($("scan"), "scanning", String(Boolean(s.scan)));
  const clutch = s.clutch || {};
  if ($("clutch").getAttribute("aria-pressed") !== String(Boolean(clutch.on))) {
    $("clutch").setAttribute("aria-pressed", String(Boolean(clutch.on)));
  }
  setText($("clutch"), clutch.engaged ? "Clutch (engaged)" : "Clutch");
  const f = s.force || {};
  setText($("n-pose"), link.pose_age_ms == null ? "–" : link.stale ? "stale" : fmt(link.pose_age_ms, 0, " ms"));
  setText($("n-fm"), link.stale ? "stale" : fmt(f.measured_n, 2, " N"));
  setText($("n-fr"), fmt(f.rendered_n, 2, " N"));
  setText($("n-servo"), servo.alive ? fmt(servo.rate_hz, 0, " Hz") : "stopped");
  plot.add(performance.now(), link.stale ? null : f.measured_n ?? null, servo.alive ? f.rendered_n ?? null : null);
  setData($("fbar"), "stale", String(Boolean(link.stale) || f.measured_n == null));
  const width = `${Math.max(0, Math.min(100, (100 * (f.measured_n || 0)) / FORCE_BAR_MAX_N)).toFixed(1)}%`;
  if ($("fbar-fill").style.width !== width) $("fbar-fill").style.width = width;
  setText($("fbar-value"), link.stale || f.measured_n == null ? "–" : fmt(f.measured_n, 1, " N"));
  plot.draw(performance.now());
  const cap = s.captures;
  if (cap) $("capture").title = `Save this frame with the probe pose (S): ${cap.saved} saved, ${cap.refused} refused this run`;
}


const fmtS = (ms) => `${(ms / 1000).toFixed(1)} s`;
const staleBound = () => (app.hello && app.hello.stale_after_ms) || 1000;

// Each chip's source: "daemon" (the expert's own word: stale when its state is), "follower"
// (over the link: stale also when the follower's poses are).
const CHIP_SOURCE = { "chip-link": "daemon", "chip-cal": "follower", "chip-align": "follower",
  "chip-servo": "daemon", "chip-rec": "daemon", "chip-scan": "daemon" };

// How old the session state on the page is (ms): from its time on the daemon's clock when the
// clocks are mapped, and never less than since it arrived.
function stateAge(now) {
  if (!app.state) return Infinity;
  const at = hb.toPage(app.state.t);
  return Math.max(now - app.stateAt, at === null ? 0 : now - at);
}

function greyChips(now, age) {
  const bound = staleBound();
  const linkStale = !app.state || Boolean((app.state.link || {}).stale);
  for (const [id, src] of Object.entries(CHIP_SOURCE)) {
    const el = $(id), old = age > bound || !hb.open; // no socket: nothing is now's
    const stale = old || (src === "follower" && linkStale);
    setData(el, "stale", String(stale));
    const title = !stale ? "" : old ? `as the expert daemon last said, ${age === Infinity ? "never" : `${fmtS(age)} ago`}`
      : "the follower's data is stale: no fresh pose over the link";
    if (el.title !== title) el.title = title;
  }
  const old = age > bound || !hb.open;
  for (const id of ["force-panel", "numbers"]) setData($(id), "stale", String(old));
  if (old) { // the numbers the state gave are not now's: not shown as such
    for (const id of ["n-pose", "n-fm", "n-fr", "n-servo"]) setText($(id), app.state ? "stale" : "–");
    setText($("fbar-value"), "–");
  }
}

// The picture on screen: how old it is (ms, from its capture on the daemon's clock mapped to
// this page's; before the clocks are mapped, from when it was drawn, with the daemon's word on
// its newest frame), and whether that is live (younger than the stale bound).
function videoInfo(track, now) {
  const s = app.state, v = s && s.video ? s.video[track] : null;
  const last = app.lastFrame[track];
  let age = null, mapped = false;
  if (last) {
    const cap = hb.toPage(last.tCapture);
    mapped = cap !== null;
    age = mapped ? Math.max(now - cap, now - last.at) : now - last.at;
  }
  const live = Boolean(last) && hb.open && age <= staleBound() && (mapped || Boolean(v && !v.stale));
  return { v, live, age, last };
}

function drawnFps(track, now) {
  const q = app.drawn[track];
  q.push([now, app.frames[track]]);
  while (q.length > 2 && now - q[0][0] > 2000) q.shift();
  const dt = (q[q.length - 1][0] - q[0][0]) / 1000;
  return dt > 0.5 ? (q[q.length - 1][1] - q[0][1]) / dt : null;
}

// Why there is no picture yet, from what the page knows.
function noFrameYet(track) {
  const link = (app.state && app.state.link) || {};
  if (!hb.open) return "this page is not connected to the expert daemon";
  if (link.state !== "connected") return `waiting for the link to the follower (${link.state || "connecting"})`;
  return track === "us" ? "waiting for the follower's ultrasound" : "waiting for the follower's camera";
}

// An empty ultrasound picture explained: live frames while the follower's probe is not on the
// patient (the image of a probe in air is black).
function emptyReason() {
  const s = app.state || {}, f = s.force || {}, link = s.link || {}, cal = s.calibration || {};
  if (link.stale || f.contact !== false) return null;
  const calibrating = cal.state === "calibrating" ? ` (the follower is calibrating: ${cal.landmark ? `press ${cal.landmark}` : "…"})` : "";
  return `No ultrasound yet: waiting for the follower's probe contact. The probe is not on the patient, so the image is empty${calibrating}.`;
}

// Ten times a second: the daemon's health, staleness of every panel, clicks not answered.
function tick() {
  const now = performance.now();
  hb.tick(now);
  clicks.tick(now);
  const age = stateAge(now);
  app.stateAge = age;
  const h = hb.health(now);
  app.health = h;
  const bound = staleBound();
  chip("chip-expert", app.closedReason && !hb.open ? "bad" : { ok: "ok", slow: "warn", behind: "warn", connecting: "off", lost: "bad" }[h.level],
    h.level === "ok" ? `ok · ${fmt(h.delay, 0, " ms")}` : h.level === "slow" ? `slow (${Math.round(h.peak)} ms)`
      : h.level === "behind" ? `page behind (${Math.round(h.behind)} ms)` : app.closedReason ? "not connected"
      : h.level === "lost" ? "lost contact" : "connecting");
  const lost = !hb.open;
  // Late by the stale bound or more: the page's fault when it reads late ("behind"), else the
  // daemon's.
  const late = Math.max(h.delay ?? 0, h.level === "behind" ? h.behind : 0);
  const pageBehind = !lost && h.level === "behind" && late >= bound;
  const slow = !lost && !pageBehind && late >= bound;
  setHidden($("lost"), !lost || (app.stateAt === -Infinity && !app.closedReason && now < 3000));
  if (lost) {
    setText($("lost"), app.closedReason ? `The console is not connected: ${app.closedReason}`
      : "Lost contact with the expert daemon: nothing on this page is live (reconnecting…)");
  }
  setHidden($("slow"), !slow && !pageBehind);
  if (slow) {
    setText($("slow"), `The expert daemon is slow: no answer for ${fmtS(h.delay)} (its connection is open). `
      + "What is older than the stale bound is greyed.");
  } else if (pageBehind) {
    setText($("slow"), `This page is behind: it reads the expert daemon's messages ${fmtS(late)} late `
      + "(this browser cannot keep up; the machine is busy). What is older than the stale bound is greyed.");
  }
  setData(document.body, "conn", lost ? "lost" : slow || pageBehind ? "slow" : "live");
  greyChips(now, age);
  for (const track of TRACKS) {
    const { v, live, age: fAge, last } = videoInfo(track, now);
    const box = $(`${track}-box`), overlay = $(`${track}-stale`);
    const frozenUs = track === "us" && app.frozen;
    const stale = !live;
    setData(box, "stale", String(stale && !frozenUs));
    setHidden(overlay, !stale || frozenUs);
    const fps = drawnFps(track, now);
    if (stale && !frozenUs && !(app.hello && app.hello.video === "none")) {
      const what = track === "us" ? "ultrasound" : "video";
      setText(overlay.querySelector("b"), last ? `No live ${what}` : `No ${what} yet`);
      let why;
      if (!last) why = noFrameYet(track);
      else {
        const newer = v && !v.stale && v.age_ms != null && v.age_ms < fAge - 250;
        why = `last frame ${fmtS(fAge)} old` + (lost ? " (daemon out of reach)" : slow ? " (the expert daemon is slow)"
          : pageBehind ? " (this page is behind)"
          : newer ? `: the expert daemon has one ${fmtS(v.age_ms)} old, this page is behind drawing them` : "");
      }
      setText(overlay.querySelector("span"), why);
    }
    const info = $(`${track}-info`);
    if (frozenUs && app.shown) setText(info, `frozen · frame ${app.shown.seq}`);
    else if (live) {
      const sim = app.hello && app.hello.video === "sim" ? "simulated · " : "";
      setText(info, `${sim}${fmt(fps, 0)} fps · ${fmt(fAge, 0)} ms old`);
    }
    else setText(info, "not live");
  }
  const empty = !app.frozen && videoInfo("us", now).live ? emptyReason() : null;
  setHidden($("us-empty"), empty === null);
  if (empty !== null) setText($("us-empty"), empty);
  if (lost || age > bound) plot.draw(now); // no state messages: the plot still scrolls, with a gap
}

fit();
connect();
setInterval(tick, 100);
