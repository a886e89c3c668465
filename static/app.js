// floornav dashboard: plain JavaScript, no build step, no network beyond the daemon.
//
// Sockets: /ws/telemetry (status JSON ~10 Hz), /ws/video (a JSON header, then the JPEG),
// /ws/control (teleop, e-stop, start/stop; needs the token). REST for the rest.
// Browsers cannot set headers on WebSockets, so the token travels as the subprotocol
// "bearer.<token>" next to "floornav" (the server selects "floornav").
"use strict";

const TOKEN_KEY = "floornav.token";
const TELEOP_HZ = 15;
const MAP_PERIOD_MS = 500;
const GAMEPAD_DEADZONE = 0.15;
const LATENCY_WINDOW = 120;

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

function openTokenDialog(message) {
  $("token-message").textContent = message || "";
  $("token-message").className = message ? "message bad" : "message";
  $("token-input").value = token();
  const dialog = $("token-dialog");
  if (!dialog.open) dialog.showModal();
  $("token-input").focus();
}

async function checkToken() {
  if (!token()) {
    setControlLink("off", "no token");
    return false;
  }
  const reply = await api("GET", "/api/auth", undefined, { quiet401: true });
  if (reply.status === 401) {
    openTokenDialog("The saved token was refused; enter the daemon's current token.");
    return false;
  }
  return reply.ok;
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

function setCell(id, text, kind) {
  const el = $(id);
  el.textContent = text;
  el.className = kind || "";
}

function renderStatus(s) {
  stats.status = s;
  const state = $("state");
  state.textContent = s.state + (s.autonomous && s.state !== "running" ? " (autonomy on)" : "");
  state.className = "state state-" + s.state;

  const banner = $("banner");
  if (s.state === "estopped") {
    banner.hidden = false;
    banner.className = "banner bad";
    banner.textContent = "E-STOP latched: " + (s.estop || "") + ". Reset it to drive again.";
  } else if (s.fault) {
    banner.hidden = false;
    banner.className = "banner bad";
    banner.textContent = "Fault latched, motors held at zero: " + s.fault +
      ". Fix the cause, then Reset fault and Start.";
  } else if (s.stop_reason && s.stop_cause !== "clearance") {
    // A protective stop: it clears by itself, so a warning rather than an alarm.
    banner.hidden = false;
    banner.className = "banner";
    banner.textContent = "Protective stop (clears by itself): " + s.stop_reason;
  } else {
    banner.hidden = true;
  }

  $("frame-age").textContent = fmt(s.frame_age_ms);
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
  setCell("h-zone", typeof s.zone_floor_confidence === "number"
    ? fmt(s.zone_floor_confidence * 100) + " %" + (zoneLow ? " · not floor (below " + fmt(zoneMin * 100) + " %)" : "")
    : "–", zoneLow ? "bad" : (typeof s.zone_floor_confidence === "number" ? "ok" : ""));
  setCell("h-stop", s.stop_reason || "none", s.stop_reason ? "warn" : "");
  const c = s.command;
  setCell("h-command", c ? `${fmt(c.v_m_s, 2)} m/s · ${fmt(c.omega_rad_s, 2)} rad/s · PWM ${c.left_pwm}/${c.right_pwm} · ${c.source}` : "none yet");
  setCell("h-calibration", s.calibration ? "reprojection RMS " + fmt(s.calibration.reprojection_rms_px, 2) + " px"
    : (s.calibration_problem || "none"), s.calibration ? "ok" : "warn");
  setCell("h-fault", s.fault || "none", s.fault ? "bad" : "ok");
  const last = s.last_stop;
  setCell("h-last-stop", last ? `${last.cause}: ${last.reason} · ${fmt(last.age_s, 0)} s ago` +
    (last.latched ? " · latched" : "") : "none", last && last.latched ? "bad" : "");
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
    row.cells[0].textContent = name;
    row.cells[1].textContent = fmt(stages[name], 2);
  });

  const p = s.pose || {};
  $("pose").textContent = `${fmt(p.x_m, 2)}, ${fmt(p.y_m, 2)} m · ${fmt((p.theta_rad || 0) * 180 / Math.PI)}°`;
  $("distance").textContent = fmt(s.distance_m, 2);
  const f = s.frontier;
  $("frontier").textContent = f
    ? [f.goal_xy ? `goal ${fmt(f.goal_xy[0], 2)}, ${fmt(f.goal_xy[1], 2)} m` : "", f.reason, `${f.clusters} clusters`]
      .filter(Boolean).join(" · ")
    : "not searched yet";

  $("teleop-driver").textContent = s.teleop_driver || "nobody";
  const other = s.teleop_driver && stats.me && s.teleop_driver !== stats.me;
  if (other) {
    $("takeover-box").hidden = false;
    $("takeover-text").textContent = s.teleop_driver + " is driving.";
  } else if (!teleop.refused) {
    $("takeover-box").hidden = true;
  }
  $("estop-reset").disabled = s.state !== "estopped";
  $("fault-reset").hidden = !s.fault;
  $("start").disabled = s.autonomous || s.state === "estopped";
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

