// pregrasp live dashboard. Reads the service's JSON routes (/api/v1/scene, /api/v1/tracks,
// /api/v1/objects/{id}/mesh, /api/v1/cameras/{id}/latest[...]) and follows the event stream
// /api/v1/events (track, decision, frame, stats). No build step, nothing fetched from outside.
//
// Test hooks on <body>: data-connection (connecting | live | reconnecting), data-updates
// (events handled), data-tracks, data-decision (verdict of the selected track),
// data-particles-drawn (particles in the last 3D frame), data-plot-points (points in the
// fullest plot), data-event-rate-hz (events/s seen over the last 10 s), data-connects (event
// stream connections opened), data-track-updates (`track` events handled).

import { composePose, cross, invertPose, normalize, parsePose, transformPoint, unprojectPixel } from "./math.js";
import { SceneGeometry, View3D } from "./view3d.js";
import { TimePlot } from "./plots.js";
import { CameraPanel } from "./cameras.js";

// Okabe-Ito palette (colour-blind safe), black replaced by grey on the dark background.
const OKABE = {
  orange: "#E69F00",
  sky: "#56B4E9",
  green: "#009E73",
  yellow: "#F0E442",
  blue: "#0072B2",
  vermillion: "#D55E00",
  purple: "#CC79A7",
  grey: "#BBBBBB",
};
const CAMERA_COLORS = [OKABE.orange, OKABE.sky, OKABE.green, OKABE.purple, OKABE.yellow, OKABE.vermillion, OKABE.blue];
const OBJECT_COLORS = [OKABE.vermillion, OKABE.sky, OKABE.yellow, OKABE.purple, OKABE.green, OKABE.orange];
const AXIS_COLORS = [OKABE.vermillion, OKABE.green, OKABE.sky]; // x, y, z
const EVENT_RATE_WINDOW_MS = 10_000;
const SCENE_REFRESH_MS = 500;
const TRACKS_RESYNC_MS = 5_000;
const MIN_RENDER_INTERVAL_MS = 100;
const MIN_LIST_INTERVAL_MS = 250;
const FRUSTUM_DEPTH_M = 0.12;
const TABLE_HALF_SIZE_M = 0.8;
const TABLE_CELL_M = 0.1;
const GRIPPER_FINGER_M = 0.05;
const DRIVER_MIN_CORRELATION = 0.2;
const GRIPPER_MARGIN_M = 0.01;

const state = {
  scene: null,
  tracks: new Map(), // id -> TrackView
  meshes: new Map(), // object_id -> { edges: [[a, b]], vertices } | "loading" | "failed"
  cameraColorIndex: new Map(),
  objectColorIndex: new Map(),
  selected: null,
  t0Ns: null,
  updates: 0,
  eventTimes: [],
  stats: null,
  panels: new Map(), // camera id -> CameraPanel
  connects: 0,
  trackUpdates: 0,
  historyLoaded: new Set(),
  userSelected: false,
};

const colors = {
  cameraCss(id) {
    if (!state.cameraColorIndex.has(id)) state.cameraColorIndex.set(id, state.cameraColorIndex.size);
    return CAMERA_COLORS[state.cameraColorIndex.get(id) % CAMERA_COLORS.length];
  },
  /** Display name of an object id (from the tracks), for detection labels. */
  objectLabel(objectId) {
    for (const t of state.tracks.values()) if (String(t.object_id) === String(objectId)) return t.object_name ?? objectId;
    return objectId;
  },
  objectCss(name) {
    if (!state.objectColorIndex.has(name)) state.objectColorIndex.set(name, state.objectColorIndex.size);
    return OBJECT_COLORS[state.objectColorIndex.get(name) % OBJECT_COLORS.length];
  },
};

function rgba(css, alpha = 1) {
  const n = parseInt(css.slice(1), 16);
  return [((n >> 16) & 255) / 255, ((n >> 8) & 255) / 255, (n & 255) / 255, alpha];
}

// ---- DOM --------------------------------------------------------------------------------

const el = (id) => document.getElementById(id);
let view = null;
try {
  view = new View3D(el("view3d"), el("view3d-labels"));
  view.onFit = () => fitView(true);
  document.body.dataset.renderer = view.renderer;
} catch (e) {
  el("view-error").hidden = false;
  el("view-error").textContent = `3D view unavailable: ${e.message}`;
}

