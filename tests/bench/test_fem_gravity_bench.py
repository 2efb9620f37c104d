"""``python -m haptic_collab.bench.fem_gravity``: the JSON it writes on a small sphere (its
contract, not its timings)."""

from __future__ import annotations

import json

from haptic_collab.bench.fem_gravity import bench_fem_gravity, main


def test_the_bench_reports_the_sag_and_both_start_ups_side_by_side():
    out = bench_fem_gravity(repeats=2, cases=(("balloon", "liver"),), subdivisions=2)
    json.dumps(out)  # JSON-able
    (row,) = out["objects"]
    assert (row["mesh"], row["material"], row["n_vertices"]) == ("balloon", "liver", 162)
    assert [len(row["startup_s"][k]) for k in ("without", "with")] == [2, 2]
    # the coarse liver ball sags about as the fine one: 1-3 cm at its top, under its weight
    assert 10.0 <= row["sag_top_mm"] <= row["sag_max_mm"] <= 30.0
    assert row["weight_n"] == 9.81 * row["mass_kg"]
    assert (
        row["startup_ratio"] == row["startup_median_s"]["with"] / row["startup_median_s"]["without"]
    )
    assert row["k_o_top_n_m"]["with"] == row["k_o_top_n_m"]["without"]  # the linear model's


def test_the_command_writes_its_command_commit_and_machine(tmp_path, monkeypatch):
    import haptic_collab.bench.fem_gravity as bench

    monkeypatch.setattr(  # the measurement itself is the test above
        bench,
        "bench_fem_gravity",
        lambda g, repeats: {"benchmark": "fem-gravity", "g_m_s2": g, "repeats": repeats},
    )
    path = tmp_path / "out.json"
    assert main(["--repeats", "1", "--g", "3.7", "--json", str(path)]) == 0
    data = json.loads(path.read_text())
    assert data["command"].endswith(f"--repeats 1 --g 3.7 --json {path}")
    assert data["g_m_s2"] == 3.7 and data["repeats"] == 1
    assert data["machine"]["cpus"] >= 1 and "load_average_at_end" in data["machine"]
    assert "commit" in data
