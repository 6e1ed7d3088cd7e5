// The officer's page: opens a replay session, shows its stream and wires the panels together.
// Each frame message is drawn everywhere (video, overlay, plan, panels) in one go, so all of
// them always show the same instant.

import { Alarms } from "./alarms.js";
import { api } from "./api.js";
import { BirdsEye } from "./birdseye.js";
import { Controls, fmtTime } from "./controls.js";
import { drawLegend, drawOverlay, drawVideo, fitCanvas, toImage } from "./overlay.js";
import { Limits, Panel } from "./panel.js";
import { Status } from "./status.js";
import { Stream } from "./stream.js";
import { Targets } from "./targets.js";
import { colors, currentTheme, initTheme, setTheme } from "./theme.js";
import { Viewer } from "./viewer.js";

const PREDICT_MAX_S = 10; // outlines the server computes; the slider shows 0..this many
const PREDICT_KEY = "berthing.predictSeconds";

const $ = (id) => document.getElementById(id);
const el = {
  wrap: $("video-wrap"), video: $("video"), overlay: $("overlay"), plan: $("birdseye"),
  hint: $("hint"), toast: $("toast"), theme: $("theme"), orient: $("orient"),
  berthSet: $("berth-set"), legendBands: $("legend-bands"), legendKind: $("legend-kind"),
  allPoints: $("all-points"), berthForm: $("berth-form"),
};

const app = {
  session: null, // SessionStatus of the session on screen
  owned: false, // created by this page (deleted when it closes) or joined with ?session=
  frame: null, // header of the frame on screen
  bitmap: null, // its picture (kept for redraws on resize / theme switch)
  view: null, // image → CSS pixel mapping of the video canvas
  trust: { trusted: false, reasons: [], advisories: [] },
  picking: false, // setting the berth line: collecting two clicks
  picks: [], // [{space: "image" | "plan", p: [u, v] | [n, e]}]
  statusSeq: 0, // stream status messages received: they are newer than any HTTP answer in flight
  local: null, // edits not yet in any frame (see withLocal)
  shown: null, // the frame as drawn (app.frame + local edits)
};

const status = new Status(document);
const panel = new Panel(document);
const limits = new Limits(document, {
  load: () => app.session && api.approachLimits(app.session.id).catch((err) => toast(err.message)),
  save: (body) => app.session && api.setApproachLimits(app.session.id, body)
    .catch((err) => toast(`Limits not set: ${err.message}`)),
});
const alarms = new Alarms(document, (alarmId) => api.acknowledgeAlarm(app.session?.id, alarmId));
const plan = new BirdsEye(el.plan);
const viewer = new Viewer(document);
const targets = new Targets($("targets"), removeTarget);
const controls = new Controls(document, {
  play: () => play(),
  pause: () => control({ action: "pause" }),
  seek: (t) => control({ action: "seek", time: t }),
  speed: (v) => control({ action: "speed", speed: v === "max" ? "max" : parseFloat(v) }),
  recording: (name) => openSession(name),
  predict: (n) => { localStorage.setItem(PREDICT_KEY, String(n)); render(); },
});
const stream = new Stream({
  onFrame: (header, bitmap) => {
    app.bitmap?.close?.();
    app.frame = header;
    app.bitmap = bitmap;
    reconcile(header);
    render();
  },
  onStatus: (s) => {
    app.statusSeq += 1;
    app.session = s;
    controls.updateSession(s);
    followSeek(s);
    if (s.state === "error" && s.error) toast(`Replay stopped: ${s.error}`);
  },
  onState: (state, detail) => { status.setConnection(state, detail); render(); }, // (un)grey
  onGone: (detail) => {
    if (!app.session?.live) {
      toast(`Session closed: ${detail}. Reload the page to start again.`);
      return;
    }
    // the ship's live session: a restarted server runs it anew, under another id
    toast(`Live session closed: ${detail}. Looking for the server's live session…`);
    findLive();
  },
});

