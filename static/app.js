// floornav dashboard: plain JavaScript, no build step, no network beyond the daemon.
//
// Sockets: /ws/telemetry (status JSON ~10 Hz), /ws/video (a JSON header, then the JPEG),
// /ws/control (teleop, e-stop, start/stop). REST for the rest.
// Browsers cannot set headers on WebSockets, so the token travels as the subprotocol
// "bearer.<token>" next to "floornav" (the server selects "floornav"). The control
// socket admits a client without the token too; such a client may only stop and e-stop.
//
// Stopping is always possible: the E-STOP is the first element of the page, its header
// stays above every dialog (dialogs are opened with show(), never showModal(), which
// would make the rest of the page inert), it needs no token, and the space bar fires it
// from any focus but a text field.
//
// No inline scripts, handlers or style attributes: the page runs under
// Content-Security-Policy default-src 'self' (element.style from here is allowed).
"use strict";

const TOKEN_KEY = "floornav.token";
const TELEOP_HZ = 15;
const MAP_PERIOD_MS = 500;
const GAMEPAD_DEADZONE = 0.15;
const PAD_DEADZONE = 0.18;
const LATENCY_WINDOW = 120;
const ESTOP_ACK_TIMEOUT_MS = 250; // no ack over the socket by then: POST it as well

const $ = (id) => document.getElementById(id);

// Exposed for the browser tests and for curious people in the console.
const stats = {
  frames: 0,
  latenciesMs: [],
  serverMs: [],
  lastLatencyMs: null,
  status: null,
  controlReplies: [],
  me: null,
  authenticated: false,
  estops: [], // {via: "socket" | "post", wall_ms: when it was sent (epoch ms)}
  teleopSent: 0,
  zeroSentWallMs: null, // when the last let-go zero went out (epoch ms)
  session: null, // HTTP status of the last POST /api/session
};
window.floornav = stats;

// -- token ------------------------------------------------------------------------------

function takeTokenFromUrl() {
  const url = new URL(window.location.href);
  const token = url.searchParams.get("token");
  if (token) {
    localStorage.setItem(TOKEN_KEY, token);
    url.searchParams.delete("token");
    // Keep the token out of the address bar, history and screenshots.
    history.replaceState(null, "", url.pathname + url.search + url.hash);
  }
}

function token() {
  return localStorage.getItem(TOKEN_KEY) || "";
}

function authHeaders() {
  const t = token();
  return t ? { Authorization: "Bearer " + t } : {};
}

function socketProtocols() {
  const t = token();
  return t ? ["floornav", "bearer." + t] : ["floornav"];
}

function socketUrl(path) {
  const scheme = window.location.protocol === "https:" ? "wss:" : "ws:";
  return scheme + "//" + window.location.host + path;
}

// -- dialogs: non-modal, below the header ----------------------------------------------

function updateScrim() {
  $("scrim").hidden = !document.querySelector("dialog[open]");
}

/** Open a dialog without making the page inert. ``focusEl``: what gets the focus (null:
 * nothing in the dialog, so the space bar still e-stops at once). */
function openDialog(id, focusEl) {
  const dialog = $(id);
  const before = document.activeElement;
  if (!dialog.open) dialog.show();
  updateScrim();
  if (focusEl) {
    focusEl.focus();
  } else if (dialog.contains(document.activeElement)) {
    // show() may have focused the first field: give it back.
    if (before && before !== document.body && !dialog.contains(before)) before.focus();
    else document.activeElement.blur();
  }
}

function closeDialog(id) {
  const dialog = $(id);
  if (dialog.open) dialog.close();
  updateScrim();
}

function closeOpenDialogs() {
  let closed = false;
  for (const dialog of document.querySelectorAll("dialog[open]")) {
    dialog.close();
    closed = true;
  }
  updateScrim();
  return closed;
}

function openTokenDialog(message, { focus = true } = {}) {
  $("token-message").textContent = message || "";
  $("token-message").className = message ? "message bad" : "message";
  $("token-input").value = token();
  openDialog("token-dialog", focus ? $("token-input") : null);
}

async function checkToken({ prompt = true } = {}) {
  if (!token()) return false;
  const reply = await api("GET", "/api/auth", undefined, { quiet401: true });
  if (reply.status === 401) {
    if (prompt) openTokenDialog("The saved token was refused; enter the daemon's current token.", { focus: false });
    return false;
  }
  return reply.ok;
}

/** The HttpOnly cookie that opens /viser/ (the 3D view), for a valid token. */
async function openSession() {
  if (!token()) return;
  const reply = await api("POST", "/api/session", undefined, { quiet401: true });
  stats.session = reply.status;
}

async function closeSession() {
  const reply = await api("DELETE", "/api/session", undefined, { quiet401: true });
  stats.session = reply.status;
}

// -- REST -------------------------------------------------------------------------------

async function api(method, path, body, options = {}) {
  const headers = { ...authHeaders() };
  if (body !== undefined) headers["Content-Type"] = "application/json";
  let response;
  try {
    response = await fetch(path, {
      method,
      headers,
      body: body === undefined ? undefined : JSON.stringify(body),
      cache: "no-store",
    });
  } catch (error) {
    return { ok: false, status: 0, data: { detail: "daemon unreachable: " + error.message } };
  }
  let data = null;
  const type = response.headers.get("Content-Type") || "";
  if (type.includes("application/json")) {
    data = await response.json().catch(() => null);
  }
  if (response.status === 401 && !options.quiet401) {
    openTokenDialog("That needs the API token.");
  }
  return { ok: response.ok, status: response.status, data, response };
}

function detailOf(reply) {
  if (reply.data && reply.data.detail) return String(reply.data.detail);
  if (reply.status) return "HTTP " + reply.status;
  return "no answer";
}

function showMessage(id, text, bad) {
  const el = $(id);
  el.textContent = text;
  el.className = bad ? "message bad" : "message";
}

// -- status -----------------------------------------------------------------------------

function fmt(value, digits = 0) {
  return value === null || value === undefined || Number.isNaN(value) ? "–" : Number(value).toFixed(digits);
}

function pad2(n) {
  return String(n).padStart(2, "0");
}

/** Wall time (epoch seconds) as the local HH:MM:SS. */
function clockTime(t) {
  if (typeof t !== "number") return "–";
  const d = new Date(t * 1000);
  return `${pad2(d.getHours())}:${pad2(d.getMinutes())}:${pad2(d.getSeconds())}`;
}

/** Write only what changed: telemetry comes ten times a second, and an unchanged
 * write still makes the browser lay the page out again. */
function setText(el, text) {
  if (el.textContent !== text) el.textContent = text;
}

function setCell(id, text, kind) {
  const el = $(id);
  setText(el, text);
  const className = kind || "";
  if (el.className !== className) el.className = className;
}

// When a stop carries no time of its own, the time this page first saw it.
const firstSeen = new Map();

