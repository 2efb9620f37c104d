// Live browser viewer of the shared deformable object (three.js, one ES module, no build step).
//
// Connects to ws://<page host>/ws as a `viewer`, receives the surface as binary frames (FAC1 once,
// VTX1 every simulation tick) and a `room` summary per tick, and draws the balloon as it deforms,
// each user's probe, proxy and force, and a panel per user. Reconnects by itself with backoff.
//
// Test hooks: `window.viewerState` (connection, tick, frame counts, users by name) is updated live.
// Protocol constants come from ./protocol.js, generated from shared/protocol.py.
//
// Naming rule, checked by tests/web/test_protocol_js.py: a RoomState is only ever called `room`,
// a Welcome `welcome`, an ObjectInfo `obj`, a UserView `u`, a LinkConditions `link`, an error
// message `err`; every `<name>.<field>` read here must be listed in USED_FIELDS.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { CSS2DObject, CSS2DRenderer } from "three/addons/renderers/CSS2DRenderer.js";
import {
  BINARY_HEADER_BYTES,
  FACES_MAGIC,
  PROTOCOL_VERSION,
  VERTICES_MAGIC,
} from "./protocol.js";

/** Every message/model field this module reads (checked against the schema by the tests). */
export const USED_FIELDS = /* USED_FIELDS:BEGIN */ {
  "welcome": ["type", "protocol", "user_id", "sim_rate_hz", "object", "link"],
  "room": ["type", "tick", "sim_rate_hz", "tick_ms", "tick_ms_p99", "overruns", "link", "users"],
  "error": ["type", "code", "message", "fatal"],
  "ObjectInfo": ["n_vertices", "n_faces", "center_m", "radius_m", "bounds_min_m"],
  "LinkConditions": ["latency_ms", "jitter_ms", "loss"],
  "UserView": [
    "user_id", "name", "probe_m", "proxy_m", "normal", "force_n", "penetration_m", "in_contact",
    "k_o", "k_o_eff", "k_h", "i_gain", "servo_rate_hz", "rtt_ms", "device"
  ]
} /* USED_FIELDS:END */;

// ----------------------------------------------------------------------------- settings
const params = new URLSearchParams(location.search);
/** Arrow length per newton of force [m/N]: ?force_scale=0.01 for 1 cm per N; by default a third
 * of the object's radius per newton (3.3 cm per N on the 0.1 m balloon), set at welcome. */
const FORCE_SCALE_PARAM = positiveParam("force_scale", 0);
const FORCE_SCALE_PER_RADIUS = 1 / 3;
let forceScaleMPerN = FORCE_SCALE_PARAM || 0.01;
const RECONNECT_MIN_MS = 500;
const RECONNECT_MAX_MS = 8000;
const PANEL_REFRESH_MS = 100;
/** Per-user colours (the balloon is blue: none of these is). */
const USER_COLORS = ["#ff9f43", "#7bed9f", "#ff6b9d", "#ffd93d", "#b794f6", "#ff6b6b", "#63e6be"];

function positiveParam(name, fallback) {
  if (!params.has(name)) return fallback;
  const v = Number(params.get(name));
  return Number.isFinite(v) && v > 0 ? v : fallback;
}

// ----------------------------------------------------------------------------- test hooks
const viewerState = {
  connected: false,
  status: "connecting",
  protocol: PROTOCOL_VERSION,
  tick: -1,
  frames: 0, // VTX1 frames received
  faceFrames: 0, // FAC1 frames received
  roomMessages: 0,
  renders: 0,
  renderMs: null, // cost of the last render [ms]
  reconnects: 0,
  nVertices: 0,
  nFaces: 0,
  simRateHz: null,
  object: null,
  lastError: null,
  users: {}, // by name: force_n_mag [N], penetration_mm [mm], k_o, k_o_eff, k_h [N/m], ...
};
window.viewerState = viewerState;

// ----------------------------------------------------------------------------- DOM
const $ = (id) => document.getElementById(id);
const dom = {
  scene: $("scene"),
  conn: $("conn"),
  connText: $("conn-text"),
  rate: $("s-rate"),
  tick: $("s-tick"),
  cost: $("s-cost"),
  p99: $("s-p99"),
  overruns: $("s-overruns"),
  link: $("s-link"),
  mesh: $("s-mesh"),
  users: $("users"),
  userList: $("user-list"),
  userCount: $("user-count"),
  noUsers: $("no-users"),
  clientHint: $("client-hint"),
  toast: $("toast"),
  forceScale: $("force-scale"),
};