// For the end-to-end tests and for debugging from the console: what is on screen right now.
window.berthing = {
  get frame() { return app.shown; },
  get view() { return app.view; },
  get trust() { return app.trust; },
  get session() { return app.session; },
  get colors() { return colors(); },
  get plan() { return plan.view; },
  get labels() { return app.labels || []; }, // the targets' labels drawn: box (CSS px) and text
  get toasts() { return [...toasts]; },
  get stats() { return { frames: stream.frames, dropped: stream.dropped, connection: stream.state }; },
  get alarms() {
    return { list: alarms.current, sounding: alarms.sounding, beeps: alarms.beeps, chimes: alarms.chimes };
  },
  dropConnection() { stream.ws?.close(); }, // as a network glitch would: the stream reconnects
  show(header) { app.frame = header; render(); }, // draw a given header over the current picture
};

// ----------------------------------------------------------------------------- rendering

function render() {
  const f = withLocal(app.frame);
  app.shown = f;
  if (f && app.bitmap) {
    app.view = fitCanvas(el.video, f.width, f.height);
    fitCanvas(el.overlay, f.width, f.height);
    drawVideo(el.video, app.bitmap, app.view);
  }
  app.trust = status.update(f);
  const opts = {
    predictSeconds: controls.predictSeconds,
    trusted: app.trust.trusted,
    allPoints: el.allPoints.checked,
  };
  if (f && app.view) {
    app.labels = drawOverlay(el.overlay, f, app.view, { ...opts, picks: picksIn("image") });
  }
  plan.draw(f, { ...opts, picks: picksIn("plan") });
  // No new data (the link lost, or no frame for a while): the picture and its overlay stay,
  // frozen and said so, but the figures are of then, not now: none shown (a user trial read
  // a heading 41° off and a berth distance of 55 s before, in the panel's large type).
  const lost = status.noNewData;
  const figures = lost && f ? { ...f, pose: null, overlay: f.overlay && { ...f.overlay, berth: null, targets: [] } } : f;
  const level = panel.update(figures, app.trust.trusted, lost);
  limits.update(figures?.overlay?.berth);
  document.querySelector(".side").classList.toggle("unreliable", !!f && !app.trust.trusted);
  el.wrap.classList.toggle("alarm", level === "alarm");
  el.wrap.classList.toggle("warning", level === "warning");
  targets.update(figures?.overlay?.targets);
  alarms.update(f?.alarms);
  if (f) { controls.setTime(f.t); controls.setReplay(f.replay); }
  legend(f);
  recordIndicator(f?.live);
}

// Live sessions: the record indicator (and which inputs are down) from every frame.
function recordIndicator(live) {
  const chip = $("st-rec");
  chip.hidden = !live;
  if (!live) return;
  chip.dataset.level = live.inputs_down.length ? "warn" : "bad";
  chip.querySelector(".k").textContent = live.recording ? "● REC" : "LIVE";
  const rec = live.recording ? fmtTime(live.record_s) : "not recorded";
  // what is down first: a narrow header cuts the end of the chip (a user trial could not
  // read which receiver had failed at 1400 px)
  const down = live.inputs_down.length ? `${live.inputs_down.join(", ")} down` : "";
  chip.querySelector(".v").textContent = down ? `${down} · ${rec}` : rec;
  chip.title = down ? `inputs down: ${live.inputs_down.join(", ")}; recording: ${rec}` : rec;
}

// Targets and berth lines set or removed by this page show at once, until the frames from the
// server carry them: without this a paused replay (no new frames) would not show the officer's
// click at all, and a frame built just before the change would make it flicker.
const LOCAL_MAX_MS = 3000;

function editLocal(change) {
  if (!app.local) app.local = { add: [], remove: new Set(), berth: undefined };
  app.local.since = performance.now();
  change(app.local);
  render();
}

/** Forget the local edits a frame already shows (called for each new frame). */
function reconcile(f) {
  const L = app.local;
  if (!L || !f?.overlay) return;
  if (performance.now() - L.since > LOCAL_MAX_MS) { app.local = null; return; }
  const ids = new Set((f.overlay.targets || []).map((t) => t.id));
  L.add = L.add.filter((t) => !ids.has(t.id));
  for (const id of [...L.remove]) if (!ids.has(id)) L.remove.delete(id);
  const line = f.overlay.birdseye?.berth_line;
  if (L.berth === null ? line == null : L.berth && sameLine(line, L.berth.line_ne)) L.berth = undefined;
  if (!L.add.length && !L.remove.size && L.berth === undefined) app.local = null;
}