function seenSince(key, active) {
  if (!active) {
    firstSeen.delete(key);
    return null;
  }
  if (!firstSeen.has(key)) firstSeen.set(key, Date.now() / 1000);
  return firstSeen.get(key);
}

function lastTransitionTo(s, state) {
  const list = s.transitions || [];
  for (let i = list.length - 1; i >= 0; i--) {
    if (list[i].to === state) return list[i].t;
  }
  return null;
}

/** One line of the stop panel: "<label> — HH:MM:SS · detail", or hidden (label null). */
function setStopLine(id, label, time, detail) {
  const line = $(id);
  if (label === null) {
    line.hidden = true;
    return;
  }
  line.hidden = false;
  const rest = (typeof time === "number" ? " — " + clockTime(time) : "") + (detail ? " · " + detail : "");
  const text = line.querySelector(".stop-text");
  if (text.textContent === label + rest) return;
  line.title = label + rest;
  const strong = document.createElement("b");
  strong.textContent = label;
  text.replaceChildren(strong, document.createTextNode(rest));
}

const PROTECTIVE_CAUSES = {
  link: "Uno link",
  camera: "camera",
  stale: "perception or map too old",
};

// A failed calibration stops autonomy; shown until autonomy runs again (a later
// status still naming it as the last stop does not bring it back).
let calibrationFailure = null;
let calibrationFailureDone = null; // the time of the failure autonomy has run after

/** What holds the robot, each with its reason and time. Returns a one-line summary of
 * the stop (null when nothing stops it) for the health table. */
function renderStops(s) {
  let stoppedBy = null;
  const last = s.last_stop;

  // (d) the e-stop, latched until reset.
  const estopped = s.state === "estopped" || Boolean(s.estop);
  const estopTime = estopped ? (lastTransitionTo(s, "estopped") ?? seenSince("estop", true)) : seenSince("estop", false);
  setStopLine("stop-estop", estopped ? "E-STOP latched" : null, estopTime,
    (s.estop || "e-stop") + " · motors at zero until Reset e-stop");
  if (estopped) stoppedBy = "e-stop: " + (s.estop || "latched");

  // (c) a latched fault.
  const fault = s.fault_latched || (s.fault ? { cause: null, reason: s.fault } : null);
  if (fault) {
    const faultTime = typeof fault.t === "number" ? fault.t : (lastTransitionTo(s, "fault") ?? seenSince("fault", true));
    setStopLine("stop-fault", "Fault latched" + (fault.cause ? ` (${fault.cause})` : ""), faultTime,
      fault.reason + " · motors held at zero: fix the cause, then Reset fault and Start");
    stoppedBy = stoppedBy || "fault: " + fault.reason;
  } else {
    seenSince("fault", false);
    setStopLine("stop-fault", null);
  }

  // (a) a protective stop (clears by itself) and (b) forward motion cut.
  const cause = s.stop_cause;
  const protective = cause && cause !== "fault" && cause !== "clearance" && cause !== "not_floor";
  if (protective) {
    const own = last && last.cause === cause && !last.latched ? last.t : null;
    const time = own ?? lastTransitionTo(s, "protective_stop") ?? seenSince("protective:" + cause, true);
    setStopLine("stop-protective", `Protective stop: ${PROTECTIVE_CAUSES[cause] || cause}`, time,
      (s.stop_reason || cause) + " · clears by itself");
    stoppedBy = stoppedBy || `protective stop (${cause}): ${s.stop_reason || ""}`;
  } else {
    for (const key of firstSeen.keys()) if (key.startsWith("protective:")) firstSeen.delete(key);
    setStopLine("stop-protective", null);
  }
  if (cause === "clearance") {
    const time = last && last.cause === "clearance" ? last.t : seenSince("clearance", true);
    // A map too old to judge holds forward motion too; its distance would be stale.
    const unknown = (s.stop_reason || "").startsWith("clearance unknown");
    const ahead = unknown ? "clearance unknown (map too old)"
      : typeof s.clearance_ahead_m === "number" ? fmt(s.clearance_ahead_m, 2) + " m ahead" : "too close";
    setStopLine("stop-blocked", "blocked: " + ahead, time,
      (s.stop_reason || "too little clearance") + " · turning and reversing still work");
    stoppedBy = stoppedBy || "blocked: " + ahead;
  } else if (cause === "not_floor") {
    const time = last && last.cause === "not_floor" ? last.t : seenSince("not_floor", true);
    setStopLine("stop-blocked", "blocked: safe zone is not floor", time, s.stop_reason || "");
    stoppedBy = stoppedBy || "blocked: safe zone is not floor";
  } else {
    seenSince("clearance", false);
    seenSince("not_floor", false);
    setStopLine("stop-blocked", null);
  }

  // (e) calibration failed (autonomy off), or no calibration at all.
  if (last && last.cause === "calibration" && last.t !== calibrationFailureDone) {
    calibrationFailure = { t: last.t, reason: last.reason };
  }
  if (s.autonomous && calibrationFailure) {
    calibrationFailureDone = calibrationFailure.t;
    calibrationFailure = null;
  }
  if (calibrationFailure) {
    const reason = calibrationFailure.reason.replace(/^calibration failed:\s*/i, "");
    setStopLine("stop-calibration", "Calibration failed", calibrationFailure.t,
      /autonomy/i.test(reason) ? reason : reason + " · autonomy off: start it again when ready");
    stoppedBy = stoppedBy || "a failed calibration (autonomy off)";
  } else if (s.calibration_problem && !s.calibration) {
    setStopLine("stop-calibration", "No floor calibration", seenSince("calibration", true),
      s.calibration_problem + " · autonomy off (teleop works)");
  } else {
    seenSince("calibration", false);
    setStopLine("stop-calibration", null);
  }

  // (f) the last stop of any kind.
  setStopLine("stop-last", last ? `last stop: ${last.cause}` : null, last ? last.t : null,
    last ? last.reason + (last.latched ? " (latched)" : "") : "");

  $("estop-reset").disabled = !estopped;
  return stoppedBy;
}

