// Unit tests of the servo core and the message builders: `node --test client/js/test/`.
import { test } from "node:test";
import assert from "node:assert/strict";
import {
  LocalModel,
  Servo,
  SimHand,
  movedOut,
  penetration,
  primitiveFromPatch,
  scriptedTarget,
} from "../lib/servo.mjs";
import { chooseGains, helloMessage, ownOffsetM, stateMessage } from "../lib/protocol.mjs";

const close = (a, b, tol = 1e-9) => assert.ok(Math.abs(a - b) <= tol, `${a} != ${b} (tol ${tol})`);

test("plane: penetration positive inside, force along the outward normal", () => {
  const prim = primitiveFromPatch({ primitive: { kind: "plane", point: [0, 0, 0.1], normal: [0, 0, 2] } });
  const { e, n } = penetration(prim, [0.05, 0, 0.098]);
  close(e, 0.002);
  assert.deepEqual(n, [0, 0, 1]);
  close(penetration(prim, [0, 0, 0.125]).e, -0.025); // out of contact: negative
});

test("sphere: a bump (object inside) and a dent (object outside) read off the patch", () => {
  const sphere = { kind: "sphere", center: [0, 0, 0], radius: 0.1 };
  const bump = primitiveFromPatch({ primitive: sphere, proxy_m: [0, 0, 0.1], normal: [0, 0, 1] });
  assert.equal(bump.inside, true);
  const b = penetration(bump, [0, 0.097, 0]);
  close(b.e, 0.003);
  assert.deepEqual(b.n, [0, 1, 0]); // radial, outward
  const dent = primitiveFromPatch({ primitive: sphere, proxy_m: [0, 0, 0.1], normal: [0, 0, -1] });
  assert.equal(dent.inside, false);
  const d = penetration(dent, [0, 0.103, 0]);
  close(d.e, 0.003);
  assert.deepEqual(d.n, [-0, -1, -0]); // toward the centre, out of the object
  assert.throws(() => primitiveFromPatch({ primitive: { kind: "cone" } }), RangeError);
});

test("P model: f = K_h e in contact, nothing out of contact", () => {
  const m = new LocalModel();
  m.setGains({ k_h: 100 });
  close(m.step(0.002, 0, 0.001), 0.2);
  assert.equal(m.step(-0.001, 0, 0.001), 0);
});

test("PI model: the integral removes the error above theta and bleeds to zero on release", () => {
  const m = new LocalModel({ bleedS: 0.1 });
  m.setGains({ k_h: 100, i_gain: 4000, theta_m: 0.001 });
  let f = 0;
  for (let i = 0; i < 1000; i++) f = m.step(0.002, 0, 0.001); // 1 s at e = 2 mm
  close(f, 100 * 0.002 + 4000 * 0.001 * 1.0, 1e-9); // K_h e + I * (e - theta) * t
  for (let i = 0; i < 1000; i++) m.step(0.0005, 0, 0.001); // below theta: the integral unwinds
  assert.ok(m.s < 4.0);
  const s0 = m.s;
  m.step(-0.001, 0, 0.05);
  close(m.s, s0 / 2, 1e-9); // half the bleed time: half the integral
  m.step(-0.001, 0, 0.06);
  assert.equal(m.s, 0);
});

test("new gains mid-press: the integral is held (even with I = 0) and K_h's step is ramped", () => {
  const m = new LocalModel({ transferS: 0.25 });
  m.setGains({ k_h: 40, i_gain: 400 });
  let f = 0;
  for (let i = 0; i < 1000; i++) f = m.step(0.005, 0, 0.001); // 1 s at e = 5 mm
  const held = m.s;
  assert.ok(held > 1.5);
  // interim P gains of a new cell (I = 0, softer K_h): the force the hand holds does not drop
  m.setGains({ k_h: 36, i_gain: 0 });
  close(m.step(0.005, 0, 0.001), f, 1e-9);
  assert.equal(m.s, held); // held, not dropped and not growing
  let last = f;
  for (let i = 0; i < 300; i++) {
    const g = m.step(0.005, 0, 0.001);
    assert.ok(last - g <= (4 * 0.005) / 250 + 1e-12); // at most the step / 250 per tick
    last = g;
  }
  close(last, 36 * 0.005 + held, 1e-9); // then the new gains' own force
  // leaving ends the transfer; the integral bleeds as on any release
  m.setGains({ k_h: 100, i_gain: 0 });
  m.step(-0.001, 0, 0.001);
  assert.equal(m.b, 0);
});