const plots = {
  std: new TimePlot(el("plot-std"), { title: "Translation std", yLabel: "std [m]", logY: true }),
  rotation: new TimePlot(el("plot-rotation"), { title: "Rotation uncertainty", yLabel: "[nats] / [–]", yMin: 0 }),
  pSuccess: new TimePlot(el("plot-psuccess"), { title: "Grasp success probability", yLabel: "p_success [–]", yMin: 0, yMax: 1 }),
  tErr: new TimePlot(el("plot-terr"), { title: "Translation error vs ground truth", yLabel: "error [m]", yMin: 0 }),
  rErr: new TimePlot(el("plot-rerr"), { title: "Orientation error vs ground truth (modulo symmetry)", yLabel: "error [deg]", yMin: 0 }),
};

function setConnection(status, text) {
  document.body.dataset.connection = status;
  el("connection").textContent = text;
}

// ---- data --------------------------------------------------------------------------------

async function getJson(path) {
  const r = await fetch(path, { cache: "no-store" });
  if (!r.ok) throw new Error(`${path}: HTTP ${r.status}`);
  return r.json();
}

async function refreshScene() {
  try {
    state.scene = await getJson("/api/v1/scene");
    // Camera colours follow the scene's camera order, whatever arrived first.
    const known = [...state.cameraColorIndex.keys()];
    state.cameraColorIndex.clear();
    for (const id of [...(state.scene.cameras ?? []).map((c) => c.id), ...known]) colors.cameraCss(id);
    for (const panel of state.panels.values()) panel.updateCaption();
    for (const cam of state.scene.cameras ?? []) {
      colors.cameraCss(cam.id);
      let panel = state.panels.get(cam.id);
      if (!panel) {
        panel = new CameraPanel(el("cameras-panel"), cam, colors);
        state.panels.set(cam.id, panel);
        if (cam.latest_stamp_ns !== null && cam.latest_stamp_ns !== undefined) panel.onFrame(cam.latest_stamp_ns);
      } else {
        panel.setCamera(cam);
      }
    }
    scheduleRender();
  } catch (e) {
    console.warn("scene refresh failed", e);
  }
}

let sceneTimer = null;
let lastSceneMs = 0;
function refreshSceneSoon() {
  if (sceneTimer) return;
  const wait = Math.max(0, SCENE_REFRESH_MS - (performance.now() - lastSceneMs));
  sceneTimer = setTimeout(async () => {
    lastSceneMs = performance.now();
    await refreshScene();
    sceneTimer = null;
  }, wait);
}

async function resyncTracks() {
  try {
    const list = await getJson("/api/v1/tracks");
    const seen = new Set();
    for (const t of list) {
      seen.add(t.id);
      upsertTrack(t);
    }
    for (const id of [...state.tracks.keys()]) {
      if (seen.has(id)) continue;
      state.tracks.delete(id);
      const key = String(id);
      for (const p of Object.values(plots)) p.removeWhere((k) => k === key || k.startsWith(`${key}/`));
    }
    scheduleRender();
  } catch (e) {
    console.warn("tracks resync failed", e);
  }
}

function timeS(stampNs) {
  if (!Number.isFinite(stampNs)) return NaN;
  if (state.t0Ns === null) state.t0Ns = stampNs;
  return (stampNs - state.t0Ns) / 1e9;
}

/** Objects are coloured by their id, the key detections carry too. */
function objectColor(t) {
  return colors.objectCss(String(t.object_id ?? t.object_name));
}

function trackLabel(t) {
  return `${t.object_name ?? t.object_id} #${t.id}`;
}

function upsertTrack(t) {
  const prev = state.tracks.get(t.id);
  if (!prev && !state.historyLoaded.has(t.id)) loadHistory(t);
  // A track event without a decision keeps the last one from the `decision` events.
  if (prev && (t.decision === undefined || t.decision === null)) t.decision = prev.decision;
  state.tracks.set(t.id, t);
  if (state.selected === null) state.selected = t.id;
  const key = String(t.id);
  const color = objectColor(t);
  const label = trackLabel(t);
  const tS = timeS(t.stamp_ns);
  plots.std.setSeries(key, label, color);
  plots.std.add(key, tS, t.translation_std_m);
  plots.rotation.setSeries(`${key}/entropy`, `${label} entropy [nats]`, color);
  plots.rotation.add(`${key}/entropy`, tS, t.rotation_entropy);
  plots.rotation.setSeries(`${key}/top`, `${label} top-mode mass [–]`, color, [4, 3]);
  plots.rotation.add(`${key}/top`, tS, t.top_mode_mass);
  if (t.truth) {
    plots.tErr.setSeries(key, label, color);
    plots.tErr.add(key, tS, t.truth.translation_error_m);
    plots.rErr.setSeries(key, label, color);
    plots.rErr.add(key, tS, t.truth.orientation_error_deg);
  }
  if (t.decision) addDecisionPoint(t, t.decision, tS);
  if (t.object_id !== undefined) loadMesh(t.object_id);
}