function renderStatus(s) {
  stats.status = s;
  const state = $("state");
  setText(state, s.state + (s.autonomous && s.state !== "running" ? " (autonomy on)" : ""));
  if (state.className !== "state state-" + s.state) state.className = "state state-" + s.state;

  const stoppedBy = renderStops(s);

  setText($("frame-age"), fmt(s.frame_age_ms));
  const cam = s.camera || {};
  setCell("h-camera", (cam.ok ? "ok" : cam.state || "?") + (cam.detail ? " · " + cam.detail : "") +
    (cam.description ? " · " + cam.description : ""), cam.ok ? "ok" : "bad");
  const ser = s.serial || {};
  setCell("h-serial", (ser.state || "?") + " · " + (ser.port || "") +
    " · reconnects " + fmt(ser.reconnects) + (ser.detail ? " · " + ser.detail : ""),
  ser.state === "connected" ? "ok" : "bad");
  setCell("h-fps", fmt(s.fps, 1) + " fps · frame age " + fmt(s.frame_age_ms) + " ms",
    s.frame_age_ms !== null && s.frame_age_ms < 300 ? "ok" : "warn");
  setCell("h-clearance", s.clearance_ahead_m === null ? "–" : fmt(s.clearance_ahead_m, 2) + " m",
    s.clearance_ahead_m !== null && s.clearance_ahead_m < 0.2 ? "warn" : "");
  const zoneMin = typeof s.zone_min_floor_confidence === "number" ? s.zone_min_floor_confidence : 0.5;
  const zoneLow = typeof s.zone_floor_confidence === "number" && s.zone_floor_confidence < zoneMin;
  // The map's geometry can know the zone is floor where colour doubts it (a threshold).
  const knownMin = typeof s.zone_min_known_floor === "number" ? s.zone_min_known_floor : 1;
  const zoneKnown = typeof s.zone_known_floor === "number" && s.zone_known_floor >= knownMin;
  const knownText = typeof s.zone_known_floor === "number"
    ? " · map knows " + fmt(s.zone_known_floor * 100) + " %" : "";
  setCell("h-zone", typeof s.zone_floor_confidence === "number"
    ? fmt(s.zone_floor_confidence * 100) + " %" + knownText +
      (zoneLow ? (zoneKnown ? " · floor by the map" : " · not floor (below " + fmt(zoneMin * 100) + " %)") : "")
    : "–", zoneLow && !zoneKnown ? "bad" : (typeof s.zone_floor_confidence === "number" ? (zoneLow ? "warn" : "ok") : ""));
  const estopped = s.state === "estopped";
  // What holds the robot now: the current stop's reason, else what the stop lines say
  // (a failed calibration leaves autonomy off without a protective stop).
  const holding = s.stop_reason || stoppedBy;
  setCell("h-stop", estopped ? "e-stop latched: " + (s.estop || "") : (holding || "none"),
    estopped ? "bad" : (holding ? "warn" : ""));
  const c = s.command;
  setCell("h-command", c ? `${fmt(c.v_m_s, 2)} m/s · ${fmt(c.omega_rad_s, 2)} rad/s · PWM ${c.left_pwm}/${c.right_pwm} · ${c.source}` : "none yet");
  setCell("h-calibration", s.calibration ? "reprojection RMS " + fmt(s.calibration.reprojection_rms_px, 2) + " px"
    : (s.calibration_problem || "none"), s.calibration ? "ok" : "warn");
  // Never "none" while something stops the robot: say what does.
  if (s.fault) setCell("h-fault", s.fault, "bad");
  else if (stoppedBy) setCell("h-fault", "not latched · stopped by " + stoppedBy, "warn");
  else setCell("h-fault", "none", "ok");
  const last = s.last_stop;
  setCell("h-last-stop", last ? `${last.cause}: ${last.reason} · ${clockTime(last.t)} (${fmt(last.age_s, 0)} s ago)` +
    (last.latched ? " · latched" : "") : "none yet", last && last.latched ? "bad" : "");
  setCell("h-estops", fmt(s.estops));

  const body = $("stages").tBodies[0];
  const stages = s.stage_ms || {};
  const names = Object.keys(stages).sort();
  while (body.rows.length > names.length) body.deleteRow(-1);
  names.forEach((name, i) => {
    const row = body.rows[i] || body.insertRow();
    if (row.cells.length === 0) {
      row.appendChild(document.createElement("th"));
      row.appendChild(document.createElement("td"));
    }
    setText(row.cells[0], name);
    setText(row.cells[1], fmt(stages[name], 2));
  });

  const p = s.pose || {};
  setText($("pose"), `${fmt(p.x_m, 2)}, ${fmt(p.y_m, 2)} m · ${fmt((p.theta_rad || 0) * 180 / Math.PI)}°`);
  setText($("distance"), fmt(s.distance_m, 2));
  const f = s.frontier;
  setText($("frontier"), f
    ? [f.goal_xy ? `goal ${fmt(f.goal_xy[0], 2)}, ${fmt(f.goal_xy[1], 2)} m` : "", f.reason, `${f.clusters} clusters`]
      .filter(Boolean).join(" · ")
    : "not searched yet");

  setText($("teleop-driver"), s.teleop_driver || "nobody");
  const other = s.teleop_driver && stats.me && s.teleop_driver !== stats.me;
  if (other) {
    $("takeover-box").hidden = false;
    $("takeover-text").textContent = s.teleop_driver + " is driving.";
  } else if (!teleop.refused) {
    $("takeover-box").hidden = true;
  }
  $("start").disabled = s.autonomous || estopped;
  $("stop").disabled = !s.autonomous;
}

function setLink(id, state, title) {
  const el = $(id);
  el.className = "dot " + state;
  if (title) el.title = title;
}

function setControlLink(state, title) {
  setLink("conn-control", state, title);
}

function connectTelemetry() {
  const ws = new WebSocket(socketUrl("/ws/telemetry"), socketProtocols());
  ws.onopen = () => setLink("conn-telemetry", "on");
  ws.onmessage = (event) => {
    try {
      renderStatus(JSON.parse(event.data));
    } catch (error) {
      console.error("bad telemetry", error);
    }
  };
  ws.onclose = () => {
    setLink("conn-telemetry", "off");
    $("state").textContent = "disconnected";
    $("state").className = "state state-unknown";
    setTimeout(connectTelemetry, 1000);
  };
}

// -- video ------------------------------------------------------------------------------

const video = { ws: null, header: null, url: null, arrivals: [], size: null };

function median(values) {
  if (!values.length) return null;
  const sorted = [...values].sort((a, b) => a - b);
  return sorted[Math.floor(sorted.length / 2)];
}

function connectVideo() {
  // ?ack=2: the daemon keeps at most two frames unacknowledged, so a slow phone gets
  // fewer but always the newest frames instead of a growing backlog.
  const ws = new WebSocket(socketUrl("/ws/video?ack=2"), socketProtocols());
  ws.binaryType = "blob";
  video.ws = ws;
  ws.onopen = () => setLink("conn-video", "on");
  ws.onmessage = (event) => {
    if (typeof event.data === "string") {
      video.header = JSON.parse(event.data);
      return;
    }
    const header = video.header;
    video.header = null;
    if (!header) return;
    showFrame(event.data, header, ws);
  };
  ws.onclose = () => {
    setLink("conn-video", "off");
    setTimeout(connectVideo, 1000);
  };
}

function ackFrame(ws, seq) {
  if (ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify({ type: "ack", seq }));
}