test("servo: force ramps up after a patch, clamps, and ramps to zero when patches stop", () => {
  const dev = new SimHand({ start: [0, 0, 0.095], target: () => [0, 0, 0.095], handMass: 1e6 });
  const s = new Servo({ device: dev, maxForceN: 7.9, linkTimeoutS: 0.25, rampS: 0.05 });
  const prim = primitiveFromPatch({ primitive: { kind: "plane", point: [0, 0, 0.1], normal: [0, 0, 1] } });
  let t = 0;
  s.tick(t);
  s.setPatch({ prim, tick: 1, gains: { k_h: 100, proxy_hold: "zoh", source: "t" }, simPeriodS: 0.05, tS: t });
  const forces = [];
  for (let i = 0; i < 600; i++) {
    t += 0.001;
    forces.push(s.tick(t)[2]);
  }
  close(forces[24], 0.5 * 0.5, 0.02); // halfway up the 50 ms ramp (e = 5 mm, K_h e = 0.5 N)
  close(forces[200], 0.5, 1e-3); // full force
  assert.equal(forces[599], 0); // 0.25 s without a patch + 50 ms ramp: zero
  const steps = forces.slice(1).map((f, i) => Math.abs(f - forces[i]));
  assert.ok(Math.max(...steps) < 0.02, "a ramp, never a jump");
  assert.equal(s.linkLosses, 1);
  // forces come back only after a new patch
  s.setPatch({ prim, tick: 2, gains: { k_h: 100, proxy_hold: "zoh", source: "t" }, simPeriodS: 0.05, tS: t });
  for (let i = 0; i < 100; i++) t += 0.001, s.tick(t);
  close(s.fMag, 0.5, 1e-3);
  // clamp to the device's limit
  s.setPatch({ prim, tick: 3, gains: { k_h: 1e5, proxy_hold: "zoh", source: "t" }, simPeriodS: 0.05, tS: t });
  for (let i = 0; i < 10; i++) t += 0.001, s.tick(t);
  close(s.fMag, 7.9, 1e-9);
});

test("a simulated hand resting on a plane settles where hand spring and K_h balance", () => {
  const target = scriptedTarget({ anchor: [0, 0, 0.1], normal: [0, 0, 1], restDepthM: 0.004, approachAtS: 0, approachS: 0.2 });
  const dev = new SimHand({ start: target.start, target });
  const s = new Servo({ device: dev });
  const prim = primitiveFromPatch({ primitive: { kind: "plane", point: [0, 0, 0.1], normal: [0, 0, 1] } });
  s.setPatch({ prim, tick: 1, gains: { k_h: 100, source: "t" }, simPeriodS: 0.05, tS: 0 });
  for (let k = 0; k <= 2000; k++) {
    if (k % 50 === 0) s.setPatch({ prim, tick: k + 2, gains: { k_h: 100, source: "t" }, simPeriodS: 0.05, tS: k / 1000 });
    s.tick(k / 1000);
  }
  // series springs: hand 300 N/m and K_h 100 N/m over 4 mm -> 0.3 N
  close(s.fMag, (0.004 * 300 * 100) / 400, 0.005);
});

test("gains: the patch's recommendation when present, else 0.3 k_o_eff and P only", () => {
  const o = { mode: "patch", maxStiffnessNPerM: 1000, localModel: "pi" };
  const g = chooseGains({ k_o: 400, k_o_eff: 300, gains: { k_h: 120, i_gain: 3000, b_h: 0.5, proxy_hold: "foh", theta_m: 0.0004 } }, o);
  assert.deepEqual(g, { k_h: 120, i_gain: 3000, b_h: 0.5, theta_m: 0.0004, proxy_hold: "foh", own_gain: 0, source: "patch" });
  const f = chooseGains({ k_o: 400, k_o_eff: 300 }, o);
  assert.equal(f.source, "fallback");
  close(f.k_h, 90);
  assert.equal(f.i_gain, 0);
  assert.equal(chooseGains({ k_o: 400, k_o_eff: 300, gains: { k_h: 120 } }, { ...o, mode: "fallback" }).source, "fallback");
  assert.equal(chooseGains({ k_o: 0, k_o_eff: 0 }, o), null);
});