function addDecisionPoint(t, d, tS) {
  const key = String(t.id);
  plots.pSuccess.setSeries(key, trackLabel(t), objectColor(t));
  plots.pSuccess.add(key, tS, d.p_success);
  if (Number.isFinite(d.threshold)) {
    plots.pSuccess.setRefLines([{ y: d.threshold, label: `threshold ${d.threshold}`, color: OKABE.grey }]);
  }
}

/** Fills the plots with what happened before this page was opened (/tracks/{id}/history). */
async function loadHistory(t) {
  state.historyLoaded.add(t.id);
  try {
    const history = await getJson(`/api/v1/tracks/${encodeURIComponent(t.id)}/history`);
    if (!Array.isArray(history) || !history.length) return;
    const key = String(t.id);
    const pts = (f) => history.map((h) => [timeS(h.stamp_ns), f(h)]).filter(([x, y]) => Number.isFinite(x) && Number.isFinite(y));
    plots.std.prepend(key, pts((h) => h.translation_std_m));
    plots.rotation.prepend(`${key}/entropy`, pts((h) => h.rotation_entropy));
    if (history.some((h) => h.truth)) {
      const label = trackLabel(t);
      plots.tErr.setSeries(key, label, objectColor(t));
      plots.rErr.setSeries(key, label, objectColor(t));
      plots.tErr.prepend(key, pts((h) => h.truth?.translation_error_m ?? NaN));
      plots.rErr.prepend(key, pts((h) => h.truth?.orientation_error_deg ?? NaN));
    }
    scheduleRender();
  } catch (e) {
    console.warn("track history unavailable", e);
  }
}

async function loadMesh(objectId) {
  if (state.meshes.has(objectId)) return;
  state.meshes.set(objectId, "loading");
  try {
    const m = await getJson(`/api/v1/objects/${encodeURIComponent(objectId)}/mesh`);
    const seen = new Set();
    const edges = [];
    for (const [a, b, c] of m.triangles ?? []) {
      for (const [i, j] of [
        [a, b],
        [b, c],
        [c, a],
      ]) {
        const k = i < j ? `${i},${j}` : `${j},${i}`;
        if (!seen.has(k)) {
          seen.add(k);
          edges.push([i, j]);
        }
      }
    }
    state.meshes.set(objectId, { vertices: m.vertices_m ?? [], edges });
    scheduleRender();
  } catch (e) {
    state.meshes.set(objectId, "failed");
    setTimeout(() => state.meshes.delete(objectId), 5_000); // retry later
  }
}

// ---- events ---------------------------------------------------------------------------------

function countEvent() {
  state.updates += 1;
  const now = performance.now();
  state.eventTimes.push(now);
  while (state.eventTimes.length && now - state.eventTimes[0] > EVENT_RATE_WINDOW_MS) state.eventTimes.shift();
  document.body.dataset.updates = String(state.updates);
}

function eventRateHz() {
  const now = performance.now();
  const recent = state.eventTimes.filter((t) => now - t <= EVENT_RATE_WINDOW_MS);
  if (recent.length < 2) return 0;
  const spanMs = Math.max(1000, Math.min(EVENT_RATE_WINDOW_MS, now - recent[0]));
  return (recent.length * 1000) / spanMs;
}

