// netpose page: live data over one WebSocket (the daemon pushes; nothing here polls), the
// settings form and recordings over small JSON requests. Every URL is relative, so the page
// works at / as well as behind BlueOS's /extensionv2/netpose/.
"use strict";

const $ = (id) => document.getElementById(id);
const view = document.body.dataset.view;
const page = {
  instance: null,        // the daemon's, from its hello: another one is a restarted daemon
  bootId: null,          // the computer's boot: another one is another clock for the points
  points: [],            // plotPoint(): [t, raw, rawTilt, sent, filteredTilt, seen, along]
  spanS: 300, historyS: 300, tokenRequired: false, liveHz: 4, pushHz: 10,
  frames: 0, frameTimes: [], estimates: 0, lastStatusAt: 0, liveUrl: null,
  settings: null, calibrationId: null, recording: null,
  groupMessages: {},     // the last message of each settings group (kept across re-renders)
  // Freshness, judged here by the browser's clock (a stalled camera sends nothing to say so):
  connected: false,
  clockOffsetS: null,    // the daemon's monotonic clock minus performance.now(), s (see daemonNow)
  estimateGapS: null,    // median time between estimates arriving, s
  estimateArrivals: [], frameAt: null, statusAt: null, statusGapS: null,
  health: null,          // the last judgement (judge()), for tests and the curious
};
window.netpose = page;   // for tests and the curious

// -- the live connection -----------------------------------------------------------------
function wsUrl() {
  const url = new URL("ws", document.baseURI);
  url.protocol = url.protocol === "https:" ? "wss:" : "ws:";
  return url.href;
}

let retryMs = 500;
function connect() {
  const ws = new WebSocket(wsUrl());
  ws.binaryType = "blob";
  ws.onopen = () => {
    // The daemon may have restarted (another clock, another rate): learn both again.
    retryMs = 500; page.connected = true; page.clockOffsetS = null; refresh();
  };
  ws.onclose = () => {
    page.connected = false; refresh();
    setTimeout(connect, retryMs);
    retryMs = Math.min(5000, retryMs * 2);
  };
  ws.onmessage = (event) => {
    if (typeof event.data === "string") onMessage(JSON.parse(event.data));
    else onFrame(event.data);
  };
}

function setLink(cls, text) { const el = $("link"); el.className = "conn " + cls; el.textContent = text; }

function onMessage(msg) {
  switch (msg.kind) {
    case "hello":
      // Another computer boot: the plot's points are on another clock, and go. Another daemon
      // (restarted): its settings are reloaded (a "Restart now" banner from before an outside
      // restart stayed up); a mere reconnect keeps a form being edited.
      if (page.bootId !== null && msg.boot_id !== page.bootId) page.points = [];
      if (page.instance !== null && msg.instance !== page.instance && view === "full") {
        loadSettings().catch(() => {}); loadRecordings().catch(() => {});
      }
      page.instance = msg.instance; page.bootId = msg.boot_id;
      page.tokenRequired = msg.token_required; page.historyS = msg.history_s;
      page.liveHz = msg.live_hz || page.liveHz; page.pushHz = msg.push_hz || page.pushHz;
      if ($("vehicle")) $("vehicle").textContent = "· " + msg.vehicle;
      if ($("token-row")) $("token-row").hidden = !msg.token_required;
      break;
    case "history": {
      // A daemon that restarted sends the little history it has: the minutes before, still
      // on this page and on the same host clock, are kept (the plot went from 1056 points to
      // 23, losing what led up to the restart). The time between shows as a gap.
      const first = msg.points.length ? msg.points[0][0] : Infinity;
      page.points = page.points.filter((p) => p[0] < first).concat(msg.points);
      drawPlots(); break;
    }
    case "estimate": onEstimate(msg); break;
    case "status":
      onStatus(msg);
      // The form is locked while the vehicle is armed (settings_editor.ARMED): shown as it
      // changes, not at the next page load.
      if (view === "full" && page.settings && msg.autopilot
          && (msg.autopilot.armed === true) !== (page.armedShown === true)) {
        page.armedShown = msg.autopilot.armed === true;
        loadSettings().catch((e) => { $("config-path").textContent = "cannot load settings: " + e.message; });
      }
      break;
    case "recording": onRecording(msg); break;
    case "damage": onDamage(msg.holes || []); break;
    case "settings": if (view === "full") loadSettings(); break;
  }
}

function onFrame(blob) {
  const url = URL.createObjectURL(blob);
  const img = $("live");
  img.onload = () => { if (page.liveUrl) URL.revokeObjectURL(page.liveUrl); page.liveUrl = url; };
  img.src = url;
  page.frames += 1;
  const now = performance.now();
  page.frameAt = now;
  page.frameTimes.push(now);
  refresh();
}

