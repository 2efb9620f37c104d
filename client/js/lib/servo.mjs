// The servo core: everything one haptic tick does, with no clock, no sockets and no threads.
//
// Written from docs/protocol.md ("What a user does with a patch") and the paper it cites
// (Barbagli et al. 2005, eq. 12 and 17). SI units everywhere: m, N, N/m, N/(m*s), s.
//
// One tick (CHAI3D's three phases):
//   1. update from device:  the simulated hand+device advances to `now` with the force held
//                           since the last tick (zero-order hold), then x_h = its position
//   2. compute:             (e, n) = primitive penetration of x_h;  f = L(z) e  (P or PI)
//                           F = g * min(f, F_max) * n,  g in [0, 1] the safety ramp
//   3. apply to device:     the device renders F until the next tick
//
// A new patch is handed in between two ticks (setPatch), so a primitive and its gains are
// always applied whole.

/** @typedef {[number, number, number]} Vec3 */

const EPS = 1e-9;

// Layout of the servo thread's snapshot (Float64Array in a SharedArrayBuffer), latest wins.
export const SNAP = {
  probe: 0, // 3
  force: 3, // 3
  e: 6,
  inContact: 7,
  kH: 8,
  iGain: 9,
  rateHz: 10,
  p99Us: 11,
  patchTick: 12,
  g: 13,
  ticks: 14,
  size: 15,
};


export function dot(a, b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}
export function norm(a) {
  return Math.sqrt(dot(a, a));
}
export function unit(a) {
  const n = norm(a);
  if (!(n > EPS)) throw new RangeError("zero-length vector");
  return [a[0] / n, a[1] / n, a[2] / n];
}
function finite3(v) {
  return Array.isArray(v) && v.length === 3 && v.every(Number.isFinite);
}

/**
 * The local geometric model of a patch, ready to render.
 *
 * Plane {kind:"plane", point, normal}: the object is on the side opposite to `normal`;
 *   e = (point - x) . normal,  n = normal.
 * Sphere {kind:"sphere", center, radius}: docs/protocol.md does not say whether the object is
 *   inside the sphere (a bump) or outside it (a dent). We read it off the patch itself: the
 *   patch's `normal` at `proxy_m` points out of the object, so if it points away from the
 *   centre the object is inside (bump: e = r - |x - c|, n = (x - c)/|x - c|), otherwise it is
 *   outside (dent: e = |x - c| - r, n = (c - x)/|x - c|). Without proxy/normal: a bump.
 *
 * e > 0 means the probe is inside the object (in contact), in m; n is the unit outward normal
 * the force on the user points along.
 *
 * @param {object} patch  a `patch` message (primitive, proxy_m, normal)
 * @returns {{kind: string, point?: Vec3, normal?: Vec3, center?: Vec3, radius?: number, inside?: boolean}}
 * @throws {RangeError} a primitive that is missing, unknown or not finite
 */
export function primitiveFromPatch(patch) {
  const p = patch && patch.primitive;
  if (!p || typeof p !== "object") throw new RangeError("patch without a primitive");
  if (p.kind === "plane") {
    if (!finite3(p.point) || !finite3(p.normal)) throw new RangeError("bad plane");
    return { kind: "plane", point: p.point.slice(), normal: unit(p.normal) };
  }
  if (p.kind === "sphere") {
    if (!finite3(p.center) || !(Number.isFinite(p.radius) && p.radius > 0)) {
      throw new RangeError("bad sphere");
    }
    let inside = true;
    if (finite3(patch.proxy_m) && finite3(patch.normal)) {
      const r = [
        patch.proxy_m[0] - p.center[0],
        patch.proxy_m[1] - p.center[1],
        patch.proxy_m[2] - p.center[2],
      ];
      inside = dot(r, patch.normal) >= 0;
    }
    return { kind: "sphere", center: p.center.slice(), radius: p.radius, inside };
  }
  throw new RangeError(`unknown primitive kind ${JSON.stringify(p.kind)}`);
}

/**
 * The primitive moved out along its outward normals by d >= 0 [m] (own-force compensation,
 * shared/full_loop.py): a plane shifted along its normal, a bump's sphere grown, a dent's shrunk.
 */
export function movedOut(prim, d) {
  return Number.isFinite(d) && d > 0 ? shiftedOut(prim, d) : prim;
}