let source = null;
let backoffMs = 500;
function connect() {
  setConnection(state.updates ? "reconnecting" : "connecting", state.updates ? "reconnecting…" : "connecting…");
  source = new EventSource("/api/v1/events");
  source.onopen = () => {
    backoffMs = 500;
    state.connects += 1;
    document.body.dataset.connects = String(state.connects);
    setConnection("live", "live");
    refreshScene();
    resyncTracks();
  };
  source.onerror = () => {
    source.close();
    setConnection("reconnecting", `connection lost, retrying in ${(backoffMs / 1000).toFixed(1)} s`);
    setTimeout(connect, backoffMs);
    backoffMs = Math.min(5_000, backoffMs * 2);
  };
  const handle = (name, fn) =>
    source.addEventListener(name, (ev) => {
      let data;
      try {
        data = JSON.parse(ev.data);
      } catch {
        return;
      }
      countEvent();
      fn(data);
      scheduleRender();
    });
  handle("track", (t) => {
    state.trackUpdates += 1;
    document.body.dataset.trackUpdates = String(state.trackUpdates);
    upsertTrack(t);
  });
  handle("decision", (d) => {
    const t = state.tracks.get(d.track_id);
    if (!t) return;
    t.decision = d.decision;
    if (d.decision) addDecisionPoint(t, d.decision, timeS(t.stamp_ns));
  });
  handle("frame", (f) => {
    const panel = state.panels.get(f.camera);
    if (panel) panel.onFrame(f.stamp_ns);
    refreshSceneSoon();
  });
  handle("stats", (s) => {
    state.stats = s;
  });
}

// ---- rendering ----------------------------------------------------------------------------

let renderPending = false;
let lastRenderMs = -Infinity;
let lastListMs = -Infinity;
/** Coalesces events into at most one redraw per MIN_RENDER_INTERVAL_MS (the service may publish
 *  far faster than a person reads; a software-rendered browser should not eat a core). */
function scheduleRender() {
  if (renderPending) return;
  renderPending = true;
  const wait = Math.max(0, MIN_RENDER_INTERVAL_MS - (performance.now() - lastRenderMs));
  setTimeout(
    () =>
      requestAnimationFrame(() => {
        renderPending = false;
        lastRenderMs = performance.now();
        render();
        // Cost of one redraw (DOM, 3D geometry, plots, overlays), smoothed: a test hook.
        const ms = performance.now() - lastRenderMs;
        state.renderMs = state.renderMs === undefined ? ms : 0.9 * state.renderMs + 0.1 * ms;
        document.body.dataset.renderMs = state.renderMs.toFixed(2);
      }),
    wait,
  );
}

function render() {
  const tracks = [...state.tracks.values()].sort((a, b) => a.id - b.id);
  if (state.selected !== null && !state.tracks.has(state.selected)) {
    state.selected = tracks[0]?.id ?? null;
    state.userSelected = false;
  }
  // Until the user picks one, select the first object the planner is deciding about.
  if (!state.userSelected && !state.tracks.get(state.selected)?.decision) {
    const decided = tracks.find((t) => t.decision);
    if (decided) state.selected = decided.id;
  }
  document.body.dataset.tracks = String(tracks.length);
  const sel = state.tracks.get(state.selected);
  const selDecision = sel?.decision ?? tracks.find((t) => t.decision)?.decision;
  document.body.dataset.decision = selDecision ? verdictOf(selDecision) : "";
  // The list is rebuilt at a calmer rate so that clicks on it are not lost mid-rebuild.
  const now = performance.now();
  if (now - lastListMs >= MIN_LIST_INTERVAL_MS || tracks.length !== el("track-list").childElementCount) {
    lastListMs = now;
    renderTrackList(tracks);
  } else {
    setTimeout(scheduleRender, MIN_LIST_INTERVAL_MS);
  }
  renderLegend();
  renderStats();
  if (view) {
    const { geometry, particles } = buildGeometry(tracks);
    view.afterDraw = () => {
      document.body.dataset.particlesDrawn = String(Math.min(particles, view.drawnPoints));
    };
    view.setGeometry(geometry);
    // Follow the scene until the user takes the camera (then double click fits again).
    if (tracks.length || state.scene) fitView(false);
  }
  // One time axis for all plots; the selected object in front, the others faint.
  let range = null;
  for (const p of Object.values(plots)) {
    const e = p.extent();
    if (e) range = range ? [Math.min(range[0], e[0]), Math.max(range[1], e[1])] : e;
  }
  if (range && range[1] - range[0] < 1) range = [range[0], range[0] + 1];
  const selectedKey = String(state.selected);
  const isSelected = (key) => key === selectedKey || key.startsWith(`${selectedKey}/`);
  let maxPoints = 0;
  for (const p of Object.values(plots)) {
    p.setTimeRange(range);
    if (p.highlight?.selectedKey !== selectedKey) {
      const h = (key) => isSelected(key);
      h.selectedKey = selectedKey;
      p.setHighlight(h);
    }
    p.draw();
    maxPoints = Math.max(maxPoints, p.pointCount());
  }
  document.body.dataset.plotPoints = String(maxPoints);
  for (const panel of state.panels.values()) panel.drawOverlay(tracks);
}