// The daemon's monotonic clock now, s: each message's `time_mono` plus the time since it
// arrived, the largest over the messages of this connection (the one that spent the least time
// on the way). A message stored by the daemon and sent when the page connects (the last
// estimate of a camera that has stopped) is old by this clock, not new.
function noteClock(timeMono) {
  if (timeMono === null || timeMono === undefined) return;
  const offset = timeMono - performance.now() / 1000;
  if (page.clockOffsetS === null || offset > page.clockOffsetS) page.clockOffsetS = offset;
}
const daemonNow = () => (page.clockOffsetS === null ? null : performance.now() / 1000 + page.clockOffsetS);
const median = (xs) => { const s = [...xs].sort((a, b) => a - b); return s.length ? s[s.length >> 1] : null; };
const clamp = (v, lo, hi) => Math.min(hi, Math.max(lo, v));

// -- estimates: header and plots ------------------------------------------------------------
const fmt = (v, digits = 2) => (v === null || v === undefined ? "–" : Number(v).toFixed(digits));
const tiltOf = (n) => (n ? (Math.acos(Math.min(1, Math.abs(n[2]))) * 180) / Math.PI : null);

const ALONG = {
  optical_axis: { short: "along the camera axis", other: "perpendicular", otherKey: "distance_m" },
  perpendicular: { short: "perpendicular to the net", other: "along the axis", otherKey: "range_m" },
};

// The same point as drivers/web/live.py's plot_point: the distances are the one the autopilot
// gets (filtered.autopilot_along): the raw estimate of that kind, and what was handed over.
function plotPoint(m) {
  const f = m.filtered; const valid = f && f.valid;
  const along = f ? f.autopilot_along : null;
  const raw = along === "optical_axis" ? m.range_m : m.distance_m;
  const t = m.frame_time_mono !== null ? m.frame_time_mono : m.time_mono;
  // [5]: a net seen but too uncertain for a distance: its refused range, drawn hollow.
  const seen = !m.detected && m.net_seen && m.approx_range_m !== null && m.approx_range_m !== undefined;
  return [t, m.detected ? raw : null, m.detected ? m.tilt_deg : null,
          f ? f.autopilot_distance_m : null, valid ? tiltOf(f.normal) : null,
          seen ? m.approx_range_m : null, along];
}

function onEstimate(m) {
  const now = performance.now();
  page.estimates += 1;
  page.lastEstimate = m;
  noteClock(m.time_mono);
  page.estimateArrivals.push(now);
  if (page.estimateArrivals.length > 21) page.estimateArrivals.shift();
  const gaps = page.estimateArrivals.slice(1).map((t, i) => (t - page.estimateArrivals[i]) / 1000);
  if (gaps.length >= 3) page.estimateGapS = median(gaps);
  const point = plotPoint(m);
  // Points are in time order: one older than the newest held is from another clock (a daemon
  // on a computer that rebooted and said no boot id): the held ones after it go.
  while (page.points.length && page.points[page.points.length - 1][0] > point[0]) page.points.pop();
  page.points.push(point);
  const oldest = m.frame_time_mono - Math.max(page.historyS, page.spanS);
  while (page.points.length && page.points[0][0] < oldest) page.points.shift();
  refresh();
  if (!page.drawPending) { page.drawPending = true; requestAnimationFrame(drawPlots); }
}

// -- is what the page shows current? ------------------------------------------------------------
// Nothing arrives from a camera that stalls: the page judges by its own clock how old the newest
// estimate and frame are, and reads the status for the source's state and whether a distance is
// going to the autopilot.
const STALE_MIN_S = 1.5, STALE_MAX_S = 6, STATUS_STALE_MIN_S = 5;