const video = { ws: null, header: null, url: null, arrivals: [] };

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

// -- control socket, teleop -------------------------------------------------------------

const control = { ws: null, nextId: 1, retryMs: 500 };
const teleop = { keys: new Set(), pad: { v: 0, w: 0 }, active: false, takeOver: false, refused: false };

function connectControl() {
  if (!token()) {
    setControlLink("off", "no token: driving disabled");
    return;
  }
  const ws = new WebSocket(socketUrl("/ws/control"), socketProtocols());
  control.ws = ws;
  ws.onopen = () => {
    control.retryMs = 500;
    setControlLink("on", "control connected");
  };
  ws.onmessage = (event) => {
    const reply = JSON.parse(event.data);
    stats.controlReplies.push(reply);
    if (stats.controlReplies.length > 50) stats.controlReplies.shift();
    if (reply.type === "hello") {
      stats.me = reply.driver;
      $("me").textContent = reply.driver;
    } else if (reply.type === "error") {
      showMessage("control-message", reply.detail, true);
      if (/teleop is held by/.test(reply.detail)) {
        teleop.refused = true;
        $("takeover-box").hidden = false;
        $("takeover-text").textContent = reply.detail;
      }
    } else if (reply.type === "ack" && !["teleop", "release"].includes(reply.detail)) {
      showMessage("control-message", reply.detail + ": ok · state " + reply.state, false);
    }
  };
  ws.onclose = () => {
    control.ws = null;
    setControlLink("off", "control disconnected");
    control.retryMs = Math.min(5000, control.retryMs * 2);
    setTimeout(async () => { if (await checkToken()) connectControl(); }, control.retryMs);
  };
}

function sendControl(message) {
  const ws = control.ws;
  if (!ws || ws.readyState !== WebSocket.OPEN) return false;
  ws.send(JSON.stringify({ ...message, id: control.nextId++ }));
  return true;
}

function keyCommand() {
  const k = teleop.keys;
  const speed = Number($("speed").value);
  const turn = Number($("turn").value);
  const forward = (k.has("up") ? 1 : 0) - (k.has("down") ? 1 : 0);
  const left = (k.has("left") ? 1 : 0) - (k.has("right") ? 1 : 0);
  return { v: forward * speed, w: left * turn };
}

function teleopTick() {
  const key = keyCommand();
  const v = key.v !== 0 ? key.v : teleop.pad.v;
  const w = key.w !== 0 ? key.w : teleop.pad.w;
  const moving = v !== 0 || w !== 0;
  if (moving) {
    teleop.active = true;
    sendControl({ type: "teleop", v_m_s: round3(v), omega_rad_s: round3(w), take_over: teleop.takeOver });
  } else if (teleop.active) {
    // Let go: an explicit zero first (stops at once), then hand teleop back.
    teleop.active = false;
    teleop.takeOver = false;
    sendControl({ type: "teleop", v_m_s: 0, omega_rad_s: 0 });
    sendControl({ type: "release" });
  }
}