function verdictOf(d) {
  const v = d?.decision ?? d?.verdict;
  return typeof v === "string" ? v.toLowerCase() : "";
}

/** What the answer's probability is: calibrated by the shipped map, or the raw sample rate
 * because the map was fitted for other settings (stale) or there is none. */
function calibrationLine(d) {
  const c = d.calibration;
  if (!c || !c.state) return "";
  const raw = `raw ${fmt(d.p_success_raw, 2)}`;
  if (c.state === "calibrated") {
    // the rule's own quantity (e.g. the smoothed raw rate) against its threshold, and the spread
    const r = d.rule;
    const quantity = typeof r?.quantity === "string" ? `${r.quantity.replaceAll("_", " ")} ` : "";
    const rule = r && Number.isFinite(r.value) ? ` · rule ${quantity}${fmt(r.value, 3)} / ${fmt(r.threshold, 3)}` : "";
    const s = d.smoothing?.translation_std_m_smoothed;
    const spread = Number.isFinite(s) ? ` · spread ${fmt(s * 1000, 1)} mm` : "";
    return `calibrated · ${raw}${rule}${spread}`;
  }
  if (c.state === "stale") return `map fitted for other settings: raw rate and rule · ${raw}`;
  // no map, or an answer of fewer samples than the map was fitted on: the message says which
  return `not calibrated: raw rate and rule · ${raw}`;
}

function mainReason(d) {
  const reasons = Array.isArray(d?.reasons) ? d.reasons : [];
  if (!reasons.length) return "";
  const share = (r) => Number(r?.share ?? r?.failure_share ?? r?.weight ?? r?.fraction ?? 0);
  const best = reasons.reduce((a, b) => (share(b) > share(a) ? b : a), reasons[0]);
  if (typeof best === "string") return best;
  const text = best.message ?? best.description ?? best.text ?? best.summary ?? best.detail;
  const name = best.test ?? best.kind ?? best.name ?? best.reason ?? best.type;
  const pct = share(best) > 0 ? ` (${(share(best) * 100).toFixed(0)} %)` : "";
  if (text) return text; // the service's message already states the share
  if (name) return `${typeof name === "string" ? name : JSON.stringify(name)}${pct}`;
  return JSON.stringify(best).slice(0, 120);
}

/** The pose axis whose spread correlates most with failing (decision.uncertainty[0]). */
function mainDriver(d) {
  const u = Array.isArray(d?.uncertainty) ? d.uncertainty[0] : null;
  if (!u || !(Number(u.failure_correlation) >= DRIVER_MIN_CORRELATION)) return "";
  const motion = typeof u.motion === "string" ? u.motion.toLowerCase() : "";
  const rotational = motion.startsWith("rot");
  const spread = rotational ? `${fmt((u.spread * 180) / Math.PI, 1)}°` : `${fmt(u.spread * 1000, 1)} mm`;
  return `${motion || "offset"} ${rotational ? "about" : "along"} ${u.axis} (spread ${spread}, correlation ${fmt(u.failure_correlation, 2)})`;
}

function fmt(v, digits = 3) {
  return Number.isFinite(v) ? Number(v).toFixed(digits) : "–";
}