function judge() {
  const now = performance.now();
  const m = page.lastEstimate, s = page.status;
  const statusAge = page.statusAt === null ? null : (now - page.statusAt) / 1000;
  const statusLimit = Math.max(STATUS_STALE_MIN_S, 3 * (page.statusGapS || 1));
  const status = s && statusAge !== null && statusAge <= statusLimit ? s : null;
  const clock = daemonNow();
  // The age of what the estimate shows: since its frame was captured (a frame held up in a
  // stalling stream arrives seconds old), when the capture stamp is on the daemon's clock.
  const toPublishMs = m && m.latency_ms ? m.latency_ms.frame_to_publish : null;
  const lagS = typeof toPublishMs === "number" && toPublishMs >= 0 && toPublishMs <= 60000
    ? toPublishMs / 1000 : 0;
  const estimateAge = m && clock !== null ? Math.max(0, clock - m.time_mono) + lagS : null;
  const staleAfter = clamp(3 * (page.estimateGapS || 1 / page.pushHz), STALE_MIN_S, STALE_MAX_S);
  const frameAge = page.frameAt === null ? null : (now - page.frameAt) / 1000;
  const source = status ? status.frame_source.state : null;
  const h = {
    connected: page.connected, estimateAge, frameAge, statusAge, source,
    sending: status ? status.autopilot.sending_distance : null,
    autopilot: status ? status.autopilot.state : null,
    estimateStale: estimateAge === null || estimateAge > staleAfter,
    statusStale: !status,
    sourceDown: source !== null && source !== "streaming",
  };
  h.frameStale = frameAge === null || frameAge > Math.max(staleAfter, 3 / page.liveHz);
  h.live = h.connected && !h.estimateStale && !h.statusStale && !h.sourceDown;
  const ago = (age) => (age === null ? "" : ` for ${fmt(age, 0)} s`);
  if (!h.connected) h.reason = "disconnected from the daemon – retrying";
  else if (h.sourceDown) {
    const lastFrame = status.frame_source.last_frame_age_s;
    h.reason = `camera ${source}` + (lastFrame !== null && lastFrame !== undefined
      ? `: no frame for ${fmt(lastFrame + statusAge, 0)} s` : "");
  } else if (h.estimateStale) h.reason = m ? `no estimate${ago(estimateAge)}` : "no estimate yet";
  else if (h.statusStale) h.reason = statusAge === null ? "no status from the daemon yet" : `no status from the daemon${ago(statusAge)}`;
  else h.reason = "";
  return h;
}

function setText(id, text, cls) {
  const el = $(id); if (!el) return;
  el.textContent = text;
  if (cls !== undefined) el.className = cls;
}

function refresh() {
  const h = page.health = judge();
  document.body.classList.toggle("stale", !h.live);
  // The connection line says "live" only while estimates are current, not merely connected.
  if (h.live) setLink("live", "live");
  else setLink("down", h.connected ? h.reason : "disconnected – retrying");
  renderHeader(h);
  const img = $("live"), note = $("live-note");
  if (img) img.classList.toggle("stale", h.frameStale || !h.live);
  if (note) {
    note.hidden = !(h.frameStale || !h.live) || !page.frames;
    const frame = h.frameAge === null ? "" : `frame from ${fmt(h.frameAge, 0)} s ago`;
    note.textContent = [h.live ? "" : h.reason, frame].filter(Boolean).join(" · ");
  }
  // The Health card's rows are the last status: once the daemon stops answering they are no
  // longer the state of anything ("heartbeat 0.2 s ago · sending distance" in green, 15 s
  // after the daemon was gone).
  const table = $("health");
  if (table) {
    const old = !h.connected || h.statusStale;
    table.classList.toggle("stale", old);
    if (old && $("digest")) {
      const age = h.statusAge === null ? "" : ` ${fmt(h.statusAge, 0)} s ago`;
      $("digest").textContent = `as of the last status${age}: the daemon is not answering`;
    }
  }
  if ($("live-rate")) {
    const now = performance.now();
    while (page.frameTimes.length && page.frameTimes[0] < now - 5000) page.frameTimes.shift();
    $("live-rate").textContent = page.frameTimes.length || h.frameAge === null
      ? `${(page.frameTimes.length / 5).toFixed(1)} frames/s`
      : `no frame for ${fmt(h.frameAge, 0)} s`;
  }
}