function showFrame(blob, header, ws) {
  const img = $("video");
  const url = URL.createObjectURL(blob);
  const previous = video.url;
  video.url = url;
  img.onerror = () => {
    ackFrame(ws, header.seq);
    URL.revokeObjectURL(url);
  };
  img.onload = () => {
    ackFrame(ws, header.seq);
    // Glass to browser: the frame is decoded and on screen now. Comparable only when
    // the robot's and this device's clocks agree (NTP); same machine in the tests.
    const latency = Date.now() - header.capture_wall_s * 1000;
    stats.frames += 1;
    stats.lastLatencyMs = latency;
    stats.latenciesMs.push(latency);
    if (stats.latenciesMs.length > LATENCY_WINDOW) stats.latenciesMs.shift();
    // The daemon's share (capture to send, one clock): the rest is network and browser.
    stats.serverMs.push((header.sent_wall_s - header.capture_wall_s) * 1000);
    if (stats.serverMs.length > LATENCY_WINDOW) stats.serverMs.shift();
    $("latency-server").textContent = fmt(median(stats.serverMs));
    $("latency").textContent = fmt(latency);
    $("latency-p50").textContent = fmt(median(stats.latenciesMs));
    $("video-placeholder").hidden = true;
    const now = performance.now();
    video.arrivals.push(now);
    while (video.arrivals.length && now - video.arrivals[0] > 2000) video.arrivals.shift();
    $("video-fps").textContent = fmt(video.arrivals.length / 2, 1);
    $("video-method").textContent = header.method ? "· " + header.method : "";
    if (previous) URL.revokeObjectURL(previous);
    if (!video.size || video.size[0] !== img.naturalWidth || video.size[1] !== img.naturalHeight) {
      video.size = [img.naturalWidth, img.naturalHeight];
      layoutZoneSvg();
    }
  };
  img.src = url;
}

// -- map --------------------------------------------------------------------------------

let mapUrl = null;

async function refreshMap() {
  const size = $("map-size").value;
  const side = Math.min(900, Math.max(240, Math.round($("map").clientWidth * (window.devicePixelRatio || 1))));
  try {
    const response = await fetch(`/api/map.png?size_m=${size}&px=${side}`, { headers: authHeaders(), cache: "no-store" });
    if (response.ok && (response.headers.get("Content-Type") || "").startsWith("image/")) {
      const url = URL.createObjectURL(await response.blob());
      const previous = mapUrl;
      mapUrl = url;
      $("map").onload = () => { if (previous) URL.revokeObjectURL(previous); };
      $("map").src = url;
      $("map-note").hidden = true;
    } else {
      const data = await response.json().catch(() => ({}));
      $("map-note").hidden = false;
      $("map-note").textContent = data.detail || "no map (HTTP " + response.status + ")";
    }
  } catch (error) {
    $("map-note").hidden = false;
    $("map-note").textContent = "map unavailable: " + error.message;
  }
  setTimeout(refreshMap, document.hidden ? 2000 : MAP_PERIOD_MS);
}

// -- control socket ---------------------------------------------------------------------

const control = { ws: null, nextId: 1, retryMs: 500, retryTimer: null, authenticated: false, pendingEstops: new Map() };

function connectControl() {
  clearTimeout(control.retryTimer);
  control.retryTimer = null;
  let ws;
  try {
    ws = new WebSocket(socketUrl("/ws/control"), socketProtocols());
  } catch (error) {
    console.error("control socket", error);
    scheduleControlRetry();
    return;
  }
  control.ws = ws;
  control.authenticated = false;
  stats.authenticated = false;
  ws.onopen = () => {
    control.retryMs = 500;
    setControlLink("limited", "control connected; waiting for the greeting");
  };
  ws.onmessage = (event) => onControlMessage(ws, event);
  ws.onclose = () => onControlClosed(ws);
}

function onControlMessage(ws, event) {
  let reply;
  try {
    reply = JSON.parse(event.data);
  } catch (error) {
    return;
  }
  stats.controlReplies.push(reply);
  if (stats.controlReplies.length > 50) stats.controlReplies.shift();
  if (reply.id !== undefined && control.pendingEstops.has(reply.id)) {
    clearTimeout(control.pendingEstops.get(reply.id));
    control.pendingEstops.delete(reply.id);
  }
  if (reply.type === "hello") {
    stats.me = reply.driver;
    // An older daemon admitted only clients with the token and said nothing about it.
    control.authenticated = reply.authenticated !== false;
    stats.authenticated = control.authenticated;
    $("me").textContent = reply.driver + (control.authenticated ? "" : " (stop only)");
    setControlLink(control.authenticated ? "on" : "limited",
      control.authenticated ? "control connected" : "control connected without the token: stop and e-stop only");
    updatePadState();
  } else if (reply.type === "error") {
    showMessage("control-message", reply.detail, true);
    if (/teleop is held by/.test(reply.detail)) {
      teleop.refused = true;
      $("takeover-box").hidden = false;
      $("takeover-text").textContent = reply.detail;
    }
  } else if (reply.type === "ack" && reply.detail === "estop") {
    showMessage("control-message", "E-STOP latched · state " + reply.state, true);
  } else if (reply.type === "ack" && !["teleop", "release"].includes(reply.detail)) {
    showMessage("control-message", reply.detail + ": ok · state " + reply.state, false);
  }
}

function onControlClosed(ws) {
  if (control.ws !== ws) return; // replaced on purpose
  control.ws = null;
  control.authenticated = false;
  stats.authenticated = false;
  // Whatever was driving from here stops (the daemon releases this socket's teleop).
  stopDrivingLocally();
  for (const [id, timer] of control.pendingEstops) {
    clearTimeout(timer);
    control.pendingEstops.delete(id);
    estopByPost("dashboard (socket closed)");
  }
  setControlLink("off", "control disconnected");
  updatePadState();
  scheduleControlRetry();
}

function scheduleControlRetry() {
  clearTimeout(control.retryTimer);
  control.retryMs = Math.min(5000, control.retryMs * 2);
  control.retryTimer = setTimeout(connectControl, control.retryMs);
}

/** Reconnect at once (the token changed). */
function reconnectControl() {
  const old = control.ws;
  control.ws = null;
  stopDrivingLocally();
  if (old) old.close();
  control.retryMs = 500;
  connectControl();
}

/** Send a control message; returns its id, or null if the socket is not open. */
function sendControl(message) {
  const ws = control.ws;
  if (!ws || ws.readyState !== WebSocket.OPEN) return null;
  const id = control.nextId++;
  ws.send(JSON.stringify({ ...message, id }));
  return id;
}

// -- e-stop -----------------------------------------------------------------------------

/** Latch the e-stop: over the control socket when it is open (fastest), else (or when
 * the socket does not acknowledge within ESTOP_ACK_TIMEOUT_MS) with POST /api/estop,
 * which needs no token. Idempotent. */
function estop(source) {
  const id = sendControl({ type: "estop" });
  if (id !== null) {
    stats.estops.push({ via: "socket", wall_ms: performance.timeOrigin + performance.now() });
    control.pendingEstops.set(id, setTimeout(() => {
      control.pendingEstops.delete(id);
      estopByPost(source + " (socket silent)");
    }, ESTOP_ACK_TIMEOUT_MS));
  } else {
    estopByPost(source);
  }
  stopDrivingLocally();
  showMessage("control-message", "E-STOP sent…", true);
}