test("own-force compensation: the patch's primitive moved out by own_gain times the force applied", () => {
  const o = { mode: "patch", maxStiffnessNPerM: 1000, localModel: "p" };
  const patch = {
    k_o: 500, k_o_eff: 500, own_force_n: 2,
    primitive: { kind: "plane", point: [0, 0, 0.1], normal: [0, 0, 1] },
    gains: { k_h: 500, own_gain: 1 / 500 },
  };
  const g = chooseGains(patch, o);
  close(g.own_gain, 1 / 500);
  const prim = movedOut(primitiveFromPatch(patch), ownOffsetM(patch, g));
  // the probe resting on the deformed surface still feels the 2 N that hold it there
  close(penetration(prim, [0, 0, 0.1]).e, 0.004);
  // fallback gains (P at 0.3 k_o_eff) compensate with C_h = 1 / K_h: F = K_h (x - x_o) + F_s
  const fb = chooseGains(patch, { ...o, mode: "fallback" });
  close(fb.k_h, 150);
  close(ownOffsetM(patch, fb), 2 / 150);
  // a bump grows, a dent shrinks: both move out along their outward normals
  const bump = { kind: "sphere", center: [0, 0, 0], radius: 0.05, inside: true };
  close(movedOut(bump, 0.002).radius, 0.052);
  close(movedOut({ ...bump, inside: false }, 0.002).radius, 0.048);
  assert.equal(movedOut(bump, -1), bump);
  const st = stateMessage({ seq: 1, snap: { probe: [0, 0, 0.1], force: [0, 0, 2], penetration: 0.004, inContact: true, kH: 500, iGain: 0, ownGain: 0.002, rateHz: 1000, p99Us: 1010, patchTick: 5 }, rttMs: null });
  assert.equal(st.own_gain, 0.002);
});

test("messages: token only when given; a state with NaN is not sent", () => {
  const dev = { profile: "js-sim", maxForceN: 7.9, maxStiffnessNPerM: 1000 };
  const h = helloMessage({ name: "A", device: dev, servoRateHz: 1000, localModel: "pi" });
  assert.equal("token" in h, false);
  assert.equal(helloMessage({ name: "A", device: dev, servoRateHz: 1000, localModel: "pi", token: "s3cret" }).token, "s3cret");
  assert.throws(() => helloMessage({ name: "no spaces", device: dev, servoRateHz: 1000, localModel: "p" }), RangeError);
  const snap = { probe: [0, 0, 0.1], force: [0, 0, 0.2], penetration: 0.002, inContact: true, kH: 90, iGain: 0, rateHz: 1000, p99Us: 1010, patchTick: 5 };
  const st = stateMessage({ seq: 3, snap, rttMs: null });
  assert.equal(st.type, "state");
  assert.equal("rtt_ms" in st, false);
  assert.equal(st.penetration_m, 0.002);
  // before the first patch there is no local model: no penetration (not 0 m), even a NaN one
  const early = stateMessage({ seq: 5, snap: { ...snap, penetration: NaN, inContact: false, patchTick: -1 }, rttMs: null });
  assert.equal("penetration_m" in early, false);
  assert.equal(stateMessage({ seq: 4, snap: { ...snap, probe: [0, 0, NaN] }, rttMs: 1 }), null);
});