function renderHeader(h) {
  const m = page.lastEstimate;
  const f = (m && m.filtered) || { state: "lost", valid: false, autopilot: "none" };
  const along = ALONG[f.autopilot_along];
  const setting = f.autopilot_along ? ` (service.autopilot_distance = ${f.autopilot_along})` : "";
  if (!m || !h.live) {
    setText("state", m ? (h.sourceDown ? "camera down" : "stale") : "waiting", "badge stale");
    setText("distance", "–", "big stale");
    setText("distance-kind", m ? "no current distance" : "");
    $("distance").title = "No current distance: " + (h.reason || "waiting for the daemon");
    // The reason is on the connection line and over the picture; here, what is no longer current.
    const age = h.estimateAge === null ? "" : `, ${fmt(h.estimateAge, 0)} s ago`;
    setText("tilt", m && f.autopilot === "good"
      ? `last sent: ${fmt(f.autopilot_distance_m)} m${along ? " " + along.short : ""}${age}`
      : m ? `last estimate${age}` : "");
    return;
  }
  const handed = f.autopilot === "good" ? fmt(f.autopilot_distance_m) + " m"
    : f.autopilot === "too_close" ? "too close" : "–";
  // Sent is not received: with the link to the autopilot down (a router restarting, a wrong
  // port), the number must not read as what the autopilot has.
  const unheard = h.autopilot === "lost" ? "autopilot link lost: nothing reaches it"
    : h.autopilot === "waiting" ? "no autopilot heard: nothing reaches one" : "";
  // Outside the rangefinder's limits the autopilot reads no distance (OutOfRangeLow/High).
  const limits = page.status ? page.status.autopilot : {};
  const value = f.autopilot === "good" ? f.autopilot_distance_m : null;
  const outside = typeof value !== "number" ? ""
    : typeof limits.min_distance_m === "number" && value < limits.min_distance_m
      ? `below the rangefinder's ${fmt(limits.min_distance_m)} m minimum: the autopilot reads "too close"`
    : typeof limits.max_distance_m === "number" && value > limits.max_distance_m
      ? `beyond the rangefinder's ${fmt(limits.max_distance_m)} m maximum: the autopilot reads no distance` : "";
  // Nearer than the autopilot's minimum, or too close to measure: the state that matters most
  // near a net, shown loudest (red, never struck through, never "no net"); it read as a grey
  // LOST with "too close" struck through (pilot review).
  const close = f.autopilot === "too_close" || outside.startsWith("below");
  const sent = f.autopilot !== "none" && h.sending !== false && !unheard && !outside;
  // The badge says what reaches the autopilot before what the filter believes: a green
  // TRACKING beside a distance that reaches nothing read as "net hold is working".
  // Beyond the maximum the autopilot reads no distance (OutOfRangeHigh): not a green hold.
  const notSent = f.autopilot !== "none" && (h.sending === false || outside.startsWith("beyond"));
  const stateText = h.autopilot === "lost" ? "link lost" : unheard ? "no autopilot"
    : close ? "too close" : notSent ? "not sent" : f.state;
  const stateClass = h.autopilot === "lost" ? "bad" : unheard ? "notsent"
    : close ? "tooclose" : notSent ? "notsent" : f.state;
  setText("state", stateText, "badge " + stateClass);
  $("state").title = `What reaches the autopilot; the filter is ${f.state}`;
  setText("distance", handed, "big" + (close && !unheard ? " close" : sent ? "" : " unsent"));
  let kind;
  if (f.autopilot === "none") kind = "nothing sent to the autopilot";
  else if (unheard) kind = unheard;
  else if (outside) kind = outside;
  else if (h.sending === false) kind = `${along ? along.short + " – " : ""}not being sent to the autopilot`;
  else kind = f.autopilot === "too_close" ? "to the autopilot: below its minimum" : `to the autopilot, ${along ? along.short : ""}`;
  setText("distance-kind", kind);
  $("distance").title = f.autopilot === "too_close"
    ? "The net is nearer than the mesh can be resolved: the autopilot gets a reading below its minimum"
    : `What the autopilot gets (DISTANCE_SENSOR): the filtered distance ${along ? along.short : ""}${setting}`;
  const other = along && f.valid ? ` · ${along.other} ${fmt(f[along.otherKey])} m` : "";
  const raw = f.autopilot_along === "optical_axis" ? m.range_m : m.distance_m;
  setText("tilt", m.detected ? `raw ${fmt(raw)} m, tilt ${fmt(m.tilt_deg, 0)}°, conf ${fmt(m.confidence)}${other}`
    : m.net_seen ? `net seen, ~${fmt(m.approx_range_m)} ± ${fmt(m.approx_sigma_range_m)} m: no distance (${(m.reason || "").split(":")[0]})`
    : f.autopilot === "too_close" ? `back off: ${(m.reason || "").startsWith("net too close")
      ? m.reason : "net too close to measure"}`
    : `no net: ${m.reason || "–"}${other}`);
}

function drawPlots() {
  page.drawPending = false; page.drawnAt = performance.now();
  if ($("points")) $("points").textContent = `(${page.points.length} points)`;
  const newest = page.points.length ? ALONG[page.points[page.points.length - 1][6]] : null;
  if ($("plot-kind")) $("plot-kind").textContent = newest ? newest.short : "";
  plot($("plot-distance"), 1, 3, `distance to the autopilot${newest ? ", " + newest.short : ""}, m`, 5);
  if ($("plot-tilt")) plot($("plot-tilt"), 2, 4, "tilt, deg");
}

// The right end of the plots: now, on the points' clock (capture times). The newest point plus
// how long ago, by the daemon's clock, its estimate was made: while nothing comes the time axis
// runs on and the gap shows.
function plotEnd() {
  const pts = page.points, m = page.lastEstimate;
  if (!pts.length) return null;
  const last = pts[pts.length - 1][0];
  const clock = daemonNow();
  if (!m || clock === null) return last;
  const t = m.frame_time_mono !== null ? m.frame_time_mono : m.time_mono;
  return Math.max(last, t + Math.max(0, clock - m.time_mono));
}

