// The inclusions ("lumps") of a FEM solid, as the viewer stream sends them: decoding and checking
// the INC1 frames (server/viewer_stream.py has the format; docs/protocol.md, "Viewer stream"),
// with no three.js and no DOM, so that node can test it (tests/web/test_lump_js.py).
//
// A viewer of a solid with `--inclusion` gets one INC1 frame per inclusion after the keyframe:
// the inclusion's surface at rest (it does not follow the deformation), its name, its material's
// name and its Young's modulus over the solid's. Everything in a frame is checked before it is
// used: a frame that is short, long, over the server's bounds, or holds a non-finite or far-away
// vertex or a triangle index out of range is refused whole (decodeInclusion says why), so bad
// numbers never reach the scene. The same checks as server/viewer_decoder.py decode_inclusion.

/** INC1 frames, as server/viewer_stream.py defines them (checked by tests/web/test_lump_js.py). */
export const INCLUSION = Object.freeze({
  MAGIC: "INC1",
  // magic, uint32 index, of, vertices k, faces m, float32 Young's modulus ratio, uint32 flags,
  // uint16 name bytes, uint16 material bytes; then the texts (padded to 4), k x 3 float32 [m],
  // m x 3 uint16
  HEADER_BYTES: 32,
  FLAG_DECIMATED: 1, // the server simplified the surface to fit its triangle budget
  MAX_INCLUSIONS: 16, // frames a viewer gets at most (index < MAX_INCLUSIONS)
  MAX_FACES: 4096, // triangles in all frames together (and so in one)
  MAX_VERTICES: 12288, // vertices in one frame
  MAX_TEXT_BYTES: 64, // UTF-8 bytes of a name or a material's name
  MAX_COORD_M: 1000, // largest |coordinate| [m] accepted (server/viewer_decoder.py: the same)
});

const utf8 = new TextDecoder("utf-8"); // not fatal: a bad byte shows as U+FFFD, never throws

/**
 * Decode and check one INC1 frame.
 *
 * @param {ArrayBuffer} buf the binary websocket frame
 * @returns {{ok: true, lump: object} | {ok: false, reason: string}} the lump: `index`, `of`,
 *   `name`, `material` (strings, for textContent only), `youngRatio` (finite > 0, or null when
 *   the server did not know it), `decimated`, `positions` (Float32Array, 3k, [m], a copy) and
 *   `indices` (Uint16Array, 3m, a copy).
 */
export function decodeInclusion(buf) {
  const fail = (reason) => ({ ok: false, reason });
  if (!(buf instanceof ArrayBuffer)) return fail("not binary");
  if (buf.byteLength < INCLUSION.HEADER_BYTES) return fail("shorter than its header");
  const dv = new DataView(buf);
  const magic = String.fromCharCode(
    dv.getUint8(0), dv.getUint8(1), dv.getUint8(2), dv.getUint8(3),
  );
  if (magic !== INCLUSION.MAGIC) return fail(`not ${INCLUSION.MAGIC}`);
  const index = dv.getUint32(4, true);
  const of = dv.getUint32(8, true);
  const k = dv.getUint32(12, true);
  const m = dv.getUint32(16, true);
  const ratio = dv.getFloat32(20, true);
  const flags = dv.getUint32(24, true);
  const nameBytes = dv.getUint16(28, true);
  const materialBytes = dv.getUint16(30, true);
  if (!(index < of && index < INCLUSION.MAX_INCLUSIONS)) return fail(`index ${index} of ${of}`);
  if (k < 3 || k > INCLUSION.MAX_VERTICES) return fail(`${k} vertices`);
  if (m < 1 || m > INCLUSION.MAX_FACES) return fail(`${m} triangles`);
  if (nameBytes > INCLUSION.MAX_TEXT_BYTES || materialBytes > INCLUSION.MAX_TEXT_BYTES) {
    return fail("name too long");
  }
  const text = nameBytes + materialBytes;
  const start = INCLUSION.HEADER_BYTES + text + ((4 - (text % 4)) % 4);
  if (buf.byteLength !== start + 12 * k + 6 * m) return fail("length does not match its counts");
  const positions = new Float32Array(buf.slice(start, start + 12 * k));
  for (let i = 0; i < positions.length; i++) {
    const x = positions[i];
    if (!Number.isFinite(x) || Math.abs(x) > INCLUSION.MAX_COORD_M) {
      return fail("a vertex is not finite or out of range");
    }
  }
  const indices = new Uint16Array(buf.slice(start + 12 * k, start + 12 * k + 6 * m));
  for (let i = 0; i < indices.length; i++) {
    if (indices[i] >= k) return fail("a triangle index is out of range");
  }
  const bytes = new Uint8Array(buf, INCLUSION.HEADER_BYTES, text);
  return {
    ok: true,
    lump: {
      index,
      of,
      name: utf8.decode(bytes.subarray(0, nameBytes)),
      material: utf8.decode(bytes.subarray(nameBytes)),
      youngRatio: Number.isFinite(ratio) && ratio > 0 ? ratio : null,
      decimated: (flags & INCLUSION.FLAG_DECIMATED) !== 0,
      positions,
      indices,
    },
  };
}

/** How stiff a lump is, in words: "10× as stiff", "0.5× as stiff", "as stiff as the solid". */
export function stiffnessText(youngRatio) {
  if (youngRatio === null || !Number.isFinite(youngRatio)) return "stiffness unknown";
  if (Math.abs(youngRatio - 1) < 0.005) return "as stiff as the solid";
  return `${+youngRatio.toPrecision(3)}× as stiff`;
}

/** A lump's colour (sRGB hex): red when stiffer than the solid, green when softer, grey when
 * the same (a twin meshed like the lump, or a region of the solid's own material). */
export function lumpColor(youngRatio) {
  if (youngRatio === null || !Number.isFinite(youngRatio)) return "#c8ccd6";
  if (youngRatio > 1.005) return "#ff3355";
  if (youngRatio < 0.995) return "#4de38a";
  return "#c8ccd6";
}