async function estopByPost(source) {
  stats.estops.push({ via: "post", wall_ms: performance.timeOrigin + performance.now() });
  const headers = { "Content-Type": "application/json", ...authHeaders() };
  try {
    const response = await fetch("/api/estop", {
      method: "POST",
      headers,
      body: JSON.stringify({ source: "dashboard " + source }),
      cache: "no-store",
      keepalive: true,
    });
    showMessage("control-message", response.ok ? "E-STOP latched" : "e-stop: HTTP " + response.status, true);
  } catch (error) {
    showMessage("control-message", "E-STOP could not reach the daemon: " + error.message, true);
  }
}

let lastPointerEstopMs = -1e9;

function onEstopPointerDown(event) {
  if (event.pointerType === "mouse" && event.button !== 0) return;
  // On the press, not the release: a click needs the finger to come up on the button.
  lastPointerEstopMs = performance.now();
  estop("E-STOP button");
}

function onEstopClick() {
  // Keyboard activation (Enter), or a click whose pointerdown we did not see.
  if (performance.now() - lastPointerEstopMs < 1000) return;
  estop("E-STOP button");
}

// -- teleop: keys, touch pad, gamepad -----------------------------------------------------

const teleop = {
  keys: new Set(),
  touch: { v: 0, w: 0, pointerId: null },
  gamepad: { v: 0, w: 0 },
  gamepadLatched: false, // after a stop: the stick must come back to neutral first
  active: false,
  takeOver: false,
  refused: false,
  warned: false,
};

function keyCommand() {
  const k = teleop.keys;
  const speed = Number($("speed").value);
  const turn = Number($("turn").value);
  const forward = (k.has("up") ? 1 : 0) - (k.has("down") ? 1 : 0);
  const left = (k.has("left") ? 1 : 0) - (k.has("right") ? 1 : 0);
  return { v: forward * speed, w: left * turn };
}

function teleopCommand() {
  const key = keyCommand();
  if (key.v !== 0 || key.w !== 0) return key;
  if (teleop.touch.pointerId !== null) return teleop.touch;
  return teleop.gamepad;
}

/** Send the current hand command (every 1/TELEOP_HZ s, and at once on any change): the
 * keyboard, the touch pad and the gamepad share this path to the control socket. */
function teleopTick() {
  const { v, w } = teleopCommand();
  const moving = v !== 0 || w !== 0;
  if (moving) {
    if (!control.authenticated) {
      if (!teleop.warned) {
        teleop.warned = true;
        showMessage("control-message", control.ws ? "Driving needs the token (Token button above)."
          : "Not connected to the robot.", true);
      }
      return;
    }
    teleop.active = true;
    if (sendControl({ type: "teleop", v_m_s: round3(v), omega_rad_s: round3(w), take_over: teleop.takeOver }) !== null) {
      stats.teleopSent += 1;
    }
  } else if (teleop.active) {
    // Let go: an explicit zero first (stops at once), then hand teleop back.
    teleop.active = false;
    teleop.takeOver = false;
    sendControl({ type: "teleop", v_m_s: 0, omega_rad_s: 0 });
    stats.zeroSentWallMs = performance.timeOrigin + performance.now();
    sendControl({ type: "release" });
  }
}

function round3(x) {
  return Math.round(x * 1000) / 1000;
}

/** Forget every held key, the pad's finger and the gamepad's stick, and send the zero. */
function stopDrivingLocally() {
  for (const name of teleop.keys) $("key-" + name).classList.remove("active");
  teleop.keys.clear();
  releasePad(false);
  teleop.gamepad = { v: 0, w: 0 };
  teleop.gamepadLatched = true;
  teleopTick();
}

const KEY_NAMES = {
  ArrowUp: "up", KeyW: "up",
  ArrowDown: "down", KeyS: "down",
  ArrowLeft: "left", KeyA: "left",
  ArrowRight: "right", KeyD: "right",
};
const NON_TEXT_INPUTS = new Set(["range", "button", "submit", "reset", "checkbox", "radio", "color", "file", "image"]);

/** A field where the space bar types: there it does not e-stop. */
function isTextField(el) {
  if (!el || !el.tagName) return false;
  if (el.isContentEditable) return true;
  if (el.tagName === "TEXTAREA") return true;
  if (el.tagName === "INPUT") return !NON_TEXT_INPUTS.has((el.type || "text").toLowerCase());
  return false;
}

function isSpace(event) {
  return event.code === "Space" || event.key === " ";
}

/** Capture phase on window: runs before any focused control sees the key. */
function onKeyDown(event) {
  const target = event.target;
  const text = isTextField(target);
  if (isSpace(event)) {
    if (text) return;
    // A focused button would click, a select would open, the page would scroll.
    event.preventDefault();
    if (!event.repeat) estop("space bar");
    return;
  }
  if (event.key === "Escape") {
    if (closeOpenDialogs()) event.preventDefault();
    return;
  }
  const name = KEY_NAMES[event.code];
  if (!name || text || event.ctrlKey || event.metaKey || event.altKey) return;
  // The safe-zone editor's sliders keep their arrow keys; the speed sliders do not
  // (arrows after touching them drive the robot, not the slider).
  if (event.code.startsWith("Arrow") && target && target.closest && target.closest("#zone-sliders")) return;
  event.preventDefault();
  // A key still held after an e-stop or a focus loss repeats: it does not start again.
  if (event.repeat || teleop.keys.has(name)) return;
  teleop.keys.add(name);
  teleop.warned = false;
  $("key-" + name).classList.add("active");
  teleopTick(); // do not wait for the next tick to start moving
}

function onKeyUp(event) {
  if (isSpace(event)) {
    if (!isTextField(event.target)) event.preventDefault(); // no click on a focused button
    return;
  }
  const name = KEY_NAMES[event.code];
  if (!name || !teleop.keys.has(name)) return;
  teleop.keys.delete(name);
  $("key-" + name).classList.remove("active");
  teleopTick();
}

// -- touch pad ----------------------------------------------------------------------------

function updatePadState() {
  $("pad").classList.toggle("disabled", !control.authenticated);
}

function padVector(event) {
  const rect = $("pad").getBoundingClientRect();
  const r = rect.width / 2;
  let dx = (event.clientX - (rect.left + r)) / r;
  let dy = (event.clientY - (rect.top + rect.height / 2)) / r;
  const magnitude = Math.hypot(dx, dy);
  if (magnitude > 1) {
    dx /= magnitude;
    dy /= magnitude;
  }
  return { dx, dy, r };
}

function padAxis(x) {
  const magnitude = Math.abs(x);
  if (magnitude < PAD_DEADZONE) return 0;
  return Math.sign(x) * Math.min(1, (magnitude - PAD_DEADZONE) / (1 - PAD_DEADZONE));
}

