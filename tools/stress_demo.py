"""Run the two-user demo and a scripted slide over the stress set of meshes; write JSON and a table.

Not installed, not a test: the measurements behind docs/real-objects.md. Each demo run is the real
``haptic demo --headless`` (server and two simulated users as processes over websockets, 12 s by
default); the slide runs the server's World in-process.

Usage (from the repository, after ``make install meshes``)::

    .venv/bin/python tools/stress_demo.py --runs 3 --out docs/results/real-objects.json
    .venv/bin/python tools/stress_demo.py --slide-only

Per demo run: both users' ``stable`` verdicts and hold peak-to-peak [mm], B's largest force [N],
whether B feels A (``b_feels_a``: a force change of a JND that follows the surface under B), and
the resting user B's largest step of the rendered proxy in one servo tick while in contact,
with the probe's step at that tick [mm]. Per slide: a probe slid 2 mm per simulation tick along
the surface, 3 and 6 mm below its proxy, over edges, corners and into creases, with the proxy
following the surface and with the closest point: the largest proxy step per tick [mm].
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from haptic_collab.demo import SERVER_START_TIMEOUT_S

ROOT = Path(__file__).resolve().parents[1]
MESHES = ROOT / "tests" / "data" / "meshes"
HAPTIC = str(Path(sys.executable).with_name("haptic"))


def mesh_specs(tmp: Path) -> list[tuple[str, list[str]]]:
    """(label, demo arguments) of every mesh exercised."""
    from haptic_collab.server.objects.shapes import STRESS_MESHES, write_textured_obj

    specs: list[tuple[str, list[str]]] = [("balloon", ["--mesh", "balloon"])]
    specs += [(name, ["--mesh", name]) for name in STRESS_MESHES]
    textured = write_textured_obj(tmp / "textured-torus.obj", "torus")
    specs.append(("textured OBJ (torus, UV seams)", ["--mesh", str(textured)]))
    bunny, nut = MESHES / "bunny.obj", MESHES / "nut.ply"
    if bunny.is_file():
        specs.append(("bunny (npm bunny) 0.2 m", ["--mesh", str(bunny), "--mesh-size", "0.2"]))
        specs.append(("bunny x0.08 (0.8 m)", ["--mesh", str(bunny), "--mesh-scale", "0.08"]))
    if nut.is_file():
        specs.append(
            (
                "hex nut (pyvista) 0.15 m, refined",
                ["--mesh", str(nut), "--mesh-size", "0.15", "--mesh-max-edge", "0.007"],
            )
        )
    specs += repaired_specs(tmp)
    return specs


def repaired_specs(tmp: Path) -> list[tuple[str, list[str]]]:
    """The parts only ``--mesh-repair`` makes usable, repaired here and written to ``tmp``.

    ``haptic demo`` has no ``--mesh-repair`` flag yet (haptic_collab/cli/args.py), so the repair
    runs in this process (:func:`server.objects.mesh.load_mesh` ``repair=True``) and the demo
    loads its result: pyvista's ant (15 intersecting bodies) and a CAD-like part of two boxes
    overlapping off each other's grid, written as an STL (a triangle soup).
    """
    import trimesh

    from haptic_collab.server.objects.mesh import load_mesh

    out: list[tuple[str, list[str]]] = []
    ant = MESHES / "ant.ply"
    if ant.is_file():
        mesh = load_mesh(ant, target_size_m=0.2, repair=True, max_edge_m=0.0075)
        path = tmp / "ant-repaired.ply"
        mesh.export(path)
        out.append(("ant (pyvista, 15 bodies) repaired, 0.2 m, refined", ["--mesh", str(path)]))
    boxes = []
    for offset in ((0.0, 0.0, 0.0), (0.037, 0.021, 0.013)):
        box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
        box.apply_translation(np.asarray(offset) + 0.05)
        boxes.append(box)
    soup = tmp / "two-boxes.stl"
    trimesh.util.concatenate(boxes).export(soup)
    part = load_mesh(soup, repair=True, max_edge_m=0.0075)
    path = tmp / "two-boxes-repaired.ply"
    part.export(path)
    out.append(("two overlapping boxes (STL) repaired, refined", ["--mesh", str(path)]))
    return out


def _largest_proxy_step(work: Path, user: str) -> tuple[float, float]:
    """B's largest rendered-proxy step in one servo tick in contact, and the probe's then [m]."""
    cols = np.genfromtxt(work / f"{user}.csv", delimiter=",", names=True)
    proxy = np.stack([cols["proxy_x_m"], cols["proxy_y_m"], cols["proxy_z_m"]], axis=1)
    probe = np.stack([cols["probe_x_m"], cols["probe_y_m"], cols["probe_z_m"]], axis=1)
    contact = (cols["in_contact"][1:] > 0) & (cols["in_contact"][:-1] > 0)
    dp = np.linalg.norm(np.diff(proxy, axis=0), axis=1)
    dh = np.linalg.norm(np.diff(probe, axis=0), axis=1)
    dp = np.where(contact & np.isfinite(dp), dp, 0.0)
    i = int(np.argmax(dp))
    return float(dp[i]), float(dh[i])


def run_demo(
    label: str,
    args: list[str],
    run: int,
    latency: bool,
    duration: float,
    keep: Path | None = None,
    keep_all: bool = False,
) -> dict:
    """One ``haptic demo`` run; with ``keep``, an unstable run's workdir and report (every run's
    with ``keep_all``) are copied there (``<keep>/<label>-<run>``) for analysis."""
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp) / "work"
        report = Path(tmp) / "report.json"
        extra = ["--latency-ms", "50", "--jitter-ms", "10"] if latency else []
        cmd = [HAPTIC, "demo", "--headless", "--duration", f"{duration:g}", "--port", "0"]
        cmd += ["--report", str(report), "--workdir", str(work), *args, *extra]
        start = time.monotonic()
        # the demo waits up to SERVER_START_TIMEOUT_S for a FEM solid's start-up, then runs
        limit = duration + SERVER_START_TIMEOUT_S + 60.0
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=limit)
        row: dict = {"mesh": label, "run": run, "latency": "50 +- 10 ms" if latency else "none"}
        row["wall_s"] = round(time.monotonic() - start, 1)
        if not report.is_file():  # exit 1 or 3 with a report is a verdict, not an error
            row["error"] = (proc.stderr or proc.stdout).strip().splitlines()[-1:]
            return row
        row["exit"] = proc.returncode
        rep = json.loads(report.read_text())
        for name in ("A", "B"):
            u = rep["users"][name]
            row[f"{name}_stable"] = u["stable"]
            row[f"{name}_verdict"] = u.get("verdict")
            for key, out in (
                ("hold_oscillation_mm", "hold_p2p_mm"),
                ("max_force_n", "max_force_n"),
            ):
                value = u.get(key)  # None: no verdict (the contact never settled)
                row[f"{name}_{out}"] = None if value is None else round(value, 3)
        c = rep["coupling"]
        row["b_feels_a"] = c.get("b_feels_a")
        for key in ("b_force_rise_n", "b_surface_displacement_mm", "b_force_at_rest_n"):
            row[key] = None if c.get(key) is None else round(c[key], 3)
        # B's rendered stiffness where its force is compared: a change of K_h (B's gains
        # redesigned for the coupled contact) changes B's force with no change of the surface
        cols = np.genfromtxt(work / "B.csv", delimiter=",", names=True)
        origin = {u: json.loads((work / f"{u}.json").read_text())["clock_origin_s"] for u in "AB"}
        t_on_a = cols["t_s"] + origin["B"] - origin["A"]  # the windows are on A's clock
        for name, key in (("rest", "rest_window_s"), ("hold", "hold_window_s")):
            span = c.get(key)
            if span is not None:
                inside = (t_on_a >= span[0]) & (t_on_a <= span[1])
                if inside.any():
                    row[f"b_k_h_{name}"] = round(float(np.median(cols["k_h_n_per_m"][inside])), 1)
        step, probe_step = _largest_proxy_step(work, "B")
        row["b_proxy_step_mm"] = round(step * 1e3, 2)
        row["b_probe_step_at_it_mm"] = round(probe_step * 1e3, 3)
        if keep is not None and (keep_all or not (row["A_stable"] and row["B_stable"])):
            dest = keep / f"{''.join(ch if ch.isalnum() else '-' for ch in label)}-{run}"
            shutil.copytree(work, dest, dirs_exist_ok=True)
            shutil.copy(report, dest / "report.json")
            row["kept"] = str(dest)
        return row


def slide(label: str, mesh, proxy: str, depth_m: float, ticks: int = 120) -> dict:  # type: ignore[no-untyped-def]
    """A probe slid along the surface ``depth_m`` below its proxy, 2 mm per tick, 9 paths."""
    from haptic_collab.server.object_info import object_info
    from haptic_collab.server.objects.balloon import Balloon
    from haptic_collab.server.world import ContactInput, World

    obj = Balloon(mesh)
    info = object_info(mesh.vertices, mesh.faces)
    worst, jumps, steps = 0.0, 0, 0
    for anchor, normal in [
        (info.top_m, info.top_normal),
        *((s.point_m, s.normal) for s in info.sides[:2]),
    ]:
        for direction in ((1.0, 0.3, 0.0), (0.0, 1.0, -0.4), (-0.7, 0.0, -1.0)):
            obj.reset()
            world = World(obj, proxy=proxy)  # type: ignore[arg-type]
            zero = np.zeros(3)
            d = np.asarray(direction, float)
            probe = np.asarray(anchor) - depth_m * np.asarray(normal)
            out = world.tick({"u": ContactInput(probe=probe, force=zero)})["u"]
            for _ in range(ticks):
                n = np.asarray(out.normal)
                t = d - float(d @ n) * n
                t /= max(float(np.linalg.norm(t)), 1e-12)
                probe = np.asarray(out.proxy) + 0.002 * t - depth_m * n
                new = world.tick({"u": ContactInput(probe=probe, force=zero)})["u"]
                step = float(np.linalg.norm(np.subtract(new.proxy, out.proxy)))
                worst = max(worst, step)
                jumps += step > 0.005
                steps += 1
                out = new
    return {
        "mesh": label,
        "proxy": proxy,
        "depth_mm": round(depth_m * 1e3, 1),
        "largest_step_mm": round(worst * 1e3, 2),
        "steps_over_5mm": int(jumps),
        "ticks": steps,
    }


def pair_rows(tmp: Path, delays_ms: tuple[float, ...] = (0.0, 100.0)) -> list[dict]:
    """The two-user scene in-process, deterministic (no scheduler, no load): the fidelity
    benchmark's pair (:func:`haptic_collab.research.fidelity_pairs_3d.run_3d_pair`, the
    product's ``local-pi`` servo, simulated device and hand, B resting on the side while A
    presses the top) on every demo mesh: A's and B's hold peak-to-peak [mm]."""
    from haptic_collab.research.fidelity_pairs_3d import run_3d_pair
    from haptic_collab.server.objects.shapes import load_object_mesh

    rows = []
    for k, (label, args) in enumerate(mesh_specs(tmp)):
        spec = args[1]
        opts = dict(zip(args[2::2], (float(x) for x in args[3::2]), strict=True))
        if opts:  # the pair takes a mesh spec only: scale and refine it into a file here
            mesh = load_object_mesh(
                spec,
                scale=opts.get("--mesh-scale"),
                target_size_m=opts.get("--mesh-size"),
                max_edge_m=opts.get("--mesh-max-edge"),
            )
            spec = str(tmp / f"pair-{k}.ply")
            mesh.export(spec)
        for delay in delays_ms:
            r = run_3d_pair("local-pi", mesh=spec, delay_ms=delay).to_json()
            row = {"mesh": label, "delay_ms": delay}
            row.update(
                {k: round(v, 3) if isinstance(v, float) else v for k, v in r.items() if k != "mesh"}
            )
            print(json.dumps(row), flush=True)
            rows.append(row)
    return rows


def plane_jumps(label: str, mesh, depth_m: float, seed: int = 0) -> dict:  # type: ignore[no-untyped-def]
    """How far the plane local model jumps at a resting probe that moves a little: 60 probes
    ``depth_m`` under random vertices, each moved 20 times by 0.1 mm (normal noise per axis);
    per move, the new plane's penetration at the new probe less the old plane's [mm]."""
    from haptic_collab.server.objects.balloon import Balloon
    from haptic_collab.server.world import ContactInput, World

    world = World(Balloon(mesh))
    rng = np.random.default_rng(seed)
    v, vn = np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals)
    zero = np.zeros(3)
    worst = []
    for i in rng.choice(len(v), 60, replace=False):
        p = v[i] - depth_m * vn[i]
        out = world.tick({str(i): ContactInput(p, zero)})[str(i)]
        w = 0.0
        for _ in range(20):
            q = p + rng.normal(0.0, 1e-4, 3)
            new = world.tick({str(i): ContactInput(q, zero)})[str(i)]
            old_e = out.primitive.contact(*map(float, q))[0]
            w = max(w, abs(new.primitive.contact(*map(float, q))[0] - old_e))
            out, p = new, q
        worst.append(w * 1e3)
    a = np.asarray(worst)
    return {
        "mesh": label,
        "depth_mm": depth_m * 1e3,
        "median_mm": round(float(np.median(a)), 4),
        "p90_mm": round(float(np.percentile(a, 90)), 4),
        "max_mm": round(float(a.max()), 4),
    }


def slide_meshes(tmp: Path) -> list[tuple[str, object]]:
    from haptic_collab.server.objects.mesh import default_balloon, load_mesh
    from haptic_collab.server.objects.shapes import STRESS_MESHES, stress_mesh

    out: list[tuple[str, object]] = [("balloon", default_balloon())]
    out += [(name, stress_mesh(name)) for name in STRESS_MESHES]
    if (MESHES / "bunny.obj").is_file():
        out.append(("bunny 0.2 m", load_mesh(MESHES / "bunny.obj", target_size_m=0.2)))
    if (MESHES / "nut.ply").is_file():
        nut = load_mesh(MESHES / "nut.ply", target_size_m=0.15, max_edge_m=0.007)
        out.append(("hex nut 0.15 m, refined", nut))
    for label, args in repaired_specs(tmp):
        out.append((label, load_mesh(args[1])))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--runs", type=int, default=3, help="demo runs per mesh (the last with latency)"
    )
    ap.add_argument("--duration", type=float, default=12.0)
    ap.add_argument("--out", type=Path, default=None, help="write the JSON here")
    ap.add_argument("--slide-only", action="store_true")
    ap.add_argument(
        "--pairs",
        action="store_true",
        help="also the two-user scene in-process (deterministic) and the plane jumps",
    )
    ap.add_argument(
        "--demo-only",
        action="store_true",
        help="skip the slides (an existing --out file keeps its slide rows)",
    )
    ap.add_argument("--object", default=None, help="haptic demo --object (balloon or fem)")
    ap.add_argument("--material", default=None, help="haptic demo --material")
    ap.add_argument(
        "--only", default=None, help="only meshes whose label contains one of these (a,b,...)"
    )
    ap.add_argument("--keep", type=Path, default=None, help="copy an unstable run's workdir here")
    ap.add_argument("--keep-all", action="store_true", help="with --keep: every run's workdir")
    opts = ap.parse_args()
    result: dict = {"demo": [], "slide": []}
    if opts.demo_only and opts.out is not None and opts.out.is_file():
        result["slide"] = json.loads(opts.out.read_text()).get("slide", [])
    extra = [] if opts.object is None else ["--object", opts.object]
    extra += [] if opts.material is None else ["--material", opts.material]
    with tempfile.TemporaryDirectory() as tmp:
        for label, mesh in [] if opts.demo_only else slide_meshes(Path(tmp)):
            if opts.only and not any(part in label for part in opts.only.split(",")):
                continue
            for depth in (0.003, 0.006):
                for proxy in ("follow", "closest"):
                    row = slide(label, mesh, proxy, depth)
                    print(json.dumps(row), flush=True)
                    result["slide"].append(row)
        if opts.pairs:
            result["pairs"] = pair_rows(Path(tmp))
            result["plane_jumps"] = []
            for label, mesh in slide_meshes(Path(tmp)):
                for depth in (0.002, 0.008):
                    row = plane_jumps(label, mesh, depth)
                    print(json.dumps(row), flush=True)
                    result["plane_jumps"].append(row)
        if not opts.slide_only:
            for label, args in mesh_specs(Path(tmp)):
                if opts.only and not any(part in label for part in opts.only.split(",")):
                    continue
                for run in range(1, opts.runs + 1):
                    latency = opts.runs > 1 and run == opts.runs
                    row = run_demo(
                        label,
                        [*args, *extra],
                        run,
                        latency,
                        opts.duration,
                        opts.keep,
                        opts.keep_all,
                    )
                    print(json.dumps(row), flush=True)
                    result["demo"].append(row)
    result["date"] = time.strftime("%Y-%m-%d")
    result["commit"] = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    result["command"] = "tools/stress_demo.py " + " ".join(sys.argv[1:])
    if opts.out is not None:
        opts.out.parent.mkdir(parents=True, exist_ok=True)
        opts.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
