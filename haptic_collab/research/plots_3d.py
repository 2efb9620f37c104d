"""The drawings of Fig. 10-11: the stiffened balloon's surface, its cross-section and the depth traces.

Matplotlib's object API (no pyplot, no global backend; matplotlib is the ``plots`` extra, imported
only when drawing). :func:`plot_fig10` draws one column per case (the surface at the end of the
hold, the section through the top, the probe and proxy depths); :func:`plot_fig11` consecutive
World ticks of the surface of one case and its depth trace. The runs are
:class:`haptic_collab.research.press_3d.CaseRun` and the results
:func:`haptic_collab.research.press_3d.case_result`.
"""

from __future__ import annotations

import pathlib
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from haptic_collab.research.press_3d import Case3D, CaseRun, Timeline3D
from haptic_collab.shared.types import FloatArray

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.gridspec import SubplotSpec

_DPI = 110
_CMAP = "coolwarm"
#: Half-width [m] of the cross-section drawn around the top.
_SECTION_HALF_M = 0.06


def _new_figure(width_in: float, height_in: float) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=_DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _surface(run: CaseRun, frame: int) -> FloatArray:
    """Vertex positions (n, 3) [m] after world tick ``frame``."""
    w = run.displacement_m[frame]
    return run.vertices_rest + w[:, None] * run.normals_rest


def _probe_depth_at(run: CaseRun, frame: int) -> float:
    """Probe depth [m] at the servo tick of world tick ``frame``."""
    i = min(int(np.searchsorted(run.t_s, run.sim_t_s[frame])), len(run.t_s) - 1)
    return float(run.probe_depth_m[i])


def _mesh_panel(
    fig: Figure, spec: SubplotSpec, run: CaseRun, frame: int, norm: Any, title: str
) -> Axes:
    """3-D view of the balloon after world tick ``frame``, faces coloured by displacement."""
    from matplotlib import colormaps
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    ax = fig.add_subplot(spec, projection="3d")
    verts = _surface(run, frame)
    f = np.asarray(run.faces, dtype=np.int64)
    tri = verts[f]
    face_w_mm = run.displacement_m[frame][f].mean(axis=1) * 1000.0
    rgba = colormaps[_CMAP](norm(face_w_mm))
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-18)
    light = np.array([-0.4, -0.5, 0.77])
    shade = 0.6 + 0.4 * np.clip(fn @ (light / np.linalg.norm(light)), 0.0, 1.0)
    rgba[:, :3] *= shade[:, None]
    ax.add_collection3d(Poly3DCollection(tri, facecolors=rgba, edgecolors="none"))
    top = float(run.vertices_rest[:, 2].max())
    tip = top - _probe_depth_at(run, frame)
    ax.plot([0.0, 0.0], [0.0, 0.0], [tip, top + 0.05], color="k", lw=2.0)
    r = float(np.max(np.abs(run.vertices_rest)))
    ax.set_xlim(-r, r)
    ax.set_ylim(-r, r)
    ax.set_zlim(-r, r + 0.03)
    ax.set_box_aspect((1.0, 1.0, (2 * r + 0.03) / (2 * r)), zoom=1.25)
    ax.view_init(elev=18.0, azim=-60.0)
    ax.set_axis_off()
    ax.set_title(title, fontsize=10)
    return ax