function fmt(x, digits = 1) {
  return typeof x === "number" && Number.isFinite(x) ? x.toFixed(digits) : "–";
}

function fmtInt(x) {
  return typeof x === "number" && Number.isFinite(x) ? Math.round(x).toLocaleString("en-US") : "–";
}

function setStatus(status, text) {
  viewerState.status = status;
  dom.conn.className = `conn ${status}`;
  dom.connText.textContent = text;
  document.body.classList.toggle("offline", status !== "connected"); // dims stale numbers
}

let toastTimer = 0;
function toast(text, ms = 6000) {
  dom.toast.textContent = text;
  dom.toast.hidden = false;
  clearTimeout(toastTimer);
  toastTimer = setTimeout(() => (dom.toast.hidden = true), ms);
}

// ----------------------------------------------------------------------------- three.js scene
let sceneDirty = true; // render only when something changed: new data, resize, camera motion
let panelsDirty = false; // user panels need a refresh (at most every PANEL_REFRESH_MS)

const renderer = new THREE.WebGLRenderer({
  antialias: params.get("aa") !== "0", // ?aa=0 for slow (software) GL
  alpha: true,
  preserveDrawingBuffer: true, // lets tests (and "save image") read the canvas back
});
renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
renderer.setClearColor(0x000000, 0);
renderer.toneMapping = THREE.ACESFilmicToneMapping;
renderer.toneMappingExposure = 1.05;
dom.scene.appendChild(renderer.domElement);

const labels = new CSS2DRenderer();
labels.domElement.className = "labels";
dom.scene.appendChild(labels.domElement);

const scene = new THREE.Scene();

const camera = new THREE.PerspectiveCamera(36, 1, 0.001, 100);
camera.up.set(0, 0, 1); // the physics is z-up
camera.position.set(0.25, -0.3, 0.2);

const controls = new OrbitControls(camera, renderer.domElement);
controls.enableDamping = true;
controls.dampingFactor = 0.12;
controls.addEventListener("change", () => (sceneDirty = true));

scene.add(new THREE.HemisphereLight(0xcfe6ff, 0x1a1f2e, 0.9));
const key = new THREE.DirectionalLight(0xffffff, 2.2);
key.position.set(1.2, -1.0, 2.0);
scene.add(key);
const rim = new THREE.DirectionalLight(0x7fb8ff, 1.4);
rim.position.set(-1.5, 1.4, 0.6);
scene.add(rim);

// The balloon: back faces first (darker, the inside wall), then the front skin, then a faint
// wireframe so that the deformation reads clearly. All three share one BufferGeometry that VTX1
// frames update in place.
const surface = new THREE.BufferGeometry();
const skinBack = new THREE.Mesh(
  surface,
  new THREE.MeshPhysicalMaterial({
    color: 0x123a7a,
    roughness: 0.4,
    transparent: true,
    opacity: 0.55,
    side: THREE.BackSide,
    depthWrite: false,
  }),
);
const skin = new THREE.Mesh(
  surface,
  new THREE.MeshPhysicalMaterial({
    color: 0x2f86ff,
    roughness: 0.18,
    metalness: 0.0,
    clearcoat: 0.8,
    clearcoatRoughness: 0.1,
    transparent: true,
    opacity: 0.5,
    side: THREE.FrontSide,
    depthWrite: false,
  }),
);
const wire = new THREE.Mesh(
  surface,
  new THREE.MeshBasicMaterial({
    color: 0xa8d8ff,
    wireframe: true,
    transparent: true,
    opacity: 0.09,
    depthWrite: false,
  }),
);
skinBack.renderOrder = 1;
skin.renderOrder = 3;
wire.renderOrder = 4;
for (const m of [skinBack, skin, wire]) {
  m.frustumCulled = false; // the bounding sphere changes as it deforms
  m.visible = false;
  scene.add(m);
}

const floor = new THREE.Group();
scene.add(floor);

const usersGroup = new THREE.Group();
scene.add(usersGroup);

let objectRadius = 0.05;
let framed = false;