/** The primitive moved out along its outward normals by d [m], d < 0 moving it in. */
export function shiftedOut(prim, d) {
  if (!(Number.isFinite(d) && d !== 0)) return prim;
  if (prim.kind === "plane") {
    return { ...prim, point: [0, 1, 2].map((i) => prim.point[i] + d * prim.normal[i]) };
  }
  const radius = prim.inside ? prim.radius + d : Math.max(prim.radius - d, 1e-6);
  return { ...prim, radius };
}

/**
 * Blend two primitives of the same kind (first-order hold of the proxy): a = 0 gives `from`,
 * a = 1 gives `to`. Different kinds or conventions: `to` (a jump).
 */
export function blendPrimitive(from, to, a) {
  if (!from || a >= 1 || from.kind !== to.kind || from.inside !== to.inside) return to;
  const b = 1 - a;
  if (to.kind === "plane") {
    const pt = [0, 1, 2].map((i) => b * from.point[i] + a * to.point[i]);
    const nn = [0, 1, 2].map((i) => b * from.normal[i] + a * to.normal[i]);
    return { kind: "plane", point: pt, normal: norm(nn) > EPS ? unit(nn) : to.normal };
  }
  return {
    kind: "sphere",
    center: [0, 1, 2].map((i) => b * from.center[i] + a * to.center[i]),
    radius: b * from.radius + a * to.radius,
    inside: to.inside,
  };
}

/**
 * Penetration of the probe x [m] past a primitive.
 * @returns {{e: number, n: Vec3}} e [m] > 0 inside the object; n the unit outward normal.
 */
export function penetration(prim, x) {
  if (prim.kind === "plane") {
    const n = prim.normal;
    const e = (prim.point[0] - x[0]) * n[0] + (prim.point[1] - x[1]) * n[1] + (prim.point[2] - x[2]) * n[2];
    return { e, n };
  }
  const d = [x[0] - prim.center[0], x[1] - prim.center[1], x[2] - prim.center[2]];
  const r = norm(d);
  let radial;
  if (r > EPS) radial = [d[0] / r, d[1] / r, d[2] / r];
  else radial = [0, 0, 1]; // the probe at the centre: any direction
  if (prim.inside) return { e: prim.radius - r, n: radial };
  return { e: r - prim.radius, n: [-radial[0], -radial[1], -radial[2]] };
}

/**
 * The local model L(z) of eq. 12: K_h (P) or K_h + T*I/(z-1) (PI), with the integration
 * threshold of eq. 17 and a linear bleed of the integral on release (paper section 5.1).
 *
 * In contact (e > 0):  s += dt * I * (e - theta)   (s kept in [0, sMax], no wind-up)
 *                      f  = K_h * e + s + b + b_h * de/dt, never negative (a surface only pushes;
 *                      b: the transfer force of a change of gains, see setGains)
 * Out of contact:      f  = 0; s ramps linearly to 0 over `bleedS` so a quick re-entry does
 *                      not find a wound-up integral.
 */
export class LocalModel {
  constructor({ bleedS = 0.1, sMax = 10, transferS = 0.25 } = {}) {
    this.kH = 0;
    this.iGain = 0;
    this.bH = 0;
    this.theta = 0;
    this.s = 0;
    this.bleedS = bleedS;
    this.sMax = sMax;
    this.transferS = transferS;
    this.b = 0; // transfer force [N] of the last change of gains, driven to zero
    this._bStep = 0;
    this._lastE = 0;
    this._bleedRate = 0;
    this._bleeding = false;
  }

  /**
   * Swap gains between ticks without a bump (as shared/local_model.py does): the integral is
   * kept (with I = 0 it is held, not dropped: interim P gains in mid-press must not let go of the
   * force it carries), and in contact the step (K_h,old - K_h,new) * e becomes a transfer force
   * driven linearly to zero over `transferS` (0: the force steps as eq. 12 says). With own-force
   * compensation (own_gain > 0) the integral is handed to the transfer force instead: the
   * compensation carries the force the object holds, an integral beside it would push for ever.
   * `carryN` [N]: a further force step to carry off (the K_h step of a depth the caller adds to
   * e, as the own-force slide's next decrement).
   */
  setGains({ k_h, i_gain = 0, b_h = 0, theta_m = 0, own_gain = 0 }, carryN = 0) {
    const kOld = this.kH;
    this.kH = k_h;
    this.iGain = i_gain;
    this.bH = b_h;
    this.theta = theta_m;
    let step = (kOld - k_h) * this._lastE + (Number.isFinite(carryN) ? carryN : 0);
    if (own_gain > 0 && this._lastE > 0 && this.s !== 0) {
      step += this.s;
      this.s = 0;
    }
    if (this._lastE > 0 && this.transferS > 0 && step !== 0 && Number.isFinite(step)) {
      this.b += step;
      this._bStep = this.b / this.transferS;
    }
  }