function round3(x) {
  return Math.round(x * 1000) / 1000;
}

const KEY_NAMES = {
  ArrowUp: "up", KeyW: "up",
  ArrowDown: "down", KeyS: "down",
  ArrowLeft: "left", KeyA: "left",
  ArrowRight: "right", KeyD: "right",
};

function typingInForm(event) {
  const t = event.target;
  return t && (t.tagName === "INPUT" || t.tagName === "TEXTAREA" || t.tagName === "SELECT" || t.isContentEditable);
}

function onKeyDown(event) {
  if (typingInForm(event) || document.querySelector("dialog[open]")) return;
  if (event.code === "Space") {
    event.preventDefault();
    if (!event.repeat) estop();
    return;
  }
  const name = KEY_NAMES[event.code];
  if (!name) return;
  event.preventDefault();
  if (!teleop.keys.has(name)) {
    teleop.keys.add(name);
    $("key-" + name).classList.add("active");
    teleopTick(); // do not wait for the next tick to start moving
  }
}

function onKeyUp(event) {
  const name = KEY_NAMES[event.code];
  if (!name) return;
  teleop.keys.delete(name);
  $("key-" + name).classList.remove("active");
  teleopTick();
}

function releaseAllKeys() {
  // A key held while the window loses focus never sends its keyup.
  for (const name of teleop.keys) $("key-" + name).classList.remove("active");
  teleop.keys.clear();
  teleopTick();
}

// -- gamepad ----------------------------------------------------------------------------

function deadzone(x) {
  const magnitude = Math.abs(x);
  if (magnitude < GAMEPAD_DEADZONE) return 0;
  return Math.sign(x) * (magnitude - GAMEPAD_DEADZONE) / (1 - GAMEPAD_DEADZONE);
}

let padEstopWasPressed = false;

function pollGamepad() {
  const pads = navigator.getGamepads ? Array.from(navigator.getGamepads()).filter(Boolean) : [];
  const pad = pads[0];
  if (pad) {
    const v = -deadzone(pad.axes[1] || 0) * Number($("speed").value);
    const w = -deadzone(pad.axes[0] || 0) * Number($("turn").value);
    teleop.pad = { v, w };
    $("gamepad-status").textContent = `gamepad: ${pad.id.slice(0, 40)} · B = e-stop`;
    const estopPressed = Boolean(pad.buttons[1] && pad.buttons[1].pressed);
    if (estopPressed && !padEstopWasPressed) estop();
    padEstopWasPressed = estopPressed;
  } else {
    teleop.pad = { v: 0, w: 0 };
  }
  requestAnimationFrame(pollGamepad);
}

// -- commands ---------------------------------------------------------------------------

async function estop() {
  // Both paths: the socket is fastest, the POST works without it. The latch is idempotent.
  sendControl({ type: "estop" });
  const reply = await api("POST", "/api/estop", { source: "dashboard" });
  showMessage("control-message", reply.ok ? "E-STOP latched" : "e-stop: " + detailOf(reply), !reply.ok);
}

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
    const why = reply.status === 409 ? "Refused now" : reply.status === 422 ? "Calibration failed" : "Error";
    calibError(`${why} (${reply.status}): ${detailOf(reply)}`);
    return;
  }
  const r = reply.data;
  $("calib-info").textContent = r.saved_to ? "Saved to " + r.saved_to + "; the map starts afresh." : "Applied.";
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
const zone = { saved: null, draft: null, dragging: null };

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
      zone.draft[key] = Number(input.value);
      renderZone();
    });
    const out = document.createElement("output");
    out.id = "zone-out-" + key;
    label.append(input, out);
    holder.appendChild(label);
  }
}