/** Place the floor and frame the camera on the object (first welcome only: keep the user's view). */
function frameObject(obj) {
  const c = new THREE.Vector3(...obj.center_m);
  const r = Math.max(obj.radius_m, 1e-3);
  objectRadius = r;
  forceScaleMPerN = FORCE_SCALE_PARAM || r * FORCE_SCALE_PER_RADIUS;
  dom.forceScale.textContent = `${+(forceScaleMPerN * 100).toPrecision(2)} cm`;
  const zFloor = obj.bounds_min_m[2];
  buildFloor(c, r, zFloor);
  if (framed) return;
  framed = true;
  // Fit the bounding sphere in the part of the window the panels leave free (72 % of it).
  const view = freeRegion();
  const halfV = THREE.MathUtils.degToRad(camera.fov / 2) * (view.h / window.innerHeight);
  const halfH = Math.atan(Math.tan(THREE.MathUtils.degToRad(camera.fov / 2)) * camera.aspect) *
    (view.w / window.innerWidth);
  const dist = r / Math.sin(0.72 * Math.min(halfV, halfH));
  const dir = new THREE.Vector3(0.55, -0.8, 0.72).normalize(); // about 40 degrees above the equator
  camera.position.copy(c).addScaledVector(dir, dist);
  camera.near = r * 0.01;
  camera.far = r * 200;
  camera.updateProjectionMatrix();
  controls.target.copy(c);
  controls.minDistance = r * 1.2;
  controls.maxDistance = r * 30;
  controls.update();
  sceneDirty = true;
}

function buildFloor(c, r, zFloor) {
  floor.clear();
  const grid = new THREE.GridHelper(r * 8, 16, 0x3a4a6b, 0x222c42);
  grid.rotation.x = Math.PI / 2; // GridHelper lies in XZ; the floor is the XY plane
  grid.position.set(c.x, c.y, zFloor - r * 0.002);
  grid.material.transparent = true;
  grid.material.opacity = 0.55;
  floor.add(grid);
  const shadow = new THREE.Mesh(
    new THREE.CircleGeometry(r * 1.5, 48),
    new THREE.MeshBasicMaterial({ map: radialTexture(), transparent: true, depthWrite: false }),
  );
  shadow.position.set(c.x, c.y, zFloor);
  floor.add(shadow);
}

function radialTexture() {
  const cv = document.createElement("canvas");
  cv.width = cv.height = 128;
  const g = cv.getContext("2d");
  const grad = g.createRadialGradient(64, 64, 0, 64, 64, 64);
  grad.addColorStop(0, "rgba(60,140,255,0.38)");
  grad.addColorStop(0.55, "rgba(30,80,180,0.12)");
  grad.addColorStop(1, "rgba(0,0,0,0)");
  g.fillStyle = grad;
  g.fillRect(0, 0, 128, 128);
  const tex = new THREE.CanvasTexture(cv);
  tex.colorSpace = THREE.SRGBColorSpace;
  return tex;
}

// ----------------------------------------------------------------------------- surface frames
function readHeader(buf) {
  if (buf.byteLength < BINARY_HEADER_BYTES) return null;
  const dv = new DataView(buf);
  const magic = String.fromCharCode(dv.getUint8(0), dv.getUint8(1), dv.getUint8(2), dv.getUint8(3));
  const tick = dv.getUint32(4, true);
  const count = dv.getUint32(8, true);
  if (buf.byteLength !== BINARY_HEADER_BYTES + count * 12) return null;
  return { magic, tick, count };
}

/** Little-endian count x 3 values after the header (typed arrays are little-endian in browsers). */
function body(buf, count, Kind) {
  return new Kind(buf, BINARY_HEADER_BYTES, count * 3);
}

function onBinary(buf) {
  const h = readHeader(buf);
  if (!h) {
    console.warn("viewer: malformed binary frame ignored");
    return;
  }
  if (h.magic === FACES_MAGIC) {
    viewerState.faceFrames += 1;
    viewerState.nFaces = h.count;
    surface.dispose(); // (re)connected: free the previous GPU buffers, they are re-uploaded
    surface.setIndex(new THREE.BufferAttribute(body(buf, h.count, Uint32Array).slice(), 1));
    updateNormalsAndShow();
  } else if (h.magic === VERTICES_MAGIC) {
    viewerState.frames += 1;
    viewerState.tick = h.tick;
    frameTimes.push(performance.now());
    const src = body(buf, h.count, Float32Array);
    let pos = surface.getAttribute("position");
    if (!pos || pos.count !== h.count) {
      pos = new THREE.BufferAttribute(new Float32Array(h.count * 3), 3);
      pos.setUsage(THREE.DynamicDrawUsage);
      surface.setAttribute("position", pos);
      surface.deleteAttribute("normal"); // recomputed at the new size
      viewerState.nVertices = h.count;
    }
    pos.array.set(src); // in place: no new geometry per frame
    pos.needsUpdate = true;
    updateNormalsAndShow();
  } else {
    console.warn(`viewer: unknown binary frame ${h.magic}`);
  }
}