function plot(canvas, rawIndex, filtIndex, label, seenIndex = null) {
  if (!canvas) return;
  // Drawn at the size it is shown (CSS pixels times the screen's density), so its labels stay
  // 11 px: a 600 px canvas shrunk into Cockpit's 384 px widget had 7 px labels.
  const rect = canvas.getBoundingClientRect(), dpr = window.devicePixelRatio || 1;
  if (rect.width >= 1 && rect.height >= 1) {
    const w = Math.round(rect.width * dpr), h = Math.round(rect.height * dpr);
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
  }
  const ctx = canvas.getContext("2d");
  const scale = rect.width >= 1 ? canvas.width / rect.width : 1;
  ctx.setTransform(scale, 0, 0, scale, 0, 0);
  const W = canvas.width / scale, H = canvas.height / scale, L = 44, B = 18, T = 6;
  ctx.clearRect(0, 0, W, H);
  const pts = page.points;
  if (!pts.length) return;
  const tEnd = plotEnd(), tStart = tEnd - page.spanS;
  let lo = Infinity, hi = -Infinity;
  for (const p of pts) {
    if (p[0] < tStart) continue;
    for (const i of [rawIndex, filtIndex, seenIndex]) if (i !== null && p[i] != null) { lo = Math.min(lo, p[i]); hi = Math.max(hi, p[i]); }
  }
  if (!isFinite(lo)) { lo = 0; hi = 1; }
  const pad = Math.max(0.05 * (hi - lo), rawIndex === 1 ? 0.05 : 1);
  lo -= pad; hi += pad;
  const x = (t) => L + ((t - tStart) / page.spanS) * (W - L - 4);
  const y = (v) => T + (1 - (v - lo) / (hi - lo)) * (H - T - B);
  ctx.strokeStyle = "#223"; ctx.fillStyle = "#8b9bab"; ctx.font = "11px sans-serif"; ctx.lineWidth = 1;
  for (let k = 0; k <= 4; k++) {
    const v = lo + ((hi - lo) * k) / 4;
    ctx.beginPath(); ctx.moveTo(L, y(v)); ctx.lineTo(W, y(v)); ctx.stroke();
    // Tenths where whole degrees would repeat ("11, 11, 10, 9, 9" over a 2 deg span).
    ctx.fillText(v.toFixed(rawIndex === 1 ? 2 : hi - lo < 8 ? 1 : 0), 2, y(v) + 4);
  }
  const step = page.spanS > 120 ? 60 : 10;
  for (let s = 0; s <= page.spanS; s += step) {
    const xx = x(tEnd - s);
    ctx.beginPath(); ctx.moveTo(xx, T); ctx.lineTo(xx, H - B); ctx.stroke();
    ctx.fillText(s === 0 ? "now" : `-${s}s`, xx - 12, H - 4);
  }
  ctx.fillText(label, L + 4, T + 10);
  ctx.fillStyle = "#8b9bab";
  for (const p of pts) if (p[0] >= tStart && p[rawIndex] !== null) ctx.fillRect(x(p[0]) - 1, y(p[rawIndex]) - 1, 2, 2);
  if (seenIndex !== null) {
    ctx.strokeStyle = "#e0a030"; ctx.lineWidth = 1;
    for (const p of pts) if (p[0] >= tStart && p[seenIndex] != null) ctx.strokeRect(x(p[0]) - 2, y(p[seenIndex]) - 2, 4, 4);
  }
  ctx.strokeStyle = "#2a9df4"; ctx.lineWidth = 2; ctx.beginPath();
  let open = false, lastT = null, lastAlong;
  for (const p of pts) {
    if (p[0] < tStart) continue;
    const v = p[filtIndex];
    // A gap where nothing was sent, where no estimate came for a second, and where the
    // distance sent changed kind (service.autopilot_distance reloaded).
    if (v === null || (lastT !== null && p[0] - lastT > 1.0) || p[6] !== lastAlong) open = false;
    if (v !== null) { if (open) ctx.lineTo(x(p[0]), y(v)); else ctx.moveTo(x(p[0]), y(v)); open = true; }
    lastT = p[0]; lastAlong = p[6];
  }
  ctx.stroke();
}

// -- health -----------------------------------------------------------------------------------
const LEVEL = {
  streaming: "ok", starting: "warn", reconnecting: "warn", ended: "bad", stopped: "off", failed: "bad",
  connected: "ok", waiting: "warn", lost: "bad", disabled: "off",
  online: "ok", connecting: "warn", idle: "warn", closed: "off",
  running: "ok", degraded: "warn", stopping: "off",
};

