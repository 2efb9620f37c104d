// Live browser viewer of the shared deformable object (three.js, one ES module, no build step).
//
// Connects to ws://<page host>/ws as a `viewer` (on the page /rooms/NAME/: /rooms/NAME/ws, that
// room's) and receives the surface as the viewer stream
// (docs/protocol.md, "Viewer stream"): on join the triangles (FAC1), the rest positions (VTX1) and
// rest normals (NRM1) and a keyframe of displacements; then one displacement frame per simulation
// tick with only the displacements that changed, and a `room` summary. The displacements are
// normal (DSP1, the balloon: drawn rest + w * normal) or vectors (DSV1, the FEM solid, whose
// vertices also move sideways: drawn rest + d). It draws the object coloured
// by how far each point is pushed in or bulged out (legend in mm), turns the camera toward the
// deepest dent until the user moves it, and shows each user's probe, proxy and force (arrows
// scaled to stay in view) and a card per user with the surface indentation at its contact.
// A FEM solid with inclusions (`--inclusion`) also sends each lump's rest surface (INC1, decoded
// and checked by ./lump.js); the "show lump" checkbox (or `?lump=1`) draws it inside the object,
// which turns more transparent; it is hidden by default, since palpation is finding it by touch.
// A user in contact that has sent no state for 0.5 s is marked stale and shown with no force
// (see "stale users" below). Reconnects by itself with backoff.
//
// Late data is shown as late: the users panel and the connection indicator say how old the last
// `room` summary is ("last update 3.2 s ago") once it is older than LATE_AFTER_S, and keep the
// users as they were then; "Nobody is touching" is shown only when a fresh summary says so.
// `?snapshot=1` marks the page ready for a screenshot once the first `room` summary and the
// surface are in and drawn: `<html data-ready="1">` and "ready · " before the title (a headless
// browser waits for either, then takes its screenshot; see docs/usage.md).
//
// Test hooks: `window.viewerState` (connection, tick, frame counts, users by name, colour scale,
// dent, bytes per second, the last room summary's age and lateness, readiness, the lumps) is
// updated live; `window.viewerPositions(indices)` returns where the
// surface vertices are drawn ([x, y, z] [m] each, from the geometry the renderer uses).
// Protocol constants come from ./protocol.js, generated from shared/protocol.py; the viewer
// stream's own constants (STREAM below) mirror server/viewer_stream.py, checked by a test.
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
import { INCLUSION, decodeInclusion, lumpColor, stiffnessText } from "./lump.js";

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

/** Viewer-stream frames, as server/viewer_stream.py defines them (not in shared/protocol.py). */
export const STREAM = Object.freeze({
  NORMALS_MAGIC: "NRM1", // rest unit normals: BINARY_HEADER, count x 3 float32
  DISPLACEMENT_MAGIC: "DSP1", // magic, uint32 tick, count, quantum [nm], flags; then the body
  VECTOR_MAGIC: "DSV1", // the same header; three int16 (x, y, z) per vertex instead of one
  DSP_HEADER_BYTES: 20,
  FLAG_DENSE: 1, // body: n values (DSP1) or n x 3 (DSV1) int16 in vertex order
  FLAG_KEY: 2, // keyframe (every vertex)
  FLAG_INDEX32: 4, // uint32 indices (else uint16), then int16 values
  FLAG_CLAMPED: 8,
  FLAG_PARTIAL: 16, // the server's byte budget held changes back; they follow
});

// ----------------------------------------------------------------------------- settings
const params = new URLSearchParams(location.search);
/** Arrow length per newton of force [m/N]: ?force_scale=0.01 for a fixed 1 cm per N; by default
 * a third of the object's radius per newton, reduced in steps of 1-2-5 so that the largest force
 * stays within ARROW_MAX_PER_RADIUS of the radius and every arrow tip stays in view. */
const FORCE_SCALE_PARAM = positiveParam("force_scale", 0);
const FORCE_SCALE_PER_RADIUS = 1 / 3;
const ARROW_MAX_PER_RADIUS = 0.55;
const RECONNECT_MIN_MS = 500;
const RECONNECT_MAX_MS = 8000;
const PANEL_REFRESH_MS = 100;
/** Per-user colours, picked by a hash of the name (the balloon is blue: none of these is). */
const USER_COLORS = [
  "#ff9f43", "#7bed9f", "#ff6b9d", "#ffd93d", "#b794f6",
  "#ff5c5c", "#38d9a9", "#c0eb75", "#e599f7", "#e9ecef",
];
/** Colour-scale ranges [mm]: the smallest that holds the largest displacement is shown. */
const COLOR_RANGES_MM = [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000];
/** A dent shallower than this [m] (or 0.5 % of the radius) is not worth turning the camera for. */
const DENT_MIN_M = 0.0005;
/** A user silent this long [s] is stale: the server no longer applies its force (its
 * RoomLimits.stale_after_s) and the viewer shows no force for it. */
const STALE_AFTER_S = 0.5;
/** The last `room` summary is late when older than this [s] (it comes every simulation tick,
 * 50 ms at 20 Hz): the users shown are then said to be as they were that long ago. */
const LATE_AFTER_S = 1.0;
/** `?snapshot=1`: mark the page ready for a screenshot once data is in (see the header). */
const SNAPSHOT = params.get("snapshot") === "1";
/** `?lump=1`: show the object's inclusions from the start (hidden by default: palpation is blind). */
const LUMP_PARAM = ["1", "true", "show"].includes(params.get("lump") ?? "");
/** Opacities of the skin (front, back) while the lumps are hidden and while they are shown. */
const SKIN_OPACITY = { hidden: [0.72, 0.55], shown: [0.3, 0.18] };

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
  frames: 0, // surface frames received (DSP1 or DSV1 after the keyframe)
  vectorFrames: 0, // of all surface frames, those with vector displacements (DSV1)
  faceFrames: 0, // FAC1 frames received
  keyframes: 0, // DSP1/DSV1 keyframes received
  partialFrames: 0, // DSP1/DSV1 frames the server's byte budget cut short
  roomMessages: 0,
  renders: 0,
  renderMs: null, // cost of the last render [ms]
  reconnects: 0,
  nVertices: 0,
  nFaces: 0,
  bytesPerS: 0, // binary bytes received over the last second
  simRateHz: null,
  object: null,
  lastError: null,
  colorScale: { range_mm: COLOR_RANGES_MM[0], max_in_mm: 0, max_out_mm: 0 },
  dent: null, // { index, depth_mm, px: [x, y], facing, in_view } of the deepest dent, or null
  autoView: true,
  forceScaleMPerN: 0.01,
  arrows: {}, // by name: { tip_px: [x, y], in_view, visible } of the force arrow, after a render
  users: {}, // by name: force_n_mag [N], penetration_mm, indentation_mm [mm], color, stale, ...
  roomAgeS: null, // how long ago the last room summary arrived [s] (null: none yet)
  late: false, // that summary is older than LATE_AFTER_S: the users shown are as they were then
  surfaceTick: -1, // tick of the last surface frame (DSP1/DSV1)
  // the object's inclusions (INC1): how many drawn, of how many the object has, shown or not,
  // triangles, frames refused as malformed; per lump its name, material, Young's modulus ratio,
  // whether the server decimated it, and where its centre is drawn ({ px: [x, y], in_view })
  lumps: { count: 0, of: 0, shown: LUMP_PARAM, triangles: 0, rejected: 0, items: [] },
  ready: false, // the first room summary and the surface are in and drawn (?snapshot=1 says so)
};
window.viewerState = viewerState;