test("first-order hold: a new surface slides in over one simulation period instead of stepping", () => {
  const dev = new SimHand({ start: [0, 0, 0.095], target: () => [0, 0, 0.095], handMass: 1e6 });
  const s = new Servo({ device: dev, rampS: 0.001 });
  const plane = (z) => primitiveFromPatch({ primitive: { kind: "plane", point: [0, 0, z], normal: [0, 0, 1] } });
  const gains = (hold) => ({ k_h: 100, proxy_hold: hold, source: "t" });
  let t = 0;
  s.setPatch({ prim: plane(0.1), tick: 1, gains: gains("foh"), simPeriodS: 0.05, tS: t });
  for (let i = 0; i < 20; i++) t += 0.001, s.tick(t);
  close(s.fMag, 0.5, 1e-6); // e = 5 mm
  s.setPatch({ prim: plane(0.102), tick: 2, gains: gains("foh"), simPeriodS: 0.05, tS: t });
  t += 0.025;
  s.tick(t);
  close(s.fMag, 0.6, 1e-6); // halfway through the slide: e = 6 mm
  t += 0.03;
  s.tick(t);
  close(s.fMag, 0.7, 1e-6); // the slide is over: e = 7 mm
  s.setPatch({ prim: plane(0.1), tick: 3, gains: gains("zoh"), simPeriodS: 0.05, tS: t });
  t += 0.001;
  s.tick(t);
  close(s.fMag, 0.5, 1e-6); // zero-order hold: at once
});

test("a withdrawn compensation slides the surface in instead of dropping the force", () => {
  // the compensated probe rests on the object's own surface (1 mm deformed, F_s = 1 N);
  // uncompensated gains put the rendered surface right there: as a step the contact ended on
  // the next tick and the force with it
  const K = 300;
  const F = 1;
  const device = { x: [0, 0, -0.001], advance() {}, write() {} };
  const s = new Servo({ device, linkTimeoutS: 10 });
  const plane = primitiveFromPatch({ primitive: { kind: "plane", point: [0, 0, -0.001], normal: [0, 0, 1] } });
  const comp = { k_h: K, own_gain: 1 / K, proxy_hold: "zoh", source: "t" };
  s.setPatch({ prim: movedOut(plane, F / K), tick: 1, gains: comp, simPeriodS: 0.05, tS: 0, ownForceN: F });
  let t = 0;
  for (let k = 0; k < 200; k++) s.tick((t += 0.001));
  close(s.fMag, F, 1e-9);
  const plain = { k_h: K / 2, own_gain: 0, proxy_hold: "zoh", source: "t" };
  s.setPatch({ prim: plane, tick: 2, gains: plain, simPeriodS: 0.05, tS: t, ownForceN: F });
  let prev = F;
  let worst = 0;
  const forces = [];
  for (let k = 0; k < 400; k++) {
    s.tick((t += 0.001));
    worst = Math.max(worst, Math.abs(s.fMag - prev));
    prev = s.fMag;
    forces.push(s.fMag);
  }
  close(forces[0], F, 0.02); // no drop at the change
  assert.ok(worst <= (F / 0.25) * 0.001 * 1.05 + 1e-9, `largest step ${worst} N`);
  close(forces.at(-1), 0, 1e-9); // then the probe is on the surface: no force
});

for (const hold of ["zoh", "foh"]) {
  test(`new gains with their own compensation keep a held press steady (${hold})`, () => {
    // 3 N held by K_h 580 N/m with C_h K_h = 1; the next cell's design, K_h 67 N/m with C_h K_h =
    // 1, renders the same 3 N. With a first-order hold the slide carried the change of C_h on top
    // of the K_h step's transfer force: 5.45 N in 20 ms, the probe still (client/render.py)
    const F = 3;
    const device = { x: [0, 0, -0.001], advance() {}, write() {} };
    const s = new Servo({ device, linkTimeoutS: 10 });
    const plane = primitiveFromPatch({ primitive: { kind: "plane", point: [0, 0, -0.001], normal: [0, 0, 1] } });
    const design = (k, proxyHold) => ({ k_h: k, own_gain: 1 / k, proxy_hold: proxyHold, source: "t" });
    s.setPatch({ prim: movedOut(plane, F / 580), tick: 1, gains: design(580, "zoh"), simPeriodS: 0.02, tS: 0, ownForceN: F });
    let t = 0;
    for (let k = 0; k < 300; k++) s.tick((t += 0.001));
    close(s.fMag, F, 1e-6);
    let tick = 2;
    for (const k of [67, 580]) {
      s.setPatch({ prim: movedOut(plane, F / k), tick: tick++, gains: design(k, hold), simPeriodS: 0.02, tS: t, ownForceN: F });
      let worst = 0;
      for (let i = 0; i < 400; i++) {
        s.tick((t += 0.001));
        worst = Math.max(worst, Math.abs(s.fMag - F));
      }
      assert.ok(worst < 0.01 * F, `K_h ${k} N/m, ${hold}: the force strayed ${worst} N from ${F} N`);
    }
  });
}

