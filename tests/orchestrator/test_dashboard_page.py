"""The dashboard page's own script, run by Node against a stub page: a refresh waits for the last one, every request
has a timeout, and a hidden tab does not refresh (about six tabs on a slow data directory filled the server's 32
connection slots with refreshes that piled up every 2 s)."""

from __future__ import annotations

import json
import shutil
import subprocess

import pytest

from orchestrator.dashboard_page import render_page

NODE = shutil.which("node")

HARNESS = r"""
const script = require("fs").readFileSync(0, "utf8");
const fetches = [], pending = [];
let timers = [];  // [fn, repeats]
globalThis.fetch = (path, opts) => { fetches.push({path, signal: !!(opts && opts.signal instanceof AbortSignal)});
  return new Promise((resolve) => pending.push({path, resolve})); };
globalThis.setTimeout = (fn) => { timers.push([fn, false]); return timers.length; };
globalThis.setInterval = (fn) => { timers.push([fn, true]); return timers.length; };
globalThis.clearTimeout = () => {};
const el = () => ({textContent: "", src: "", replaceChildren() {}, appendChild() {}, setAttribute() {}});
globalThis.document = {hidden: false, getElementById: el, querySelector: el, createElement: el,
  createElementNS: el, addEventListener() {}};
const settle = () => new Promise((r) => setImmediate(r));
function tick() { const now = timers; timers = now.filter(([, repeats]) => repeats); for (const [fn] of now) fn(); }
const BODIES = {"/api/stats": {episodes: {train: 1}, workers_alive: 0, champion_h1_mse: null},
  "/api/queue": {counts: {}, requests: []}, "/api/models": {champion: null, models: []},
  "/api/workers": {workers: []}, "/api/curve": {points: []}};
(async () => {
  const seen = {};
  new Function(script)();
  await settle(); seen.first = fetches.length;
  for (let i = 0; i < 3; i++) { tick(); await settle(); }
  seen.while_slow = fetches.length;
  for (const p of pending.splice(0)) p.resolve({ok: true, json: async () => BODIES[p.path]});
  for (let i = 0; i < 5; i++) await settle();
  tick(); await settle(); seen.after_answers = fetches.length;
  for (const p of pending.splice(0)) p.resolve({ok: true, json: async () => BODIES[p.path]});
  for (let i = 0; i < 5; i++) await settle();
  document.hidden = true; tick(); await settle(); seen.hidden = fetches.length; seen.timers_hidden = timers.length;
  seen.signals = fetches.every((f) => f.signal);
  console.log(JSON.stringify(seen));
})();
"""


@pytest.mark.skipif(NODE is None, reason="needs Node.js to run the page's script")
def test_a_refresh_waits_for_the_last_one_and_each_request_times_out():
    page = render_page(2.0).decode()
    script = page[page.index("<script>") + len("<script>"):page.index("</script>")]
    out = subprocess.run([NODE, "-e", HARNESS], input=script, capture_output=True, text=True, timeout=60, check=True)
    seen = json.loads(out.stdout)
    assert seen["first"] == 5  # the five API reads of one refresh
    assert seen["while_slow"] == 5  # unanswered: no refresh on top of them (setInterval added 5 every period)
    assert seen["after_answers"] == 10  # answered: the next refresh comes a period later
    assert seen["hidden"] == 10 and seen["timers_hidden"] == 1  # hidden: no requests, the loop goes on
    assert seen["signals"]  # each request is aborted after FETCH_TIMEOUT_MS


FAST_FAILURE = r"""
const script = require("fs").readFileSync(0, "utf8");
let sent = 0, unanswered = 0, peak = 0, timers = [];
globalThis.fetch = (path) => { sent++;
  if (path === "/api/stats") return Promise.resolve({ok: false, status: 503, text: async () => "busy"});
  unanswered++; peak = Math.max(peak, unanswered); return new Promise(() => {}); };
globalThis.setTimeout = (fn) => { timers.push(fn); return timers.length; };
globalThis.clearTimeout = () => {};
const el = () => ({textContent: "", src: "", replaceChildren() {}, appendChild() {}, setAttribute() {}});
globalThis.document = {hidden: false, getElementById: el, querySelector: el, createElement: el,
  createElementNS: el, addEventListener() {}};
const settle = () => new Promise((r) => setImmediate(r));
(async () => {
  new Function(script)();
  for (let period = 0; period < 5; period++) { for (let i = 0; i < 5; i++) await settle();
    const now = timers; timers = []; for (const fn of now) fn(); }
  console.log(JSON.stringify({sent, peak}));
})();
"""


@pytest.mark.skipif(NODE is None, reason="needs Node.js to run the page's script")
def test_a_read_that_fails_fast_does_not_start_the_next_refresh_while_the_others_are_unanswered():
    """A server at its connection cap answers one read 503 at once while the refresh's other reads are still
    served: the next refresh waits for them too (with Promise.all it came a period later, 4 more each period)."""
    page = render_page(2.0).decode()
    script = page[page.index("<script>") + len("<script>"):page.index("</script>")]
    out = subprocess.run([NODE, "-e", FAST_FAILURE], input=script, capture_output=True, text=True, timeout=60,
                         check=True)
    assert json.loads(out.stdout) == {"sent": 5, "peak": 4}


