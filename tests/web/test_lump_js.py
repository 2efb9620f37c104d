"""web/lump.js reads the server's INC1 frames as the server wrote them and refuses malformed ones.

No browser: node runs web/lump.js (an ES module with no three.js and no DOM) on frames the
server's encoder made (:func:`server.viewer_stream.encode_inclusions`) and on the same frames
broken in each way the reference decoder refuses (``tests/server/test_viewer_inclusions.py``).
Skipped without node.
"""

from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from haptic_collab.server import viewer_decoder as vd
from haptic_collab.server import viewer_stream as vs
from haptic_collab.server.viewer_stream import encode_inclusions
from tests.server.test_viewer_inclusions import malformed_frames, sphere

ROOT = Path(__file__).resolve().parents[2]
LUMP_JS = ROOT / "web" / "lump.js"

needs_node = pytest.mark.skipif(shutil.which("node") is None, reason="node is not installed")

#: Decodes each base64 frame of stdin's JSON list with lump.js; prints what it made of each.
_RUN = """
import { decodeInclusion, stiffnessText, lumpColor } from %s;
let input = "";
process.stdin.on("data", (d) => (input += d));
process.stdin.on("end", () => {
  const out = JSON.parse(input).map((b64) => {
    const bytes = Buffer.from(b64, "base64");
    const buf = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.length);
    const res = decodeInclusion(buf);
    if (!res.ok) return { ok: false, reason: res.reason };
    const l = res.lump;
    return {
      ok: true, index: l.index, of: l.of, name: l.name, material: l.material,
      youngRatio: l.youngRatio, decimated: l.decimated, positions: Array.from(l.positions),
      indices: Array.from(l.indices), words: stiffnessText(l.youngRatio),
      color: lumpColor(l.youngRatio),
    };
  });
  process.stdout.write(JSON.stringify(out));
});
"""


def run_lump_js(frames: list[bytes]) -> list[dict[str, Any]]:
    script = _RUN % json.dumps(LUMP_JS.as_uri())
    res = subprocess.run(
        ["node", "--input-type=module", "-e", script],
        input=json.dumps([base64.b64encode(f).decode() for f in frames]),
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert res.returncode == 0, res.stderr
    out: list[dict[str, Any]] = json.loads(res.stdout)
    return out


def test_lump_js_constants_match_the_server() -> None:
    text = LUMP_JS.read_text(encoding="utf-8")
    m = re.search(r"export const INCLUSION = Object\.freeze\(\{(.*?)\}\);", text, re.S)
    assert m, "lump.js must declare `export const INCLUSION = Object.freeze({...});`"
    js = dict(re.findall(r'^\s*(\w+): ("?\w+"?),', m.group(1), re.M))
    assert js == {
        "MAGIC": f'"{vs.INCLUSION_MAGIC.decode()}"',
        "HEADER_BYTES": str(vs.INC_HEADER.size),
        "FLAG_DECIMATED": str(vs.INC_FLAG_DECIMATED),
        "MAX_INCLUSIONS": str(vs.MAX_INCLUSIONS_SENT),
        "MAX_FACES": str(vs.MAX_INCLUSION_FACES),
        "MAX_VERTICES": str(vs.MAX_INCLUSION_VERTICES),
        "MAX_TEXT_BYTES": str(vs.MAX_INCLUSION_TEXT_BYTES),
        "MAX_COORD_M": f"{vd.MAX_INCLUSION_COORD_M:g}",
    }


@needs_node
def test_lump_js_reads_what_the_server_wrote() -> None:
    lump = sphere(2, 0.02, (0.0, 0.0, 0.05))
    lump.name = "lump.stl"
    twin = sphere(1, 0.01, (0.0, 0.0, -0.05))
    twin.name, twin.material, twin.young_ratio = "twin.stl", "liver", 1.0
    frames = encode_inclusions([lump, twin])
    got = run_lump_js(frames)
    assert [g["ok"] for g in got] == [True, True]
    for g, frame in zip(got, frames, strict=True):
        ref = vd.decode_inclusion(frame)
        assert (g["index"], g["of"], g["name"], g["material"]) == (
            ref.index, ref.of, ref.name, ref.material
        )  # fmt: skip
        np.testing.assert_array_equal(np.reshape(g["positions"], (-1, 3)), ref.vertices)
        np.testing.assert_array_equal(np.reshape(g["indices"], (-1, 3)), ref.faces)
        assert not g["decimated"]
    assert got[0]["youngRatio"] == pytest.approx(10.0) and got[0]["words"] == "10× as stiff"
    assert got[1]["words"] == "as stiff as the solid"
    assert got[0]["color"] != got[1]["color"]  # a stiff lump stands out from its twin
    np.testing.assert_allclose(
        np.reshape(got[0]["positions"], (-1, 3)).mean(axis=0), (0.0, 0.0, 0.05), atol=1e-3
    )


@needs_node
def test_lump_js_refuses_malformed_inclusion_frames() -> None:
    frames = malformed_frames()
    names = list(frames)
    got = dict(zip(names, run_lump_js(list(frames.values())), strict=True))
    assert got.pop("good")["ok"]
    refused = {name: g for name, g in got.items() if not g["ok"]}
    assert sorted(refused) == sorted(got), {n: g for n, g in got.items() if g["ok"]}
    assert "vertex" in refused["nan vertex"]["reason"]
    assert "vertex" in refused["vertex 5 km away"]["reason"]
    assert "index" in refused["triangle index out of range"]["reason"]
    assert "length" in refused["truncated"]["reason"]
    # an unknown stiffness is said so, never shown as a number
    (frame,) = encode_inclusions([sphere(1, 0.01, (0.0, 0.0, 0.0))])
    nan_ratio = bytearray(frame)
    nan_ratio[20:24] = np.float32(np.nan).tobytes()
    (g,) = run_lump_js([bytes(nan_ratio)])
    assert g["ok"] and g["youngRatio"] is None and g["words"] == "stiffness unknown"
