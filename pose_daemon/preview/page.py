"""The preview page: one self-contained HTML document (inline style and script, no external
assets, no build step), so it works offline on a field laptop."""

PAGE_HTML = r"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>pose-daemon preview</title>
<style>
body { font: 14px/1.35 system-ui, sans-serif; margin: 0; background: #16181c; color: #e6e6e6; }
header { padding: 6px 12px; background: #23262c; display: flex; gap: 16px; align-items: center; }
header h1 { font-size: 16px; margin: 0; }
main { display: flex; flex-wrap: wrap; gap: 12px; padding: 12px; }
#view { flex: 0 1 auto; }
#live { display: block; max-width: 100%; background: #000; min-width: 320px; min-height: 240px; }
#side { flex: 1 1 320px; min-width: 300px; }
section { background: #202328; border-radius: 4px; padding: 8px 10px; margin-bottom: 10px; }
h2 { font-size: 13px; margin: 0 0 6px; color: #9fb3c8; text-transform: uppercase; letter-spacing: .04em; }
table { border-collapse: collapse; width: 100%; }
td, th { padding: 1px 6px 1px 0; text-align: left; font-variant-numeric: tabular-nums; }
th { color: #9aa0a6; font-weight: normal; }
.num { text-align: right; }
#warnings li { color: #ffa640; }
#warnings li.none { color: #7ccf7c; list-style: none; }
#warnings { margin: 0; padding-left: 18px; }
#statusline { font: 11px monospace; color: #9aa0a6; word-break: break-word; }
button, input { font: inherit; background: #2f343b; color: #e6e6e6; border: 1px solid #4a5058; border-radius: 3px; padding: 2px 8px; }
#plot { width: 100%; height: 220px; display: block; background: #111316; }
.ok { color: #7ccf7c; } .bad { color: #ff6b6b; }
</style>
</head>
<body>
<header><h1>pose-daemon</h1><span id="marker"></span><span id="conn" class="bad">connecting</span></header>
<main>
<div id="view">
  <img id="live" alt="live annotated camera image">
  <section style="margin-top:8px">
    <button id="snap">snapshot</button>
    record <input id="secs" type="number" value="10" min="1" max="600" style="width:4em"> s
    <button id="rec">record</button>
    <span id="action"></span>
  </section>
</div>
<div id="side">
  <section><h2>Why no pose?</h2><ul id="warnings"><li class="none">waiting for data</li></ul></section>
  <section><h2>Pose <span id="frame" data-frame=""></span></h2>
    <table>
      <tr><th>camera in marker frame</th><td class="num" id="pos-x"></td><td class="num" id="pos-y"></td><td class="num" id="pos-z"></td><td>m</td></tr>
      <tr><th>alpha beta gamma</th><td class="num" id="alpha"></td><td class="num" id="beta"></td><td class="num" id="gamma"></td><td>deg</td></tr>
      <tr><th>reprojection</th><td class="num" id="reproj"></td><th>ambiguity</th><td class="num" id="ambig"></td><td></td></tr>
      <tr><th>detector step</th><td id="step" colspan="4"></td></tr>
    </table>
  </section>
  <section><h2>Last 10 s</h2><canvas id="plot" width="600" height="220"></canvas></section>
  <section><h2>Pipeline</h2>
    <table>
      <tr><th>fps</th><td class="num" id="fps"></td><th>camera fps</th><td class="num" id="camfps"></td></tr>
      <tr><th>detected</th><td class="num" id="detected"></td><th>frames</th><td class="num" id="frames"></td></tr>
      <tr><th>drops</th><td id="drops" colspan="3"></td></tr>
      <tr><th>source</th><td id="source" colspan="3"></td></tr>
    </table>
    <table id="latency"><tr><th>latency ms</th><th class="num">p50</th><th class="num">p95</th><th class="num">max</th></tr></table>
    <table id="outputs"></table>
    <p id="preview"></p>
    <div id="statusline"></div>
  </section>
</div>
</main>
<script>
"use strict";
const $ = (id) => document.getElementById(id);
const fmt = (v, d) => (v === null || v === undefined || !isFinite(v)) ? "-" : Number(v).toFixed(d);
const signed = (v, d) => (v === null || v === undefined || !isFinite(v)) ? "-" : (v >= 0 ? "+" : "") + Number(v).toFixed(d);
function text(id, value) { $(id).textContent = value; }

function showStatus(data) {
  const s = data.status, last = data.last;
  window.lastStatus = data;
  $("conn").textContent = "live"; $("conn").className = "ok";
  const m = s.marker;
  text("marker", m.type === "aruco" ? `ArUco ${m.dictionary} id ${m.id}` : `square ${m.width} x ${m.height} m`);
  const ul = $("warnings"); ul.textContent = "";
  for (const w of s.warnings) { const li = document.createElement("li"); li.textContent = w.text; li.dataset.code = w.code; ul.appendChild(li); }
  if (!s.warnings.length) { const li = document.createElement("li"); li.className = "none"; li.textContent = "none: the marker is tracked"; ul.appendChild(li); }
  if (last) {
    text("frame", `frame ${last.frame}`); $("frame").dataset.frame = last.frame;
    const p = last.camera_position || [null, null, null];
    text("pos-x", signed(p[0], 3)); text("pos-y", signed(p[1], 3)); text("pos-z", signed(p[2], 3));
    text("alpha", signed(last.alpha_deg, 1)); text("beta", signed(last.beta_deg, 1)); text("gamma", signed(last.gamma_deg, 1));
    text("reproj", last.ok ? fmt(last.reprojection_error_px, 2) + " px" : (last.error || "no pose"));
    text("ambig", fmt(last.ambiguity_ratio, 2));
  }
  text("step", s.detector_step || "not found");
  text("fps", fmt(s.fps, 1)); text("camfps", fmt(s.camera_fps, 1));
  text("detected", s.detected_pct === null ? "-" : fmt(s.detected_pct, 0) + " %"); text("frames", s.frames);
  const drops = Object.entries(s.drops).filter(([k, v]) => v).map(([k, v]) => `${k} ${v}`);
  text("drops", drops.length ? drops.join(", ") : "none"); text("source", s.source);
  const lat = $("latency");
  while (lat.rows.length > 1) lat.deleteRow(1);
  for (const [stage, v] of Object.entries(s.latency_ms)) {
    const r = lat.insertRow(); r.insertCell().textContent = stage;
    for (const x of v) { const c = r.insertCell(); c.className = "num"; c.textContent = fmt(x, 1); }
  }
  const outs = $("outputs"); outs.textContent = "";
  for (const o of s.outputs) { const r = outs.insertRow(); r.insertCell().textContent = o.name; const c = r.insertCell(); c.textContent = o.state; c.className = o.link_up === false ? "bad" : ""; }
  const pv = s.preview;
  text("preview", `preview: ${pv.viewers} viewer(s), ${pv.frames_sent} frames sent, ${pv.frames_skipped} skipped (newest wins), ` +
    `${pv.viewers_dropped} stalled viewers dropped, encode ${fmt(pv.encode_ms, 1)} ms` +
    (s.recording ? `; recording ${s.recording.path}: ${s.recording.frames} frames${s.recording.done ? " (done)" : ""}` : ""));
  text("statusline", s.line);
}

const SERIES = [["x", "#ff6b6b", 0], ["y", "#7ccf7c", 0], ["z", "#6bb0ff", 0], ["alpha", "#ffa640", 1], ["beta", "#c77dff", 1], ["gamma", "#e6e6e6", 1]];
function plot(h) {
  const cv = $("plot"), ctx = cv.getContext("2d"), W = cv.width, H = cv.height, half = H / 2;
  ctx.clearRect(0, 0, W, H);
  ctx.font = "11px sans-serif";
  for (const panel of [0, 1]) {
    const keys = SERIES.filter((s) => s[2] === panel);
    let lo = Infinity, hi = -Infinity;
    for (const [k] of keys) for (const v of h[k]) if (v !== null) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
    const y0 = panel * half;
    ctx.fillStyle = "#9aa0a6";
    ctx.fillText(panel ? "attitude deg" : "position m", 4, y0 + 12);
    if (!isFinite(lo)) { ctx.fillText("no pose", W / 2 - 20, y0 + half / 2); continue; }
    if (hi - lo < (panel ? 2 : 0.02)) { const c = (hi + lo) / 2, r = panel ? 1 : 0.01; lo = c - r; hi = c + r; }
    ctx.fillText(hi.toFixed(panel ? 0 : 2), W - 40, y0 + 12); ctx.fillText(lo.toFixed(panel ? 0 : 2), W - 40, y0 + half - 4);
    const X = (t) => W * (1 + t / 10), Y = (v) => y0 + 4 + (half - 8) * (hi - v) / (hi - lo);
    keys.forEach(([k, colour], i) => {
      ctx.strokeStyle = colour; ctx.beginPath(); let pen = false;
      h.t.forEach((t, j) => { const v = h[k][j]; if (v === null) { pen = false; return; } if (pen) ctx.lineTo(X(t), Y(v)); else ctx.moveTo(X(t), Y(v)); pen = true; });
      ctx.stroke(); ctx.fillStyle = colour; ctx.fillText(k, 90 + 40 * i, y0 + 12);
    });
  }
}

async function poll(url, show, every) {
  for (;;) {
    try { const r = await fetch(url, {cache: "no-store"}); show(await r.json()); }
    catch (e) { $("conn").textContent = "daemon not answering"; $("conn").className = "bad"; }
    await new Promise((ok) => setTimeout(ok, every));
  }
}

async function act(url) {
  try {
    const r = await fetch(url, {method: "POST", headers: {"X-Pose-Daemon": "1"}});
    const j = await r.json();
    text("action", j.error ? "error: " + j.error : (j.saved ? "saved " + j.saved : "recording into " + j.recording));
  } catch (e) { text("action", "error: " + e); }
}
$("snap").onclick = () => act("/snapshot");
$("rec").onclick = () => act("/record?seconds=" + encodeURIComponent($("secs").value));

// A daemon restart ends the stream: ask again (the status poll says when it is back).
$("live").onerror = () => setTimeout(() => { $("live").src = "/stream.mjpg?t=" + Date.now(); }, 2000);
window.addEventListener("load", () => {
  $("live").src = "/stream.mjpg";
  poll("/status.json", showStatus, 500);
  poll("/history.json", plot, 1000);
});
</script>
</body>
</html>
"""