function sameLine(a, b) {
  return !!a && !!b && a.every((p, i) => Math.hypot(p[0] - b[i][0], p[1] - b[i][1]) < 0.01);
}

function withLocal(f) {
  const L = app.local;
  if (!f?.overlay || !L) return f;
  const ov = { ...f.overlay, birdseye: { ...f.overlay.birdseye } };
  if (L.berth !== undefined) {
    ov.berth = L.berth;
    ov.birdseye.berth_line = L.berth ? L.berth.line_ne : null;
  }
  const keep = (t) => !L.remove.has(t.id);
  // a frame that already carries a target shows it once (a trial saw "T12" drawn twice)
  const shown = new Set((ov.targets || []).map((t) => t.id));
  const added = L.add.filter((t) => keep(t) && !shown.has(t.id));
  ov.targets = [...(ov.targets || []).filter(keep), ...added];
  ov.birdseye.targets = [...(ov.birdseye.targets || []).filter(keep),
    ...added.map((t) => ({ id: t.id, ne: t.position_ned.slice(0, 2) }))];
  return { ...f, overlay: ov };
}

let legendKey = null;
function legend(f) {
  const bands = f?.overlay?.distance_bands_m || [2, 5, 10, 20, 50, 100];
  const palette = colors().bands || [];
  const key = `${bands.join(",")}|${palette.join(",")}`;
  if (key !== legendKey) { legendKey = key; drawLegend(el.legendBands, bands, palette); }
  el.legendKind.textContent = el.allPoints.checked ? "all points (○ not an obstacle)"
    : "quay points near ship and berth";
}

function picksIn(space) {
  return app.picks.filter((k) => k.space === space).map((k) => k.p);
}

new ResizeObserver(() => render()).observe(el.wrap);
new ResizeObserver(() => render()).observe(el.plan);

// ------------------------------------------------------------------------------ session

async function openSession(name) {
  const old = app.session;
  stream.close();
  if (old && app.owned) api.deleteSession(old.id);
  app.frame = null;
  app.session = null;
  render();
  try {
    const s = await api.createSession({
      recording: name, speed: 1, prediction_seconds: PREDICT_MAX_S,
    });
    app.owned = true;
    watch(s);
    const url = new URL(location.href);
    url.searchParams.set("recording", name);
    url.searchParams.delete("session");
    history.replaceState(null, "", url);
  } catch (err) {
    toast(`Cannot open ${name}: ${err.message}`);
  }
}

// A live session gone (the server restarted): the page joins the server's live session as
// soon as there is one again, without a reload (a user trial's page stayed "closed").
let liveSearch = null;
function findLive() {
  if (liveSearch) return;
  liveSearch = setInterval(async () => {
    const live = (await api.sessions().catch(() => ({ sessions: [] }))).sessions.find((x) => x.live);
    if (!live) return;
    clearInterval(liveSearch);
    liveSearch = null;
    app.owned = false;
    watch(live);
    toast("Joined the server's live session again");
  }, 2000);
}

function watch(s) {
  app.session = s;
  controls.updateSession(s);
  controls.setPredictMax(s.prediction_seconds);
  stream.open(s.id);
  limits.refresh();
}

// While a seek runs no frame comes: the session's status is asked for a few times a second
// so that the badge shows how far the seek has got.
let seekPoll = null;
function followSeek(s) {
  if (s.state !== "seeking" || seekPoll) return;
  seekPoll = setInterval(async () => {
    if (!app.session || app.session.state !== "seeking") { clearInterval(seekPoll); seekPoll = null; return; }
    try {
      const now = await api.session(app.session.id);
      if (app.session.state === "seeking") { app.session = now; controls.updateSession(now); }
      if (now.state !== "seeking") { clearInterval(seekPoll); seekPoll = null; }
    } catch { /* the stream's status messages still come */ }
  }, 250);
}

async function control(body) {
  if (!app.session) return;
  const seq = app.statusSeq;
  try {
    const s = await api.control(app.session.id, body);
    if (app.statusSeq !== seq) return; // the stream already told us what happened next
    app.session = s;
    controls.updateSession(s);
    followSeek(s);
  } catch (err) {
    toast(err.message);
  }
}