function renderTrackList(tracks) {
  const list = el("track-list");
  el("no-tracks").hidden = tracks.length > 0;
  const items = [];
  for (const t of tracks) {
    const li = document.createElement("li");
    li.className = `track${t.id === state.selected ? " selected" : ""}`;
    li.dataset.trackId = String(t.id);
    li.dataset.status = t.status;
    const d = t.decision;
    const verdict = d ? verdictOf(d) : "";
    li.dataset.decision = verdict;
    const row = document.createElement("div");
    row.className = "row";
    const sw = document.createElement("span");
    sw.className = "swatch";
    sw.style.background = objectColor(t);
    const name = document.createElement("span");
    name.className = "name";
    name.textContent = trackLabel(t);
    const status = document.createElement("span");
    status.className = `badge status-${t.status}`;
    status.textContent = t.status;
    const vd = document.createElement("span");
    vd.className = `verdict ${verdict || "none"}`;
    vd.textContent = verdict || "no decision";
    row.append(sw, name, status, vd);
    li.append(row);
    if (d) {
      const p = document.createElement("div");
      p.className = "metrics";
      const ci = Array.isArray(d.ci95) ? ` [${fmt(d.ci95[0], 2)}, ${fmt(d.ci95[1], 2)}]` : "";
      p.textContent = `p_success ${fmt(d.p_success, 2)}${ci} (95 %) · threshold ${fmt(d.threshold, 2)}`;
      li.append(p);
      const cal = calibrationLine(d);
      if (cal) {
        const c = document.createElement("div");
        c.className = `metrics calibration calibration-${d.calibration.state}`;
        c.textContent = cal;
        if (d.calibration.message) c.title = d.calibration.message;
        li.append(c);
      }
      const reason = mainReason(d);
      if (reason) {
        const r = document.createElement("div");
        r.className = "reason";
        r.textContent = `Main reason: ${reason}`;
        li.append(r);
      }
      const driver = mainDriver(d);
      if (driver) {
        const r = document.createElement("div");
        r.className = "reason muted";
        r.textContent = `Look more along: ${driver}`;
        li.append(r);
      }
    }
    const m = document.createElement("div");
    m.className = "metrics";
    let text =
      `σ_t ${fmt(t.translation_std_m * 1000, 1)} mm · H_rot ${fmt(t.rotation_entropy, 2)} nats` +
      ` · top mode ${fmt(t.top_mode_mass, 2)} · ${(t.particles ?? []).length} particles`;
    if (t.truth) {
      text += ` · err ${fmt(t.truth.translation_error_m * 1000, 1)} mm / ${fmt(t.truth.orientation_error_deg, 1)}°`;
    }
    m.textContent = text;
    li.append(m);
    li.addEventListener("click", () => {
      state.selected = t.id;
      state.userSelected = true;
      scheduleRender();
    });
    items.push(li);
  }
  list.replaceChildren(...items);
}

let legendKey = "";
function renderLegend() {
  const key = (state.scene?.cameras ?? []).map((c) => `${c.id}:${c.mount}:${colors.cameraCss(c.id)}`).join(",");
  if (key === legendKey && el("legend").childElementCount) return;
  legendKey = key;
  const entries = [];
  for (const cam of state.scene?.cameras ?? []) {
    entries.push([colors.cameraCss(cam.id), `camera ${cam.id} (${cam.mount}): frustum + its particles`]);
  }
  entries.push(["rgba(230,159,0,0.45)", "particle opacity: its weight"]);
  entries.push([OKABE.grey, "table plane (0.1 m grid)"]);
  entries.push(["linear-gradient(90deg,#D55E00 33%,#009E73 33% 66%,#56B4E9 66%)", "axes x / y / z (0.2 m)"]);
  entries.push(["#FFFFFF", "mean pose: mesh wireframe"]);
  entries.push(["rgba(255,255,255,0.35)", "sampled poses (selected object)"]);
  entries.push([OKABE.green, "planned gripper: grasp"]);
  entries.push([OKABE.orange, "planned gripper: observe"]);
  const items = entries.map(([color, text]) => {
    const li = document.createElement("li");
    const sw = document.createElement("span");
    sw.className = "swatch";
    sw.style.background = color;
    const span = document.createElement("span");
    span.textContent = text;
    li.append(sw, span);
    return li;
  });
  el("legend").replaceChildren(...items);
}

function renderStats() {
  const rate = eventRateHz();
  document.body.dataset.eventRateHz = rate.toFixed(2);
  const s = state.stats;
  let text = `page: ${rate.toFixed(1)} events/s`;
  if (s) {
    text += ` · tracker ${fmt(s.step_rate_hz, 1)} Hz · ingest ${fmt(s.ingest_rate_hz, 1)} Hz · queue ${s.queue_depth ?? "–"}`;
  }
  el("stats").textContent = text;
}
setInterval(renderStats, 1000);