function compensatedServo(F) {
  const device = { x: [0, 0, -0.001], advance() {}, write() {} };
  const s = new Servo({ device, linkTimeoutS: 10 });
  const plane = primitiveFromPatch({ primitive: { kind: "plane", point: [0, 0, -0.001], normal: [0, 0, 1] } });
  return { s, device, at: (k) => movedOut(plane, F / k) };
}

/** A compensated design (C_h K_h = 1). */
const compDesign = (k, hold = "zoh") => ({ k_h: k, own_gain: 1 / k, proxy_hold: hold, source: "t" });

/** F [N] held at 580 N/m for 0.3 s, the probe still on the object's surface 1 mm deep. */
function heldPress(F) {
  const { s, device, at } = compensatedServo(F);
  s.setPatch({ prim: at(580), tick: 1, gains: compDesign(580), simPeriodS: 0.02, tS: 0, ownForceN: F });
  let t = 0;
  for (let k = 0; k < 300; k++) s.tick((t += 0.001));
  return { s, device, at, t };
}

test("a new design steps the force as it would itself at the new own force", () => {
  // a 500 N/m spring pressed with 2 N under K_h 250 N/m; the next patch brings K_h = K_o and the
  // surface under 3 N. The change of C_h slides in at the last patch's 2 N: the change of F_s is
  // the new design's, which with K_h = K_o feels no step (client/render.py)
  const kO = 500;
  const device = { x: [0, 0, -2 / kO], advance() {}, write() {} };
  const s = new Servo({ device, linkTimeoutS: 10 });
  const surface = (f) => primitiveFromPatch({ primitive: { kind: "plane", point: [0, 0, -f / kO], normal: [0, 0, 1] } });
  const design = (k) => ({ k_h: k, own_gain: 1 / k, proxy_hold: "zoh", source: "t" });
  s.setPatch({ prim: movedOut(surface(2), 2 / 250), tick: 1, gains: design(250), simPeriodS: 0.02, tS: 0, ownForceN: 2 });
  let t = 0;
  for (let k = 0; k < 300; k++) s.tick((t += 0.001));
  close(s.fMag, 2, 1e-6);
  s.setPatch({ prim: movedOut(surface(3), 3 / kO), tick: 2, gains: design(kO), simPeriodS: 0.02, tS: t, ownForceN: 3 });
  let worst = 0;
  for (let k = 0; k < 400; k++) {
    s.tick((t += 0.001));
    worst = Math.max(worst, Math.abs(s.fMag - 2));
  }
  assert.ok(worst < 0.02, `the force strayed ${worst} N from 2 N`);
});

test("compensated designs arriving mid-slide keep a held press steady", () => {
  const F = 3;
  const design = compDesign;
  const held = heldPress(F);
  const { s, at } = held;
  let { t } = held;
  let worst = 0;
  let tick = 2;
  for (const k of [67, 934, 200, 580, 67, 400]) {
    s.setPatch({ prim: at(k), tick: tick++, gains: design(k, "foh"), simPeriodS: 0.02, tS: t, ownForceN: F });
    for (let i = 0; i < 7; i++) {
      s.tick((t += 0.001));
      worst = Math.max(worst, Math.abs(s.fMag - F));
    }
  }
  for (let i = 0; i < 300; i++) {
    s.tick((t += 0.001));
    worst = Math.max(worst, Math.abs(s.fMag - F));
  }
  assert.ok(worst < 0.01 * F, `the force strayed ${worst} N from ${F} N`);
});

for (const hold of ["zoh", "foh"]) {
  test(`a probe leaving during the slide is not pushed again (${hold})`, () => {
    // C_h rose (580 -> 67 N/m): the slide holds the surface back while the probe is withdrawn
    // at 0.5 m/s; dropped with the contact, it put the surface out at once, into the probe
    const F = 3;
    const design = compDesign;
    const held = heldPress(F);
    const { s, device, at } = held;
    let { t } = held;
    s.setPatch({ prim: at(67), tick: 2, gains: design(67, hold), simPeriodS: 0.02, tS: t, ownForceN: F });
    const forces = [];
    for (let k = 0; k < 300; k++) {
      device.x = [0, 0, device.x[2] + 0.0005];
      s.tick((t += 0.001));
      forces.push(s.fMag);
    }
    const left = forces.findIndex((f) => f === 0);
    assert.ok(left > 0 && Math.max(...forces.slice(left)) === 0, `pushed again: ${Math.max(...forces.slice(left))} N`);
  });
}