function updateNormalsAndShow() {
  const pos = surface.getAttribute("position");
  if (!pos || !surface.index) return;
  surface.computeVertexNormals();
  sceneDirty = true;
  if (!skin.visible) {
    surface.computeBoundingSphere();
    for (const m of [skinBack, skin, wire]) m.visible = true;
  }
}

// ----------------------------------------------------------------------------- users (3-D)
const colorOf = new Map(); // user_id -> colour
const actors = new Map(); // user_id -> { group, probe, proxy, tether, arrow, label, tag }
const Z = new THREE.Vector3(0, 0, 1);
const tmpA = new THREE.Vector3();
const tmpB = new THREE.Vector3();

function userColor(userId) {
  if (!colorOf.has(userId)) colorOf.set(userId, USER_COLORS[colorOf.size % USER_COLORS.length]);
  return colorOf.get(userId);
}

function makeActor(u) {
  const color = new THREE.Color(userColor(u.user_id));
  const r = objectRadius;
  const group = new THREE.Group();
  const probe = new THREE.Mesh(
    new THREE.SphereGeometry(r * 0.032, 24, 16),
    new THREE.MeshStandardMaterial({ color, emissive: color, emissiveIntensity: 0.7, roughness: 0.4 }),
  );
  // Drawn after and over the translucent skin (transparent objects render last, by renderOrder):
  // a probe in contact is inside the balloon and should keep its colour.
  probe.material.transparent = true;
  probe.material.depthTest = false;
  probe.renderOrder = 6;
  const proxyColor = color.clone().lerp(new THREE.Color(0xffffff), 0.55);
  const proxy = new THREE.Mesh(
    new THREE.RingGeometry(r * 0.04, r * 0.065, 32),
    new THREE.MeshBasicMaterial({ color: proxyColor, side: THREE.DoubleSide, transparent: true, opacity: 0.95 }),
  );
  proxy.renderOrder = 5;
  const tether = new THREE.Line(
    new THREE.BufferGeometry().setFromPoints([new THREE.Vector3(), new THREE.Vector3()]),
    new THREE.LineDashedMaterial({ color: proxyColor, dashSize: r * 0.02, gapSize: r * 0.015 }),
  );
  tether.renderOrder = 5;
  const arrow = makeArrow(color, r);
  const tag = document.createElement("div");
  tag.className = "tag";
  tag.style.setProperty("--c", color.getStyle());
  const label = new CSS2DObject(tag);
  label.center.set(-0.45, 0.5); // to the right of the probe, clear of the force arrow
  group.add(probe, proxy, tether, arrow, label);
  usersGroup.add(group);
  return { group, probe, proxy, tether, arrow, label, tag };
}

/** A solid arrow along +y from the origin: unit shaft (scaled to length) and a cone head. */
function makeArrow(color, r) {
  const mat = new THREE.MeshStandardMaterial({ color, emissive: color, emissiveIntensity: 0.5 });
  mat.transparent = true; // rendered after the skin ...
  mat.depthTest = false; // ... and over it: a force is always worth seeing
  const shaft = new THREE.Mesh(new THREE.CylinderGeometry(r * 0.014, r * 0.014, 1, 12), mat);
  const head = new THREE.Mesh(new THREE.ConeGeometry(r * 0.04, 1, 16), mat);
  const arrow = new THREE.Group();
  arrow.add(shaft, head);
  shaft.renderOrder = head.renderOrder = 7;
  arrow.userData = { shaft, head, r };
  return arrow;
}

const Y = new THREE.Vector3(0, 1, 0);

function setArrow(arrow, origin, dir, length) {
  const { shaft, head, r } = arrow.userData;
  const headLen = Math.min(length * 0.4, r * 0.1);
  const shaftLen = Math.max(length - headLen, 1e-6);
  arrow.position.copy(origin);
  arrow.quaternion.setFromUnitVectors(Y, dir);
  shaft.scale.set(1, shaftLen, 1);
  shaft.position.set(0, shaftLen / 2, 0);
  head.scale.set(1, headLen, 1);
  head.position.set(0, shaftLen + headLen / 2, 0);
}