function onStatus(s) {
  const now = performance.now();
  if (page.statusAt !== null) page.statusGapS = (now - page.statusAt) / 1000;
  page.lastStatusAt = Date.now(); page.statusAt = now; page.status = s;
  noteClock(s.time_mono);
  refresh();
  const body = $("health") && $("health").tBodies[0];
  if (!body) return;
  const fs = s.frame_source, ap = s.autopilot, tm = s.telemetry, es = s.estimator, lat = s.latency_ms;
  const rows = [
    ["Service", s.state, `${s.version}, up ${fmt(s.uptime_s, 0)} s`, ""],
    ["Source", fs.state, `${fmt(fs.fps, 1)} frames/s, ${fs.dropped} skipped, ${fs.corrupt} damaged`, fs.error],
    ["Autopilot link", ap.state, `${ap.url} · ${ap.heartbeat_age_s === null || ap.heartbeat_age_s === undefined ? "no heartbeat yet" : `heartbeat ${fmt(ap.heartbeat_age_s, 1)} s ago`} · ${ap.sending_distance ? "sending distance" : "not sending"}${ap.net_plane && ap.net_plane !== "off" ? ` · net hold input: ${ap.net_plane}` : ""}`, ap.last_error],
    ["Telemetry", tm ? tm.state : "disabled", tm ? `${tm.key_root} · ${tm.links ?? 0} links` : "", tm ? tm.last_error : ""],
    ["Frame rate", es.fps ? "ok" : "warn", `${fmt(es.fps, 1)} frames/s measured${es.searching_hz ? ` (no net in view: searching at ${fmt(es.searching_hz, 0)} frames/s)` : ""}, net in ${fmt(100 * (es.detected_fraction ?? 0), 0)} %`, es.last_error],
    // Judged, not always green: a loop that had to lower its work per frame (budget level 2
    // and more) is short of CPU; a p99 past half the link's freshness limit eats the margin
    // before the autopilot's distance goes stale.
    ["CPU", (es.budget_level ?? 0) >= 2 ? "warn" : "ok", `${fmt(s.cpu.process_percent, 0)} % of a core · load ${fmt(s.cpu.load_1m)} · ${fmt(s.cpu.rss_mb, 0)} MB · work level ${es.budget_level ?? 0}`, ""],
    ["Inspection", s.inspection ? "ok" : "off", s.inspection ? `${s.inspection.inspected_frames} frames searched, ${s.inspection.judged_cells} cells judged, ${s.inspection.holes} holes (none reported is no proof of an intact net)` : "damage.enabled = false", ""],
    ["Latency", typeof lat.capture_to_link_p99 === "number" && typeof ap.freshness_s === "number" && lat.capture_to_link_p99 > 500 * ap.freshness_s ? "warn" : "ok", `capture → MAVLink link ${fmt(lat.capture_to_link_p50, 0)} ms median, ${fmt(lat.capture_to_link_p99, 0)} ms p99 · estimator ${fmt(es.latency_ms_mean, 0)} ms`, ""],
  ];
  body.replaceChildren(...rows.map(([name, state, text, error]) => {
    const tr = document.createElement("tr");
    const level = LEVEL[state] || state;
    tr.innerHTML = `<td><span class="dot ${level}"></span>${name}</td><td></td><td class="err"></td>`;
    tr.children[1].textContent = `${state === "ok" || state === "warn" ? "" : state + " · "}${text}`;
    tr.children[2].textContent = error || "";
    tr.dataset.row = name;
    return tr;
  }));
  $("digest").textContent = `configuration ${s.config_digest}`;
}

// Nothing arriving is news too: judge freshness, the frame rate and the plots' "now" on a timer.
setInterval(() => {
  refresh();
  if (!page.drawPending && (!page.drawnAt || performance.now() - page.drawnAt > 1000)) drawPlots();
}, 250);

// -- requests that change something --------------------------------------------------------
async function send(url, body) {
  // A page of another site cannot send this header without asking first (security.py).
  const headers = { "X-Netpose-Change": "1" };
  const token = $("token") ? $("token").value || sessionStorage.getItem("netpose-token") : null;
  if (token) { headers["X-Netpose-Token"] = token; sessionStorage.setItem("netpose-token", token); }
  if (body !== undefined && !(body instanceof FormData)) { headers["Content-Type"] = "application/json"; body = JSON.stringify(body); }
  const response = await fetch(url, { method: "POST", headers, body });
  let data = {};
  try { data = await response.json(); } catch (e) { data = { error: `HTTP ${response.status}` }; }
  if (!response.ok) throw new Error(data.error || `HTTP ${response.status}`);
  return data;
}