  /** Whether the last tick was in contact (e > 0). */
  get inContact() {
    return this._lastE > 0;
  }

  reset() {
    this.s = 0;
    this.b = 0;
    this._lastE = 0; // and the contact (as shared/local_model.py's reset)
    this._bleeding = false;
  }

  /**
   * @param {number} e penetration [m], > 0 in contact
   * @param {number} eDot its rate [m/s] (positive going in)
   * @param {number} dt the tick's duration [s]
   * @returns {number} force magnitude [N] along the outward normal, >= 0
   */
  step(e, eDot, dt) {
    const b = this.b;
    if (b !== 0) {
      const nb = b - this._bStep * dt;
      this.b = nb > 0 === b > 0 && nb !== 0 ? nb : 0;
    }
    this._lastE = e;
    if (e > 0) {
      this._bleeding = false;
      if (this.iGain > 0) {
        this.s += dt * this.iGain * (e - this.theta);
        if (this.s < 0) this.s = 0;
        else if (this.s > this.sMax) this.s = this.sMax;
      }
      const f = this.kH * e + this.s + b + this.bH * eDot;
      return f > 0 ? f : 0;
    }
    this.b = 0; // no transfer out of contact
    if (this.s > 0) {
      if (!this._bleeding) {
        this._bleeding = true;
        this._bleedRate = this.s / this.bleedS;
      }
      this.s = Math.max(0, this.s - this._bleedRate * dt);
    }
    return 0;
  }
}

/**
 * The simulated user: device handle (point mass with damping) held by a hand modelled as a
 * spring-damper pulling toward a target position; integrated in sub-steps with the device force
 * held constant over each servo tick (what a real device does between two writes).
 *
 *   (m_hand + m_dev) a = k_hand (target(t) - x) - (b_hand + b_dev) v + F
 */
export class SimHand {
  constructor({
    start,
    target,
    handK = 300,
    handB = 5,
    handMass = 0.45,
    deviceMass = 0.05,
    deviceB = 0.5,
    subStepS = 2.5e-4,
  }) {
    this.x = start.slice();
    this.v = [0, 0, 0];
    this.target = target; // (t [s]) -> Vec3
    this.k = handK;
    this.b = handB + deviceB;
    this.m = handMass + deviceMass;
    this.h = subStepS;
    this.force = [0, 0, 0];
  }

  /** Advance from time t0 by dt [s] with the held force (semi-implicit Euler sub-steps). */
  advance(t0, dt) {
    if (!(dt > 0)) return;
    const n = Math.max(1, Math.ceil(dt / this.h));
    const h = dt / n;
    const tgt = this.target(t0 + dt); // the hand target moves slowly: one value per tick
    for (let s = 0; s < n; s++) {
      for (let i = 0; i < 3; i++) {
        const a = (this.k * (tgt[i] - this.x[i]) - this.b * this.v[i] + this.force[i]) / this.m;
        this.v[i] += h * a;
        this.x[i] += h * this.v[i];
      }
    }
  }

  write(f) {
    this.force[0] = f[0];
    this.force[1] = f[1];
    this.force[2] = f[2];
  }
}

/**
 * A scripted hand target: start `standoffM` outside `anchor` along `normal`, approach to
 * `restDepthM` inside, and optionally press to `pressDepthM` and come back.
 * Times in s since the client started. Returns (t) -> Vec3.
 */