function updateActor(a, u) {
  a.probe.position.set(...u.probe_m);
  a.label.position.set(...u.probe_m);
  a.tag.textContent = u.name;
  a.proxy.position.set(...u.proxy_m);
  tmpA.set(...u.normal);
  if (tmpA.lengthSq() > 1e-12) a.proxy.quaternion.setFromUnitVectors(Z, tmpA.normalize());
  a.proxy.visible = u.in_contact;
  const pts = a.tether.geometry.getAttribute("position");
  pts.setXYZ(0, ...u.probe_m);
  pts.setXYZ(1, ...u.proxy_m);
  pts.needsUpdate = true;
  a.tether.computeLineDistances();
  a.tether.visible = u.in_contact;
  tmpB.set(...u.force_n);
  const mag = tmpB.length();
  if (mag > 1e-4) {
    setArrow(a.arrow, tmpA.set(...u.probe_m), tmpB.normalize(), mag * forceScaleMPerN);
    a.arrow.visible = true;
  } else {
    a.arrow.visible = false;
  }
}

function dropActor(userId) {
  const a = actors.get(userId);
  if (!a) return;
  usersGroup.remove(a.group);
  a.group.traverse((o) => {
    o.geometry?.dispose();
    o.material?.dispose();
  });
  a.tag.remove();
  actors.delete(userId);
}

// ----------------------------------------------------------------------------- users (panels)
const cards = new Map(); // user_id -> { root, fields }
let forceBarScaleN = 2.0;

const CARD_ROWS = [
  ["penetration_mm", "penetration", "mm"],
  ["k_o", "K<sub>o</sub>", "N/m"],
  ["k_o_eff", "K<sub>o,eff</sub>", "N/m"],
  ["k_h", "K<sub>h</sub>", "N/m"],
  ["i_gain", "I", "N/(m·s)"],
  ["servo_rate_hz", "servo", "Hz"],
  ["rtt_ms", "round trip", "ms"],
];

function makeCard(userId) {
  const root = document.createElement("section");
  root.className = "user";
  root.style.setProperty("--c", userColor(userId));
  root.innerHTML = `
    <header>
      <span class="swatch"></span>
      <span class="name"></span>
      <span class="badge"></span>
    </header>
    <div class="device"></div>
    <div class="force"><span class="force-value">–</span><span class="unit">N</span>
      <span class="force-label">force</span></div>
    <div class="bar"><span></span></div>
    <dl>${CARD_ROWS.map(([k, label, unit]) => `<div><dt>${label}</dt><dd><span data-k="${k}">–</span> <small>${unit}</small></dd></div>`).join("")}</dl>`;
  const fields = {};
  for (const el of root.querySelectorAll("[data-k]")) fields[el.dataset.k] = el;
  dom.userList.appendChild(root);
  return {
    root,
    fields,
    name: root.querySelector(".name"),
    badge: root.querySelector(".badge"),
    device: root.querySelector(".device"),
    force: root.querySelector(".force-value"),
    bar: root.querySelector(".bar > span"),
  };
}

function renderPanels() {
  const entries = Object.values(viewerState.users);
  dom.userCount.textContent = String(entries.length);
  dom.noUsers.hidden = entries.length > 0;
  const maxF = Math.max(0, ...entries.map((s) => s.force_n_mag));
  forceBarScaleN = Math.max(forceBarScaleN * 0.995, maxF * 1.25, 1.0);
  for (const s of entries) {
    let card = cards.get(s.user_id);
    if (!card) {
      card = makeCard(s.user_id);
      cards.set(s.user_id, card);
    }
    card.root.dataset.userName = s.name;
    card.root.classList.toggle("touching", s.in_contact);
    card.name.textContent = s.name;
    card.badge.textContent = s.in_contact ? "in contact" : "free";
    card.device.textContent = s.device;
    card.force.textContent = fmt(s.force_n_mag, 2);
    card.bar.style.width = `${Math.min(100, (100 * s.force_n_mag) / forceBarScaleN).toFixed(1)}%`;
    card.fields.penetration_mm.textContent = fmt(s.penetration_mm, 2);
    card.fields.k_o.textContent = fmtInt(s.k_o);
    card.fields.k_o_eff.textContent = fmtInt(s.k_o_eff);
    card.fields.k_h.textContent = fmtInt(s.k_h);
    card.fields.i_gain.textContent = fmtInt(s.i_gain);
    card.fields.servo_rate_hz.textContent = fmtInt(s.servo_rate_hz);
    card.fields.rtt_ms.textContent = fmt(s.rtt_ms, 1);
  }
  const live = new Set(entries.map((s) => s.user_id));
  for (const [id, card] of cards) {
    if (!live.has(id)) {
      card.root.remove();
      cards.delete(id);
    }
  }
}

