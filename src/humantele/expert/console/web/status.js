// What the console knows of its expert daemon, and what became of each click.
//
// Heartbeat: the page pings the daemon twice a second; the daemon answers at once with its
// clock (``pong``: ``n``, ``t`` in s). The oldest unanswered ping's age (else the last round
// trip) is how late the daemon answers now, and each pong says the longest its event loop
// was held of the last second (``stall_ms``, which a hold between two pings would escape the
// pings): a daemon held up is "slow (N ms)" (the longest of the last 3 s) while its socket is
// open, and lost only when the socket closes. The answers also
// map the daemon's clock onto this page's (the offset of the fastest round trip of the last
// minute, +- half of it): a frame's capture time and a state's time become ages on this page,
// so "live" means a picture captured less than the stale bound ago, whatever the page did
// with it meanwhile.
//
// Who is late: a daemon held up sends nothing, then one late message and fresh ones again; a
// page that cannot keep up reads every message long after it was sent (a busy browser). The
// least lag of the timed messages read in the last 2 s (a state's or pong's time against this
// page's clock; none read: not behind) tells them apart, and each ping tells the daemon how
// far behind the page reads, so it holds its states and frames until the page catches up.
//
// Clicks: each click's message carries an id; the daemon's ``result`` with that id says what
// became of it. A click that cannot be sent (no socket) or is not answered within ACK_MS is
// said on the page, as is one whose socket dropped before its answer.

export const PING_MS = 500;
export const SLOW_MS = 300; // answers later than this: the daemon is slow
export const ACK_MS = 3000; // a click not answered by then: said so
const OFFSET_WINDOW_MS = 60000;
const PEAK_MS = 3000;
const BEHIND_WINDOW_MS = 2000;

export class Heartbeat {
  constructor(send) {
    this.send = send; // (message) => bool (sent)
    this.n = 0;
    this.out = new Map(); // ping n -> page ms sent (oldest first)
    this.rtt = null; // ms, the last round trip
    this.samples = []; // {at, rtt, off}
    this.offset = null; // daemon ms - page ms (null: not known yet)
    this.open = false;
    this.lastPing = -Infinity;
    this.lastHeard = -Infinity; // page ms of the last message of any kind
    this.peaks = []; // [page ms, delay ms] of the last PEAK_MS
    this.lags = []; // [page ms, ms from its daemon time to its reading] of timed messages read
    this.behind = 0; // ms: the least of those lags over the last BEHIND_WINDOW_MS
  }

  opened(now) { this.open = true; this.out.clear(); this.lastHeard = now; this.lastPing = -Infinity; this.tick(now); }
  closed() { this.open = false; this.out.clear(); this.peaks = []; }
  heard(now) { this.lastHeard = now; }

  tick(now) {
    if (!this.open || now - this.lastPing < PING_MS) return;
    this.lastPing = now;
    const n = ++this.n;
    this.update(now);
    if (this.send({ type: "ping", n, behind_ms: Math.round(this.behind) })) this.out.set(n, now);
  }

  // A message with the daemon's time ``tS`` (s) read now: how late this page reads.
  saw(tS, now) {
    if (typeof tS !== "number" || !Number.isFinite(tS)) return;
    const at = this.toPage(tS);
    if (at !== null) this.lags.push([now, Math.max(0, now - at)]);
    this.update(now);
  }

  update(now) {
    while (this.lags.length && now - this.lags[0][0] > BEHIND_WINDOW_MS) this.lags.shift();
    this.behind = this.lags.length >= 2 ? Math.min(...this.lags.map((l) => l[1])) : 0;
  }