@pytest.mark.skipif(NODE is None, reason="needs Node.js to run the page's script")
def test_a_browser_without_abort_signal_timeout_still_refreshes():
    """AbortSignal.timeout came in 2022 (Safari 16, Chrome 103, Firefox 100): without it every refresh failed
    ("AbortSignal.timeout is not a function") and the page showed nothing."""
    page = render_page(2.0).decode()
    script = page[page.index("<script>") + len("<script>"):page.index("</script>")]
    out = subprocess.run([NODE, "-e", "delete AbortSignal.timeout;" + FAST_FAILURE], input=script,
                         capture_output=True, text=True, timeout=60, check=True)
    assert json.loads(out.stdout)["sent"] == 5


SHOWN_AGAIN = r"""
const script = require("fs").readFileSync(0, "utf8");
const pending = [], listeners = {};
let sent = 0, timers = [];
globalThis.fetch = (path) => { sent++; return new Promise((resolve) => pending.push({path, resolve})); };
globalThis.setTimeout = (fn) => { timers.push(fn); return timers.length; };
globalThis.clearTimeout = () => {};
const el = () => ({textContent: "", src: "", replaceChildren() {}, appendChild() {}, setAttribute() {}});
globalThis.document = {hidden: false, getElementById: el, querySelector: el, createElement: el,
  createElementNS: el, addEventListener(type, fn) { listeners[type] = fn; }};
const settle = async () => { for (let i = 0; i < 5; i++) await new Promise((r) => setImmediate(r)); };
const answer = () => { for (const p of pending.splice(0)) p.resolve({ok: true, json: async () => ({})}); };
const change = (hidden) => { document.hidden = hidden; if (listeners.visibilitychange) listeners.visibilitychange(); };
(async () => {
  const seen = {};
  new Function(script)(); await settle(); answer(); await settle();
  change(true); await settle(); seen.hidden = sent;
  const now = timers; timers = []; for (const fn of now) fn(); await settle(); seen.hidden_period = sent;
  change(false); await settle(); seen.shown = sent;
  change(true); change(false); await settle(); seen.shown_twice_while_refreshing = sent;
  console.log(JSON.stringify(seen));
})();
"""


@pytest.mark.skipif(NODE is None, reason="needs Node.js to run the page's script")
def test_a_tab_shown_again_refreshes_at_once_and_once():
    """Shown again after a hidden period, the page refreshes then, not a period later; shown again while that
    refresh is still unanswered, it starts no second one."""
    page = render_page(2.0).decode()
    script = page[page.index("<script>") + len("<script>"):page.index("</script>")]
    out = subprocess.run([NODE, "-e", SHOWN_AGAIN], input=script, capture_output=True, text=True, timeout=60,
                         check=True)
    assert json.loads(out.stdout) == {"hidden": 5, "hidden_period": 5, "shown": 10, "shown_twice_while_refreshing": 10}


NO_TIMEOUT_HANGS = r"""
delete AbortSignal.timeout;
const script = require("fs").readFileSync(0, "utf8");
let sent = 0, timers = [];
globalThis.fetch = (path, opts) => { sent++; const signal = opts && opts.signal;  // never answered: only an abort
  return new Promise((resolve, reject) => { if (signal) signal.addEventListener("abort", () => reject(new Error(
    "aborted"))); }); };
globalThis.setTimeout = (fn, ms) => { timers.push(fn); return timers.length; };
globalThis.clearTimeout = () => {};
const el = () => ({textContent: "", src: "", replaceChildren() {}, appendChild() {}, setAttribute() {}});
globalThis.document = {hidden: false, getElementById: el, querySelector: el, createElement: el,
  createElementNS: el, addEventListener() {}};
const settle = async () => { for (let i = 0; i < 5; i++) await new Promise((r) => setImmediate(r)); };
(async () => {
  new Function(script)(); await settle();
  for (let period = 0; period < 2; period++) { const now = timers; timers = []; for (const fn of now) fn();
    await settle(); }
  console.log(JSON.stringify({sent}));
})();
"""


@pytest.mark.skipif(NODE is None, reason="needs Node.js to run the page's script")
def test_without_abort_signal_timeout_a_read_never_answered_still_gives_up():
    """A browser from before AbortSignal.timeout (Safari 15) had no timeout on a read: one the server never answered
    held its refresh, and the page never refreshed again (each read waits for all: a refresh ends with its last)."""
    page = render_page(2.0).decode()
    script = page[page.index("<script>") + len("<script>"):page.index("</script>")]
    out = subprocess.run([NODE, "-e", NO_TIMEOUT_HANGS], input=script, capture_output=True, text=True, timeout=60,
                         check=True)
    assert json.loads(out.stdout) == {"sent": 10}  # the reads given up on, then the next period's refresh
