// oralnav console: the surgeon's page over the daemon's REST API and telemetry websocket.
// Plain browser JavaScript, no library: every action is one audited API request made with
// the token the user signed in with; a refusal (wrong role, wrong state) is shown as the
// API words it. Text from the daemon is only ever set as textContent (never parsed as
// HTML). docs/console.md describes the page.
"use strict";

const KEY = "oralnav.token";          // sessionStorage: the token lives as long as the tab
const VIEW_WIDTH = [64, 1920];        // px a view may ask of the daemon (it downscales)
const RECONNECT_MS = [250, 500, 1000, 2000, 4000];  // websocket back-off, then 4 s

const S = {
  token: sessionStorage.getItem(KEY) || "",
  who: null,                          // {name, role}
  ws: null, wsTries: 0, wsUp: false,
  status: null,                       // the newest /status document (telemetry)
  targets: [], tre: {},
  fps: 5, overlay: true,
  views: new Map(),                   // camera -> {card, canvas, label, counter, ...}
  frameWidth: 0,                      // px the frames are subscribed at (0: none yet)
  shown: 0, shownSince: performance.now(),
};

const $ = (id) => document.getElementById(id);

// -- requests ---------------------------------------------------------------------------
async function api(method, path, body) {
  const init = { method, headers: { Authorization: `Bearer ${S.token}` } };
  if (body !== undefined) {
    init.headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  let res;
  try {
    res = await fetch(path, init);
  } catch (err) {
    return { ok: false, status: 0, data: { detail: `daemon unreachable (${err.message})` } };
  }
  let data = null;
  const type = res.headers.get("Content-Type") || "";
  if (type.includes("application/json")) data = await res.json().catch(() => null);
  if (res.status === 401) signOut("the token was not accepted (401): sign in again");
  return { ok: res.ok, status: res.status, data, res };
}

function detail(r) {
  const d = r.data && r.data.detail;
  return d ? String(d) : `HTTP ${r.status}`;
}

let noticeTimer = null;
function notify(text, kind = "info") {
  const n = $("notice");
  n.textContent = text;
  n.dataset.kind = kind;
  n.hidden = false;
  clearTimeout(noticeTimer);
  noticeTimer = setTimeout(() => { n.hidden = true; }, kind === "error" ? 9000 : 4000);
}

async function command(path, body, label) {
  const r = await api("POST", path, body);
  if (r.ok) {
    notify(`${label}: done`, "ok");
  } else if (r.status === 403) {
    notify(`${label} refused: your token (${S.who ? S.who.role : "?"}) may only watch; ` +
           `an operator token is needed (${detail(r)})`, "error");
  } else {
    notify(`${label} refused (${r.status}): ${detail(r)}`, "error");
  }
  return r;
}

// -- sign in / out -----------------------------------------------------------------------
async function signIn(token) {
  S.token = token;
  const r = await api("GET", "/session");
  if (!r.ok) {
    $("login-error").textContent = r.status === 401 ? "unknown token" : detail(r);
    S.token = "";
    return false;
  }
  sessionStorage.setItem(KEY, token);
  S.who = r.data;
  $("who").textContent = `${S.who.name} (${S.who.role})`;
  $("login").hidden = true;
  $("main").hidden = false;
  $("signout").hidden = false;
  connect();
  refreshTargets();
  return true;
}

function signOut(why) {
  sessionStorage.removeItem(KEY);
  S.token = "";
  S.who = null;
  if (S.ws) { S.ws.onclose = null; S.ws.close(); S.ws = null; }
  for (const v of S.views.values()) {
    if (v.bitmap) v.bitmap.close();
  }
  S.views.clear();
  dirty.clear();
  $("views").replaceChildren();
  $("main").hidden = true;
  $("signout").hidden = true;
  $("who").textContent = "";
  $("login").hidden = false;
  $("login-error").textContent = why || "";
}

// -- telemetry: the daemon's state, pushed; reconnects by itself ----------------------------
function connect() {
  if (!S.token) return;
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  const ws = new WebSocket(`${scheme}://${location.host}/telemetry?token=` +
                           encodeURIComponent(S.token));
  ws.binaryType = "arraybuffer";       // the frames (binary messages): see onFrame
  S.ws = ws;
  ws.onopen = () => {
    S.wsTries = 0;
    setLink(true);
    subscribe();
  };
  ws.onmessage = (ev) => {
    if (ev.data instanceof ArrayBuffer) { onFrame(ev.data); return; }
    let doc;
    try { doc = JSON.parse(ev.data); } catch (_) { return; }
    if (doc.status) showStatus(doc.status);
    else if (doc.state) showState(doc.state, null);
  };
  ws.onclose = () => {
    setLink(false);
    if (S.ws !== ws || !S.token) return;
    const wait = RECONNECT_MS[Math.min(S.wsTries, RECONNECT_MS.length - 1)];
    S.wsTries += 1;
    setTimeout(reconnect, wait);
  };
}

async function reconnect() {
  // ask first whether the token still holds: a refused token signs out (api() does) rather
  // than retrying a websocket the daemon refuses, each refusal counting toward a lockout
  if (!S.token) return;
  const r = await api("GET", "/session");
  if (r.ok) {
    connect();
  } else if (S.token) {  // the daemon unreachable, or busy: try again later
    const wait = RECONNECT_MS[Math.min(S.wsTries, RECONNECT_MS.length - 1)];
    S.wsTries += 1;
    setTimeout(reconnect, wait);
  }
}

function setLink(up) {
  S.wsUp = up;
  $("link").dataset.up = String(up);
  $("link").textContent = up ? "live" : "reconnecting...";
}

// -- what the status says -----------------------------------------------------------------
function showState(state, why) {
  const el = $("state");
  setText(el, state);
  if (el.dataset.state !== state) el.dataset.state = state;
  if (why !== null) setText($("why"), why);
}

function fmt(x, digits) {
  return typeof x === "number" && isFinite(x) ? x.toFixed(digits) : "-";
}

function showStatus(st) {
  S.status = st;
  const sf = st.safety || {};
  const reasons = (sf.reasons || []).map((c) => `${c.source}: ${c.reason}`);
  const why = reasons.join("; ") || sf.not_ready_reason || "";
  showState(sf.state || "UNKNOWN", why);
  if (!reasons.length && sf.not_ready_reason) reasons.push(`not ready: ${sf.not_ready_reason}`);
  setList($("reasons"), reasons);
  setList($("history"), (sf.history || []).slice(-8).reverse().map((h) =>
    `${h.from} -> ${h.to} (${h.who}: ${h.reason})`));

  const p = st.procedure || {};
  setText($("stage"), p.done ? "done" : (p.stage || "-"));
  const next = p.target || (p.remaining && p.remaining[0]) || st.selected_target || "-";
  setText($("target"), next);
  setText($("error"), p.error_mm === undefined ? "-" :
    `${fmt(p.error_mm, 3)} mm, ${fmt(p.error_deg, 2)} deg`);
  S.tre = p.tre_mm || {};
  const reached = Object.entries(S.tre).map(([n, v]) => `${n} ${fmt(v, 3)} mm`);
  setText($("reached"), reached.join(", ") || "-");
  markTargets(next, st.selected_target);
}

// The status comes five times a second and mostly says the same: the page is only
// written (laid out, painted) where it changed.
function setText(el, text) {
  if (el.textContent !== text) el.textContent = text;
}

function setList(el, items) {
  const key = items.join("\n");
  if (el.dataset.key === key) return;
  el.dataset.key = key;
  el.replaceChildren(...items.map((t) => li(t)));
}

function li(text) {
  const e = document.createElement("li");
  e.textContent = text;
  return e;
}

// -- suture targets -----------------------------------------------------------------------
async function refreshTargets() {
  const r = await api("GET", "/targets");
  if (!r.ok) return;
  const targets = r.data.targets || [];
  const same = JSON.stringify(targets) === JSON.stringify(S.targets);
  S.targets = targets;
  if (same && $("targets").children.length) {  // keep the rows (and a choice being made)
    if (S.status) showStatus(S.status);
    return;
  }
  const checked = (document.querySelector("input[name=target]:checked") || {}).value;
  $("targets").replaceChildren(...S.targets.map((t) => {
    const row = document.createElement("li");
    row.dataset.name = t.name;
    const label = document.createElement("label");
    const radio = document.createElement("input");
    radio.type = "radio";
    radio.name = "target";
    radio.value = t.name;
    radio.checked = t.name === checked;
    label.append(radio, document.createTextNode(" " + t.name));
    const where = document.createElement("span");
    where.className = "tre";
    where.textContent = t.p_OM.map((v) => (v * 1e3).toFixed(1)).join(", ") + " mm";
    row.append(label, where);
    return row;
  }));
  if (!S.targets.length) $("targets").append(li("none registered"));
  if (S.status) showStatus(S.status);
}

function markTargets(current, selected) {
  for (const row of $("targets").children) {
    const name = row.dataset.name;
    if (!name) continue;
    if (row.dataset.current !== String(name === current)) {
      row.dataset.current = String(name === current);
    }
    const tre = S.tre[name];
    if (tre !== undefined) setText(row.querySelector(".tre"), `TRE ${fmt(tre, 3)} mm`);
    const title = name === selected ? "selected by the surgeon" : "";
    if (row.title !== title) row.title = title;
  }
}

async function registerTargets(targets, label) {
  const r = await command("/targets", { targets }, label);
  if (r.ok) refreshTargets();
}

// -- live views -------------------------------------------------------------------------------
// The frames come pushed over the telemetry websocket (topic "frames"): each camera's newest
// frame, at most S.fps a second, as one binary message (a 4-byte big-endian header length,
// the JSON header: camera, counter, size and the fields found in that very frame; then the
// JPEG). No request per frame; a paused console or a hidden tab is unsubscribed, so it costs
// the daemon nothing. The width asked is the widest view's in device pixels, in steps of 64
// (a few sizes: the daemon encodes each frame once per size for every console).
function subscribe() {
  if (!S.ws || S.ws.readyState !== WebSocket.OPEN) return;
  const topics = ["status"];
  const msg = { subscribe: topics };
  if (S.fps && !document.hidden) {
    S.frameWidth = frameWidth();
    topics.push("frames");
    msg.frames = { fps: S.fps, width: S.frameWidth };
  }
  S.ws.send(JSON.stringify(msg));
}

function frameWidth() {
  let px = 0;
  for (const v of S.views.values()) px = Math.max(px, v.card.clientWidth);
  px = (px || 640) * (window.devicePixelRatio || 1);
  return Math.min(VIEW_WIDTH[1], Math.max(VIEW_WIDTH[0], Math.ceil(px / 64) * 64));
}

function onFrame(buf) {
  if (buf.byteLength < 4) return;
  const n = new DataView(buf).getUint32(0);
  let head;
  try {
    head = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
  } catch (_) { return; }
  const v = viewCard(head.camera);
  const frame = { head, jpeg: new Blob([new Uint8Array(buf, 4 + n)], { type: "image/jpeg" }) };
  if (v.busy) { v.pending = frame; return; }  // one decode at a time; the newest waits
  showFrame(v, frame);
}

function viewCard(name) {
  let v = S.views.get(name);
  if (v) return v;
  const card = document.createElement("figure");
  card.className = "view";
  card.dataset.camera = name;
  // one canvas holds the frame and the fields drawn on it: one layer painted per frame
  const canvas = document.createElement("canvas");
  canvas.setAttribute("role", "img");
  canvas.setAttribute("aria-label", `camera ${name}`);
  const label = document.createElement("figcaption");
  label.className = "label";
  // the label's parts, written only when they change (no layout work per frame beyond that)
  const parts = [text("b", name), text("span", ""), text("span", ""), text("span", "", "fields")];
  label.append(...parts);
  card.append(canvas, label);
  $("views").append(card);
  v = { card, canvas, label, parts, counter: -1, shownMeta: null, bitmap: null, busy: false,
        pending: null };
  S.views.set(name, v);
  // a new card changes the layout: frames at the width the views now have
  requestAnimationFrame(() => { if (S.fps && frameWidth() !== S.frameWidth) subscribe(); });
  return v;
}

async function showFrame(v, { head, jpeg }) {
  v.busy = true;
  try {
    const bitmap = await createImageBitmap(jpeg).catch(() => null);  // off the page's thread
    if (!bitmap) return;
    if (v.bitmap) v.bitmap.close();
    v.bitmap = bitmap;
    v.counter = head.counter;
    v.shownMeta = head;  // the overlay found in this very frame
    repaint(v);
    S.shown += 1;
  } finally {
    v.busy = false;
  }
  const secs = (performance.now() - S.shownSince) / 1000;
  if (secs >= 2) {
    $("viewrate").textContent = `${(S.shown / secs).toFixed(1)} images/s shown`;
    S.shown = 0;
    S.shownSince = performance.now();
  }
  if (v.pending) {  // a frame that came while this one decoded
    const next = v.pending;
    v.pending = null;
    showFrame(v, next);
  }
}

// The frames of one round arrive within a few milliseconds of each other: they are painted
// together at the next animation frame, so the page is composited once a round, not once
// a view (measured: Chromium's CPU per round, docs/console.md).
const dirty = new Set();

function repaint(v) {
  if (!dirty.size) requestAnimationFrame(paintDirty);
  dirty.add(v);
}

function paintDirty() {
  for (const v of dirty) {
    drawView(v);
    const head = v.shownMeta;
    v.card.dataset.counter = String(head.counter);
    const fields = head.fields.map((f) => `${f.name} (${f.corners})`).join(", ") || "no field";
    const words = [`#${head.counter}`, `${head.width}x${head.height}`, fields];
    words.forEach((w, i) => { if (v.parts[i + 1].textContent !== w) v.parts[i + 1].textContent = w; });
  }
  dirty.clear();
}

function text(tag, content, cls) {
  const e = document.createElement(tag);
  e.textContent = content;
  if (cls) e.className = cls;
  return e;
}

const COLOURS = { robot: "#4fc3f7", opener: "#ffd54f", effector: "#81c784" };

function drawView(v) {
  const { canvas, bitmap } = v;
  const meta = v.shownMeta;
  if (!bitmap) return;
  const dpr = window.devicePixelRatio || 1;
  const w = Math.max(1, Math.round(v.card.clientWidth * dpr));
  const h = Math.max(1, Math.round(w * bitmap.height / bitmap.width));
  if (canvas.width !== w || canvas.height !== h) {
    canvas.width = w;  // reallocates: only when the shown size changed
    canvas.height = h;
  }
  const g = canvas.getContext("2d");
  g.drawImage(bitmap, 0, 0, w, h);
  if (!S.overlay || !meta) return;
  const k = w / meta.width;  // frame pixels -> canvas pixels
  g.lineWidth = 2 * dpr;
  for (const f of meta.fields) {
    g.strokeStyle = COLOURS[f.name] || "#ff80ab";
    if (f.hull.length > 2) {
      g.beginPath();
      f.hull.forEach(([x, y], i) => (i ? g.lineTo(x * k, y * k) : g.moveTo(x * k, y * k)));
      g.closePath();
      g.stroke();
    }
    if (f.axes) {
      const [o, ...tips] = f.axes;
      ["#ff5252", "#69f0ae", "#448aff"].forEach((c, i) => {
        g.strokeStyle = c;
        g.beginPath();
        g.moveTo(o[0] * k, o[1] * k);
        g.lineTo(tips[i][0] * k, tips[i][1] * k);
        g.stroke();
      });
      g.fillStyle = COLOURS[f.name] || "#ff80ab";
      g.font = `${13 * dpr}px system-ui, sans-serif`;
      g.fillText(f.name, o[0] * k + 6 * dpr, o[1] * k - 6 * dpr);
    }
  }
}

// -- wiring ---------------------------------------------------------------------------------
function wire() {
  $("login").addEventListener("submit", (ev) => {
    ev.preventDefault();
    signIn($("token").value.trim());
  });
  $("signout").addEventListener("click", () => signOut(""));
  $("estop").addEventListener("click", () =>
    command("/estop", { reason: "console e-stop" }, "E-stop"));
  for (const b of document.querySelectorAll("button[data-post]")) {
    b.addEventListener("click", () => command(b.dataset.post, undefined, b.textContent));
  }
  $("select").addEventListener("click", async () => {
    const pick = document.querySelector("input[name=target]:checked");
    if (!pick) { notify("choose a target in the list first", "error"); return; }
    await command("/targets/select", { name: pick.value }, `Select ${pick.value}`);
  });
  $("planned").addEventListener("click", async () => {
    const r = await api("GET", "/targets/planned");
    if (!r.ok) { notify(`no planned targets: ${detail(r)}`, "error"); return; }
    if (!r.data.targets.length) { notify("this cell has no planned targets", "error"); return; }
    registerTargets(r.data.targets, `Register ${r.data.targets.length} planned targets`);
  });
  $("import").addEventListener("change", async (ev) => {
    const file = ev.target.files[0];
    ev.target.value = "";
    if (!file) return;
    let doc;
    try { doc = JSON.parse(await file.text()); } catch (err) {
      notify(`${file.name}: not JSON (${err.message})`, "error");
      return;
    }
    const targets = Array.isArray(doc) ? doc : doc.targets;
    if (!Array.isArray(targets)) {
      notify(`${file.name}: expected {"targets": [...]} or a list of targets`, "error");
      return;
    }
    registerTargets(targets, `Import ${file.name}`);
  });
  $("fps").addEventListener("change", (ev) => {
    S.fps = Number(ev.target.value);
    subscribe();
  });
  $("overlay").addEventListener("change", (ev) => {
    S.overlay = ev.target.checked;
    for (const v of S.views.values()) drawView(v);
  });
  window.addEventListener("resize", () => {
    for (const v of S.views.values()) drawView(v);
    if (S.fps && frameWidth() !== S.frameWidth) subscribe();  // frames at the new width
  });
  // a hidden tab shows nothing: no frames sent to it; shown again, they flow at once
  document.addEventListener("visibilitychange", subscribe);
  setInterval(() => { if (S.token) refreshTargets(); }, 3000);
  if (S.token) signIn(S.token);
}

wire();
