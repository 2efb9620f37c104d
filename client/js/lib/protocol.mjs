// Messages of docs/protocol.md (wire protocol version 1), as this client builds and reads them.
// Pure functions: no sockets, no clocks.

export const PROTOCOL = 1;

const NAME_RE = /^[A-Za-z0-9_.-]{1,32}$/;

/** True when every number in a (nested) JSON value is finite: JSON has no NaN or Infinity. */
export function allFinite(v) {
  if (typeof v === "number") return Number.isFinite(v);
  if (Array.isArray(v)) return v.every(allFinite);
  if (v && typeof v === "object") return Object.values(v).every(allFinite);
  return true;
}

/**
 * The `hello` of a haptic user. `token` is sent only when given; so is `resume`, the
 * `resume_token` of the last `welcome` (docs/protocol.md, "Rejoin"): after a dropped link it
 * gets the same seat back (user id, name, contact) within the server's hold time.
 * @throws {RangeError} a name outside 1-32 of A-Za-z0-9_.-
 */
export function helloMessage({ name, device, servoRateHz, localModel, token, resume }) {
  if (!NAME_RE.test(name)) throw new RangeError(`name must be 1-32 of A-Za-z0-9_.-, got ${JSON.stringify(name)}`);
  const m = {
    type: "hello",
    protocol: PROTOCOL,
    role: "user",
    name,
    device: {
      profile: device.profile,
      max_force_n: device.maxForceN,
      max_stiffness_n_per_m: device.maxStiffnessNPerM,
    },
    servo_rate_hz: servoRateHz,
    local_model: localModel,
  };
  if (device.maxDampingNsPerM > 0) m.device.max_damping_n_s_per_m = device.maxDampingNsPerM;
  if (token) m.token = token;
  if (typeof resume === "string" && resume.length > 0) m.resume = resume;
  return m;
}

/**
 * The `state` frame from a servo snapshot. Returns null when a number is not finite (the
 * server refuses NaN/Infinity, and JSON.stringify would turn them into null): skip the frame.
 * Before the first patch (`patchTick` < 0) there is no local model: no `penetration_m`.
 */
export function stateMessage({ seq, snap, rttMs }) {
  const m = {
    type: "state",
    seq,
    probe_m: snap.probe,
    force_n: snap.force,
    penetration_m: snap.penetration,
    in_contact: snap.inContact,
    k_h: snap.kH,
    i_gain: snap.iGain,
    own_gain: snap.ownGain ?? 0,
    servo_rate_hz: snap.rateHz,
    period_us_p99: snap.p99Us,
    patch_tick: snap.patchTick,
  };
  if (rttMs !== null && rttMs !== undefined) m.rtt_ms = rttMs;
  if (!(snap.patchTick >= 0)) delete m.penetration_m;
  return allFinite(m) ? m : null;
}

function finiteNonNeg(v, dflt) {
  return Number.isFinite(v) && v >= 0 ? v : dflt;
}

/**
 * The gains to render for a patch.
 *
 * - mode "patch" and the patch carries `gains` {k_h, i_gain, b_h, proxy_hold, theta_m, own_gain}
 *   with a finite k_h: those (the server designed them for this device, servo rate and delay),
 *   with K_h and B_h clamped to the device's maximum stiffness and damping and I = 0 if we declared a P
 *   model; own_gain (C_h [m/N], own-force compensation) moves the patch's primitive out by
 *   own_gain * patch.own_force_n (ownOffsetM);
 * - otherwise the fallback: K_h = 0.3 * k_o_eff (inside eq. 8's K_h < K_o with margin for the
 *   delay and the sampling tick), P only, with own-force compensation C_h = 1 / K_h: a held
 *   press feels the object's own stiffness (the simulation loop's static gain 1 - K_h / K_o is
 *   then inside (0, 0.7]), so a user whose contact waits for new gains keeps feeling the object.
 *   Like the uncompensated fallback before it, this is not checked with the hand box: it renders
 *   only until the server's verified gains arrive.
 * Returns null when the patch allows neither (no positive k_o_eff/k_o): keep the previous gains.
 */
export function chooseGains(
  patch,
  { mode, maxStiffnessNPerM, maxDampingNsPerM = Infinity, localModel, fallbackRatio = 0.3 },
) {
  const g = patch.gains;
  if (mode === "patch" && g && typeof g === "object" && Number.isFinite(g.k_h) && g.k_h >= 0) {
    return {
      k_h: Math.min(g.k_h, maxStiffnessNPerM),
      i_gain: localModel === "p" ? 0 : finiteNonNeg(g.i_gain, 0),
      b_h: Math.min(finiteNonNeg(g.b_h, 0), maxDampingNsPerM),
      theta_m: finiteNonNeg(g.theta_m, 0),
      proxy_hold: g.proxy_hold === "foh" ? "foh" : "zoh",
      own_gain: finiteNonNeg(g.own_gain, 0),
      source: "patch",
    };
  }
  const kEff = Number.isFinite(patch.k_o_eff) && patch.k_o_eff > 0 ? patch.k_o_eff : patch.k_o;
  if (!(Number.isFinite(kEff) && kEff > 0)) return null;
  const kH = Math.min(fallbackRatio * kEff, maxStiffnessNPerM);
  return {
    k_h: kH,
    i_gain: 0,
    b_h: 0,
    theta_m: 0,
    proxy_hold: "zoh",
    own_gain: 1 / kH,
    source: "fallback",
  };
}

/**
 * How far [m] the local model renders the patch's primitive moved out: own-force compensation
 * C_h * F_s, F_s the force the server applied from this user for that surface (0 without).
 */
export function ownOffsetM(patch, gains) {
  return finiteNonNeg(gains.own_gain, 0) * finiteNonNeg(patch.own_force_n, 0);
}