/** Centre on the objects (or on everything when none is tracked yet), radius to the cameras. */
function sceneCenterAndRadius(tracks) {
  const all = [];
  const objects = [];
  for (const cam of state.scene?.cameras ?? []) {
    // The robot camera may start far away: frame the stationary cameras and the objects.
    const p = parsePose(cam.world_from_camera);
    if (p && (cam.mount !== "robot" || !tracks.length)) all.push(p.t);
  }
  for (const t of tracks) {
    const p = parsePose(t.world_from_object);
    if (p) {
      all.push(p.t);
      objects.push(p.t);
    }
  }
  if (state.scene?.support_plane?.point_m) all.push(state.scene.support_plane.point_m);
  if (!all.length) return null;
  const centerOf = (pts) => [0, 1, 2].map((i) => pts.reduce((s, p) => s + p[i], 0) / pts.length);
  const c = centerOf(objects.length ? objects : all);
  const far = Math.max(...all.map((p) => Math.hypot(p[0] - c[0], p[1] - c[1], p[2] - c[2])));
  return { c, r: Math.max(0.3, far) };
}

function fitView(force) {
  const cr = sceneCenterAndRadius([...state.tracks.values()]);
  if (!cr || !view) return;
  view.fit(cr.c, cr.r, force);
}

function meshWire(g, mesh, pose, color) {
  const v = mesh.vertices.map((p) => transformPoint(pose, p));
  for (const [i, j] of mesh.edges) if (v[i] && v[j]) g.line(v[i], v[j], color);
}