export function scriptedTarget({
  anchor,
  normal,
  standoffM = 0.03,
  approachAtS = 0.5,
  approachS = 1.0,
  restDepthM = 0.002,
  pressDepthM = null,
  pressAtS = 3.0,
  pressRampS = 1.0,
  pressHoldS = Infinity,
}) {
  const n = unit(normal);
  const depthAt = (t) => {
    if (t <= approachAtS) return -standoffM;
    if (t < approachAtS + approachS) {
      const a = (t - approachAtS) / approachS;
      return -standoffM + a * (restDepthM + standoffM);
    }
    if (pressDepthM === null || t <= pressAtS) return restDepthM;
    const t1 = pressAtS + pressRampS;
    if (t < t1) return restDepthM + ((t - pressAtS) / pressRampS) * (pressDepthM - restDepthM);
    const t2 = t1 + pressHoldS;
    if (t <= t2) return pressDepthM;
    if (t < t2 + pressRampS) return pressDepthM + ((t - t2) / pressRampS) * (restDepthM - pressDepthM);
    return restDepthM;
  };
  const fn = (t) => {
    const d = depthAt(t);
    return [anchor[0] - d * n[0], anchor[1] - d * n[1], anchor[2] - d * n[2]];
  };
  fn.start = fn(0);
  return fn;
}

/**
 * The servo core. Call tick(tS) once per servo period with the current time [s]; call
 * setPatch(...) between ticks when the network delivers one.
 */
export class Servo {
  /**
   * @param {object} o
   * @param {SimHand} o.device
   * @param {number} o.maxForceN      device force limit [N]
   * @param {number} o.linkTimeoutS   no patch for this long [s]: ramp the force to zero
   * @param {number} o.rampS          duration of a full 0<->1 ramp of the safety gain [s]
   */
  constructor({ device, maxForceN = 7.9, linkTimeoutS = 0.25, rampS = 0.05, bleedS = 0.1 }) {
    this.device = device;
    this.maxForceN = maxForceN;
    this.linkTimeoutS = linkTimeoutS;
    this.rampS = rampS;
    this.model = new LocalModel({ bleedS, sMax: maxForceN });
    this.prim = null; // primitive in force (target of the hold)
    this.primFrom = null; // previous primitive, for the first-order hold
    this.holdStartS = 0;
    this.holdS = 0; // 0: jump (zero-order hold)
    this.patchTick = -1;
    this.patchAtS = -Infinity;
    this.gains = { k_h: 0, i_gain: 0, b_h: 0, theta_m: 0, proxy_hold: "zoh", source: "none" };
    this.g = 0; // safety gain
    this.waitingForPatch = true; // after a link loss: ramp up only after a new patch
    this.linkLosses = 0;
    this.lastT = null;
    this.e = 0;
    this.n = [0, 0, 1];
    this.force = [0, 0, 0];
    this.fMag = 0;
    this._xPrev = null;
    this._vFilt = [0, 0, 0];
    this._ownGain = 0; // own-force compensation C_h [m/N] in use
    this._off = 0; // depth [m] added to e after a change of C_h, driven to zero (setPatch)
    this._offRate = 0;
    this._ownForceN = 0; // F_s [N] the last patch's compensation carried
    this._offUsed = 0; // the slide's depth [m] in the last tick's penetration
    this._fsRendered = 0; // F_s [N] of the patch the last tick rendered
  }

  /**
   * Take a new patch (between ticks). `prim` from primitiveFromPatch, already moved out by the
   * compensation; `gains` {k_h, i_gain, b_h, theta_m, proxy_hold, own_gain, source};
   * `simPeriodS` the simulation period (for the FOH); `ownForceN` the patch's own_force_n.
   *
   * A change of own-force compensation (out of contact, a rise of it) moved the surface by
   * (C_old - C_new) * F_s, F_s the own force of the patch rendered last: that step is added to the penetration and driven to zero over the model's
   * transfer time, so the surface slides (as client/render.py does). A transfer force would end
   * with the contact, and withdrawing the compensation from a probe resting on the
   * object's own surface puts the rendered surface right under it. With a first-order hold the
   * slide over the simulation period starts from the old surface with the new compensation, so
   * it carries the surface's motion alone: carrying the change of C_h too, on top of the transfer
   * force of the K_h step, it rendered 5.45 N for a held 3 N (K_h 580 -> 67 N/m, C_h K_h = 1).
   */
  setPatch({ prim, tick, gains, simPeriodS, tS, ownForceN = 0 }) {
    const foh = gains.proxy_hold === "foh";
    const cNew = Number.isFinite(gains.own_gain) && gains.own_gain > 0 ? gains.own_gain : 0;
    const fS = Number.isFinite(ownForceN) && ownForceN > 0 ? ownForceN : 0;
    const transferS = this.model.transferS;
    // the K_h step of the slide's next decrement, already taken from _off, is carried off too
    // (the model's step is on the last tick's penetration)
    const carry = (this.model.kH - gains.k_h) * (this._off - this._offUsed);
    let cStep = 0; // the change of C_h's step of the surface [m], slid in
    const slides = this.model.inContact || cNew > this._ownGain; // out of contact: a rise only
    if (this.prim && cNew !== this._ownGain && slides && transferS > 0) {
      // at the last patch's F_s: the change of F_s since is the new design's to render
      // (the last tick's: queued patches handed over together add up to the newest alone)
      cStep = (this._ownGain - cNew) * this._fsRendered;
      this._off += cStep;
      this._offUsed += cStep; // not a decrement: a second patch before the next tick
      this._offRate = this._off / transferS;
    }
    this._ownGain = cNew;
    this._ownForceN = fS;
    if (foh && this.prim) {
      this.primFrom = shiftedOut(this._currentPrimitive(tS), -cStep);
      this.holdStartS = tS;
      this.holdS = simPeriodS;
    } else {
      this.primFrom = null;
      this.holdS = 0;
    }
    this.prim = prim;
    this.patchTick = tick;
    this.patchAtS = tS;
    this.gains = gains;
    this.model.setGains(gains, carry);
    this.waitingForPatch = false;
  }