function say(el, text, ok) { el.textContent = text; el.className = "message " + (ok ? "ok" : "error"); }

// -- set-up ------------------------------------------------------------------------------------
async function loadSettings() {
  const response = await fetch("api/settings");
  let s = {};
  try { s = await response.json(); } catch (e) { s = {}; }
  // A refusal (the page reached by a name it does not trust: docs/blueos.md) says why.
  if (!response.ok) throw new Error(s.error || `HTTP ${response.status}`);
  page.settings = s;
  $("config-path").textContent = s.path ? `Configuration file: ${s.path}${s.editable ? "" : " — " + s.reason}`
                                        : s.reason;
  if (s.problem) $("config-path").textContent += ` — ${s.problem}`;
  $("token-row").hidden = !s.token_required;
  const saved = sessionStorage.getItem("netpose-token");
  if (saved && !$("token").value) $("token").value = saved;
  showRestart(s.restart_pending);
  $("settings").replaceChildren(...s.groups.map((group) => settingsGroup(group, s)));
}

function showRestart(sections) {
  $("restart-banner").hidden = !sections || !sections.length;
  $("restart-sections").textContent = (sections || []).join(", ");
}

function inputFor(field, value) {
  let input;
  if (field.type === "bool" || field.type === "choice") {
    input = document.createElement("select");
    const options = field.type === "bool" ? ["true", "false"] : field.choices.map(String);
    for (const o of options) input.add(new Option(o, o));
    input.value = String(value);
  } else {
    input = document.createElement("input");
    input.type = field.type === "number" || field.type === "integer" ? "number" : "text";
    if (input.type === "number") input.step = field.type === "integer" ? "1" : "any";
    input.value = value === null || value === undefined ? "" : Array.isArray(value) ? value.join(", ") : value;
    if (field.optional) input.placeholder = "default";
  }
  input.name = field.key; input.disabled = field.overridden || !page.settings.editable;
  return input;
}

function valueOf(field, input) {
  const text = input.value.trim();
  if (text === "" && field.optional) return null;
  switch (field.type) {
    case "bool": return text === "true";
    case "number": case "integer": return text === "" ? text : Number(text);
    case "list": return text === "" ? [] : text.split(",").map((x) => x.trim()).filter(Boolean);
    case "choice": { const c = field.choices.find((x) => String(x) === text); return c === undefined ? text : c; }
    default: return text;
  }
}

function settingsGroup(group, s) {
  const box = document.createElement("fieldset");
  box.innerHTML = `<legend></legend>`;
  box.firstChild.textContent = group.title;
  const inputs = [];
  for (const field of group.fields) {
    const row = document.createElement("label");
    row.className = "field";
    const name = document.createElement("span");
    name.textContent = field.key + (field.overridden ? " (set with --set)" : "");
    const input = inputFor(field, s.values[field.key]);
    row.append(name, input); box.append(row); inputs.push([field, input]);
  }
  const button = document.createElement("button");
  button.type = "button"; button.textContent = "Save"; button.disabled = !s.editable;
  const message = document.createElement("p"); message.className = "message";
  const last = page.groupMessages[group.title];
  if (last) say(message, last.text, last.ok);
  const report = (text, ok) => { page.groupMessages[group.title] = { text, ok }; say(message, text, ok); };
  button.onclick = async () => {
    const changes = {};
    for (const [field, input] of inputs) {
      const value = valueOf(field, input), before = s.values[field.key];
      if (JSON.stringify(value) !== JSON.stringify(before) && !input.disabled) changes[field.key] = value;
    }
    if (!Object.keys(changes).length) { report("nothing changed", true); return; }
    button.disabled = true; report("saving…", true);
    try {
      const r = await send("api/settings", { changes });
      report(r.message, true);
      showRestart(r.restart_needed);
      s.values = { ...s.values, ...changes };
    } catch (e) { report(e.message, false); }
    button.disabled = false;
  };
  box.append(button, message);
  return box;
}

// -- calibration ----------------------------------------------------------------------------------
async function uploadCalibration(event) {
  event.preventDefault();
  const file = $("calibration-file").files[0];
  if (!file) { say($("calibration-message"), "choose a calibration file first", false); return; }
  const form = new FormData(); form.append("file", file);
  $("calibration-result").hidden = true;
  try {
    const r = await send("api/calibration", form);
    page.calibrationId = r.id;
    say($("calibration-message"), `${r.file}: ${r.summary} — check the preview: straight lines stay straight`, true);
    $("calibration-preview").src = r.preview;
    $("calibration-result").hidden = false;
  } catch (e) { say($("calibration-message"), e.message, false); }
}

