"""The dashboard's one HTML page (with its script and style); the server fills in the refresh period.

Plain DOM and fetch, no framework and nothing loaded from elsewhere, so the page
works on a host with no internet. Every number has an element id the browser
test reads (``q-queued``, ``q-done``, ``episodes``, ...).
"""

PAGE = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>activecollect</title>
<link rel="icon" href="data:,">
<style>
 body { font: 14px/1.4 system-ui, sans-serif; margin: 1.5em; color: #222; background: #fafafa; }
 h1 { font-size: 1.3em; margin: 0 0 .5em; } h2 { font-size: 1.05em; margin: 1.2em 0 .4em; }
 .cards { display: flex; gap: .8em; flex-wrap: wrap; }
 .card { background: #fff; border: 1px solid #ddd; border-radius: 6px; padding: .5em .9em; min-width: 7em; }
 .card b { display: block; font-size: 1.5em; }
 table { border-collapse: collapse; background: #fff; font-size: 12.5px; }
 th, td { border: 1px solid #ddd; padding: 2px 6px; text-align: left; vertical-align: top; }
 .champion { background: #e8f5e9; font-weight: bold; }
 .muted { color: #888; } svg { background: #fff; border: 1px solid #ddd; }
</style>
</head>
<body>
<h1>activecollect <span id="updated" class="muted"></span></h1>
<div class="cards">
 <div class="card">episodes<b id="episodes">-</b><span id="budget" class="muted"></span></div>
 <div class="card">queued<b id="q-queued">-</b></div>
 <div class="card">leased<b id="q-leased">-</b></div>
 <div class="card">done<b id="q-done">-</b></div>
 <div class="card">dead<b id="q-dead">-</b></div>
 <div class="card">cancelled<b id="q-cancelled">-</b></div>
 <div class="card">workers alive<b id="workers-alive">-</b><span id="workers-note" class="muted"></span></div>
 <div class="card">champion<b id="champion">-</b><span id="champion-error" class="muted"></span></div>
 <div class="card">last retrain<b id="last-retrain">-</b><span id="last-retrain-reason" class="muted"></span></div>
 <div class="card">disk free<b id="disk-free">-</b><span id="disk-size" class="muted"></span></div>
</div>
<h2>Learning curve (eval h1 MSE per training episodes: champions joined, the current one green, rolled back
orange, other candidates grey)</h2>
<svg id="curve" width="560" height="220" viewBox="0 0 560 220"></svg>
<h2>Models</h2>
<table id="models"><thead><tr><th>version</th><th>status</th><th>h1 MSE</th><th>h5 MSE</th>
<th>created</th><th>reason</th></tr></thead><tbody></tbody></table>
<h2>Queue (latest requests)</h2>
<table id="queue"><thead><tr><th>id</th><th>status</th><th>priority</th><th>shape</th><th>policy</th>
<th>planner</th><th>score</th><th>source episode / step</th><th>model</th><th>attempts</th><th>error</th>
</tr></thead><tbody></tbody></table>
<h2>Workers</h2>
<table id="workers"><thead><tr><th>id</th><th>details</th></tr></thead><tbody></tbody></table>
<h2>Predicted vs real (champion, eval episodes)</h2>
<img id="frames" alt="predicted vs real frames of the champion" src="/frames.png">
<script>
"use strict";
const REFRESH_MS = __REFRESH_MS__;
function text(id, value) { const el = document.getElementById(id); if (el) el.textContent = value; }
function fmt(x) { return (x === null || x === undefined || Number.isNaN(x)) ? "-" :
  (typeof x === "number" ? (Math.abs(x) < 0.01 && x !== 0 ? x.toExponential(2) : x.toFixed(4)) : String(x)); }
function size(b) { const [n, u] = b >= 999.95e6 ? [b / 1e9, "GB"] : b >= 999.95e3 ? [b / 1e6, "MB"] : [b / 1e3, "kB"];
  return n.toFixed(1) + " " + u; }
function cell(tr, value, cls) { const td = document.createElement("td"); td.textContent = value;
  if (cls) td.className = cls; tr.appendChild(td); }
function fill(tableId, rows, build) { const body = document.querySelector("#" + tableId + " tbody");
  body.replaceChildren(); for (const r of rows) { const tr = document.createElement("tr");
    try { build(tr, r); } catch (err) { tr.replaceChildren(); cell(tr, "unreadable row: " + err.message); }
    body.appendChild(tr); } }
// a refresh waits for the last one, and a request for at most FETCH_TIMEOUT_MS: a slow directory no longer piles
// up requests that fill the server's connection slots; a hidden tab does not refresh
const FETCH_TIMEOUT_MS = Math.max(10000, 5 * REFRESH_MS);
function timeoutSignal(ms) {  // (AbortSignal.timeout: not in browsers before 2022, e.g. Safari 15: a timer aborts)
  if (typeof AbortSignal.timeout === "function") return AbortSignal.timeout(ms);
  const c = new AbortController(); setTimeout(() => c.abort(), ms); return c.signal; }
async function getJSON(path) {
  const r = await fetch(path, {cache: "no-store", signal: timeoutSignal(FETCH_TIMEOUT_MS)});
  // the server's one line says why (no catalog, a locked or damaged database), not only the status
  if (!r.ok) throw new Error(path + " answered " + r.status + ": " + (await r.text()).trim().slice(0, 300));
  return r.json(); }
let lastChampion = null;
function drawCurve(points) {
  const svg = document.getElementById("curve"); svg.replaceChildren();
  const ns = "http://www.w3.org/2000/svg"; const W = 560, H = 220, L = 60, B = 30;
  const pts = points.filter(p => typeof p.h1_mse === "number" && Number.isFinite(p.h1_mse));
  if (pts.length === 0) { const t = document.createElementNS(ns, "text"); t.setAttribute("x", 20);
    t.setAttribute("y", 100); t.textContent = "no trained model yet"; svg.appendChild(t); return; }
  const xs = pts.map(p => p.episodes), ys = pts.map(p => p.h1_mse);
  const x0 = Math.min(...xs), x1 = Math.max(...xs) || 1, y0 = 0, y1 = Math.max(...ys) * 1.1 || 1;
  const sx = x => L + (W - L - 10) * (x1 === x0 ? 0.5 : (x - x0) / (x1 - x0));
  const sy = y => H - B - (H - B - 10) * (y - y0) / (y1 - y0);
  // the line joins the champions only (as the report's curve): a rejected candidate is a dot, not the curve
  const line = document.createElementNS(ns, "polyline");
  line.setAttribute("points", pts.filter(p => p.promoted).map(p => sx(p.episodes) + "," + sy(p.h1_mse)).join(" "));
  line.setAttribute("fill", "none"); line.setAttribute("stroke", "#1565c0"); line.setAttribute("stroke-width", 2);
  svg.appendChild(line);
  for (const p of pts) { const c = document.createElementNS(ns, "circle"); c.setAttribute("cx", sx(p.episodes));
    c.setAttribute("cy", sy(p.h1_mse)); c.setAttribute("r", 4);
    c.setAttribute("fill", p.status === "champion" ? "#2e7d32" : (p.promoted ? "#1565c0" :
      (p.rolled_back ? "#ef6c00" : "#bbb")));
    svg.appendChild(c); }
  const labels = [[L, H - 8, x0 + " ep"], [W - 60, H - 8, x1 + " ep"], [4, sy(y1 / 1.1) + 4, fmt(y1 / 1.1)],
                  [4, H - B, "0"]];
  for (const [x, y, s] of labels) { const t = document.createElementNS(ns, "text"); t.setAttribute("x", x);
    t.setAttribute("y", y); t.setAttribute("font-size", 11); t.textContent = s; svg.appendChild(t); }
}
async function refresh() {
  try {
    // every read answered (or timed out) before the refresh ends, a failed one too: Promise.all ended it at the
    // first failure (a fast 503) and the next refresh came while the others were still being served
    const results = await Promise.allSettled(
      ["/api/stats", "/api/queue", "/api/models", "/api/workers", "/api/curve"].map(getJSON));
    const failed = results.find((r) => r.status === "rejected");
    if (failed) throw failed.reason;
    const [stats, queue, models, workers, curve] = results.map((r) => r.value);
    text("episodes", stats.episodes.train);
    const space = typeof stats.quarantine_bytes === "number" && stats.quarantine_bytes > 0
      ? " (" + size(stats.quarantine_bytes) + ")" : "";
    const held = stats.episodes.quarantined ? stats.episodes.quarantined + " quarantined" + space : "";
    text("budget", [stats.budget ? "of " + stats.budget : "", held].filter(Boolean).join(" \u00b7 "));
    for (const s of ["queued", "leased", "done", "dead", "cancelled"]) text("q-" + s, queue.counts[s] || 0);
    // null: a dashboard over a data directory, without the service, knows no workers (not "0 alive")
    text("workers-alive", stats.workers_alive ?? "-");
    text("workers-note", stats.workers_alive === null ? "unknown here: see `activecollect workers ls`" : "");
    text("champion", models.champion || "none");
    text("champion-error", stats.champion_problem ? "weights damaged: cannot be served"
      : stats.champion_h1_mse === null ? "" : "h1 MSE " + fmt(stats.champion_h1_mse));
    const disk = stats.disk, gib = (b) => (b / 2 ** 30).toFixed(1) + " GiB";
    text("disk-free", disk ? gib(disk.free_bytes) : "-");
    text("disk-size", disk ? "of " + gib(disk.size_bytes) : "");
    const last = stats.last_retrain;
    text("last-retrain", last ? last.status + (last.from ? " (newest model)" : "") : "none");
    text("last-retrain-reason", last ? (last.version || "") + " " + (last.reason || "") : "");
    fill("queue", queue.requests, (tr, q) => { const r = q.reason || {};
      for (const v of [q.id, q.status, fmt(q.priority), q.shape, q.policy, r.planner || "", fmt(r.score),
        String(r.source_episode ?? "").slice(0, 8) + (r.step === null || r.step === undefined ? "" : " @" + r.step),
        r.model_version || "", q.attempts, q.last_error || ""]) cell(tr, v); });
    fill("models", models.models, (tr, m) => { const cls = m.version === models.champion ? "champion" : "";
      for (const v of [m.version, m.status + (m.pruned_at ? " (pruned)" : ""), fmt(m.metrics.h1_mse),
                       fmt(m.metrics.h5_mse), m.created, m.reason])
        cell(tr, v, cls); });
    fill("workers", workers.workers, (tr, w) => { cell(tr, w.id); cell(tr, JSON.stringify(w.info || {})); });
    drawCurve(curve.points);
    if (models.champion !== lastChampion) { lastChampion = models.champion;
      document.getElementById("frames").src = "/frames.png?v=" + encodeURIComponent(models.champion || ""); }
    text("updated", "updated " + new Date().toLocaleTimeString());
  } catch (err) {
    text("updated", "refresh failed: " + err.message);
  }
}
let next = null;
async function loop() { clearTimeout(next); next = null;
  if (!document.hidden) await refresh();
  next = setTimeout(loop, REFRESH_MS); }
document.addEventListener("visibilitychange", () => { if (!document.hidden && next !== null) loop(); });
loop();
</script>
</body>
</html>
"""


def render_page(refresh_s: float) -> bytes:
    """The page with its refresh period filled in."""
    return PAGE.replace("__REFRESH_MS__", str(int(refresh_s * 1000))).encode()