function buildGeometry(tracks) {
  const g = new SceneGeometry();
  const origin = [0, 0, 0];
  const axes = [
    [0.2, 0, 0],
    [0, 0.2, 0],
    [0, 0, 0.2],
  ];
  axes.forEach((a, i) => {
    g.line(origin, a, rgba(AXIS_COLORS[i]));
    g.label(a, "xyz"[i], AXIS_COLORS[i]);
  });
  g.label(origin, "world", "#dddddd");

  // Table plane: a grid centred under the scene.
  const plane = state.scene?.support_plane;
  if (plane?.normal && plane?.point_m) {
    const n = normalize(plane.normal);
    const u = normalize(cross(n, Math.abs(n[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0]));
    const w = cross(n, u);
    const cr = sceneCenterAndRadius(tracks);
    let c = plane.point_m;
    if (cr) {
      const d = (cr.c[0] - c[0]) * n[0] + (cr.c[1] - c[1]) * n[1] + (cr.c[2] - c[2]) * n[2];
      c = [cr.c[0] - d * n[0], cr.c[1] - d * n[1], cr.c[2] - d * n[2]];
    }
    const at = (a, b) => [0, 1, 2].map((i) => c[i] + a * u[i] + b * w[i]);
    const steps = Math.round(TABLE_HALF_SIZE_M / TABLE_CELL_M);
    const col = rgba(OKABE.grey, 0.28);
    for (let i = -steps; i <= steps; i++) {
      const s = i * TABLE_CELL_M;
      g.line(at(s, -TABLE_HALF_SIZE_M), at(s, TABLE_HALF_SIZE_M), col);
      g.line(at(-TABLE_HALF_SIZE_M, s), at(TABLE_HALF_SIZE_M, s), col);
    }
    g.label(at(TABLE_HALF_SIZE_M, TABLE_HALF_SIZE_M), "table", "#aaaaaa");
  }

  // Cameras as frustums, the robot camera's trajectory.
  for (const cam of state.scene?.cameras ?? []) {
    const pose = parsePose(cam.world_from_camera);
    const intr = cam.intrinsics;
    if (!pose || !intr?.k) continue;
    const css = colors.cameraCss(cam.id);
    const col = rgba(css, 0.95);
    const o = pose.t;
    // the image's outer edges: pixel centres are at integers, so the edges at -0.5 and w - 0.5
    const corners = [
      [-0.5, -0.5],
      [intr.width - 0.5, -0.5],
      [intr.width - 0.5, intr.height - 0.5],
      [-0.5, intr.height - 0.5],
    ].map(([u, v]) => transformPoint(pose, unprojectPixel(intr.k, u, v, FRUSTUM_DEPTH_M)));
    for (const c of corners) g.line(o, c, col);
    g.polyline(corners, col, true);
    // A tick on the top edge shows which way is up in the image (optical y points down).
    const top = transformPoint(pose, unprojectPixel(intr.k, (intr.width - 1) / 2, -intr.height * 0.15, FRUSTUM_DEPTH_M));
    g.line(corners[0], top, col);
    g.line(corners[1], top, col);
    g.label(o, cam.id, css);
  }
  const traj = state.scene?.robot_trajectory_m ?? [];
  if (traj.length > 1) {
    const robot = (state.scene?.cameras ?? []).find((c) => c.mount === "robot");
    const css = robot ? colors.cameraCss(robot.id) : OKABE.grey;
    g.polyline(traj, rgba(css, 0.7));
    g.label(traj[0], "trajectory start", css);
  }

  // Objects: particles by source camera, mean mesh wireframe, samples, gripper.
  let particles = 0;
  for (const t of tracks) {
    // Opacity follows the particle's weight (relative to the heaviest of its track).
    const maxWeight = Math.max(1e-12, ...(t.particles ?? []).map((p) => Number(p.weight) || 0));
    for (const p of t.particles ?? []) {
      if (!Array.isArray(p.position_world_m)) continue;
      const w = Number(p.weight);
      const alpha = Number.isFinite(w) ? 0.35 + 0.65 * Math.min(1, w / maxWeight) : 0.9;
      g.point(p.position_world_m, rgba(colors.cameraCss(p.camera), alpha), 4.5);
      particles += 1;
    }
    const mean = parsePose(t.world_from_object);
    if (!mean) continue;
    const mesh = state.meshes.get(t.object_id);
    const selected = t.id === state.selected;
    if (mesh && typeof mesh === "object") {
      meshWire(g, mesh, mean, [1, 1, 1, selected ? 0.75 : 0.5]);
      if (selected) {
        for (const s of (t.samples_world ?? []).slice(0, 10)) {
          const sp = parsePose(s);
          if (sp) meshWire(g, mesh, sp, [1, 1, 1, 0.12]);
        }
      }
    }
    g.triad(mean, 0.05, AXIS_COLORS.map((c) => rgba(c)), transformPoint);
    if (selected) {
      for (const s of (t.samples_world ?? []).slice(0, 10)) {
        const sp = parsePose(s);
        if (sp) g.triad(sp, 0.025, AXIS_COLORS.map((c) => rgba(c, 0.45)), transformPoint);
      }
    }
    g.label(mean.t, trackLabel(t), objectColor(t));
    drawGripper(g, t, mean);
  }
  return { geometry: g, particles };
}

/** The planned gripper: approach along its +z, fingers closing along its x. */
function drawGripper(g, t, worldFromObject) {
  const d = t.decision;
  if (!d) return;
  let worldFromGripper = null;
  const objectFromGripper = parsePose(d.grasp?.object_from_gripper);
  if (objectFromGripper) {
    worldFromGripper = composePose(worldFromObject, objectFromGripper);
  } else {
    const referenceFromGripper = parsePose(d.reference_from_gripper);
    const referenceFromObject = parsePose(t.reference_from_object);
    if (referenceFromGripper && referenceFromObject) {
      const worldFromReference = composePose(worldFromObject, invertPose(referenceFromObject));
      worldFromGripper = composePose(worldFromReference, referenceFromGripper);
    }
  }
  if (!worldFromGripper) return;
  const verdict = verdictOf(d);
  const css = verdict === "grasp" ? OKABE.green : OKABE.orange;
  const col = rgba(css);
  // Open around the object's width along the closing axis (grasp.width_m) with a margin.
  const widthM = Number(d.grasp?.width_m);
  const halfOpening = (Number.isFinite(widthM) && widthM > 0 ? widthM : 0.08) / 2 + GRIPPER_MARGIN_M;
  const finger = GRIPPER_FINGER_M;
  const tip = 0.1 * finger;
  const P = (x, y, z) => transformPoint(worldFromGripper, [x, y, z]);
  // The frame's origin is the tool centre point between the fingers: palm across x behind it,
  // fingers along +z up to just past it, the wrist further back.
  g.line(P(-halfOpening, 0, -finger), P(halfOpening, 0, -finger), col);
  g.line(P(-halfOpening, 0, -finger), P(-halfOpening, 0, tip), col);
  g.line(P(halfOpening, 0, -finger), P(halfOpening, 0, tip), col);
  g.line(P(0, 0, -finger), P(0, 0, -finger - 0.06), col);
  // No text label: the legend explains the two colours, and labels near objects pile up.
}

// ---- start ---------------------------------------------------------------------------------

if (view) {
  const origDraw = view.draw.bind(view);
  view.draw = () => {
    origDraw();
    if (view.afterDraw) view.afterDraw();
  };
}
window.addEventListener("resize", () => {
  for (const p of Object.values(plots)) p.draw(true);
  scheduleRender();
});
setInterval(resyncTracks, TRACKS_RESYNC_MS);
refreshScene();
resyncTracks();
connect();