async function play() {
  if (app.session?.state === "ended") await control({ action: "seek", time: 0 });
  await control({ action: "play" });
}

// ----------------------------------------------------- clicks: measure, berth line picks

el.overlay.addEventListener("click", async (ev) => {
  if (!app.frame || !app.view || !app.session) return;
  const r = el.overlay.getBoundingClientRect();
  const uv = toImage(app.view, ev.clientX - r.left, ev.clientY - r.top);
  if (!uv) return;
  if (app.picking) return pick("image", uv);
  try {
    // the pixel belongs to the frame on screen, which may be older than the newest one
    const t = await api.addTarget(app.session.id, { u: uv[0], v: uv[1], frame_time: app.frame.t });
    editLocal((L) => L.add.push(t));
  } catch (err) {
    toast(`No distance there: ${err.message}`);
  }
});

el.plan.addEventListener("click", (ev) => {
  if (!app.picking) return;
  const r = el.plan.getBoundingClientRect();
  const ne = plan.toPlan(ev.clientX - r.left, ev.clientY - r.top);
  if (ne) pick("plan", ne);
});

async function pick(space, p) {
  // both points must be in the same view (pixels or plan metres); a click in the other view
  // starts over from that click
  if (app.picks.length && app.picks[0].space !== space) app.picks = [];
  app.picks.push({ space, p, t: app.frame?.t });
  if (app.picks.length < 2) {
    hint("Now click the second point of the berth line (Esc cancels)");
    render();
    return;
  }
  const [a, b] = app.picks;
  // plan clicks snap to the quay face's points near them, as video clicks are fitted to them
  const body = space === "image"
    ? { image_points: [a.p, b.p], frame_time: a.t }
    : { ned: [a.p, b.p], snap: true };
  stopPicking();
  try {
    const st = await api.setBerthLine(app.session.id, body);
    // on the video: the clicked pixels themselves (a straight line on the water is straight
    // in the picture, up to the lens distortion) until the server draws it
    const polylines = space === "image" ? [[a.p, b.p]] : [];
    editLocal((L) => { L.berth = { ...st, polylines }; });
    if (st.method === "water-plane") toast(`Berth line on the water plane: ${st.note}`);
  } catch (err) {
    toast(`Berth line not set: ${err.message}`);
  }
}

function startPicking() {
  app.picking = true;
  app.picks = [];
  el.berthSet.classList.add("active");
  el.wrap.classList.add("picking");
  hint("Berth line: click two points on the quay (coping, wall or water line) — in the video or the plan");
}

function stopPicking() {
  app.picking = false;
  app.picks = [];
  el.berthSet.classList.remove("active");
  el.wrap.classList.remove("picking");
  hint(null);
  render();
}

el.berthSet.addEventListener("click", () => (app.picking ? stopPicking() : startPicking()));
$("berth-type").addEventListener("click", () => { el.berthForm.hidden = !el.berthForm.hidden; });
el.berthForm.addEventListener("submit", async (ev) => {
  ev.preventDefault();
  if (!app.session) return;
  const body = { from_bow: { distance_m: parseFloat($("bow-distance-in").value),
    bearing_deg: parseFloat($("bow-bearing-in").value) } };
  await setBerth(() => api.setBerthLine(app.session.id, body));
  el.berthForm.hidden = true;
});
for (const [id, body] of [["nudge-out", { offset_m: 0.1 }], ["nudge-in", { offset_m: -0.1 }],
  ["nudge-ccw", { rotate_deg: -0.5 }], ["nudge-cw", { rotate_deg: 0.5 }]]) {
  $(id).addEventListener("click", () => app.session
    && setBerth(() => api.nudgeBerthLine(app.session.id, body)));
}
el.allPoints.addEventListener("change", () => render());

/** A berth line the server answered for: shown at once (the plan has it; the video gets the
 *  server's projection with the next frame). */