function onPadDown(event) {
  if (event.pointerType === "mouse" && event.button !== 0) return;
  if (teleop.touch.pointerId !== null) return; // one finger drives
  event.preventDefault();
  teleop.touch.pointerId = event.pointerId;
  try {
    $("pad").setPointerCapture(event.pointerId);
  } catch (error) {
    // the pointer is gone already: its pointerup/cancel follows
  }
  $("pad").classList.add("active");
  teleop.warned = false;
  onPadMove(event);
  teleopTick();
}

function onPadMove(event) {
  if (event.pointerId !== teleop.touch.pointerId) return;
  const { dx, dy, r } = padVector(event);
  $("pad-knob").style.transform = `translate(${(dx * r * 0.75).toFixed(1)}px, ${(dy * r * 0.75).toFixed(1)}px)`;
  teleop.touch.v = -padAxis(dy) * Number($("speed").value);
  teleop.touch.w = -padAxis(dx) * Number($("turn").value);
}

function onPadUp(event) {
  if (event.pointerId !== teleop.touch.pointerId) return;
  releasePad(true);
}

/** The finger is off the pad: zero at once (``send``), then the release. */
function releasePad(send) {
  const id = teleop.touch.pointerId;
  teleop.touch = { v: 0, w: 0, pointerId: null };
  const pad = $("pad");
  if (id !== null && pad.hasPointerCapture(id)) pad.releasePointerCapture(id);
  pad.classList.remove("active");
  $("pad-knob").style.transform = "";
  if (send) teleopTick();
}

// -- gamepad ----------------------------------------------------------------------------

function deadzone(x) {
  const magnitude = Math.abs(x);
  if (magnitude < GAMEPAD_DEADZONE) return 0;
  return Math.sign(x) * (magnitude - GAMEPAD_DEADZONE) / (1 - GAMEPAD_DEADZONE);
}

let padEstopWasPressed = false;
let gamepadPolling = false;

/** Poll the gamepad every animation frame, only while one is connected: an idle
 * requestAnimationFrame loop would keep the page drawing 60 frames a second. */
function startGamepadPolling() {
  if (gamepadPolling) return;
  gamepadPolling = true;
  requestAnimationFrame(pollGamepad);
}

function pollGamepad() {
  const pads = navigator.getGamepads ? Array.from(navigator.getGamepads()).filter(Boolean) : [];
  const pad = pads[0];
  if (!pad) {
    teleop.gamepad = { v: 0, w: 0 };
    $("gamepad-status").textContent = "no gamepad";
    gamepadPolling = false;
    teleopTick(); // unplugged while driving: the zero goes out now
    return;
  }
  const v = -deadzone(pad.axes[1] || 0) * Number($("speed").value);
  const w = -deadzone(pad.axes[0] || 0) * Number($("turn").value);
  if (teleop.gamepadLatched && v === 0 && w === 0) teleop.gamepadLatched = false;
  teleop.gamepad = teleop.gamepadLatched ? { v: 0, w: 0 } : { v, w };
  $("gamepad-status").textContent = `gamepad: ${pad.id.slice(0, 40)} · B = e-stop`;
  const estopPressed = Boolean(pad.buttons[1] && pad.buttons[1].pressed);
  if (estopPressed && !padEstopWasPressed) estop("gamepad");
  padEstopWasPressed = estopPressed;
  requestAnimationFrame(pollGamepad);
}

// -- commands ---------------------------------------------------------------------------

async function resetEstop() {
  const reply = await api("POST", "/api/estop/reset");
  showMessage("control-message", reply.ok ? "e-stop reset" : detailOf(reply), !reply.ok);
}

async function resetFault() {
  const reply = await api("POST", "/api/fault/reset");
  showMessage("control-message", reply.ok ? "fault reset: start again when ready" : detailOf(reply), !reply.ok);
}

async function startExploring() {
  const reply = await api("POST", "/api/start");
  showMessage("control-message", reply.ok ? "exploring" : "start refused: " + detailOf(reply), !reply.ok);
}

async function stopExploring() {
  const reply = await api("POST", "/api/stop");
  showMessage("control-message", reply.ok ? "stopped" : detailOf(reply), !reply.ok);
}

// -- calibration wizard -----------------------------------------------------------------

function calibRequest() {
  return {
    pattern: $("c-pattern").value.trim(),
    square_m: Number($("c-square").value),
    board_x_m: Number($("c-x").value),
    board_y_m: Number($("c-y").value),
    board_yaw_rad: Number($("c-yaw").value),
  };
}

function calibError(text) {
  const el = $("calib-error");
  el.hidden = !text;
  el.textContent = text || "";
}

async function calibDetect() {
  calibError("");
  $("calib-result").hidden = true;
  $("calib-canvas").hidden = true;
  const pattern = $("c-pattern").value.trim();
  if (!/^[0-9]{1,2}x[0-9]{1,2}$/.test(pattern)) {
    calibError("The pattern is inner corners as COLSxROWS, e.g. 9x6.");
    return;
  }
  $("calib-info").textContent = "looking for the board…";
  let response;
  try {
    response = await fetch(`/api/calibrate/preview?pattern=${encodeURIComponent(pattern)}`, { headers: authHeaders(), cache: "no-store" });
  } catch (error) {
    calibError("daemon unreachable: " + error.message);
    return;
  }
  if (!response.ok) {
    const data = await response.json().catch(() => ({}));
    calibError(`${response.status}: ${data.detail || "preview failed"}`);
    $("calib-info").textContent = "";
    return;
  }
  const found = Number(response.headers.get("X-Chessboard-Corners") || 0);
  const img = $("calib-preview");
  img.src = URL.createObjectURL(await response.blob());
  img.hidden = false;
  $("calib-info").textContent = found > 0
    ? `${found} corners found: calibrate if they sit on the board's inner corners.`
    : `No ${pattern} board found in this frame: check the pattern (inner corners), the lighting, and that the whole board is in view.`;
}

async function calibAccept() {
  calibError("");
  $("calib-info").textContent = "calibrating…";
  $("calib-accept").disabled = true;
  const reply = await api("POST", "/api/calibrate", calibRequest());
  $("calib-accept").disabled = false;
  if (!reply.ok) {
    $("calib-info").textContent = "";
    // The daemon says "calibration failed: <why>" itself (HTTP 409); other 409s are
    // refusals in the current state (e-stop latched, no recent frame).
    const detail = detailOf(reply);
    const why = /^calibration failed/i.test(detail) ? ""
      : reply.status === 409 ? "Refused now: " : reply.status === 422 ? "Invalid request: " : "Error: ";
    const text = why + detail;
    calibError(`${text.charAt(0).toUpperCase()}${text.slice(1)} (HTTP ${reply.status})`);
    return;
  }
  const r = reply.data;
  $("calib-info").textContent = r.saved_to ? "Saved to " + r.saved_to + "; the map starts afresh." : "Preview only: not applied (save to use it).";
  const body = $("calib-result").tBodies[0];
  body.replaceChildren();
  for (const [name, value] of [
    ["reprojection RMS", fmt(r.reprojection_rms_px, 3) + " px"],
    ["ground RMS", fmt(r.ground_rms_m * 1000, 1) + " mm"],
    ["inliers", `${r.inliers} of ${r.points}`],
  ]) {
    const row = body.insertRow();
    row.appendChild(document.createElement("th")).textContent = name;
    row.insertCell().textContent = value;
  }
  $("calib-result").hidden = false;
  drawCorners(r.corners_px, r.image_size);
}