def _section(
    vertices: FloatArray, faces: NDArray[np.int32], values: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """The mesh cut by the plane y = 0.

    Parameters
    ----------
    vertices : (n, 3) float [m]
    faces : (m, 3) int
    values : (n,) float
        A per-vertex quantity, interpolated linearly along the cut.

    Returns
    -------
    segments : (k, 2, 2) float [m]
        (x, z) end points of each piece of the cut.
    segment_values : (k, 2) float
        ``values`` at those end points.
    """
    f = np.asarray(faces, dtype=np.int64)
    y = vertices[:, 1] + 1e-12  # vertices exactly on the plane count as just above it
    tri_y = y[f]
    crossing = (tri_y.min(axis=1) < 0.0) & (tri_y.max(axis=1) > 0.0)
    segs: list[list[tuple[float, float]]] = []
    vals: list[list[float]] = []
    for face in f[crossing]:
        pts: list[tuple[float, float]] = []
        vs: list[float] = []
        for a, b in ((face[0], face[1]), (face[1], face[2]), (face[2], face[0])):
            ya, yb = y[a], y[b]
            if (ya < 0.0) != (yb < 0.0):
                t = ya / (ya - yb)
                p = vertices[a] + t * (vertices[b] - vertices[a])
                pts.append((float(p[0]), float(p[2])))
                vs.append(float(values[a] + t * (values[b] - values[a])))
        if len(pts) == 2:
            segs.append(pts)
            vals.append(vs)
    return np.asarray(segs, dtype=np.float64).reshape(-1, 2, 2), np.asarray(vals).reshape(-1, 2)


def _section_panel(ax: Axes, run: CaseRun, frame: int, norm: Any) -> None:
    """The surface cut by y = 0 near the top after world tick ``frame``: rest, deformed, probe."""
    from matplotlib import colormaps
    from matplotlib.collections import LineCollection

    top = float(run.vertices_rest[:, 2].max())
    h = _SECTION_HALF_M
    w = run.displacement_m[frame]
    for verts, deformed in ((run.vertices_rest, False), (_surface(run, frame), True)):
        seg, val = _section(verts, run.faces, w)
        keep = (np.abs(seg[:, :, 0]) <= h).all(axis=1) & (seg[:, :, 1] > 0.0).all(axis=1)
        seg, val = seg[keep], val[keep]
        mm = list(np.stack([seg[:, :, 0], seg[:, :, 1] - top], axis=-1) * 1000.0)
        if deformed:  # coloured by the normal displacement, as the 3-D view
            colors = colormaps[_CMAP](norm(val.mean(axis=1) * 1000.0))
            ax.add_collection(LineCollection(mm, colors=colors, linewidths=2.4))
        else:
            ax.add_collection(LineCollection(mm, colors="0.6", linestyles="--", linewidths=1.0))
    depth_mm = _probe_depth_at(run, frame) * 1000.0
    ax.plot([0.0], [-depth_mm], "o", color="k", ms=5, label="probe")
    i = min(int(np.searchsorted(run.t_s, run.sim_t_s[frame])), len(run.t_s) - 1)
    proxy_mm = run.proxy_depth_m[i] * 1000.0
    ax.plot([-15.0, 15.0], [-proxy_mm, -proxy_mm], color="tab:red", lw=1.2, label="local model")
    ax.set_xlim(-h * 1000.0, h * 1000.0)
    ax.set_ylim(-20.0, 3.0)
    ax.set_xlabel("x [mm] (section y = 0)", fontsize=9)
    ax.set_ylabel("z - top [mm]", fontsize=9)
    ax.tick_params(labelsize=8)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower center", fontsize=7.5, ncols=2)


def _colorbar(fig: Figure, axes: Any, norm: Any) -> None:
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable

    sm = ScalarMappable(norm=norm, cmap=colormaps[_CMAP])
    cb = fig.colorbar(sm, ax=axes, shrink=0.8, pad=0.01)
    lo, hi = float(norm.vmin), float(norm.vmax)
    cb.set_ticks([lo, lo / 2.0, 0.0, hi / 2.0, hi])
    cb.ax.yaxis.set_major_formatter("{x:.1f}")
    cb.set_label("normal displacement [mm]\n(dent < 0 < bulge)", fontsize=9)


def _depth_panel(
    ax: Axes,
    run: CaseRun,
    res: dict[str, Any],
    timeline: Timeline3D,
    worst: CaseRun | None = None,
) -> None:
    if worst is not None:
        ax.plot(
            worst.t_s,
            worst.probe_depth_m * 1000.0,
            color="0.55",
            lw=0.9,
            label=f"probe, world takes tick {worst.sample_tick}",
        )
    ax.plot(run.t_s, run.probe_depth_m * 1000.0, color="tab:blue", lw=1.5, label="probe $x_h$")
    ax.plot(run.t_s, run.proxy_depth_m * 1000.0, color="tab:red", lw=1.5, label="proxy $x_o$")
    ax.axvspan(timeline.run_s - 1.0, timeline.run_s, color="0.92", zorder=0)
    ax.axhline(0.0, color="0.5", lw=0.8)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("depth below the rest top [mm]")
    ax.grid(True, alpha=0.3)
    ax.set_xlim(0.0, timeline.run_s)
    sim = "stable" if res["sim_loop_stable"] else "UNSTABLE"
    full = "stable" if res["full_loop_stable"] else "UNSTABLE"
    ax.set_title(
        f"hold p2p {res['hold_p2p_mm']:.2f} mm, error {res['steady_state_error_mm']:.2f} mm\n"
        f"{res['sim_loop_condition']}: {sim}; full loop: {full} "
        f"(rho {res['full_loop_spectral_radius']:.2f})",
        fontsize=9,
    )
    ax.legend(loc="lower right", fontsize=7.5)


def _case_title(c: Case3D) -> str:
    if c.source == "paper":
        return f"P, K_h = {c.k_h / 1000.0:g} N/mm (paper)"
    extra = f", I = {c.i_gain:.0f}" if c.i_gain > 0.0 else ""
    damper = f", B_h = {c.b_h:g}" if c.b_h > 0.0 else ""
    return f"product {c.mode.upper()}: K_h = {c.k_h:.0f} N/m{extra}{damper}, {c.proxy_hold}"


def _norm(displacements_m: Sequence[FloatArray]) -> Any:
    """Colour scale: the deepest dent to the largest bulge [mm], centred on 0."""
    from matplotlib.colors import TwoSlopeNorm

    w = np.concatenate([np.ravel(d) for d in displacements_m]) * 1000.0
    return TwoSlopeNorm(
        vmin=min(float(w.min()), -1e-3), vcenter=0.0, vmax=max(float(w.max()), 1e-3)
    )


def plot_fig10(
    path: pathlib.Path,
    runs: list[CaseRun],
    results: dict[str, dict[str, Any]],
    tl: Timeline3D,
    worst: dict[str, CaseRun],
) -> None:
    """Write Fig. 10 to ``path``: per case (``results`` by case name) the surface and the section
    at the end of the hold and the depth traces, with the run at the worst sampling tick
    (``worst``, by case name) in grey where there is one."""
    ncol = len(runs)
    fig = _new_figure(4.4 * ncol + 1.2, 11.0)
    gs = fig.add_gridspec(3, ncol, height_ratios=[1.2, 0.55, 1.0])
    norm = _norm([r.displacement_m[-1] for r in runs])
    meshes = []
    for j, run in enumerate(runs):
        last = len(run.sim_t_s) - 1
        meshes.append(_mesh_panel(fig, gs[0, j], run, last, norm, _case_title(run.case)))
        _section_panel(fig.add_subplot(gs[1, j]), run, last, norm)
        _depth_panel(
            fig.add_subplot(gs[2, j]), run, results[run.case.name], tl, worst.get(run.case.name)
        )
    _colorbar(fig, meshes, norm)
    k_o = results[runs[0].case.name]["k_o_n_per_m"]
    fig.suptitle(
        f"Fig. 10: local models on the water balloon with K_o = {k_o:.0f} N/m at the top; surface "
        "at the end of the hold (the last second, shaded, is judged)",
        fontsize=11,
    )
    fig.savefig(path)


def _fig11_frames(run: CaseRun, tl: Timeline3D, count: int = 4) -> list[int]:
    """``count`` consecutive world ticks of the judged last second, from the deepest surface."""
    last = np.flatnonzero(run.sim_t_s >= tl.run_s - 1.0 - 1e-9)
    if len(last) == 0:
        last = np.arange(len(run.sim_t_s))
    k = int(last[int(np.argmin(run.displacement_m[last].min(axis=1)))])
    first = max(0, min(k, len(run.sim_t_s) - count))
    return list(range(first, min(first + count, len(run.sim_t_s))))


def plot_fig11(
    path: pathlib.Path, run: CaseRun, res: dict[str, Any], tl: Timeline3D
) -> list[float]:
    """Write Fig. 11 to ``path``: consecutive World ticks of the surface of ``run`` in the judged
    last second and its depth trace; returns the times [s] of those World ticks."""
    frames = _fig11_frames(run, tl)
    fig = _new_figure(17.0, 10.5)
    gs = fig.add_gridspec(3, len(frames), height_ratios=[1.1, 0.55, 0.9])
    norm = _norm([run.displacement_m[frames]])
    meshes = []
    for j, k in enumerate(frames):
        title = f"t = {run.sim_t_s[k]:.2f} s (world tick {k})"
        meshes.append(_mesh_panel(fig, gs[0, j], run, k, norm, title))
        _section_panel(fig.add_subplot(gs[1, j]), run, k, norm)
    _colorbar(fig, meshes, norm)
    ax = fig.add_subplot(gs[2, :])
    _depth_panel(ax, run, res, tl)
    for k in frames:
        ax.axvline(run.sim_t_s[k], color="k", lw=0.8, ls=":")
    fig.suptitle(
        f"Fig. 11: K_h = {run.case.k_h / 1000.0:g} N/mm > K_o = {res['k_o_n_per_m'] / 1000.0:.2f} "
        "N/mm violates eq. 8: consecutive world ticks of the surface (dotted lines below)",
        fontsize=11,
    )
    fig.savefig(path)
    return [float(run.sim_t_s[k]) for k in frames]
