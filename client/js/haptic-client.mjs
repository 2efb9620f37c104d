#!/usr/bin/env node
// Reference haptic user client in Node.js, written from docs/protocol.md (wire protocol 1).
//
// Main thread: the network link (the `ws` package) -- joins the room, streams `state` about twice
// per simulation tick, turns each `patch` into a primitive + gains for the servo thread, pings for
// the round trip, reconnects with backoff (its hello carrying the last welcome's resume token, so
// the server gives back the same seat within its hold time), prints a JSON summary at exit.
// With --lobby URL --room NAME it asks a lobby (haptic lobby, server/lobby.py) where the room runs
// and for a room token (GET LOBBY/rooms/NAME?role=user) before it joins, and asks again before
// rejoining once its server said it is draining (server_draining, close 1012/1013), refused the
// connection or refused an earlier token; a draining server is never picked, so it rejoins the
// room where it runs now.
// Worker thread (lib/servo-worker.mjs): the servo loop at 1 kHz with a simulated hand + device.
//
// Exit codes: 0 done; 1 a fatal `error` from the server, or the lobby refused the room (4xx but
// 429; the message on stderr); 2 bad command line; 3 never joined a room.

import { Worker, MessageChannel } from "node:worker_threads";
import { parseArgs } from "node:util";
import { writeFileSync } from "node:fs";
import { SNAP, movedOut, primitiveFromPatch } from "./lib/servo.mjs";
import { chooseGains, helloMessage, ownOffsetM, stateMessage } from "./lib/protocol.mjs";

// the `ws` package comes from client/js's lockfile: before `make js-install` say so, not a stack
let WebSocket;
try {
  ({ default: WebSocket } = await import("ws"));
} catch (err) {
  if (err && err.code === "ERR_MODULE_NOT_FOUND") {
    console.error(
      "haptic-client: the 'ws' package is not installed here: run `make js-install` " +
        "(or `npm ci` in client/js) first"
    );
    process.exit(2);
  }
  throw err;
}

const USAGE = `usage: node haptic-client.mjs [options]

Join a haptic collaboration room as a user with a simulated hand and device.

connection
  --url URL              server websocket (default ws://127.0.0.1:8765/ws)
  --lobby URL            ask this lobby (haptic lobby, http(s)://HOST:PORT) where --room runs and
                         for a room token, instead of --url; asked again after a drain
  --room NAME            the room to ask the lobby for (with --lobby)
  --lobby-token TOKEN    the lobby's token, when it asks for one (default: $HAPTIC_LOBBY_TOKEN)
  --name NAME            user name, 1-32 of A-Za-z0-9_.- (default js)
  --token TOKEN          access token sent in hello (default: $HAPTIC_TOKEN; none if unset)
  --duration S           leave after S seconds (default: run until SIGINT/SIGTERM)
  --summary FILE         also write the JSON summary to FILE (always printed on stdout)
  --record FILE          CSV of every servo tick (time, probe, force, penetration, gains)
  --window S             width of the summary's force windows [s] (default 0.5)
  --quiet                no progress lines on stderr
hand (a spring-damper pulling the device toward a target)
  --on top|side          work on the object's top or side point from welcome (default top)
  --rest-depth M         hand target depth inside the surface while resting [m] (default 0.002)
  --standoff M           start this far outside the surface [m] (default 0.03)
  --approach-at S        start approaching at S [s] (default 0.5)
  --approach-s S         approach duration [s] (default 1.0)
  --press-depth M        press: move the hand target to M inside the surface [m]
  --press-at S           press starts at S [s] (default 3)
  --press-ramp S         press (and release) ramp duration [s] (default 1)
  --press-hold S         hold the press S seconds, then release (default: to the end)
  --target X,Y,Z         fixed hand target [m] instead of the script above
  --start X,Y,Z          start position with --target (default target + 0.03 along the top normal)
  --hand-k N/M           hand stiffness (default 300)   --hand-b NS/M  hand damping (default 5)
  --hand-mass KG         hand mass (default 0.45)
device and servo
  --max-force N          device force limit [N] (default 7.9)
  --max-stiffness N/M    device max stable stiffness [N/m] (default 1000)
  --max-damping NS/M     device max virtual damping [N*s/m] declared in hello (default 0: none;
                         the server's gains then use no probe damper)
  --servo-rate HZ        servo rate (default 1000)
  --loop wait|timer      servo timing: Atomics.wait on a worker (default) or setTimeout
  --local-model pi|p     local model declared in hello (default pi)
  --gains patch|fallback use patch.gains when present (default) or always K_h = 0.3 k_o_eff, P only
  --link-timeout S       no patch for S: ramp the force to zero (default 0.25)
  --ramp S               force ramp duration [s] (default 0.05)
`;

