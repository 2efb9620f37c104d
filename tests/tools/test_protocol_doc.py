"""docs/protocol.md's field reference is generated from the schema the server validates with."""

from __future__ import annotations

from haptic_collab.shared.protocol import State
from tools.codegen import protocol_doc


def test_the_committed_field_reference_is_current() -> None:
    text = protocol_doc.DOC.read_text(encoding="utf-8")
    assert protocol_doc.render(text) == text, (
        "docs/protocol.md's field reference is stale: run python -m tools.codegen.protocol_doc"
    )


def test_the_reference_says_what_the_server_accepts() -> None:
    section = protocol_doc.generate()
    # every State field, with its requiredness as the model has it
    for name, field in State.model_fields.items():
        req = "yes" if field.is_required() or name == "type" else "no"
        assert f"| `{name}` | {req} |" in section, name
    assert "| `probe_m` | yes |  | [number in [-1000, 1000]] × 3 |" in section
    assert '| `local_model` | no | `"pi"` | `"p"` \\| `"pi"` |' in section
    # the latency injection's bounds, as ``haptic server`` enforces them
    assert "| `latency_ms` | no | `0.0` | number in [0, 60000] |" in section
    assert "| `loss` | no | `0.0` | number in [0, 1) |" in section