// ----------------------------------------------------------------------------- DOM
const $ = (id) => document.getElementById(id);
const dom = {
  scene: $("scene"),
  view: $("view-area"),
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
  roomAge: $("room-age"),
  clientHint: $("client-hint"),
  toast: $("toast"),
  forceScale: $("force-scale"),
  cmIn: $("cm-in"),
  cmOut: $("cm-out"),
  autoView: $("auto-view"),
  lumpToggle: $("lump-toggle"),
  showLump: $("show-lump"),
  lumpInfo: $("lump-info"),
};

function fmt(x, digits = 1) {
  return typeof x === "number" && Number.isFinite(x) ? x.toFixed(digits) : "–";
}

function fmtInt(x) {
  return typeof x === "number" && Number.isFinite(x) ? Math.round(x).toLocaleString("en-US") : "–";
}

function fmtLength(m) {
  if (m >= 0.01) return `${+(m * 100).toPrecision(2)} cm`;
  return `${+(m * 1000).toPrecision(2)} mm`;
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
controls.addEventListener("start", () => setAutoView(false)); // the user takes the camera

scene.add(new THREE.HemisphereLight(0xcfe6ff, 0x1a1f2e, 0.9));
const key = new THREE.DirectionalLight(0xffffff, 2.0);
key.position.set(1.2, -1.0, 2.0);
scene.add(key);
const rim = new THREE.DirectionalLight(0x7fb8ff, 1.2);
rim.position.set(-1.5, 1.4, 0.6);
scene.add(rim);

// The balloon: back faces first (darker, the inside wall), then the front skin coloured by the
// displacement, then a faint wireframe so that the shape reads clearly. All three share one
// BufferGeometry that the displacement frames update in place.
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
    color: 0xffffff,
    vertexColors: true,
    roughness: 0.3,
    metalness: 0.0,
    clearcoat: 0.6,
    clearcoatRoughness: 0.15,
    transparent: true,
    opacity: 0.72,
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
    opacity: 0.07,
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

// The inclusions, drawn opaque inside the object (at rest: they do not follow the deformation).
const lumpGroup = new THREE.Group();
lumpGroup.visible = false;
scene.add(lumpGroup);

let objectRadius = 0.05;
const objectCenter = new THREE.Vector3();
let framed = false;
let viewDistance = 0.5;
/** Where the camera looks from by default: about 40 degrees above the equator. */
const DEFAULT_VIEW_DIR = new THREE.Vector3(0.55, -0.8, 0.72).normalize();

/** Place the floor and frame the camera on the object (first welcome only: keep the user's view). */
function frameObject(obj) {
  const c = objectCenter.set(...obj.center_m);
  const r = Math.max(obj.radius_m, 1e-3);
  objectRadius = r;
  if (FORCE_SCALE_PARAM) setForceScale(FORCE_SCALE_PARAM);
  else setForceScale(niceBelow(r * FORCE_SCALE_PER_RADIUS));
  const zFloor = obj.bounds_min_m[2];
  buildFloor(c, r, zFloor);
  if (framed) return;
  framed = true;
  viewDistance = fitDistance(r);
  camera.position.copy(c).addScaledVector(DEFAULT_VIEW_DIR, viewDistance);
  camera.near = r * 0.01;
  camera.far = r * 200;
  camera.updateProjectionMatrix();
  controls.target.copy(c);
  controls.minDistance = r * 1.2;
  controls.maxDistance = r * 30;
  controls.update();
  sceneDirty = true;
}

/** Camera distance at which a sphere of radius 1.25 r (the object, probes and arrows near it)
 * fills the view area. */
function fitDistance(r) {
  const view = freeRegion();
  const halfV = THREE.MathUtils.degToRad(camera.fov / 2) * (view.h / window.innerHeight);
  const halfH = Math.atan(Math.tan(THREE.MathUtils.degToRad(camera.fov / 2)) * camera.aspect) *
    (view.w / window.innerWidth);
  return (1.25 * r) / Math.sin(0.95 * Math.max(Math.min(halfV, halfH), 0.05));
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

// ----------------------------------------------------------------------------- colour map
// Displacement t = w / range in [-1, 1], pushed in (negative) warm, bulged out cyan, blue at rest.
// The same stops (sRGB, 0-255) make the CSS legend (--cm in style.css).
const CM_STOPS = [
  [-1.0, [255, 217, 64]],
  [-0.55, [255, 115, 51]],
  [-0.22, [219, 71, 184]],
  [0.0, [46, 133, 255]],
  [0.5, [38, 217, 242]],
  [1.0, [204, 255, 242]],
];
const CM_SIZE = 512;
/** Linear-sRGB lookup table, CM_SIZE entries from t = -1 to 1 (vertex colours are linear). */
const CM_LUT = (() => {
  const lut = new Float32Array(CM_SIZE * 3);
  const toLinear = (c) => (c <= 0.04045 ? c / 12.92 : ((c + 0.055) / 1.055) ** 2.4);
  for (let i = 0; i < CM_SIZE; i++) {
    const t = -1 + (2 * i) / (CM_SIZE - 1);
    let k = 0;
    while (k < CM_STOPS.length - 2 && t > CM_STOPS[k + 1][0]) k++;
    const [t0, c0] = CM_STOPS[k];
    const [t1, c1] = CM_STOPS[k + 1];
    const a = Math.min(1, Math.max(0, (t - t0) / (t1 - t0)));
    for (let j = 0; j < 3; j++) lut[3 * i + j] = toLinear((c0[j] + a * (c1[j] - c0[j])) / 255);
  }
  return lut;
})();

function setColorRange(rangeMm) {
  viewerState.colorScale.range_mm = rangeMm;
  dom.cmIn.textContent = `−${rangeMm} mm`;
  dom.cmOut.textContent = `+${rangeMm} mm`;
}
setColorRange(COLOR_RANGES_MM[0]);

// ----------------------------------------------------------------------------- surface frames
// The surface: rest positions and normals (once), a displacement per vertex (the stream): either
// w [m] along the normal (DSP1), positions rest + w * normal, or a vector d [m] (DSV1), positions
// rest + d and w its normal component; colours by w; written in place into the shared geometry.
const mesh = {
  n: 0,
  rest: null, // Float32Array (3n) [m]
  normal: null, // Float32Array (3n), unit
  w: null, // Float32Array (n) [m], outward positive (with vectors, d . normal)
  d: null, // Float32Array (3n) [m] vector displacements once a DSV1 frame came; null with DSP1
  rangeM: COLOR_RANGES_MM[0] / 1000, // colour-scale range [m]
  shrinkFrames: 0, // frames in a row the displacement would fit a smaller range
  dentIndex: -1, // vertex of the deepest dent, -1 when there is none worth showing
};

function readMagic(buf) {
  if (buf.byteLength < 4) return "";
  const b = new Uint8Array(buf, 0, 4);
  return String.fromCharCode(b[0], b[1], b[2], b[3]);
}

/** Header of FAC1/VTX1/NRM1 (magic, uint32 tick, uint32 count) if the length matches. */
function readHeader(buf) {
  if (buf.byteLength < BINARY_HEADER_BYTES) return null;
  const dv = new DataView(buf);
  const tick = dv.getUint32(4, true);
  const count = dv.getUint32(8, true);
  if (buf.byteLength !== BINARY_HEADER_BYTES + count * 12) return null;
  return { tick, count };
}

/** Little-endian count x 3 values after the header (typed arrays are little-endian in browsers). */
function body(buf, count, Kind) {
  return new Kind(buf, BINARY_HEADER_BYTES, count * 3);
}

const byteLog = []; // [arrival time ms, bytes] of recent binary frames

function onBinary(buf) {
  const now = performance.now();
  byteLog.push([now, buf.byteLength]);
  const magic = readMagic(buf);
  if (magic === INCLUSION.MAGIC) {
    onInclusion(buf);
    return;
  }
  if (magic === STREAM.DISPLACEMENT_MAGIC || magic === STREAM.VECTOR_MAGIC) {
    if (!onDisplacement(buf, magic === STREAM.VECTOR_MAGIC)) {
      console.warn(`viewer: malformed ${magic} frame ignored`);
    }
    return;
  }
  const h = readHeader(buf);
  if (!h) {
    console.warn(`viewer: malformed binary frame ${magic} ignored`);
    return;
  }
  if (magic === FACES_MAGIC) {
    viewerState.faceFrames += 1;
    viewerState.nFaces = h.count;
    surface.dispose(); // (re)connected: free the previous GPU buffers, they are re-uploaded
    surface.setIndex(new THREE.BufferAttribute(body(buf, h.count, Uint32Array).slice(), 1));
    showSurface();
  } else if (magic === VERTICES_MAGIC) {
    setRest(body(buf, h.count, Float32Array).slice());
  } else if (magic === STREAM.NORMALS_MAGIC) {
    if (h.count === mesh.n) {
      mesh.normal = body(buf, h.count, Float32Array).slice();
      if (mesh.d) for (let i = 0; i < mesh.n; i++) mesh.w[i] = normalPart(i);
      writeAll();
    }
  } else {
    console.warn(`viewer: unknown binary frame ${magic}`);
  }
}

/** VTX1: the rest positions; the surface is at rest until displacements arrive. */
function setRest(rest) {
  const n = rest.length / 3;
  mesh.n = n;
  mesh.rest = rest;
  mesh.w = new Float32Array(n);
  mesh.d = null; // the stream's keyframe says which form follows
  if (!mesh.normal || mesh.normal.length !== 3 * n) mesh.normal = new Float32Array(3 * n);
  let pos = surface.getAttribute("position");
  if (!pos || pos.count !== n) {
    pos = new THREE.BufferAttribute(new Float32Array(3 * n), 3);
    pos.setUsage(THREE.DynamicDrawUsage);
    surface.setAttribute("position", pos);
    const col = new THREE.BufferAttribute(new Float32Array(3 * n), 3);
    col.setUsage(THREE.DynamicDrawUsage);
    surface.setAttribute("color", col);
    surface.deleteAttribute("normal"); // recomputed at the new size
    viewerState.nVertices = n;
  }
  writeAll();
}

/** DSP1 (`vector` false: w along the normals) or DSV1 (`vector` true: d, three int16 a vertex):
 * displacements of some or all vertices. Returns false, changing nothing, for a malformed frame. */
function onDisplacement(buf, vector) {
  if (buf.byteLength < STREAM.DSP_HEADER_BYTES || !mesh.rest) return false;
  const dv = new DataView(buf);
  const tick = dv.getUint32(4, true);
  const count = dv.getUint32(8, true);
  const quantumM = dv.getUint32(12, true) * 1e-9;
  const flags = dv.getUint32(16, true);
  const axes = vector ? 3 : 1; // int16 values per vertex
  const off = STREAM.DSP_HEADER_BYTES;
  let index = null;
  let values;
  if (flags & STREAM.FLAG_DENSE) {
    if (count !== mesh.n || buf.byteLength !== off + 2 * axes * count) return false;
    values = new Int16Array(buf, off, axes * count);
  } else {
    const width = flags & STREAM.FLAG_INDEX32 ? 4 : 2;
    if (buf.byteLength !== off + (width + 2 * axes) * count) return false;
    index = width === 4 ? new Uint32Array(buf, off, count) : new Uint16Array(buf, off, count);
    for (let k = 0; k < count; k++) if (index[k] >= mesh.n) return false;
    values = new Int16Array(buf, off + width * count, axes * count);
  }
  const w = mesh.w;
  let redrawAll = !index;
  if (vector) {
    if (!mesh.d) mesh.d = new Float32Array(3 * mesh.n);
    const d = mesh.d;
    for (let k = 0; k < count; k++) {
      const i = index ? index[k] : k;
      d[3 * i] = values[3 * k] * quantumM;
      d[3 * i + 1] = values[3 * k + 1] * quantumM;
      d[3 * i + 2] = values[3 * k + 2] * quantumM;
      w[i] = normalPart(i);
    }
    viewerState.vectorFrames += 1;
  } else {
    if (mesh.d) {
      mesh.d = null; // back to normal displacements: every vertex is redrawn along its normal
      redrawAll = true;
    }
    for (let k = 0; k < count; k++) w[index ? index[k] : k] = values[k] * quantumM;
  }
  if (flags & STREAM.FLAG_KEY) viewerState.keyframes += 1;
  else viewerState.frames += 1;
  if (flags & STREAM.FLAG_PARTIAL) viewerState.partialFrames += 1;
  viewerState.tick = tick;
  viewerState.surfaceTick = tick;
  frameTimes.push(performance.now());
  if (updateColorRange() || redrawAll) writeAll();
  else writeSome(index);
  return true;
}

/** The normal component d . normal [m] of vertex i's vector displacement (outward positive). */
function normalPart(i) {
  const d = mesh.d;
  const nrm = mesh.normal;
  const j = 3 * i;
  return d[j] * nrm[j] + d[j + 1] * nrm[j + 1] + d[j + 2] * nrm[j + 2];
}

/** Pick the colour range for the current displacement: up at once, down after 2 s. */
function updateColorRange() {
  const w = mesh.w;
  let lo = 0;
  let hi = 0;
  let deepest = -1;
  for (let i = 0; i < mesh.n; i++) {
    if (w[i] < lo) {
      lo = w[i];
      deepest = i;
    }
    if (w[i] > hi) hi = w[i];
  }
  viewerState.colorScale.max_in_mm = -lo * 1000;
  viewerState.colorScale.max_out_mm = hi * 1000;
  mesh.dentIndex = -lo > Math.max(DENT_MIN_M, 0.005 * objectRadius) ? deepest : -1;
  const peakMm = Math.max(-lo, hi) * 1000;
  const fit = COLOR_RANGES_MM.find((r) => r >= peakMm) ?? COLOR_RANGES_MM.at(-1);
  const current = viewerState.colorScale.range_mm;
  mesh.shrinkFrames = fit < current ? mesh.shrinkFrames + 1 : 0;
  const shrink = mesh.shrinkFrames > 2 * (viewerState.simRateHz || 20);
  if (fit > current || shrink) {
    mesh.shrinkFrames = 0;
    mesh.rangeM = fit / 1000;
    setColorRange(fit);
    return true;
  }
  return false;
}

function writeVertex(i, pos, col) {
  const w = mesh.w[i];
  const r = mesh.rest;
  const j = 3 * i;
  const d = mesh.d;
  if (d) {
    pos[j] = r[j] + d[j];
    pos[j + 1] = r[j + 1] + d[j + 1];
    pos[j + 2] = r[j + 2] + d[j + 2];
  } else {
    const nrm = mesh.normal;
    pos[j] = r[j] + w * nrm[j];
    pos[j + 1] = r[j + 1] + w * nrm[j + 1];
    pos[j + 2] = r[j + 2] + w * nrm[j + 2];
  }
  const t = Math.max(-1, Math.min(1, w / mesh.rangeM));
  const k = 3 * Math.round(((t + 1) / 2) * (CM_SIZE - 1));
  col[j] = CM_LUT[k];
  col[j + 1] = CM_LUT[k + 1];
  col[j + 2] = CM_LUT[k + 2];
}

function writeAll() {
  const pos = surface.getAttribute("position");
  const col = surface.getAttribute("color");
  if (!pos || !mesh.rest) return;
  for (let i = 0; i < mesh.n; i++) writeVertex(i, pos.array, col.array);
  pos.needsUpdate = col.needsUpdate = true;
  showSurface();
}

function writeSome(index) {
  if (index.length === 0) return;
  const pos = surface.getAttribute("position");
  const col = surface.getAttribute("color");
  for (let k = 0; k < index.length; k++) writeVertex(index[k], pos.array, col.array);
  pos.needsUpdate = col.needsUpdate = true;
  showSurface();
}

function showSurface() {
  const pos = surface.getAttribute("position");
  if (!pos || !surface.index || surface.index.count === 0) return;
  surface.computeVertexNormals();
  sceneDirty = true;
  if (!skin.visible) {
    surface.computeBoundingSphere();
    for (const m of [skinBack, skin, wire]) m.visible = true;
  }
}

/** Where vertices `indices` are drawn: [x, y, z] [m] each, null before the surface (a test hook). */
window.viewerPositions = (indices) => {
  const pos = surface.getAttribute("position");
  if (!pos || !mesh.rest) return null;
  return indices.map((i) => [pos.array[3 * i], pos.array[3 * i + 1], pos.array[3 * i + 2]]);
};

/** Displacement [m] of the current surface vertex nearest to a point, or null. */
function displacementNear(p) {
  const pos = surface.getAttribute("position");
  if (!pos || !mesh.w) return null;
  const a = pos.array;
  let best = Infinity;
  let at = -1;
  for (let i = 0, j = 0; i < mesh.n; i++, j += 3) {
    const dx = a[j] - p[0];
    const dy = a[j + 1] - p[1];
    const dz = a[j + 2] - p[2];
    const d = dx * dx + dy * dy + dz * dz;
    if (d < best) {
      best = d;
      at = i;
    }
  }
  return at < 0 ? null : mesh.w[at];
}

// ----------------------------------------------------------------------------- lumps (INC1)
const lumpMeshes = new Map(); // index -> THREE.Mesh

/** INC1: one inclusion's rest surface; a malformed one is counted and left out. */
function onInclusion(buf) {
  const lumps = viewerState.lumps;
  const res = decodeInclusion(buf);
  const old = res.ok ? lumpMeshes.get(res.lump.index) : undefined;
  const others = lumps.triangles - (old ? old.geometry.index.count / 3 : 0);
  if (res.ok && others + res.lump.indices.length / 3 > INCLUSION.MAX_FACES) {
    res.ok = false;
    res.reason = "more triangles than the server may send";
  }
  if (!res.ok) {
    lumps.rejected += 1;
    console.warn(`viewer: malformed ${INCLUSION.MAGIC} frame ignored (${res.reason})`);
    return;
  }
  const lump = res.lump;
  if (old) dropLump(lump.index);
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(lump.positions, 3));
  geometry.setIndex(new THREE.BufferAttribute(lump.indices, 1));
  geometry.computeVertexNormals();
  geometry.computeBoundingBox();
  const color = lumpColor(lump.youngRatio);
  const m = new THREE.Mesh(
    geometry,
    new THREE.MeshStandardMaterial({
      color,
      emissive: color,
      emissiveIntensity: 0.25,
      roughness: 0.5,
      metalness: 0.0,
    }),
  );
  m.renderOrder = 2; // after the inside wall, before the skin drawn over it
  m.userData = {
    index: lump.index,
    centre: geometry.boundingBox.getCenter(new THREE.Vector3()),
    info: {
      index: lump.index,
      name: lump.name,
      material: lump.material,
      young_ratio: lump.youngRatio,
      decimated: lump.decimated,
      triangles: lump.indices.length / 3,
      color,
      px: null,
      in_view: false,
    },
  };
  lumpMeshes.set(lump.index, m);
  lumpGroup.add(m);
  lumps.of = lump.of;
  updateLumps();
}

function dropLump(index) {
  const m = lumpMeshes.get(index);
  if (!m) return;
  lumpGroup.remove(m);
  m.geometry.dispose();
  m.material.dispose();
  lumpMeshes.delete(index);
}

/** A new join (welcome): the lumps come again after the surface, if the object has any. */
function clearLumps() {
  for (const index of [...lumpMeshes.keys()]) dropLump(index);
  viewerState.lumps.of = 0;
  updateLumps();
}

/** Counts, the checkbox and its text, what is drawn and how transparent the skin is. */
function updateLumps() {
  const lumps = viewerState.lumps;
  const items = [...lumpMeshes.values()].sort((a, b) => a.userData.index - b.userData.index);
  lumps.count = items.length;
  lumps.items = items.map((m) => m.userData.info);
  lumps.triangles = lumps.items.reduce((sum, it) => sum + it.triangles, 0);
  const shown = lumps.shown && lumps.count > 0;
  lumpGroup.visible = shown;
  const [front, back] = shown ? SKIN_OPACITY.shown : SKIN_OPACITY.hidden;
  skin.material.opacity = front;
  skinBack.material.opacity = back;
  dom.lumpToggle.hidden = lumps.count === 0;
  dom.showLump.checked = lumps.shown;
  dom.lumpToggle.classList.toggle("on", shown);
  const words = lumps.items.map((it) =>
    [it.name, it.material, stiffnessText(it.young_ratio)].filter(Boolean).join(" · "));
  const more = lumps.of > lumps.count ? ` (${lumps.count} of ${lumps.of})` : "";
  dom.lumpInfo.textContent = shown ? `${words.join("; ")}${more}` : `hidden${more}`;
  dom.lumpToggle.title = `${words.join("\n")}\ndrawn at rest: it does not follow the deformation`;
  sceneDirty = true;
}

function setLumpShown(on) {
  viewerState.lumps.shown = on;
  updateLumps();
}
dom.showLump.addEventListener("change", () => setLumpShown(dom.showLump.checked));
updateLumps();

/** After a render: where each lump's centre is drawn (a test hook). */
function updateLumpHook() {
  for (const m of lumpMeshes.values()) {
    const s = toScreen(m.userData.centre);
    m.userData.info.px = s.px;
    m.userData.info.in_view = s.inView;
  }
}

// ----------------------------------------------------------------------------- camera: the dent
const tmpDir = new THREE.Vector3();
const wantDir = new THREE.Vector3();

function setAutoView(on) {
  viewerState.autoView = on;
  dom.autoView.setAttribute("aria-pressed", String(on));
  if (on && framed) {
    // back to the framing distance (the user may have zoomed); the direction follows the dent
    const dir = tmpDir.copy(camera.position).sub(controls.target).normalize();
    viewDistance = fitDistance(objectRadius);
    camera.position.copy(controls.target).addScaledVector(dir, viewDistance);
    sceneDirty = true;
  }
}
dom.autoView.addEventListener("click", () => setAutoView(!viewerState.autoView));

/** Direction from the object's centre to where the camera should be to see the deepest dent:
 * from the side of the dent, raised, and turned a little so that its depth shows. */
function dentViewDir(out) {
  const i = mesh.dentIndex;
  if (i < 0) return out.copy(tmpDir.copy(camera.position).sub(objectCenter).normalize());
  const nx = mesh.normal[3 * i];
  const ny = mesh.normal[3 * i + 1];
  const nz = mesh.normal[3 * i + 2];
  const horiz = Math.hypot(nx, ny);
  const cur = tmpDir.copy(camera.position).sub(objectCenter);
  const az = horiz > 0.3 ? Math.atan2(ny, nx) - 0.35 : Math.atan2(cur.y, cur.x);
  const el = Math.min(1.0, Math.max(0.3, 0.35 + 0.6 * Math.asin(Math.max(-1, Math.min(1, nz)))));
  return out.set(Math.cos(el) * Math.cos(az), Math.cos(el) * Math.sin(az), Math.sin(el));
}

/** Turn the camera a step toward the dent (auto view only); true while it is still turning. */
function followDent() {
  if (!viewerState.autoView || !framed || mesh.dentIndex < 0) return false;
  dentViewDir(wantDir);
  const off = tmpDir.copy(camera.position).sub(controls.target);
  const dist = off.length();
  off.normalize();
  if (off.angleTo(wantDir) < 0.01) return false;
  off.lerp(wantDir, 0.06).normalize();
  camera.position.copy(controls.target).addScaledVector(off, dist);
  camera.lookAt(controls.target);
  return true;
}

const projected = new THREE.Vector3();

/** CSS-pixel position of a world point on the canvas, and whether it is inside the view area. */
function toScreen(p) {
  projected.copy(p).project(camera);
  const x = ((projected.x + 1) / 2) * window.innerWidth;
  const y = ((1 - projected.y) / 2) * window.innerHeight;
  const v = freeRegion();
  const inView = projected.z < 1 && x >= v.x && x <= v.x + v.w && y >= v.y && y <= v.y + v.h;
  return { px: [x, y], inView };
}

function updateDentHook() {
  const i = mesh.dentIndex;
  if (i < 0 || !mesh.rest) {
    viewerState.dent = null;
    return;
  }
  const pos = surface.getAttribute("position").array;
  const p = new THREE.Vector3(pos[3 * i], pos[3 * i + 1], pos[3 * i + 2]);
  const n = new THREE.Vector3(mesh.normal[3 * i], mesh.normal[3 * i + 1], mesh.normal[3 * i + 2]);
  const toCam = tmpDir.copy(camera.position).sub(p).normalize();
  const s = toScreen(p);
  viewerState.dent = {
    index: i,
    depth_mm: -mesh.w[i] * 1000,
    px: s.px,
    in_view: s.inView,
    facing: n.dot(toCam), // > 0: the camera sees the dent from outside
  };
}

// ----------------------------------------------------------------------------- users (3-D)
const actors = new Map(); // user_id -> { group, probe, proxy, tether, arrow, label, tag, tip }
const Z = new THREE.Vector3(0, 0, 1);
const tmpA = new THREE.Vector3();
const tmpB = new THREE.Vector3();
let forceScaleMPerN = 0.01;
let scaleUpFrames = 0; // room messages in a row the arrows would fit a larger scale
let viewCap = { mPerN: Infinity, forceN: 0 }; // set when an arrow tip left the view at forceN

/** A colour per user name: the same in every viewer and whoever joined first (FNV-1a hash). */
function userColor(name) {
  let h = 0x811c9dc5;
  for (const ch of String(name)) {
    h ^= ch.codePointAt(0);
    h = Math.imul(h, 0x01000193) >>> 0;
  }
  return USER_COLORS[h % USER_COLORS.length];
}

/** The largest 1-2-5 x 10^k not above x. */
function niceBelow(x) {
  const e = 10 ** Math.floor(Math.log10(x));
  const m = x / e;
  return (m >= 5 ? 5 : m >= 2 ? 2 : 1) * e;
}

function setForceScale(mPerN) {
  forceScaleMPerN = mPerN;
  viewerState.forceScaleMPerN = mPerN;
  dom.forceScale.textContent = fmtLength(mPerN);
}

/** Shrink the arrows at once when the largest force would run too long, grow back after 2 s. */
function updateForceScale(maxForceN) {
  if (FORCE_SCALE_PARAM) return;
  const preferred = niceBelow(objectRadius * FORCE_SCALE_PER_RADIUS);
  const cap = maxForceN > 0 ? niceBelow((ARROW_MAX_PER_RADIUS * objectRadius) / maxForceN) : preferred;
  if (maxForceN < 0.5 * viewCap.forceN) viewCap = { mPerN: Infinity, forceN: 0 };
  const want = Math.min(preferred, cap, viewCap.mPerN);
  if (want < forceScaleMPerN) {
    setForceScale(want);
    scaleUpFrames = 0;
  } else if (want > forceScaleMPerN) {
    scaleUpFrames += 1;
    if (scaleUpFrames > 2 * (viewerState.simRateHz || 20)) {
      setForceScale(want);
      scaleUpFrames = 0;
    }
  } else {
    scaleUpFrames = 0;
  }
}

function makeActor(u) {
  const color = new THREE.Color(userColor(u.name));
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
  return { group, probe, proxy, tether, arrow, label, tag, tip: new THREE.Vector3() };
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

/** Place a user's probe, proxy, tether and force arrow; a stale user gets a faded probe and no
 * proxy, tether or arrow (its hand no longer loads the object). */
function updateActor(a, u, stale) {
  a.probe.position.set(...u.probe_m);
  a.probe.material.opacity = stale ? 0.35 : 1;
  a.label.position.set(...u.probe_m);
  a.tag.textContent = stale ? `${u.name} · stale` : u.name;
  a.tag.classList.toggle("stale", stale);
  a.proxy.position.set(...u.proxy_m);
  tmpA.set(...u.normal);
  if (tmpA.lengthSq() > 1e-12) a.proxy.quaternion.setFromUnitVectors(Z, tmpA.normalize());
  a.proxy.visible = u.in_contact && !stale;
  const pts = a.tether.geometry.getAttribute("position");
  pts.setXYZ(0, ...u.probe_m);
  pts.setXYZ(1, ...u.proxy_m);
  pts.needsUpdate = true;
  a.tether.computeLineDistances();
  a.tether.visible = u.in_contact && !stale;
  tmpB.set(...u.force_n);
  const mag = tmpB.length();
  if (mag > 1e-4 && !stale) {
    const length = mag * forceScaleMPerN;
    setArrow(a.arrow, tmpA.set(...u.probe_m), tmpB.normalize(), length);
    a.tip.copy(tmpA).addScaledVector(tmpB, length);
    a.arrow.visible = true;
  } else {
    a.tip.set(...u.probe_m);
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
const cards = new Map(); // user_id -> { root, fields, ... }
let forceBarScaleN = 2.0;

/** [key, label, unit, tooltip]: two rows of four columns; the first cell spans two. */
const CARD_ROWS = [
  ["penetration_mm", "probe–proxy", "mm", "how far the probe is past its local model (penetration)"],
  ["k_o", "K<sub>o</sub>", "N/m", "object stiffness at the contact"],
  ["k_o_eff", "K<sub>o,eff</sub>", "N/m", "coupling-aware stiffness the gains stay below"],
  ["k_h", "K<sub>h</sub>", "N/m", "local model stiffness"],
  ["i_gain", "I", "N/(m·s)", "local model integral weight"],
  ["servo_rate_hz", "servo", "Hz", "haptic loop rate"],
  ["rtt_ms", "RTT", "ms", "network round trip"],
];

function makeCard(userId, name) {
  const root = document.createElement("section");
  root.className = "user";
  root.style.setProperty("--c", userColor(name));
  root.innerHTML = `
    <header>
      <span class="swatch"></span>
      <span class="name"></span>
      <span class="device"></span>
      <span class="badge"></span>
    </header>
    <div class="big">
      <div><span class="label">force</span>
        <span class="value"><span class="force-value">–</span><small>N</small></span></div>
      <div title="how far the surface is pushed in at this user's contact">
        <span class="label">indentation</span>
        <span class="value indent-value"><span class="indent-number">–</span><small>mm</small></span></div>
    </div>
    <div class="bar"><span></span></div>
    <dl>${CARD_ROWS.map(([k, label, unit, hint]) => `<div title="${hint}"><dt>${label} <small>${unit}</small></dt><dd data-k="${k}">–</dd></div>`).join("")}</dl>`;
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
    indent: root.querySelector(".indent-value"),
    bar: root.querySelector(".bar > span"),
  };
}

function setIndentation(card, mm) {
  if (mm === null) {
    card.indent.classList.add("none");
    card.indent.textContent = "not in contact";
    return;
  }
  if (card.indent.classList.contains("none") || !card.indent.querySelector(".indent-number")) {
    card.indent.classList.remove("none");
    card.indent.innerHTML = '<span class="indent-number"></span><small>mm</small>';
  }
  // pushed in is positive; a contact the water pushed outward reads as "out"
  card.indent.querySelector(".indent-number").textContent =
    mm >= 0 ? fmt(mm, 2) : `${fmt(-mm, 2)} out`;
}

function renderPanels() {
  const entries = Object.values(viewerState.users); // the count and "nobody": renderFreshness
  const maxF = Math.max(0, ...entries.map((s) => s.force_n_mag));
  forceBarScaleN = Math.max(forceBarScaleN * 0.995, maxF * 1.25, 1.0);
  for (const s of entries) {
    let card = cards.get(s.user_id);
    if (!card) {
      card = makeCard(s.user_id, s.name);
      cards.set(s.user_id, card);
    }
    card.root.dataset.userName = s.name;
    card.root.classList.toggle("touching", s.in_contact && !s.stale);
    card.root.classList.toggle("stale", s.stale);
    card.name.textContent = s.name;
    card.badge.textContent = s.stale ? "stale" : s.in_contact ? "in contact" : "free";
    card.badge.title = s.stale
      ? `no state from this user for ${fmt(s.stale_s, 1)} s: the server no longer applies its force`
      : "";
    card.device.textContent = s.device;
    // a stale user's force is not applied: none is shown (not its last one)
    card.force.textContent = s.stale ? "–" : fmt(s.force_n_mag, 2);
    const barN = s.stale ? 0 : s.force_n_mag;
    card.bar.style.width = `${Math.min(100, (100 * barN) / forceBarScaleN).toFixed(1)}%`;
    setIndentation(card, s.indentation_mm);
    const pen = card.fields.penetration_mm;
    if (s.in_contact) pen.textContent = fmt(s.penetration_mm, 2);
    else pen.innerHTML = '<span class="none">not in contact</span>'; // not a negative depth
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
let lastRoomMs = null; // performance.now() when the last room summary arrived
let liveText = "live"; // the connection indicator's text while the summaries are fresh
let meshInfo = "";
const frameTimes = []; // arrival times of recent displacement frames [ms]

function renderHeader() {
  const now = performance.now();
  while (frameTimes.length && now - frameTimes[0] > 1000) frameTimes.shift();
  while (byteLog.length && now - byteLog[0][0] > 1000) byteLog.shift();
  viewerState.bytesPerS = byteLog.reduce((sum, [, b]) => sum + b, 0);
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
  renderFreshness(now);
  dom.mesh.textContent = viewerState.nVertices
    ? `${meshInfo} · ${frameTimes.length} fps · ${fmt(viewerState.bytesPerS / 1000, 1)} kB/s`
    : "–";
}

/** Say how old the users shown are: "Nobody is touching" only when a fresh room summary has
 * no user; a late summary's users are kept, with its age; none yet is "waiting", not "nobody". */
function renderFreshness(now) {
  const age = lastRoomMs === null ? null : (now - lastRoomMs) / 1000;
  const late = age !== null && age > LATE_AFTER_S;
  viewerState.roomAgeS = age;
  viewerState.late = late;
  const n = lastRoom ? lastRoom.users.length : null;
  dom.userCount.textContent = n === null ? "–" : String(n);
  dom.noUsers.hidden = !(lastRoom && !late && n === 0);
  let text = "";
  if (!lastRoom) {
    text = viewerState.connected ? "waiting for the first update from the server…" : "";
  } else if (late) {
    const ago = `last update ${fmt(age, 1)} s ago`;
    text = n ? `${ago}: the users as they were then` : `${ago}: nobody was touching then`;
  }
  if (dom.roomAge.textContent !== text) dom.roomAge.textContent = text;
  dom.roomAge.hidden = !text;
  dom.users.classList.toggle("late", late);
  if (viewerState.connected) {
    if (late) setStatus("late", `late · last update ${fmt(age, 1)} s ago`);
    else if (viewerState.status !== "connected") setStatus("connected", liveText);
  }
}

/** ?snapshot=1: once the first room summary and the surface are in and drawn, say so. */
function markReady() {
  if (viewerState.ready || !lastRoom || viewerState.surfaceTick < 0 || !framed) return;
  viewerState.ready = true;
  if (!SNAPSHOT) return;
  document.documentElement.dataset.ready = "1";
  document.title = `ready · ${document.title}`;
}

function linkText(link) {
  if (!link) return "–";
  if (!(link.latency_ms > 0 || link.jitter_ms > 0 || link.loss > 0)) return "none";
  const parts = [`${fmt(link.latency_ms, 0)} ms`];
  if (link.jitter_ms > 0) parts[0] += ` ± ${fmt(link.jitter_ms, 0)}`;
  if (link.loss > 0) parts.push(`${fmt(link.loss * 100, 1)} % loss`);
  return parts.join(" · ");
}

// ----------------------------------------------------------------------------- stale users
// The room frame does not say how old a user's state is. The viewer infers it from what it sees:
// a silent user's own report (probe, penetration, contact, gains, servo rate, RTT) stays exactly
// as it was, and the server applies no force for it once its state is older than STALE_AFTER_S.
// A user is stale when all three hold: its report has not changed for STALE_AFTER_S of simulation
// ticks, that report says its local model is pushing (in contact, penetration and K_h > 0), and
// the force the server applies for it is exactly zero. A user that went silent in free air is
// not marked (it had no force to show); one holding perfectly still in free air is not mistaken
// for a silent one.
const freshness = new Map(); // user_id -> { sig, tick } of the last change in the user's report

/** How long [s] user `u`'s own report has not changed, at tick `tick` and `simRateHz`. */
function reportAge(u, tick, simRateHz) {
  const sig = [
    ...u.probe_m, u.penetration_m, u.in_contact, u.k_h, u.i_gain, u.servo_rate_hz, u.rtt_ms,
  ].join(",");
  const seen = freshness.get(u.user_id);
  if (!seen || seen.sig !== sig || tick < seen.tick) {
    freshness.set(u.user_id, { sig, tick });
    return 0;
  }
  return (tick - seen.tick) / (simRateHz > 0 ? simRateHz : 20);
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
  clearLumps();
  reconnectAttempt = 0;
  liveText = `live · ${fmt(welcome.sim_rate_hz, 0)} Hz`;
  setStatus("connected", liveText);
  const obj = welcome.object;
  meshInfo = `${fmtInt(obj.n_vertices)} v · ${fmtInt(obj.n_faces)} f`;
  frameObject(obj);
  dom.link.textContent = linkText(welcome.link);
}

function onRoom(room) {
  viewerState.roomMessages += 1;
  viewerState.tick = room.tick;
  lastRoomMs = performance.now();
  viewerState.simRateHz = room.sim_rate_hz;
  lastRoom = room;
  let maxForce = 0;
  for (const u of room.users) {
    const f = u.force_n;
    maxForce = Math.max(maxForce, Math.hypot(f[0], f[1], f[2]));
  }
  updateForceScale(maxForce);
  const byName = {};
  const live = new Set();
  for (const u of room.users) {
    live.add(u.user_id);
    const f = u.force_n;
    const w = u.in_contact ? displacementNear(u.proxy_m) : null;
    const age = reportAge(u, room.tick, room.sim_rate_hz);
    const pushing = u.in_contact && u.penetration_m > 0 && u.k_h > 0;
    const stale = pushing && age > STALE_AFTER_S && f[0] === 0 && f[1] === 0 && f[2] === 0;
    byName[u.name] = {
      user_id: u.user_id,
      name: u.name,
      color: userColor(u.name),
      device: u.device,
      stale,
      stale_s: stale ? age : 0, // how long its report has not changed [s]
      in_contact: u.in_contact,
      force_n: f,
      force_n_mag: Math.hypot(f[0], f[1], f[2]),
      penetration_mm: u.penetration_m === null || u.penetration_m === undefined ? null : u.penetration_m * 1000,
      indentation_mm: w === null ? null : -w * 1000,
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
    updateActor(a, u, stale);
  }
  viewerState.users = byName;
  for (const name of Object.keys(viewerState.arrows)) if (!byName[name]) delete viewerState.arrows[name];
  for (const id of [...actors.keys()]) if (!live.has(id)) dropActor(id);
  for (const id of [...freshness.keys()]) if (!live.has(id)) freshness.delete(id);
  panelsDirty = true;
  sceneDirty = true;
}

/** After a render: where the arrow tips are; a tip out of the view area shrinks the arrows. */
function checkArrowsInView() {
  let out = false;
  let maxForceN = 0;
  for (const s of Object.values(viewerState.users)) {
    const a = actors.get(s.user_id);
    if (!a) continue;
    const t = toScreen(a.tip);
    viewerState.arrows[s.name] = { tip_px: t.px, in_view: t.inView, visible: a.arrow.visible };
    out ||= !t.inView && a.arrow.visible;
    maxForceN = Math.max(maxForceN, s.force_n_mag);
  }
  if (out && !FORCE_SCALE_PARAM && forceScaleMPerN > objectRadius * 1e-3) {
    setForceScale(niceBelow(forceScaleMPerN * 0.99));
    viewCap = { mPerN: forceScaleMPerN, forceN: maxForceN };
    scaleUpFrames = 0;
    sceneDirty = true; // redrawn with shorter arrows at the next room message
  }
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

// The page's room: /rooms/NAME/ is room NAME (its websocket /rooms/NAME/ws), any other path the
// default room (/ws); server/urls.py routes the same paths.
function roomWsPath(pathname) {
  const m = /^\/rooms\/([a-z0-9](?:[a-z0-9-]{0,30}[a-z0-9])?)\//.exec(pathname);
  return m ? `/rooms/${m[1]}/ws` : "/ws";
}

function wsUrl() {
  const override = params.get("ws");
  if (override) return override;
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  return `${scheme}://${location.host}${roomWsPath(location.pathname)}`;
}
// one option a line (a shell continuation): the URL is never broken in two
dom.clientHint.textContent = `haptic client --name alice \\\n  --url ${wsUrl()}`;

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
    const hello = { type: "hello", protocol: PROTOCOL_VERSION, role: "viewer", name: "viewer" };
    // a server with tokens: open http(s)://HOST:PORT/#token=TOKEN (a fragment never reaches a
    // server or its logs); the token is sent only in hello and never logged here
    const token = new URLSearchParams(location.hash.slice(1)).get("token");
    if (token) hello.token = token;
    sock.send(JSON.stringify(hello));
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
/** The view area: the grid cell the panels leave free [CSS px] (the whole window as fallback). */
function freeRegion() {
  const r = dom.view.getBoundingClientRect();
  if (r.width < 40 || r.height < 40) {
    return { x: 0, y: 0, w: window.innerWidth, h: window.innerHeight };
  }
  return { x: r.left, y: r.top, w: r.width, h: r.height };
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
  if (framed && viewerState.autoView) {
    // keep the object filling the view area: the same direction, the distance that fits now
    const dir = tmpDir.copy(camera.position).sub(controls.target).normalize();
    viewDistance = fitDistance(objectRadius);
    camera.position.copy(controls.target).addScaledVector(dir, viewDistance);
  }
  sceneDirty = true;
}
window.addEventListener("resize", resize);
new ResizeObserver(resize).observe(dom.view); // the grid reflows when the header wraps
resize();

let lastPanelMs = 0;

function animate(now) {
  requestAnimationFrame(animate);
  controls.update(); // fires "change" while damping settles
  if (followDent()) sceneDirty = true;
  if (sceneDirty) {
    sceneDirty = false;
    const t0 = performance.now();
    renderer.render(scene, camera);
    labels.render(scene, camera);
    viewerState.renders += 1;
    viewerState.renderMs = performance.now() - t0;
    checkArrowsInView();
    updateDentHook();
    updateLumpHook();
    markReady();
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