function zoneCorners(z) {
  // SVG viewBox is 1000 x 1000 over the image.
  return {
    bl: [z.bottom_left_x_frac * 1000, z.bottom_y_frac * 1000],
    br: [z.bottom_right_x_frac * 1000, z.bottom_y_frac * 1000],
    tr: [z.top_right_x_frac * 1000, z.top_y_frac * 1000],
    tl: [z.top_left_x_frac * 1000, z.top_y_frac * 1000],
  };
}

function renderZone() {
  const z = zone.draft;
  if (!z) return;
  const c = zoneCorners(z);
  $("zone-poly").setAttribute("points", ["bl", "br", "tr", "tl"].map((k) => c[k].join(",")).join(" "));
  for (const handle of document.querySelectorAll("#zone-svg .handle")) {
    const [x, y] = c[handle.dataset.corner];
    handle.setAttribute("cx", x);
    handle.setAttribute("cy", y);
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
  if (!corner) return;
  zone.dragging = corner;
  event.target.setPointerCapture(event.pointerId);
  event.preventDefault();
}

function onZonePointerMove(event) {
  if (!zone.dragging) return;
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

function onZonePointerUp() {
  zone.dragging = null;
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
  $("zone-svg").hidden = !editing;
  $("zone-toggle").setAttribute("aria-pressed", String(editing));
  $("zone-toggle").textContent = editing ? "Close safe-zone editor" : "Edit safe zone";
  if (editing) loadZone();
}

// -- wiring -----------------------------------------------------------------------------

function wire() {
  $("estop").addEventListener("click", estop);
  $("estop-reset").addEventListener("click", resetEstop);
  $("fault-reset").addEventListener("click", resetFault);
  $("start").addEventListener("click", startExploring);
  $("stop").addEventListener("click", stopExploring);
  $("takeover").addEventListener("click", () => {
    teleop.takeOver = true;
    teleop.refused = false;
    $("takeover-box").hidden = true;
    showMessage("control-message", "taking over: hold a drive key", false);
  });
  for (const [input, out, digits] of [["speed", "speed-out", 2], ["turn", "turn-out", 2]]) {
    $(input).addEventListener("input", () => { $(out).textContent = Number($(input).value).toFixed(digits); });
  }
  window.addEventListener("keydown", onKeyDown);
  window.addEventListener("keyup", onKeyUp);
  window.addEventListener("blur", releaseAllKeys);
  document.addEventListener("visibilitychange", () => { if (document.hidden) releaseAllKeys(); });
  setInterval(teleopTick, 1000 / TELEOP_HZ);
  requestAnimationFrame(pollGamepad);

  $("token-button").addEventListener("click", () => openTokenDialog(""));
  $("token-cancel").addEventListener("click", () => $("token-dialog").close());
  $("token-forget").addEventListener("click", () => {
    localStorage.removeItem(TOKEN_KEY);
    $("token-input").value = "";
    showMessage("token-message", "forgotten", false);
    if (control.ws) control.ws.close();
  });
  $("token-form").addEventListener("submit", async (event) => {
    event.preventDefault();
    const value = $("token-input").value.trim();
    if (!value) return;
    localStorage.setItem(TOKEN_KEY, value);
    if (await checkToken()) {
      $("token-dialog").close();
      if (control.ws) control.ws.close(); // reconnects with the new token
      else connectControl();
    } else {
      showMessage("token-message", "The daemon refused this token.", true);
    }
  });

  $("calib-open").addEventListener("click", () => {
    calibError("");
    $("calib-info").textContent = "";
    $("calib-dialog").showModal();
  });
  $("calib-cancel").addEventListener("click", () => $("calib-dialog").close());
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
    holder.appendChild(frame);
    $("viser-load").textContent = "Hide 3D view";
  });
}

async function main() {
  takeTokenFromUrl();
  wire();
  const first = await api("GET", "/api/status", undefined, { quiet401: true });
  if (first.ok && first.data) renderStatus(first.data);
  connectTelemetry();
  connectVideo();
  refreshMap();
  if (await checkToken()) connectControl();
  else if (!token()) openTokenDialog("");
}

main();