// ----------------------------------------------------------------------------- header stats
let lastRoom = null;
let meshInfo = "";
const frameTimes = []; // arrival times of recent VTX1 frames [ms]

function renderHeader() {
  const now = performance.now();
  while (frameTimes.length && now - frameTimes[0] > 1000) frameTimes.shift();
  const room = lastRoom;
  if (room) {
    dom.rate.textContent = fmt(room.sim_rate_hz, 0);
    dom.tick.textContent = fmtInt(room.tick);
    dom.cost.textContent = fmt(room.tick_ms, 2);
    dom.p99.textContent = fmt(room.tick_ms_p99, 2);
    dom.overruns.textContent = fmtInt(room.overruns);
    dom.overruns.classList.toggle("warn", room.overruns > 0);
    dom.link.textContent = linkText(room.link);
  }
  dom.mesh.textContent = viewerState.nVertices ? `${meshInfo} · ${frameTimes.length} fps` : "–";
}

function linkText(link) {
  if (!link) return "–";
  if (!(link.latency_ms > 0 || link.jitter_ms > 0 || link.loss > 0)) return "none";
  const parts = [`${fmt(link.latency_ms, 0)} ms`];
  if (link.jitter_ms > 0) parts[0] += ` ± ${fmt(link.jitter_ms, 0)}`;
  if (link.loss > 0) parts.push(`${fmt(link.loss * 100, 1)} % loss`);
  return parts.join(" · ");
}

// ----------------------------------------------------------------------------- messages
function onWelcome(welcome) {
  if (welcome.protocol !== PROTOCOL_VERSION) {
    toast(`server speaks protocol ${welcome.protocol}, this viewer ${PROTOCOL_VERSION}`);
  }
  viewerState.connected = true;
  viewerState.userId = welcome.user_id;
  viewerState.simRateHz = welcome.sim_rate_hz;
  viewerState.object = welcome.object;
  reconnectAttempt = 0;
  setStatus("connected", `live · ${fmt(welcome.sim_rate_hz, 0)} Hz`);
  const obj = welcome.object;
  meshInfo = `${fmtInt(obj.n_vertices)} v · ${fmtInt(obj.n_faces)} f`;
  frameObject(obj);
  dom.link.textContent = linkText(welcome.link);
}

function onRoom(room) {
  viewerState.roomMessages += 1;
  viewerState.tick = room.tick;
  viewerState.simRateHz = room.sim_rate_hz;
  lastRoom = room;
  const byName = {};
  const live = new Set();
  for (const u of room.users) {
    live.add(u.user_id);
    const f = u.force_n;
    byName[u.name] = {
      user_id: u.user_id,
      name: u.name,
      device: u.device,
      in_contact: u.in_contact,
      force_n: f,
      force_n_mag: Math.hypot(f[0], f[1], f[2]),
      penetration_mm: u.penetration_m * 1000,
      k_o: u.k_o,
      k_o_eff: u.k_o_eff,
      k_h: u.k_h,
      i_gain: u.i_gain,
      servo_rate_hz: u.servo_rate_hz,
      rtt_ms: u.rtt_ms ?? null,
      probe_m: u.probe_m,
      proxy_m: u.proxy_m,
    };
    let a = actors.get(u.user_id);
    if (!a) {
      a = makeActor(u);
      actors.set(u.user_id, a);
    }
    updateActor(a, u);
  }
  viewerState.users = byName;
  for (const id of [...actors.keys()]) if (!live.has(id)) dropActor(id);
  panelsDirty = true;
  sceneDirty = true;
}

function onError(err) {
  viewerState.lastError = { code: err.code, message: err.message, fatal: err.fatal };
  toast(`${err.fatal ? "server closed the connection" : "server error"}: ${err.code} — ${err.message}`);
}