function drawCorners(corners, size) {
  const canvas = $("calib-canvas");
  if (!corners || !corners.length || !size) return;
  canvas.width = size[0];
  canvas.height = size[1];
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  ctx.strokeStyle = "#00e676";
  ctx.lineWidth = 2;
  corners.forEach(([u, v], i) => {
    ctx.beginPath();
    ctx.arc(u, v, i === 0 ? 7 : 4, 0, 2 * Math.PI);
    ctx.stroke();
  });
  canvas.hidden = false;
}

// -- safe-zone editor -------------------------------------------------------------------

const ZONE_KEYS = ["bottom_left_x_frac", "bottom_right_x_frac", "top_left_x_frac", "top_right_x_frac", "top_y_frac", "bottom_y_frac"];
const zone = { saved: null, draft: null, dragging: null, pointerId: null, box: { w: 1000, h: 750 } };

async function loadZone() {
  const reply = await api("GET", "/api/config", undefined, { quiet401: true });
  if (reply.ok && reply.data) {
    const config = reply.data.config || reply.data;
    const sz = config.perception && config.perception.safe_zone;
    if (sz) {
      zone.saved = { ...sz };
      zone.draft = { ...sz };
      renderZone();
    }
  } else {
    showMessage("zone-message", "cannot read the safe zone: " + detailOf(reply), true);
  }
}

function buildZoneSliders() {
  const holder = $("zone-sliders");
  for (const key of ZONE_KEYS) {
    const label = document.createElement("label");
    label.textContent = key.replace("_frac", "").replaceAll("_", " ");
    const input = document.createElement("input");
    input.type = "range";
    input.min = "0";
    input.max = "1";
    input.step = "0.01";
    input.id = "zone-" + key;
    input.addEventListener("input", () => {
      if (!zone.draft) return;
      zone.draft[key] = Number(input.value);
      renderZone();
    });
    const out = document.createElement("output");
    out.id = "zone-out-" + key;
    label.append(input, out);
    holder.appendChild(label);
  }
}

/** Put the SVG exactly over the image's content box (the image is letterboxed with
 * object-fit: contain), in CSS pixels, so fractions of the SVG are fractions of the
 * camera image and the handles stay round. */
function layoutZoneSvg() {
  const svg = $("zone-svg");
  const wrap = $("video-wrap");
  const W = wrap.clientWidth;
  const H = wrap.clientHeight;
  if (!W || !H) return;
  const [iw, ih] = video.size && video.size[0] ? video.size : [4, 3];
  const scale = Math.min(W / iw, H / ih);
  const w = iw * scale;
  const h = ih * scale;
  svg.style.left = ((W - w) / 2).toFixed(1) + "px";
  svg.style.top = ((H - h) / 2).toFixed(1) + "px";
  svg.style.width = w.toFixed(1) + "px";
  svg.style.height = h.toFixed(1) + "px";
  svg.setAttribute("viewBox", `0 0 ${w.toFixed(1)} ${h.toFixed(1)}`);
  zone.box = { w, h };
  renderZone();
}

function zoneCorners(z) {
  const { w, h } = zone.box;
  return {
    bl: [z.bottom_left_x_frac * w, z.bottom_y_frac * h],
    br: [z.bottom_right_x_frac * w, z.bottom_y_frac * h],
    tr: [z.top_right_x_frac * w, z.top_y_frac * h],
    tl: [z.top_left_x_frac * w, z.top_y_frac * h],
  };
}

function renderZone() {
  const z = zone.draft;
  if (!z) return;
  const c = zoneCorners(z);
  $("zone-poly").setAttribute("points", ["bl", "br", "tr", "tl"].map((k) => c[k].map((x) => x.toFixed(1)).join(",")).join(" "));
  for (const handle of document.querySelectorAll("#zone-svg .handle")) {
    const [x, y] = c[handle.dataset.corner];
    handle.setAttribute("cx", x.toFixed(1));
    handle.setAttribute("cy", y.toFixed(1));
  }
  for (const key of ZONE_KEYS) {
    $("zone-" + key).value = z[key];
    $("zone-out-" + key).textContent = Number(z[key]).toFixed(2);
  }
}

function svgFraction(event) {
  const rect = $("zone-svg").getBoundingClientRect();
  const clamp = (x) => Math.min(1, Math.max(0, x));
  return [clamp((event.clientX - rect.left) / rect.width), clamp((event.clientY - rect.top) / rect.height)];
}

function onZonePointerDown(event) {
  const corner = event.target.dataset && event.target.dataset.corner;
  if (!corner || !zone.draft || zone.dragging) return;
  if (event.pointerType === "mouse" && event.button !== 0) return;
  zone.dragging = corner;
  zone.pointerId = event.pointerId;
  try {
    event.target.setPointerCapture(event.pointerId);
  } catch (error) {
    // pointer already gone
  }
  event.target.classList.add("dragging");
  event.preventDefault();
}

function onZonePointerMove(event) {
  if (!zone.dragging || event.pointerId !== zone.pointerId) return;
  event.preventDefault();
  const [fx, fy] = svgFraction(event);
  const z = zone.draft;
  const r2 = (x) => Math.round(x * 100) / 100;
  // A corner moves its own x and the y its edge shares with the other corner.
  if (zone.dragging === "bl") { z.bottom_left_x_frac = r2(fx); z.bottom_y_frac = r2(fy); }
  if (zone.dragging === "br") { z.bottom_right_x_frac = r2(fx); z.bottom_y_frac = r2(fy); }
  if (zone.dragging === "tl") { z.top_left_x_frac = r2(fx); z.top_y_frac = r2(fy); }
  if (zone.dragging === "tr") { z.top_right_x_frac = r2(fx); z.top_y_frac = r2(fy); }
  renderZone();
}

function onZonePointerUp(event) {
  if (event.pointerId !== zone.pointerId) return;
  zone.dragging = null;
  zone.pointerId = null;
  for (const handle of document.querySelectorAll("#zone-svg .handle.dragging")) handle.classList.remove("dragging");
}

async function applyZone() {
  const reply = await api("PATCH", "/api/config", { perception: { safe_zone: zone.draft } });
  if (reply.ok) {
    zone.saved = { ...zone.draft };
    showMessage("zone-message", "applied: perception uses the new safe zone from the next frame", false);
  } else {
    showMessage("zone-message", "refused: " + detailOf(reply), true);
  }
}