async function setBerth(call) {
  try {
    const st = await call();
    editLocal((L) => { L.berth = { ...st, polylines: [] }; });
  } catch (err) {
    toast(`Berth line not set: ${err.message}`);
  }
}
$("berth-clear").addEventListener("click", async () => {
  stopPicking();
  if (!app.session) return;
  try {
    await api.clearBerthLine(app.session.id);
    editLocal((L) => { L.berth = null; });
  } catch (err) {
    toast(err.message);
  }
});

async function removeTarget(id) {
  if (!app.session) return;
  try {
    await api.deleteTarget(app.session.id, id);
    editLocal((L) => L.remove.add(id));
  } catch (err) {
    toast(err.message);
  }
}

// ------------------------------------------------------------------ views, theme, keys

for (const tab of document.querySelectorAll(".tabs button")) {
  tab.addEventListener("click", () => showView(tab.dataset.view));
}

function showView(name) {
  for (const tab of document.querySelectorAll(".tabs button")) {
    tab.setAttribute("aria-selected", String(tab.dataset.view === name));
  }
  $("view-ar").hidden = name !== "ar";
  $("view-3d").hidden = name !== "3d";
  if (name === "3d") viewer.open(app.session?.id);
  else render();
}

function applyTheme(name) {
  setTheme(name);
  el.theme.textContent = name === "night" ? "Day" : "Night";
  el.theme.title = `Switch to ${name === "night" ? "day" : "night"} colours (N)`;
  viewer.setTheme(name);
  render();
}
el.theme.addEventListener("click", () => applyTheme(currentTheme() === "night" ? "day" : "night"));

function applyOrientation(mode) {
  plan.setMode(mode);
  el.orient.textContent = mode === "head" ? "Head-up" : "North-up";
}
el.orient.addEventListener("click", () => applyOrientation(plan.mode === "head" ? "north" : "head"));
$("zoom-in").addEventListener("click", () => plan.zoom(-1));
$("zoom-out").addEventListener("click", () => plan.zoom(1));

document.addEventListener("keydown", (ev) => {
  if (ev.target.closest("input, select, textarea")) return;
  if (ev.key === " ") {
    ev.preventDefault();
    if (!app.session?.live) controls.playing ? control({ action: "pause" }) : play();
  }
  else if (ev.key === "n" || ev.key === "N") el.theme.click();
  else if (ev.key === "Escape" && app.picking) stopPicking();
});

// deleting our session frees the server's CPU for the next officer
window.addEventListener("pagehide", () => {
  if (app.session && app.owned) api.deleteSession(app.session.id);
});

function hint(text) {
  el.hint.hidden = !text;
  el.hint.textContent = text || "";
}

let toastTimer = null;
const toasts = []; // the last messages, for whoever debugs (window.berthing.toasts)
function toast(text) {
  toasts.push(text);
  if (toasts.length > 10) toasts.shift();
  el.toast.textContent = text;
  el.toast.hidden = false;
  clearTimeout(toastTimer);
  toastTimer = setTimeout(() => { el.toast.hidden = true; }, 5000);
}

// ------------------------------------------------------------------------------- start

async function start() {
  initTheme();
  applyTheme(currentTheme());
  applyOrientation(plan.mode);
  controls.predict.value = localStorage.getItem(PREDICT_KEY) || controls.predict.value;
  controls.setPredictMax(PREDICT_MAX_S);
  $("time").textContent = fmtTime(0);
  try {
    const params = new URLSearchParams(location.search);
    const { recordings, default: def } = await api.recordings();
    // ?session=ID watches a session opened elsewhere (a second screen on the bridge)
    let joined = params.get("session") && await api.session(params.get("session")).catch(() => null);
    // a server running a live session opens it (the ship's own), unless a recording is asked for
    if (!joined && !params.get("recording")) {
      joined = (await api.sessions().catch(() => ({ sessions: [] }))).sessions.find((s) => s.live);
    }
    const wanted = joined?.recording || params.get("recording");
    const name = recordings.some((r) => r.name === wanted) ? wanted : def || recordings[0]?.name;
    controls.setRecordings(recordings, name);
    if (joined) return watch(joined);
    if (!name) throw new Error("the server has no recording");
    await openSession(name);
  } catch (err) {
    toast(`Cannot start: ${err.message}`);
  }
}

start();