function onText(text) {
  let msg;
  try {
    msg = JSON.parse(text);
  } catch {
    console.warn("viewer: non-JSON text frame ignored");
    return;
  }
  switch (msg.type) {
    case "welcome":
      return onWelcome(msg);
    case "room":
      return onRoom(msg);
    case "error":
      return onError(msg);
    default:
      return undefined; // pong, patch: not for viewers
  }
}

// ----------------------------------------------------------------------------- connection
let ws = null;
let reconnectAttempt = 0;
let reconnectTimer = 0;

function wsUrl() {
  const override = params.get("ws");
  if (override) return override;
  return `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`;
}
dom.clientHint.textContent = `haptic client --name alice --url ${wsUrl()}`;

function connect() {
  clearTimeout(reconnectTimer);
  setStatus(reconnectAttempt ? "reconnecting" : "connecting", "connecting…");
  let sock;
  try {
    sock = new WebSocket(wsUrl());
  } catch (e) {
    console.warn("viewer: cannot open websocket", e);
    scheduleReconnect();
    return;
  }
  ws = sock;
  sock.binaryType = "arraybuffer";
  sock.onopen = () => {
    sock.send(JSON.stringify({ type: "hello", protocol: PROTOCOL_VERSION, role: "viewer", name: "viewer" }));
  };
  sock.onmessage = (ev) => {
    if (typeof ev.data === "string") onText(ev.data);
    else onBinary(ev.data);
  };
  sock.onclose = () => {
    if (ws !== sock) return;
    ws = null;
    viewerState.connected = false;
    scheduleReconnect();
  };
  sock.onerror = () => {}; // onclose follows and reconnects
}

function scheduleReconnect() {
  reconnectAttempt += 1;
  viewerState.reconnects += 1;
  const base = Math.min(RECONNECT_MAX_MS, RECONNECT_MIN_MS * 2 ** (reconnectAttempt - 1));
  const delay = base * (0.8 + 0.4 * Math.random());
  setStatus("reconnecting", `offline · retry in ${(delay / 1000).toFixed(1)}s`);
  reconnectTimer = setTimeout(connect, delay);
}

window.addEventListener("online", () => {
  if (!ws) {
    reconnectAttempt = 0;
    connect();
  }
});

// ----------------------------------------------------------------------------- layout & loop
/** The window area not covered by the header, the user panel and the legend [CSS px]. */
function freeRegion() {
  const w = window.innerWidth;
  const h = window.innerHeight;
  const top = $("topbar").getBoundingClientRect();
  const legend = $("legend").getBoundingClientRect();
  const panel = dom.users.getBoundingClientRect();
  const beside = panel.width > 0 && panel.left > w * 0.5; // wide layout: panel on the right
  const below = !beside && panel.height > 0 && panel.top > h * 0.5; // narrow: panel at the bottom
  const right = beside ? panel.left : w;
  const bottom = Math.min(legend.height > 0 ? legend.top : h, below ? panel.top : h);
  const y0 = Math.min(top.bottom, h * 0.4);
  const y1 = Math.max(bottom, h * 0.6);
  return { x: 0, y: y0, w: right, h: y1 - y0 };
}

function resize() {
  const w = window.innerWidth;
  const h = window.innerHeight;
  renderer.setSize(w, h);
  labels.setSize(w, h);
  camera.aspect = w / h;
  // Centre the object in the part of the window the panels do not cover.
  const view = freeRegion();
  camera.setViewOffset(w, h, w / 2 - (view.x + view.w / 2), h / 2 - (view.y + view.h / 2), w, h);
  camera.updateProjectionMatrix();
  sceneDirty = true;
}
window.addEventListener("resize", resize);
resize();

let lastPanelMs = 0;

function animate(now) {
  requestAnimationFrame(animate);
  controls.update(); // fires "change" while damping settles
  if (sceneDirty) {
    sceneDirty = false;
    const t0 = performance.now();
    renderer.render(scene, camera);
    labels.render(scene, camera);
    viewerState.renders += 1;
    viewerState.renderMs = performance.now() - t0;
  }
  if (now - lastPanelMs >= PANEL_REFRESH_MS) {
    lastPanelMs = now;
    renderHeader();
    if (panelsDirty) {
      panelsDirty = false;
      renderPanels();
    }
  }
}
requestAnimationFrame(animate);
connect();