async function applyCalibration() {
  try {
    const r = await send(`api/calibration/${page.calibrationId}/apply`, {});
    say($("calibration-message"), r.message, true); showRestart(r.restart_needed);
  } catch (e) { say($("calibration-message"), e.message, false); }
}

// -- recording -------------------------------------------------------------------------------------
// -- net damage: holes confirmed in this run, newest first ---------------------------------
function onDamage(holes) {
  page.holes = holes;
  const body = $("holes") && $("holes").tBodies[0];
  if (!body) return;
  if ($("holes-count")) $("holes-count").textContent = holes.length ? `(${holes.length})` : "";
  body.replaceChildren();
  for (const h of holes) {
    const tr = body.insertRow();
    tr.className = "hole";
    const img = document.createElement("img");
    img.alt = `evidence of hole ${h.hole_id}`;
    if (h.crop_jpeg) img.src = "data:image/jpeg;base64," + h.crop_jpeg;
    tr.insertCell().append(img);
    const size = `${Math.max(1, Math.round(h.width_m * 100))} × ${Math.max(1, Math.round(h.height_m * 100))} cm`;
    const when = new Date(h.frame_time_unix * 1000).toLocaleTimeString();
    const cells = [`hole ${h.hole_id}`, size, `${h.cells} cells`, `${h.bearing} at ${fmt(h.range_m)} m`,
                   `conf ${fmt(h.confidence)}`, when];
    for (const text of cells) tr.insertCell().textContent = text;
  }
}

function onRecording(r) {
  page.recording = r;
  if (!$("record")) return;
  $("record").textContent = r.active ? "Stop recording" : "Start recording";
  $("record-status").textContent = r.active ? `${r.name}: ${r.frames} frames, ${(r.bytes / 1e6).toFixed(1)} MB${r.dropped ? `, ${r.dropped} dropped` : ""}`
                                            : r.name ? `last: ${r.name}, ${r.frames} frames` : "";
  if (r.error) say($("record-message"), r.error, false);
}

async function toggleRecording() {
  const active = page.recording && page.recording.active;
  try {
    onRecording(await send(active ? "api/recordings/stop" : "api/recordings/start", {}));
    say($("record-message"), active ? "stopped" : "recording…", true);
    if (active) loadRecordings();
  } catch (e) { say($("record-message"), e.message, false); }
}

async function loadRecordings() {
  const response = await fetch("api/recordings");
  if (!response.ok) { $("record").disabled = true; return; }
  const data = await response.json();
  onRecording(data.status);
  // Interrupted: the daemon ended without finishing it (power lost); what it holds replays.
  $("recordings").tBodies[0].replaceChildren(...data.recordings.filter((r) => r.finished || r.interrupted).map((r) => {
    const tr = document.createElement("tr");
    tr.innerHTML = "<td><a></a></td><td></td><td><button type='button'>Delete</button></td>";
    const a = tr.querySelector("a"); a.href = `api/recordings/${r.name}.tar`; a.textContent = r.name;
    a.setAttribute("download", `${r.name}.tar`);
    tr.children[1].textContent = `${r.frames} frames, ${((r.bytes || 0) / 1e6).toFixed(1)} MB` +
      (r.interrupted ? " (interrupted)" : "");
    // The card is BlueOS's too (its updates, other extensions): old recordings go from here.
    tr.querySelector("button").onclick = async () => {
      if (!window.confirm(`Delete ${r.name}? It cannot be undone.`)) return;
      try {
        const done = await send(`api/recordings/${r.name}/delete`, {});
        say($("record-message"), `deleted ${done.deleted} (${(done.bytes / 1e6).toFixed(1)} MB)`, true);
      } catch (e) { say($("record-message"), e.message, false); }
      loadRecordings();
    };
    return tr;
  }));
}

// -- start -------------------------------------------------------------------------------------------
if (view === "full") {
  $("span").onchange = () => { page.spanS = Number($("span").value); drawPlots(); };
  $("calibration-form").onsubmit = uploadCalibration;
  $("calibration-apply").onclick = applyCalibration;
  $("record").onclick = toggleRecording;
  $("restart").onclick = async () => {
    // A restart costs the autopilot its distance for seconds: asked, not one click away.
    if (!confirm("Restart netpose now? The autopilot gets no distance for a few seconds."))
      return;
    try { await send("api/restart", {}); setLink("down", "restarting…"); showRestart([]); }
    catch (e) { alert(e.message); }
  };
  loadSettings().catch((e) => { $("config-path").textContent = "cannot load settings: " + e.message; });
  loadRecordings().catch(() => {});
} else {
  page.spanS = 60;
}
connect();
