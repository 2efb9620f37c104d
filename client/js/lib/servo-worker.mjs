// The servo thread: runs the Servo core at a fixed rate on a worker thread, away from the
// network's event loop.
//
// Timing (loop "wait", the default): tick k is due at t0 + k*T (integer tick counts, never an
// accumulated float time). Between ticks the thread blocks in Atomics.wait with a sub-millisecond
// timeout (a futex wait: no CPU used, no busy spin). A deadline missed by more than one period
// is counted as an overrun and skipped, never piled up.
// Loop "timer": the same tick driven by setTimeout(0) on the worker's event loop (Node's timers
// have 1 ms granularity: about 900 Hz with more jitter); kept to measure the difference.
//
// Messages in (polled between ticks with receiveMessageOnPort, so a patch is applied whole):
//   {type:"patch", prim, tick, gains, simPeriodS}   {type:"stop"}
// Snapshot out (every tick, SharedArrayBuffer with a sequence lock, latest wins): see SNAP.
// Final message out: {type:"done", servo, windows, linkLosses, ...}.

import { workerData, parentPort, receiveMessageOnPort } from "node:worker_threads";
import { writeFileSync } from "node:fs";
import { SNAP, Servo, SimHand, scriptedTarget } from "./servo.mjs";

function main() {
  const w = workerData;
  const clockMs = () => performance.timeOrigin + performance.now(); // absolute (unix) ms
  const originMs = w.originUnixMs;
  const nowS = () => (clockMs() - originMs) / 1000;

  const target =
    w.script.kind === "fixed"
      ? Object.assign(() => w.script.target, { start: w.script.start })
      : scriptedTarget(w.script);
  const device = new SimHand({ start: w.script.start ?? target.start, target, ...w.hand });
  const servo = new Servo({
    device,
    maxForceN: w.maxForceN,
    linkTimeoutS: w.linkTimeoutS,
    rampS: w.rampS,
    bleedS: w.bleedS,
  });
  const port = w.port;
  const snapF = new Float64Array(w.snapBuffer);
  const snapSeq = new Int32Array(w.seqBuffer);

  const T = 1 / w.servoRateHz;
  const waitCell = new Int32Array(new SharedArrayBuffer(4));

  // period statistics: recent ring (for state's rate and p99) and a whole-run histogram
  const RING = 1024;
  const ring = new Float64Array(RING);
  let ringN = 0;
  let ringI = 0;
  const BIN_US = 10;
  const hist = new Uint32Array(2001); // 0..20 ms in 10 us bins, last bin: longer
  let periodsN = 0;
  let periodsSum = 0;
  let periodMax = 0;
  let overruns = 0;
  let lastTickS = null;
  let p99Us = 0;
  let rateHz = 0;
  let ticks = 0;

  // force windows
  const windowS = w.windowS;
  const windows = [];
  let win = null;
  const newWindow = (k) => ({ k, dt: 0, fdt: 0, edt: 0, contact: 0, fmax: 0, gmin: 1 });
  const closeWindow = (wd) => {
    if (!wd || !(wd.dt > 0)) return;
    windows.push({
      t0_s: +(wd.k * windowS).toFixed(6),
      t1_s: +((wd.k + 1) * windowS).toFixed(6),
      mean_force_n: wd.fdt / wd.dt,
      max_force_n: wd.fmax,
      mean_penetration_m: wd.edt / wd.dt,
      contact_fraction: wd.contact / wd.dt,
      min_safety_gain: wd.gmin,
    });
  };

  // optional per-tick record
  const COLS = ["t_s", "probe_x_m", "probe_y_m", "probe_z_m", "force_x_n", "force_y_n", "force_z_n",
    "force_n", "penetration_m", "in_contact", "safety_gain", "k_h", "i_gain", "patch_tick"];
  const chunks = [];
  let chunk = null;
  let chunkN = 0;
  const CHUNK = 65536;
  const record = (row) => {
    if (!chunk || chunkN === CHUNK) {
      chunk = new Float64Array(CHUNK * COLS.length);
      chunks.push(chunk);
      chunkN = 0;
    }
    chunk.set(row, chunkN * COLS.length);
    chunkN += 1;
  };
  const row = new Float64Array(COLS.length);

  let stopping = false;
  let stopAtS = Infinity;

  const poll = () => {
    for (;;) {
      const m = receiveMessageOnPort(port);
      if (!m) break;
      const msg = m.message;
      if (msg.type === "patch") {
        servo.setPatch({ ...msg, tS: nowS() });
      } else if (msg.type === "stop") {
        stopping = true;
        stopAtS = nowS() + (msg.rampS ?? 0);
      }
    }
  };

  const tickOnce = () => {
    poll();
    const t = nowS();
    if (stopping) {
      servo.patchAtS = -Infinity; // a stop ramps the force down like a link loss...
      servo.waitingForPatch = true; // ...that is not counted as one
    }
    const f = servo.tick(t);
    ticks += 1;
    if (lastTickS !== null) {
      const p = t - lastTickS;
      ring[ringI] = p;
      ringI = (ringI + 1) % RING;
      ringN = Math.min(RING, ringN + 1);
      periodsN += 1;
      periodsSum += p;
      if (p > periodMax) periodMax = p;
      hist[Math.min(hist.length - 1, Math.floor((p * 1e6) / BIN_US))] += 1;
      if (w.loop === "timer" && p > 2 * T) overruns += 1; // the wait loop counts its skips
      if (ticks % 250 === 0 && ringN > 10) {
        const s = Array.from(ring.subarray(0, ringN)).sort((a, b) => a - b);
        p99Us = s[Math.min(s.length - 1, Math.floor(0.99 * s.length))] * 1e6;
        rateHz = ringN / s.reduce((a, b) => a + b, 0);
      }
      // windows
      const k = Math.floor(t / windowS);
      if (!win || win.k !== k) {
        closeWindow(win);
        win = newWindow(k);
      }
      win.dt += p;
      win.fdt += servo.fMag * p;
      win.edt += servo.e * p;
      if (servo.e > 0) win.contact += p;
      if (servo.fMag > win.fmax) win.fmax = servo.fMag;
      if (servo.g < win.gmin) win.gmin = servo.g;
    }
    lastTickS = t;
    const x = servo.device.x;
    // publish the snapshot (sequence lock: odd while writing)
    Atomics.add(snapSeq, 0, 1);
    snapF[SNAP.probe] = x[0];
    snapF[SNAP.probe + 1] = x[1];
    snapF[SNAP.probe + 2] = x[2];
    snapF[SNAP.force] = f[0];
    snapF[SNAP.force + 1] = f[1];
    snapF[SNAP.force + 2] = f[2];
    snapF[SNAP.e] = servo.prim ? servo.e : 0;
    snapF[SNAP.inContact] = servo.prim && servo.e > 0 ? 1 : 0;
    snapF[SNAP.kH] = servo.gains.k_h;
    snapF[SNAP.iGain] = servo.gains.i_gain;
    snapF[SNAP.rateHz] = rateHz;
    snapF[SNAP.p99Us] = p99Us;
    snapF[SNAP.patchTick] = servo.patchTick;
    snapF[SNAP.g] = servo.g;
    snapF[SNAP.ticks] = ticks;
    Atomics.add(snapSeq, 0, 1);
    if (w.record) {
      row[0] = t;
      row[1] = x[0];
      row[2] = x[1];
      row[3] = x[2];
      row[4] = f[0];
      row[5] = f[1];
      row[6] = f[2];
      row[7] = servo.fMag;
      row[8] = servo.prim ? servo.e : NaN;
      row[9] = servo.prim && servo.e > 0 ? 1 : 0;
      row[10] = servo.g;
      row[11] = servo.gains.k_h;
      row[12] = servo.gains.i_gain;
      row[13] = servo.patchTick;
      record(row);
    }
    return stopping && t >= stopAtS && servo.g === 0;
  };

  const finish = () => {
    closeWindow(win);
    const pct = (q) => {
      const want = q * periodsN;
      let acc = 0;
      for (let i = 0; i < hist.length; i++) {
        acc += hist[i];
        if (acc >= want) return (i + 1) * BIN_US;
      }
      return periodMax * 1e6;
    };
    if (w.record) {
      const lines = [COLS.join(",")];
      chunks.forEach((c, ci) => {
        const rows = ci === chunks.length - 1 ? chunkN : CHUNK;
        for (let r = 0; r < rows; r++) {
          const vals = [];
          for (let j = 0; j < COLS.length; j++) vals.push(c[r * COLS.length + j]);
          lines.push(vals.map((v) => (Number.isFinite(v) ? +v.toPrecision(7) : "nan")).join(","));
        }
      });
      writeFileSync(w.record, lines.join("\n") + "\n");
    }
    parentPort.postMessage({
      type: "done",
      servo: {
        loop: w.loop,
        target_hz: w.servoRateHz,
        ticks,
        rate_hz: periodsN > 0 ? periodsN / periodsSum : 0,
        period_us_mean: periodsN > 0 ? (1e6 * periodsSum) / periodsN : 0,
        period_us_p50: pct(0.5),
        period_us_p99: pct(0.99),
        period_us_max: periodMax * 1e6,
        overruns,
      },
      windows,
      link_losses: servo.linkLosses,
      final_probe_m: servo.device.x.slice(),
      final_gains: servo.gains,
    });
  };

  if (w.loop === "timer") {
    const step = () => {
      if (tickOnce()) finish();
      else setTimeout(step, 0);
    };
    step();
    return;
  }
  // loop "wait": absolute deadlines, futex sleep, no spin
  const t0 = nowS();
  let k = 0;
  for (;;) {
    if (tickOnce()) break;
    k += 1;
    let due = t0 + k * T;
    let now = nowS();
    if (now - due > T) {
      overruns += 1; // late by more than a period: skip, do not pile up
      k = Math.floor((now - t0) / T) + 1;
      due = t0 + k * T;
    }
    const waitMs = (due - now) * 1000;
    if (waitMs > 0) Atomics.wait(waitCell, 0, 0, waitMs);
  }
  finish();
}

main();