  pong(m, now) {
    const sent = this.out.get(m.n);
    if (sent === undefined) { this.saw(m.t, now); return; }
    for (const k of [...this.out.keys()]) if (k <= m.n) this.out.delete(k);
    this.rtt = now - sent;
    this.samples.push({ at: now, rtt: this.rtt, off: m.t * 1000 - (sent + now) / 2 });
    while (this.samples.length > 1 && (now - this.samples[0].at > OFFSET_WINDOW_MS || this.samples.length > 240)) this.samples.shift();
    let best = this.samples[0];
    for (const s of this.samples) if (s.rtt < best.rtt) best = s;
    this.offset = best.off;
    // The daemon's own measure of how long its loop was held (the last second): a hold that
    // fell between two pings is as slow as one a ping waited through.
    if (typeof m.stall_ms === "number" && Number.isFinite(m.stall_ms)) this.peaks.push([now, m.stall_ms]);
    this.saw(m.t, now);
  }

  // How late the daemon answers now (ms): the oldest unanswered ping's age, else the last
  // round trip; null before the first ping.
  delay(now) {
    for (const sent of this.out.values()) return Math.max(now - sent, this.rtt ?? 0);
    return this.rtt;
  }

  // A daemon time (s) as a page time (ms), or null while the clocks are not mapped.
  toPage(tS) { return this.offset === null || tS == null ? null : tS * 1000 - this.offset; }

  // The daemon as the page sees it: {level: ok|slow|lost|connecting, delay (ms, now),
  // peak (ms, the longest of the last PEAK_MS: a daemon held up now and then stays "slow"
  // with it, rather than flickering between ok and slow)}.
  // "behind": this page reads the daemon's messages late (the daemon is not to blame).
  health(now) {
    if (!this.open) return { level: this.n === 0 && this.lastHeard === -Infinity ? "connecting" : "lost", delay: null, peak: null, behind: 0 };
    const d = this.delay(now);
    this.update(now);
    if (d !== null) this.peaks.push([now, d]);
    while (this.peaks.length && now - this.peaks[0][0] > PEAK_MS) this.peaks.shift();
    const peak = this.peaks.reduce((m, p) => Math.max(m, p[1]), d ?? 0);
    const level = this.behind >= SLOW_MS ? "behind" : peak >= SLOW_MS ? "slow" : "ok";
    return { level, delay: d, peak, behind: this.behind };
  }
}

export class Clicks {
  // send(message) => bool; show({of, state: "sent"|"ok"|"failed"|"late", detail}); why() =>
  // who is late (text), for a click not acknowledged in time
  constructor(send, show, why = () => "the expert daemon is slow") {
    this.send = send;
    this.show = show;
    this.why = why;
    this.id = 0;
    this.pending = new Map(); // id -> {of, at, late}
  }

  // Send a click's message with its id; what becomes of it is shown. The id, or null when
  // it could not be sent.
  click(of, msg) {
    const id = ++this.id;
    if (!this.send({ ...msg, id })) {
      this.show({ of, state: "failed", detail: "not sent: this page is not connected to the expert daemon (reconnecting); click again" });
      return null;
    }
    this.pending.set(id, { of, at: performance.now(), late: false });
    this.show({ of, state: "sent", detail: "sent…" });
    return id;
  }

  // The daemon's answer to a click (a result with an id): true if it was ours.
  answered(m) {
    const p = this.pending.get(m.id);
    if (!p) return false;
    this.pending.delete(m.id);
    if (p.late) m.detail = `${m.detail} (answered after ${((performance.now() - p.at) / 1000).toFixed(1)} s)`;
    return true;
  }

  tick(now) {
    for (const p of this.pending.values()) {
      if (!p.late && now - p.at > ACK_MS) {
        p.late = true;
        this.show({ of: p.of, state: "late", detail: `sent ${((now - p.at) / 1000).toFixed(1)} s ago, not acknowledged yet: ${this.why()}` });
      }
    }
  }

  closed() {
    for (const p of this.pending.values()) {
      this.show({ of: p.of, state: "failed", detail: "not acknowledged: the connection to the expert daemon dropped; click again" });
    }
    this.pending.clear();
  }
}
