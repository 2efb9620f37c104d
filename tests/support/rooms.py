"""A room's counterparts for the sans-I/O room tests: a recording world that stands in for the
physics, and the frames a user sends (hello, state)."""

from __future__ import annotations

import json

import numpy as np

from haptic_collab.server.world import Coupling
from haptic_collab.shared.local_model_update import SurfacePatch
from haptic_collab.shared.primitives import make_plane
from haptic_collab.shared.protocol import PROTOCOL_VERSION


class RecordingWorld:
    """Minimal world: an octahedron; echoes a plane patch per input and records every input."""

    def __init__(self) -> None:
        self.vertices = np.array(
            [[0.1, 0, 0], [-0.1, 0, 0], [0, 0.1, 0], [0, -0.1, 0], [0, 0, 0.1], [0, 0, -0.1]], float
        )
        self.faces = np.array(
            [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
        )
        self.inputs: list[dict] = []
        self.sim_period_s = 0.05  # a 20 Hz object, as the rooms below
        self.coupling = Coupling((), np.zeros((0, 0)), np.zeros(0), 0.005)

    def tick(self, inputs, tick=None):
        self.inputs.append(dict(inputs))
        out = {}
        for key, inp in inputs.items():
            assert np.all(np.isfinite(inp.probe)) and np.all(np.isfinite(inp.force))
            out[key] = SurfacePatch(
                tick=len(self.inputs) if tick is None else tick,
                primitive=make_plane((0, 0, 0.1), (0, 0, 1)),
                proxy=(float(inp.probe[0]), float(inp.probe[1]), 0.1),
                normal=(0.0, 0.0, 1.0),
                penetration_m=0.1 - float(inp.probe[2]),
                in_contact=True,
                k_o=400.0,
                k_o_eff=380.0,
                k_o_stiff=400.0,
                b_o=0.0,
            )
        # every contact its own 400 N/m, uncoupled, 5 mm in (as the patches say)
        m = len(out)
        self.coupling = Coupling(tuple(out), np.eye(m) / 400.0, np.full(m, 0.005), 0.005)
        return out

    def modal_contact(self, name):
        return None  # no modes: nothing for the modal guard to check

    def contact_modes(self, name):
        return None


def hello(name: str, role: str = "user") -> str:
    return json.dumps({"type": "hello", "protocol": PROTOCOL_VERSION, "role": role, "name": name})


def state(seq: int, z: float = 0.095, force: float = 1.0, k_h: float = 400.0) -> str:
    """A state with gains that can render ``force`` at that depth (the server bounds forces)."""
    return json.dumps(
        {"type": "state", "seq": seq, "probe_m": [0, 0, z], "force_n": [0, 0, force], "k_h": k_h}
    )


def prime(room, conns, now_s=0.0):
    """One tick with a resting state from each user, so each has a patch (forces need one)."""
    for c in conns:
        room.receive(c, state(0, z=0.099, force=0.0), now_s)
    room.tick(0, now_s)


def texts(outs, conn):
    return [json.loads(o.data) for o in outs if o.conn_id == conn and isinstance(o.data, str)]