  _currentPrimitive(tS) {
    if (!this.primFrom || !(this.holdS > 0)) return this.prim;
    const a = (tS - this.holdStartS) / this.holdS;
    if (a >= 1) {
      this.primFrom = null;
      return this.prim;
    }
    return blendPrimitive(this.primFrom, this.prim, Math.max(0, a));
  }

  /** One servo tick at time tS [s]. Returns the force [N] written to the device. */
  tick(tS) {
    const dt = this.lastT === null ? 0 : Math.min(0.05, Math.max(0, tS - this.lastT));
    // 1. update from device (the force of the previous tick was held meanwhile)
    if (this.lastT !== null) this.device.advance(this.lastT, tS - this.lastT);
    this.lastT = tS;
    const x = this.device.x;
    if (this._xPrev && dt > 0) {
      const a = dt / (dt + 0.005); // first-order filter, 5 ms (the damper's velocity filter)
      for (let i = 0; i < 3; i++) {
        this._vFilt[i] += a * ((x[i] - this._xPrev[i]) / dt - this._vFilt[i]);
      }
    }
    this._xPrev = x.slice();

    // safety ramp: down when the link is silent, back up only after a new patch
    const fresh = tS - this.patchAtS <= this.linkTimeoutS;
    if (!fresh && !this.waitingForPatch) {
      this.waitingForPatch = true;
      this.linkLosses += 1;
    }
    const step = dt / this.rampS;
    if (fresh && !this.waitingForPatch && this.prim) this.g = Math.min(1, this.g + step);
    else this.g = Math.max(0, this.g - step);

    // 2. compute
    let f = 0;
    if (this.prim) {
      const { e: e0, n } = penetration(this._currentPrimitive(tS), x);
      let e = e0;
      const off = this._off;
      this._offUsed = off;
      this._fsRendered = this._ownForceN;
      if (off !== 0) {
        // a change of C_h, sliding in (setPatch)
        e += off;
        const nxt = off - this._offRate * dt;
        this._off = nxt > 0 === off > 0 && nxt !== 0 ? nxt : 0;
      }
      this.e = e;
      this.n = n;
      const eDot = -dot(this._vFilt, n);
      if (this.g > 0) f = this.model.step(e, eDot, dt);
      else this.model.reset(); // forces withheld: no integral winds up
      // forces withheld: no slide (the Python client's reset). Out of contact a slide that
      // deepens the surface ends; one that holds it back holds it no further back than the
      // probe has left (dropped, it put the surface out at once, into a retreating probe; kept
      // whole, the probe met the surface deep inside on its way back: client/render.py)
      if (this.g <= 0) this._off = 0;
      else if (!(e > 0) && this._off !== 0) {
        this._off = this._off > 0 ? 0 : Math.min(0, Math.max(this._off, off - e));
      }
    }
    f = Math.min(f, this.maxForceN) * this.g;
    this.fMag = f;
    this.force[0] = f * this.n[0];
    this.force[1] = f * this.n[1];
    this.force[2] = f * this.n[2];
    // 3. apply to device
    this.device.write(this.force);
    return this.force;
  }
}