function toggleZoneEditor() {
  const editing = $("zone-editor").hidden;
  $("zone-editor").hidden = !editing;
  // An <svg> has no .hidden property (that is HTMLElement's): set the attribute.
  $("zone-svg").toggleAttribute("hidden", !editing);
  $("video-wrap").classList.toggle("editing", editing);
  $("zone-toggle").setAttribute("aria-pressed", String(editing));
  $("zone-toggle").textContent = editing ? "Close safe-zone editor" : "Edit safe zone";
  if (editing) {
    layoutZoneSvg();
    loadZone();
    // The corners are dragged on the video: bring it into view (below the header).
    $("video-wrap").scrollIntoView({ block: "nearest" });
  }
}

// -- wiring -----------------------------------------------------------------------------

/** The header's height, for dialogs placed below it. */
function trackHeaderHeight() {
  const header = $("topbar");
  const update = () => document.documentElement.style.setProperty("--header-h", header.offsetHeight + "px");
  update();
  if (window.ResizeObserver) new ResizeObserver(update).observe(header);
}

function wire() {
  // The E-STOP first of all.
  $("estop").addEventListener("pointerdown", onEstopPointerDown);
  $("estop").addEventListener("click", onEstopClick);
  window.addEventListener("keydown", onKeyDown, true);
  window.addEventListener("keyup", onKeyUp, true);
  window.addEventListener("blur", stopDrivingLocally);
  window.addEventListener("pagehide", stopDrivingLocally);
  document.addEventListener("visibilitychange", () => { if (document.hidden) stopDrivingLocally(); });
  setInterval(teleopTick, 1000 / TELEOP_HZ);
  trackHeaderHeight();

  $("estop-reset").addEventListener("click", resetEstop);
  $("fault-reset").addEventListener("click", resetFault);
  $("start").addEventListener("click", startExploring);
  $("stop").addEventListener("click", stopExploring);
  $("takeover").addEventListener("click", () => {
    teleop.takeOver = true;
    teleop.refused = false;
    $("takeover-box").hidden = true;
    showMessage("control-message", "taking over: hold a drive key or the pad", false);
  });
  for (const [input, out, digits] of [["speed", "speed-out", 2], ["turn", "turn-out", 2]]) {
    $(input).addEventListener("input", () => { $(out).textContent = Number($(input).value).toFixed(digits); });
    // Done with the slider: give the keys back to driving.
    $(input).addEventListener("change", () => $(input).blur());
  }
  $("map-size").addEventListener("change", () => $("map-size").blur());

  const pad = $("pad");
  pad.addEventListener("pointerdown", onPadDown);
  pad.addEventListener("pointermove", onPadMove);
  pad.addEventListener("pointerup", onPadUp);
  pad.addEventListener("pointercancel", onPadUp);
  pad.addEventListener("lostpointercapture", onPadUp);
  pad.addEventListener("contextmenu", (event) => event.preventDefault());
  updatePadState();
  window.addEventListener("gamepadconnected", startGamepadPolling);
  if (navigator.getGamepads && Array.from(navigator.getGamepads()).some(Boolean)) startGamepadPolling();

  $("scrim").addEventListener("click", closeOpenDialogs);
  for (const dialog of document.querySelectorAll("dialog")) dialog.addEventListener("close", updateScrim);
  $("token-button").addEventListener("click", () => openTokenDialog(""));
  $("token-cancel").addEventListener("click", () => closeDialog("token-dialog"));
  $("token-forget").addEventListener("click", async () => {
    await closeSession();
    localStorage.removeItem(TOKEN_KEY);
    $("token-input").value = "";
    showMessage("token-message", "forgotten: this browser can still stop the robot", false);
    reconnectControl();
  });
  $("token-form").addEventListener("submit", async (event) => {
    event.preventDefault();
    const value = $("token-input").value.trim();
    if (!value) return;
    const previous = token();
    localStorage.setItem(TOKEN_KEY, value);
    if (await checkToken({ prompt: false })) {
      closeDialog("token-dialog");
      showMessage("control-message", "token accepted", false);
      reconnectControl();
      await openSession();
    } else {
      if (previous) localStorage.setItem(TOKEN_KEY, previous);
      else localStorage.removeItem(TOKEN_KEY);
      showMessage("token-message", "The daemon refused this token.", true);
    }
  });

  $("calib-open").addEventListener("click", () => {
    calibError("");
    $("calib-info").textContent = "";
    // Focus on a button, not a field: the space bar still e-stops.
    openDialog("calib-dialog", $("calib-detect"));
  });
  $("calib-cancel").addEventListener("click", () => closeDialog("calib-dialog"));
  $("calib-detect").addEventListener("click", calibDetect);
  $("calib-accept").addEventListener("click", calibAccept);

  buildZoneSliders();
  $("zone-toggle").addEventListener("click", toggleZoneEditor);
  $("zone-apply").addEventListener("click", applyZone);
  $("zone-revert").addEventListener("click", () => {
    if (zone.saved) { zone.draft = { ...zone.saved }; renderZone(); }
  });
  const svg = $("zone-svg");
  svg.addEventListener("pointerdown", onZonePointerDown);
  svg.addEventListener("pointermove", onZonePointerMove);
  svg.addEventListener("pointerup", onZonePointerUp);
  svg.addEventListener("pointercancel", onZonePointerUp);
  svg.addEventListener("lostpointercapture", onZonePointerUp);
  if (window.ResizeObserver) new ResizeObserver(layoutZoneSvg).observe($("video-wrap"));

  $("viser-load").addEventListener("click", () => {
    const holder = $("viser-holder");
    if (holder.firstChild) {
      holder.replaceChildren();
      $("viser-load").textContent = "Show 3D view here";
      return;
    }
    const frame = document.createElement("iframe");
    frame.src = "/viser/";
    frame.title = "viser 3D view";
    frame.id = "viser-frame";
    // Same origin: the space bar e-stops with the focus inside the 3D view too.
    frame.addEventListener("load", () => {
      try {
        frame.contentWindow.addEventListener("keydown", (event) => {
          if (isSpace(event) && !isTextField(event.target)) {
            event.preventDefault();
            if (!event.repeat) estop("space bar");
          }
        }, true);
      } catch (error) {
        // not same-origin after all: the page's own handler still covers the rest
      }
    });
    holder.appendChild(frame);
    $("viser-load").textContent = "Hide 3D view";
  });
}

async function main() {
  takeTokenFromUrl();
  wire();
  // The control socket first: it carries the e-stop (with or without the token).
  connectControl();
  const first = await api("GET", "/api/status", undefined, { quiet401: true });
  if (first.ok && first.data) renderStatus(first.data);
  connectTelemetry();
  connectVideo();
  refreshMap();
  if (token()) {
    if (await checkToken()) await openSession();
  } else {
    // Not focused: the space bar must still e-stop on a page just opened.
    openTokenDialog("", { focus: false });
  }
}

main();