test("two patches between ticks keep a held press steady", () => {
  // the worker hands over every queued patch before its next tick: the second change of C_h
  // took the first one's surface step for the slide's pending decrement (3 N rose to 7.9 N)
  const F = 3;
  const design = compDesign;
  const held = heldPress(F);
  const { s, at } = held;
  let { t } = held;
  s.setPatch({ prim: at(67), tick: 2, gains: design(67, "foh"), simPeriodS: 0.02, tS: t, ownForceN: F });
  s.setPatch({ prim: at(400), tick: 3, gains: design(400, "zoh"), simPeriodS: 0.02, tS: t, ownForceN: F });
  let worst = 0;
  for (let k = 0; k < 300; k++) {
    s.tick((t += 0.001));
    worst = Math.max(worst, Math.abs(s.fMag - F));
  }
  assert.ok(worst < 0.01 * F, `the force strayed ${worst} N from ${F} N`);
});

test("a probe coming back meets the surface where it is", () => {
  // C_h rose (580 -> 67 N/m), the probe left at 0.5 m/s; the object, released, is at rest and
  // the probe comes back at 0.1 m/s: the first force within 0.2 mm of the object's surface
  const F = 3;
  const design = compDesign;
  const held = heldPress(F);
  const { s, device, at } = held;
  let { t } = held;
  s.setPatch({ prim: at(67), tick: 2, gains: design(67), simPeriodS: 0.02, tS: t, ownForceN: F });
  for (let k = 0; k < 40; k++) {
    device.x = [0, 0, device.x[2] + 0.0005];
    s.tick((t += 0.001));
  }
  const rest = primitiveFromPatch({ primitive: { kind: "plane", point: [0, 0, 0], normal: [0, 0, 1] } });
  s.setPatch({ prim: rest, tick: 3, gains: design(67), simPeriodS: 0.02, tS: t, ownForceN: 0 });
  for (let k = 0; k < 1000 && s.fMag === 0; k++) {
    device.x = [0, 0, device.x[2] - 0.0001];
    s.tick((t += 0.001));
  }
  assert.ok(s.fMag > 0 && -device.x[2] < 2e-4, `the first force at ${-device.x[2]} m deep`);
});

test("a rise of compensation out of contact does not jump into the probe", () => {
  // the probe just left a 3 N press (580 N/m) by 0.8 mm; the next design (67 N/m, F_s still 3 N)
  // puts the surface 39 mm further out: it comes out no faster than the slide (client/render.py)
  const F = 3;
  const design = compDesign;
  const held = heldPress(F);
  const { s, device, at } = held;
  let { t } = held;
  device.x = [0, 0, -0.001 + F / 580 + 0.0008];
  for (let k = 0; k < 3; k++) s.tick((t += 0.001));
  close(s.fMag, 0);
  s.setPatch({ prim: at(67), tick: 2, gains: design(67), simPeriodS: 0.02, tS: t, ownForceN: F });
  let prev = 0;
  let worst = 0;
  for (let k = 0; k < 300; k++) {
    s.tick((t += 0.001));
    worst = Math.max(worst, Math.abs(s.fMag - prev));
    prev = s.fMag;
  }
  assert.ok(worst < 0.02, `the force stepped by ${worst} N`);
});