class UsageError extends Error {}

function num(name, v, { min = -Infinity, max = Infinity, gt = false } = {}) {
  const x = Number(v);
  if (v === undefined || v === "" || !Number.isFinite(x) || (gt ? x <= min : x < min) || x > max) {
    throw new UsageError(`--${name} must be a finite number ${gt ? ">" : ">="} ${min}${max < Infinity ? ` and <= ${max}` : ""}, got ${JSON.stringify(v)}`);
  }
  return x;
}
function vec3(name, v) {
  const parts = String(v).split(",").map(Number);
  if (parts.length !== 3 || !parts.every(Number.isFinite)) {
    throw new UsageError(`--${name} must be X,Y,Z (three finite numbers), got ${JSON.stringify(v)}`);
  }
  return parts;
}
function choice(name, v, options) {
  if (!options.includes(v)) throw new UsageError(`--${name} must be one of ${options.join(", ")}, got ${JSON.stringify(v)}`);
  return v;
}

function parseCli(argv, env = process.env) {
  const str = { type: "string" };
  const { values } = parseArgs({
    args: argv,
    strict: true,
    allowPositionals: false,
    options: {
      help: { type: "boolean", short: "h" },
      quiet: { type: "boolean" },
      url: str, lobby: str, room: str, "lobby-token": str, name: str, token: str, duration: str, summary: str, record: str, window: str,
      on: str, "rest-depth": str, standoff: str, "approach-at": str, "approach-s": str,
      "press-depth": str, "press-at": str, "press-ramp": str, "press-hold": str,
      target: str, start: str, "hand-k": str, "hand-b": str, "hand-mass": str,
      "max-force": str, "max-stiffness": str, "max-damping": str, "servo-rate": str, loop: str,
      "local-model": str, gains: str, "link-timeout": str, ramp: str,
    },
  });
  if (values.help) return { help: true };
  const v = (k, d) => (values[k] === undefined ? d : values[k]);
  const o = {
    url: values.lobby === undefined ? v("url", "ws://127.0.0.1:8765/ws") : null,
    lobby: values.lobby ?? null,
    room: values.room ?? null,
    lobbyToken: values["lobby-token"] ?? (env.HAPTIC_LOBBY_TOKEN || null),
    name: v("name", "js"),
    token: values.token ?? (env.HAPTIC_TOKEN || null),
    durationS: values.duration === undefined ? Infinity : num("duration", values.duration, { min: 0, gt: true }),
    summary: values.summary ?? null,
    record: values.record ?? null,
    windowS: num("window", v("window", "0.5"), { min: 0.001, max: 3600 }),
    quiet: !!values.quiet,
    on: choice("on", v("on", "top"), ["top", "side"]),
    restDepthM: num("rest-depth", v("rest-depth", "0.002"), { min: -1, max: 1 }),
    standoffM: num("standoff", v("standoff", "0.03"), { min: 0, max: 1 }),
    approachAtS: num("approach-at", v("approach-at", "0.5"), { min: 0 }),
    approachS: num("approach-s", v("approach-s", "1.0"), { min: 0, gt: true }),
    pressDepthM: values["press-depth"] === undefined ? null : num("press-depth", values["press-depth"], { min: -1, max: 1 }),
    pressAtS: num("press-at", v("press-at", "3"), { min: 0 }),
    pressRampS: num("press-ramp", v("press-ramp", "1"), { min: 0, gt: true }),
    pressHoldS: values["press-hold"] === undefined ? Infinity : num("press-hold", values["press-hold"], { min: 0 }),
    target: values.target === undefined ? null : vec3("target", values.target),
    start: values.start === undefined ? null : vec3("start", values.start),
    hand: {
      handK: num("hand-k", v("hand-k", "300"), { min: 0, gt: true, max: 1e5 }),
      handB: num("hand-b", v("hand-b", "5"), { min: 0, max: 1e4 }),
      handMass: num("hand-mass", v("hand-mass", "0.45"), { min: 0, max: 100 }),
    },
    maxForceN: num("max-force", v("max-force", "7.9"), { min: 0, gt: true, max: 100 }),
    maxStiffnessNPerM: num("max-stiffness", v("max-stiffness", "1000"), { min: 0, gt: true, max: 1e5 }),
    maxDampingNsPerM: num("max-damping", v("max-damping", "0"), { min: 0, max: 1e3 }),
    servoRateHz: num("servo-rate", v("servo-rate", "1000"), { min: 10, max: 20000 }),
    loop: choice("loop", v("loop", "wait"), ["wait", "timer"]),
    localModel: choice("local-model", v("local-model", "pi"), ["pi", "p"]),
    gainsMode: choice("gains", v("gains", "patch"), ["patch", "fallback"]),
    linkTimeoutS: num("link-timeout", v("link-timeout", "0.25"), { min: 0.001, gt: true, max: 60 }),
    rampS: num("ramp", v("ramp", "0.05"), { min: 0.001, max: 10 }),
  };
  if (!/^[A-Za-z0-9_.-]{1,32}$/.test(o.name)) throw new UsageError(`--name must be 1-32 of A-Za-z0-9_.-, got ${JSON.stringify(o.name)}`);
  if (o.lobby !== null && values.url !== undefined) throw new UsageError("--lobby finds the room's server: give it or --url, not both");
  if ((o.lobby === null) !== (o.room === null)) throw new UsageError("--lobby URL and --room NAME go together");
  if (o.lobby !== null && !/^https?:\/\/[^/]/.test(o.lobby)) throw new UsageError(`--lobby is http(s)://HOST:PORT, got ${JSON.stringify(o.lobby)}`);
  if (o.url !== null && !/^wss?:\/\//.test(o.url)) throw new UsageError(`--url must start with ws:// or wss://, got ${JSON.stringify(o.url)}`);
  return o;
}

class Client {
  constructor(opts) {
    this.o = opts;
    this.originUnixMs = performance.timeOrigin + performance.now();
    this.url = opts.url; // with a lobby: null until it answers, then where the room runs
    this.token = opts.token; // with a lobby: the room token it gave
    this.reask = opts.lobby !== null; // ask the lobby before the next connection
    this.tokenFresh = false; // the token came from the lobby just before this connection
    this.lobbyAsks = 0;
    this.lobbyJoined = []; // {url, server} of each lobby answer a connection joined with
    this.ws = null;
    this.joined = false;
    this.stopping = false;
    this.exitCode = 0;
    this.exitReason = "duration";
    this.backoffS = 0.2;
    this.reconnectTimer = null;
    this.timers = [];
    this.welcome = null;
    this.userId = null;
    this.userIds = []; // the user id of every join, in order (a resumed seat keeps its id)
    this.resumeToken = null; // the last welcome's resume_token: sent in the next hello
    this.simRateHz = null;
    this.lastTick = -1;
    this.lastRxS = 0;
    this.stateSeq = 0;
    this.pingId = 0;
    this.rttMs = null;
    this.rtts = [];
    this.worker = null;
    this.port = null;
    this.snapF = new Float64Array(new SharedArrayBuffer(8 * SNAP.size));
    this.snapSeq = new Int32Array(new SharedArrayBuffer(4));
    this.workerDone = null;
    this.stats = {
      connects: 0, joins: 0, resumes: 0, patches: 0, patches_by_kind: {}, stale_patches: 0, bad_patches: 0,
      states_sent: 0, states_skipped_non_finite: 0, pings_sent: 0, pongs: 0,
      errors: {}, error_messages: [], fatal_error: null, gains_sources: {}, last_gains: null,
      binary_frames: 0, unknown_frames: 0, last_patch_tick: -1, patch_gap_max_s: 0,
    };
    this.lastPatchAtS = null;
  }

  nowS() {
    return (performance.timeOrigin + performance.now() - this.originUnixMs) / 1000;
  }

  log(msg) {
    if (!this.o.quiet) process.stderr.write(`haptic-client[${this.o.name}] ${this.nowS().toFixed(2)}s: ${msg}\n`);
  }

  start() {
    this.connect();
    if (Number.isFinite(this.o.durationS)) {
      setTimeout(() => this.finish(0, "duration"), this.o.durationS * 1000);
    }
    for (const sig of ["SIGINT", "SIGTERM"]) process.on(sig, () => this.finish(0, sig));
  }

  // ---- lobby -----------------------------------------------------------------------------------
  // Ask the lobby where the room runs (GET LOBBY/rooms/NAME?role=user): true when it answered
  // with a room URL (this.url, this.token set). A 4xx but 429 (a bad name, a lobby token it does
  // not accept) ends the client: asking again cannot help. No answer, 429 or 5xx: false, and the
  // caller tries again after its backoff.
  async askLobby() {
    const o = this.o;
    const url = `${o.lobby.replace(/\/+$/, "")}/rooms/${encodeURIComponent(o.room)}?role=user`;
    const headers = { Accept: "application/json" };
    if (o.lobbyToken) headers.Authorization = `Bearer ${o.lobbyToken}`;
    this.lobbyAsks += 1;
    let res;
    let body = null;
    try {
      res = await fetch(url, { headers, signal: AbortSignal.timeout(10000) });
      body = await res.json().catch(() => null);
    } catch (err) {
      this.log(`the lobby ${o.lobby} cannot be reached: ${err.cause?.code || err.message}`);
      return false;
    }
    if (res.ok && body && typeof body.url === "string" && /^wss?:\/\//.test(body.url)) {
      this.url = body.url;
      this.token = typeof body.token === "string" ? body.token : null;
      this.lobbyServer = body.server ?? null;
      this.log(`the lobby places room ${o.room} at ${this.url}`);
      return true;
    }
    const why = body && typeof body.error === "string" ? body.error : res.statusText;
    if (res.ok || res.status >= 500 || res.status === 429) {
      this.log(`the lobby ${o.lobby} has no room for us now: ${why} (${res.status})`);
      return false;
    }
    this.stats.fatal_error = { code: "lobby_refused", message: `${why} (${res.status})` };
    process.stderr.write(`haptic-client[${o.name}]: the lobby ${o.lobby} refused room ${JSON.stringify(o.room)}: ${why} (${res.status})\n`);
    this.finish(1, "lobby_refused");
    return false;
  }

  retryLater() {
    const delay = this.backoffS;
    this.backoffS = Math.min(5.0, this.backoffS * 2);
    this.reconnectTimer = setTimeout(() => this.connect(), delay * 1000);
  }

  // ---- link ------------------------------------------------------------------------------------
  async connect() {
    if (this.stopping) return;
    this.tokenFresh = false;
    if (this.o.lobby !== null && this.reask) {
      const answered = await this.askLobby();
      if (this.stopping) return;
      if (answered) {
        this.reask = false;
        this.tokenFresh = true;
      } else if (this.url === null) {
        this.retryLater(); // nowhere to go yet
        return;
      } // else: try the last place the lobby gave, and ask again next time
    }
    this.stats.connects += 1;
    const ws = new WebSocket(this.url, { handshakeTimeout: 5000, maxPayload: 1 << 20 });
    this.ws = ws;
    let helloTimer = null;
    ws.on("open", () => {
      this.lastRxS = this.nowS();
      const hello = helloMessage({
        name: this.o.name,
        device: {
          profile: "js-sim",
          maxForceN: this.o.maxForceN,
          maxStiffnessNPerM: this.o.maxStiffnessNPerM,
          maxDampingNsPerM: this.o.maxDampingNsPerM,
        },
        servoRateHz: this.o.servoRateHz,
        localModel: this.o.localModel,
        token: this.token,
        resume: this.resumeToken,
      });
      ws.send(JSON.stringify(hello));
      helloTimer = setTimeout(() => {
        if (!this.joined) {
          this.log("no welcome within 5 s: reconnecting");
          ws.terminate();
        }
      }, 5000);
    });
    ws.on("message", (data, isBinary) => {
      this.lastRxS = this.nowS();
      if (isBinary) {
        this.stats.binary_frames += 1;
        return;
      }
      let m;
      try {
        m = JSON.parse(data.toString());
      } catch {
        this.stats.unknown_frames += 1;
        return;
      }
      this.onMessage(ws, m);
    });
    ws.on("error", (err) => {
      if (!this.stopping) this.log(`link error: ${err.code || err.message}`);
    });
    ws.on("close", (code, reason) => {
      clearTimeout(helloTimer);
      const wasJoined = this.joined;
      this.leaveSession();
      if (this.ws === ws) this.ws = null;
      if (this.stopping) return;
      if (this.stats.fatal_error) return; // finish() is under way
      // with a lobby: a drain (1012; 1013 try again later) or a server that never let us in
      // may mean the room runs elsewhere now: ask before rejoining
      if (this.o.lobby !== null && (code === 1012 || code === 1013 || !wasJoined)) this.reask = true;
      if (wasJoined) this.backoffS = 0.2; // a session that joined resets the backoff
      this.log(`link closed (${code}${reason && reason.length ? ` ${reason}` : ""}); reconnecting in ${this.backoffS.toFixed(1)} s`);
      this.retryLater();
    });
  }

  leaveSession() {
    this.joined = false;
    for (const t of this.timers) clearInterval(t);
    this.timers = [];
  }

  onMessage(ws, m) {
    switch (m && m.type) {
      case "welcome":
        return this.onWelcome(ws, m);
      case "patch":
        return this.onPatch(m);
      case "pong":
        if (Number.isFinite(m.t_client_s)) {
          this.rttMs = Math.max(0, (this.nowS() - m.t_client_s) * 1000);
          this.rtts.push(this.rttMs);
          this.stats.pongs += 1;
        }
        return;
      case "error":
        return this.onError(m);
      default:
        this.stats.unknown_frames += 1; // newer protocol additions: ignored
    }
  }

  onWelcome(ws, m) {
    this.joined = true;
    this.welcome = m;
    this.userId = m.user_id;
    this.userIds.push(m.user_id);
    // one use each: the next hello (after a dropped link) sends this one back
    this.resumeToken = typeof m.resume_token === "string" && m.resume_token ? m.resume_token : null;
    if (m.resumed === true) this.stats.resumes += 1;
    this.simRateHz = Number.isFinite(m.sim_rate_hz) && m.sim_rate_hz > 0 ? m.sim_rate_hz : 20;
    this.lastTick = -1; // a new session (maybe a restarted server) counts ticks from its own start
    this.lastPatchAtS = null; // patch_gap_max_s: within a session
    this.stats.joins += 1;
    if (this.o.lobby !== null) this.lobbyJoined.push({ url: this.url, server: this.lobbyServer ?? null });
    this.log(`${m.resumed === true ? "rejoined, seat resumed," : "joined"} as ${m.name} (${m.user_id}), simulation at ${this.simRateHz} Hz`);
    if (!this.worker) this.startWorker(m.object);
    // patches start only after the first state: send one now, then about twice per tick
    this.sendState(ws);
    const stateEveryMs = 1000 / (2 * this.simRateHz);
    this.timers.push(setInterval(() => this.sendState(ws), stateEveryMs));
    this.timers.push(setInterval(() => this.ping(ws), 1000));
  }

  onPatch(m) {
    if (!Number.isInteger(m.tick) || m.tick <= this.lastTick) {
      this.stats.stale_patches += 1; // a state stream: an older one is ignored
      return;
    }
    let prim;
    try {
      prim = primitiveFromPatch(m);
    } catch (err) {
      this.stats.bad_patches += 1;
      return;
    }
    const gains = chooseGains(m, {
      mode: this.o.gainsMode,
      maxStiffnessNPerM: this.o.maxStiffnessNPerM,
      maxDampingNsPerM: this.o.maxDampingNsPerM,
      localModel: this.o.localModel,
    }) ?? this.stats.last_gains;
    if (!gains) {
      this.stats.bad_patches += 1;
      return;
    }
    prim = movedOut(prim, ownOffsetM(m, gains));
    this.lastTick = m.tick;
    const t = this.nowS();
    if (this.lastPatchAtS !== null && t - this.lastPatchAtS > this.stats.patch_gap_max_s) {
      this.stats.patch_gap_max_s = t - this.lastPatchAtS;
    }
    this.lastPatchAtS = t;
    this.stats.last_patch_tick = m.tick;
    this.stats.patches += 1;
    this.stats.patches_by_kind[prim.kind] = (this.stats.patches_by_kind[prim.kind] || 0) + 1;
    this.stats.gains_sources[gains.source] = (this.stats.gains_sources[gains.source] || 0) + 1;
    this.stats.last_gains = gains;
    if (this.port) {
      this.port.postMessage({
        type: "patch",
        prim,
        tick: m.tick,
        gains,
        simPeriodS: 1 / this.simRateHz,
        ownForceN: m.own_force_n ?? 0,
      });
    }
  }

  onError(m) {
    const code = String(m.code);
    this.stats.errors[code] = (this.stats.errors[code] || 0) + 1;
    if (this.stats.error_messages.length < 20) {
      this.stats.error_messages.push({ code, message: String(m.message), fatal: !!m.fatal });
    }
    if (m.fatal && (code === "server_draining" || code === "room_restarting")) {
      // a restart, not a fault: the server closes with 1012 and the client rejoins (a drained
      // room runs elsewhere next: with a lobby, ask it first)
      this.log(`the server says ${code}: ${m.message}; rejoining`);
      if (this.o.lobby !== null && code === "server_draining") this.reask = true;
    } else if (m.fatal && code === "unauthorized" && this.o.lobby !== null && !this.tokenFresh) {
      // a room token of an earlier answer (expired, or for another server): ask again
      this.log(`the server refused the lobby's earlier token; asking the lobby again`);
      this.reask = true;
    } else if (m.fatal) {
      this.stats.fatal_error = { code, message: String(m.message) };
      process.stderr.write(`haptic-client[${this.o.name}]: fatal error from the server: ${code}: ${m.message}\n`);
      this.finish(1, "fatal_error");
    } else if (this.stats.errors[code] <= 5) {
      this.log(`server refused a frame: ${code}: ${m.message}`);
    }
  }

  readSnap() {
    for (let i = 0; i < 1000; i++) {
      const s1 = Atomics.load(this.snapSeq, 0);
      if (s1 & 1) continue;
      const c = Float64Array.from(this.snapF);
      if (Atomics.load(this.snapSeq, 0) === s1) return c;
    }
    return null;
  }

  sendState(ws) {
    if (ws.readyState !== WebSocket.OPEN) return;
    const c = this.readSnap();
    const started = c && c[SNAP.ticks] > 0;
    const snap = started
      ? {
          probe: [c[SNAP.probe], c[SNAP.probe + 1], c[SNAP.probe + 2]],
          force: [c[SNAP.force], c[SNAP.force + 1], c[SNAP.force + 2]],
          penetration: c[SNAP.e],
          inContact: c[SNAP.inContact] > 0,
          kH: c[SNAP.kH],
          iGain: c[SNAP.iGain],
          ownGain: this.stats.last_gains ? this.stats.last_gains.own_gain ?? 0 : 0,
          rateHz: c[SNAP.rateHz],
          p99Us: c[SNAP.p99Us],
          patchTick: c[SNAP.patchTick],
        }
      : { // before the servo's first tick: where the hand starts, no force
          probe: this.handStart ?? [0, 0, 0], force: [0, 0, 0], penetration: 0, inContact: false,
          kH: 0, iGain: 0, rateHz: 0, p99Us: 0, patchTick: -1,
        };
    const m = stateMessage({ seq: ++this.stateSeq, snap, rttMs: this.rttMs });
    if (!m) {
      this.stats.states_skipped_non_finite += 1;
      return;
    }
    ws.send(JSON.stringify(m));
    this.stats.states_sent += 1;
  }

  ping(ws) {
    if (ws.readyState !== WebSocket.OPEN) return;
    if (this.nowS() - this.lastRxS > 2.0) {
      this.log("no frame from the server for 2 s: dropping the link");
      ws.terminate();
      return;
    }
    ws.send(JSON.stringify({ type: "ping", id: ++this.pingId, t_client_s: this.nowS() }));
    this.stats.pings_sent += 1;
  }

  // ---- servo thread ----------------------------------------------------------------------------
  startWorker(object) {
    const o = this.o;
    let script;
    if (o.target) {
      const start = o.start ?? [o.target[0], o.target[1], o.target[2] + o.standoffM];
      script = { kind: "fixed", target: o.target, start };
    } else {
      const anchor = o.on === "side" ? object.side_m : object.top_m;
      const normal = o.on === "side" ? object.side_normal : object.top_normal;
      script = {
        kind: "scripted", anchor, normal, standoffM: o.standoffM, approachAtS: o.approachAtS,
        approachS: o.approachS, restDepthM: o.restDepthM, pressDepthM: o.pressDepthM,
        pressAtS: o.pressAtS, pressRampS: o.pressRampS, pressHoldS: o.pressHoldS,
      };
      const n = Math.hypot(...normal);
      script.start = anchor.map((a, i) => a + (o.standoffM * normal[i]) / n);
    }
    this.handStart = script.start;
    const { port1, port2 } = new MessageChannel();
    this.port = port1;
    this.worker = new Worker(new URL("./lib/servo-worker.mjs", import.meta.url), {
      workerData: {
        originUnixMs: this.originUnixMs, script, hand: o.hand, maxForceN: o.maxForceN,
        linkTimeoutS: o.linkTimeoutS, rampS: o.rampS, bleedS: 2 / this.simRateHz,
        servoRateHz: o.servoRateHz, loop: o.loop, windowS: o.windowS, record: o.record,
        snapBuffer: this.snapF.buffer, seqBuffer: this.snapSeq.buffer, port: port2,
      },
      transferList: [port2],
    });
    this.workerDone = new Promise((resolve) => {
      this.worker.on("message", (m) => m.type === "done" && resolve(m));
      this.worker.on("error", (err) => {
        process.stderr.write(`haptic-client[${o.name}]: servo thread failed: ${err.stack || err}\n`);
        resolve(null);
      });
      this.worker.on("exit", () => resolve(null));
    });
  }

  // ---- exit ------------------------------------------------------------------------------------
  async finish(code, reason) {
    if (this.stopping) return;
    this.stopping = true;
    this.exitCode = code;
    this.exitReason = reason;
    clearTimeout(this.reconnectTimer);
    this.leaveSession();
    let servo = null;
    if (this.worker) {
      this.port.postMessage({ type: "stop", rampS: this.o.rampS });
      const timeout = new Promise((r) => setTimeout(() => r(null), 3000));
      servo = await Promise.race([this.workerDone, timeout]);
      await this.worker.terminate();
    }
    const ws = this.ws;
    if (ws && ws.readyState === WebSocket.OPEN) {
      ws.send(JSON.stringify({ type: "bye" }));
      await new Promise((r) => {
        const t = setTimeout(r, 500);
        ws.once("close", () => { clearTimeout(t); r(); });
        ws.close(1000, "bye");
      });
    }
    if (ws) ws.terminate();
    if (code === 0 && this.stats.joins === 0) {
      this.exitCode = 3;
      this.exitReason = "never_joined";
      process.stderr.write(`haptic-client[${this.o.name}]: never joined a room at ${this.url ?? this.o.lobby}\n`);
    }
    const summary = this.summary(servo);
    const text = JSON.stringify(summary, null, 2) + "\n";
    if (this.o.summary) writeFileSync(this.o.summary, text);
    process.stdout.write(text, () => process.exit(this.exitCode));
  }

  summary(done) {
    const windows = done ? done.windows : [];
    let fdt = 0;
    let dt = 0;
    let fmax = 0;
    for (const w of windows) {
      const d = w.t1_s - w.t0_s;
      fdt += w.mean_force_n * d;
      dt += d;
      fmax = Math.max(fmax, w.max_force_n);
    }
    const cpu = process.cpuUsage();
    const wallS = this.nowS();
    const mean = (a) => (a.length ? a.reduce((x, y) => x + y, 0) / a.length : null);
    const s = this.stats;
    return {
      client: "haptic-client.mjs (Node.js)",
      protocol: 1,
      name: this.o.name,
      assigned_name: this.welcome ? this.welcome.name : null,
      user_id: this.userId,
      user_ids: this.userIds,
      url: this.url,
      lobby: this.o.lobby === null ? null : { url: this.o.lobby, room: this.o.room, asks: this.lobbyAsks, joined: this.lobbyJoined },
      exit: this.exitReason,
      exit_code: this.exitCode,
      clock_origin_unix_s: this.originUnixMs / 1000,
      wall_s: wallS,
      sim_rate_hz: this.simRateHz,
      connects: s.connects,
      joins: s.joins,
      resumes: s.resumes,
      patches: s.patches,
      patches_by_kind: s.patches_by_kind,
      stale_patches: s.stale_patches,
      bad_patches: s.bad_patches,
      last_patch_tick: s.last_patch_tick,
      patch_gap_max_s: s.patch_gap_max_s,
      states_sent: s.states_sent,
      states_skipped_non_finite: s.states_skipped_non_finite,
      pings_sent: s.pings_sent,
      pongs: s.pongs,
      rtt_ms_mean: mean(this.rtts),
      rtt_ms_last: this.rttMs,
      errors: s.errors,
      error_messages: s.error_messages,
      fatal_error: s.fatal_error,
      gains_sources: s.gains_sources,
      last_gains: s.last_gains,
      link_losses: done ? done.link_losses : 0,
      servo: done ? done.servo : null,
      process_cpu_pct: (100 * (cpu.user + cpu.system)) / 1e6 / Math.max(1e-3, wallS),
      window_s: this.o.windowS,
      mean_force_n: dt > 0 ? fdt / dt : 0,
      max_force_n: fmax,
      force_windows: windows,
      final_probe_m: done ? done.final_probe_m : null,
    };
  }
}

function main() {
  let opts;
  try {
    opts = parseCli(process.argv.slice(2));
  } catch (err) {
    if (err instanceof UsageError || err.code?.startsWith?.("ERR_PARSE_ARGS")) {
      process.stderr.write(`haptic-client: error: ${err.message}\n`);
      process.exit(2);
    }
    throw err;
  }
  if (opts.help) {
    process.stdout.write(USAGE);
    return;
  }
  new Client(opts).start();
}

main();