test("patches queued between ticks add up to the newest one alone", () => {
  // the worker hands over every queued patch before its next tick: the change of C_h is taken
  // at the F_s of the patch the last tick rendered (the first's F_s: 1.55 N went to 8.9 N)
  const run = (patches) => {
    const { s, at } = compensatedServo(3);
    const design = (k) => ({ k_h: k, own_gain: 1 / k, proxy_hold: "zoh", source: "t" });
    s.setPatch({ prim: at(580), tick: 1, gains: design(580), simPeriodS: 0.02, tS: 0, ownForceN: 3 });
    let t = 0;
    for (let k = 0; k < 300; k++) s.tick((t += 0.001));
    let tick = 2;
    for (const [k, f] of patches) {
      const prim = movedOut(primitiveFromPatch({ primitive: { kind: "plane", point: [0, 0, -0.001], normal: [0, 0, 1] } }), f / k);
      s.setPatch({ prim, tick: tick++, gains: design(k), simPeriodS: 0.02, tS: t, ownForceN: f });
    }
    const out = [];
    for (let k = 0; k < 300; k++) {
      s.tick((t += 0.001));
      out.push(s.fMag);
    }
    return out;
  };
  const both = run([[67, 4], [580, 5]]);
  const newest = run([[580, 5]]);
  for (let k = 0; k < both.length; k++) close(both[k], newest[k], 1e-9);
});

test("forces withheld end the slide and forget the contact", () => {
  // a link loss ramps the force to zero: no slide and no transfer force from the old contact
  // are left for the patch that comes after it (as the Python client's reset)
  const F = 3;
  const { at } = compensatedServo(F);
  const device = { x: [0, 0, -0.001], advance() {}, write() {} };
  const s = new Servo({ device, linkTimeoutS: 0.02, rampS: 0.01 });
  const design = (k) => ({ k_h: k, own_gain: 1 / k, proxy_hold: "zoh", source: "t" });
  let t = 0;
  s.setPatch({ prim: at(580), tick: 1, gains: design(580), simPeriodS: 0.02, tS: t, ownForceN: F });
  for (let k = 0; k < 300; k++) {
    if (k % 10 === 0) s.setPatch({ prim: at(580), tick: 1 + k, gains: design(580), simPeriodS: 0.02, tS: t, ownForceN: F });
    s.tick((t += 0.001));
  }
  s.setPatch({ prim: at(67), tick: 400, gains: design(67), simPeriodS: 0.02, tS: t, ownForceN: F });
  s.tick((t += 0.001));
  assert.ok(s._off < 0 && s.model.b !== 0); // a slide and a transfer force under way
  while (s.g > 0) s.tick((t += 0.001)); // the link falls silent: the force ramps to zero
  s.tick((t += 0.001));
  assert.ok(t < 0.35, "withheld before the slide's own end");
  assert.equal(s._off, 0);
  assert.equal(s.model.inContact, false);
  assert.equal(s.model.b, 0);
});

test("a declared damper goes into hello and bounds the recommended B_h", () => {
  const dev = { profile: "js-sim", maxForceN: 7.9, maxStiffnessNPerM: 1000, maxDampingNsPerM: 10 };
  const h = helloMessage({ name: "A", device: dev, servoRateHz: 1000, localModel: "p" });
  assert.equal(h.device.max_damping_n_s_per_m, 10);
  const none = helloMessage({ name: "A", device: { ...dev, maxDampingNsPerM: 0 }, servoRateHz: 1000, localModel: "p" });
  assert.equal("max_damping_n_s_per_m" in none.device, false); // no damper: the server's default 0
  const patch = { k_o: 300, k_o_eff: 300, gains: { k_h: 300, b_h: 25, own_gain: 1 / 300 } };
  const o = { mode: "patch", maxStiffnessNPerM: 1000, localModel: "p" };
  assert.equal(chooseGains(patch, { ...o, maxDampingNsPerM: 10 }).b_h, 10);
  assert.equal(chooseGains(patch, o).b_h, 25); // no limit given: as recommended
});

test("hello: resume carries the last welcome's resume token, and only when there is one", () => {
  const base = {
    name: "A",
    device: { profile: "js-sim", maxForceN: 7.9, maxStiffnessNPerM: 1000, maxDampingNsPerM: 0 },
    servoRateHz: 1000,
    localModel: "pi",
  };
  assert.equal("resume" in helloMessage(base), false); // a first join: no field at all
  assert.equal("resume" in helloMessage({ ...base, resume: null }), false);
  assert.equal("resume" in helloMessage({ ...base, resume: "" }), false);
  const m = helloMessage({ ...base, resume: "Zq3k9V8tS1o0d2aM4mWbq0cJ7oY6uE5r" });
  assert.equal(m.resume, "Zq3k9V8tS1o0d2aM4mWbq0cJ7oY6uE5r");
  assert.equal(m.type, "hello");
});
