"""The plots of Fig. 7, 8 and 9 of the paper, and ``haptic reproduce``'s files for them.

This module owns the drawing: it turns the data computed by :mod:`haptic_collab.research.reproduce`
(which draws nothing) into the PNG figures, and :func:`reproduce_figures` writes each figure's
``<fig>.png`` and ``<fig>.json``. The plots use mm and s like the paper; the JSON files are in SI
units.

matplotlib is the optional ``plots`` extra and is imported inside the functions. Only its object
API is used (:class:`matplotlib.figure.Figure` with a
:class:`matplotlib.backends.backend_agg.FigureCanvasAgg`, style settings inside
:func:`matplotlib.rc_context`): never ``pyplot``, never ``matplotlib.use``, so the caller's
backend and rc settings are left as they were.

Usage::

    from pathlib import Path
    from haptic_collab.research.plots import reproduce_figures
    results = reproduce_figures("all", Path("figs"))   # writes figs/fig7.json, figs/fig7.png, ...
"""

from __future__ import annotations

import pathlib
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import numpy as np

from haptic_collab.research.reproduce import (
    SERVO_RATE_HZ,
    SIM_RATE_HZ,
    Fig7Data,
    Fig8Data,
    Fig9Data,
    FigureData,
    FigureName,
    figure_data,
    figure_names,
    json_text,
)
from haptic_collab.shared.stability import STABILITY_TOL

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

_DPI = 140
_PROBE_STYLE: dict[str, Any] = {"color": "tab:blue", "lw": 1.8, "label": "probe $x_h$ (device)"}
_PROXY_STYLE: dict[str, Any] = {"color": "tab:red", "lw": 1.8, "label": "proxy $x_o$ (surface)"}
#: Fig. 7: the unstable case's proxy is drawn up to this |x_o| [mm].
_FIG7_YCLIP_MM = 300.0


def _rc() -> dict[Any, Any]:
    return {
        "font.size": 11,
        "axes.titlesize": 12,
        "axes.labelsize": 11,
        "legend.fontsize": 9.5,
        "xtick.labelsize": 10,
        "ytick.labelsize": 10,
        "figure.dpi": _DPI,
        "savefig.dpi": _DPI,
    }


@contextmanager
def _figure(figsize: tuple[float, float], path: pathlib.Path) -> Iterator[Figure]:
    """A new Agg figure of ``figsize`` [in], saved as the PNG ``path`` when the block ends.

    The ``with`` block draws; on leaving it the figure is laid out (``tight_layout``) and saved,
    still inside this module's rc settings (restored after): tick labels take the rc settings when
    they are drawn. Nothing is saved when the block raises.
    """
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    with matplotlib.rc_context(_rc()):
        fig = Figure(figsize=figsize)
        FigureCanvasAgg(fig)
        yield fig
        fig.tight_layout()
        fig.savefig(path)


def _style(ax: Axes, xlabel: str, ylabel: str) -> None:
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)


# --------------------------------------------------------------------------------------------
# Fig. 7
# --------------------------------------------------------------------------------------------


def plot_fig7(data: Fig7Data, path: pathlib.Path) -> None:
    """Draw Fig. 7 (probe and proxy [mm] vs time [s], one panel per case) into the PNG ``path``.

    Parameters
    ----------
    data : haptic_collab.research.reproduce.Fig7Data
        From :func:`haptic_collab.research.reproduce.fig7_data`.
    path : pathlib.Path
        The PNG file written (its folder must exist).

    Raises
    ------
    ModuleNotFoundError
        matplotlib (the ``plots`` extra) is not installed.
    """
    result = data.result
    step_t_s = result["probe"]["t_step_s"]
    step_m = result["probe"]["x_after_m"]
    run_s = result["run_s"]
    with _figure((15.0, 4.9), path) as fig:
        axes = fig.subplots(1, 3, sharex=True)
        for ax, (name, c) in zip(axes, result["cases"].items(), strict=True):
            k_o, k_h = c["k_o"], c["k_h"]
            tr = data.traces[name]
            t = tr.t_s
            ax.plot(t, tr.probe_m * 1e3, zorder=3, **_PROBE_STYLE)
            proxy_mm = tr.proxy_m * 1e3
            if c["stable"]:
                ax.plot(t, proxy_mm, **_PROXY_STYLE)
                ss = c["eq11_ratio"] * step_m * 1e3
                ax.axhline(
                    ss,
                    color="0.35",
                    ls="--",
                    lw=1.0,
                    label=rf"eq. 11: $\frac{{K_h}}{{K_h+K_o}}x_h$ = {ss:.1f} mm",
                )
                ts = c["settling_time_s"]
                ax.axvline(step_t_s + ts, color="tab:green", ls=":", lw=1.3)
                ax.text(
                    step_t_s + ts + 0.1,
                    0.25 * step_m * 1e3 if ss < 20.0 else 8.0,
                    f"settled (2 %)\n{ts:.2f} s after the step",
                    color="tab:green",
                    fontsize=9.5,
                    va="bottom",
                )
                ax.set_ylim(-5.0, 92.0)
            else:
                off = np.nonzero(np.abs(proxy_mm) > _FIG7_YCLIP_MM)[0]
                i_off = int(off[0]) if off.size else t.size
                ax.plot(t[:i_off], proxy_mm[:i_off], **_PROXY_STYLE)
                if off.size:
                    ax.text(
                        t[i_off] + 0.1,
                        0.62 * _FIG7_YCLIP_MM,
                        f"off scale\nfrom t = {t[i_off]:.2f} s",
                        color="darkred",
                        fontsize=10,
                    )
                ax.set_ylim(-_FIG7_YCLIP_MM, _FIG7_YCLIP_MM)
                ax.annotate(
                    f"diverges\nslow pole z = {c['slow_pole']:.2f}:\n"
                    f"$K_h > K_o$ violates eq. 8\n"
                    f"($|x_o|$ reaches {c['max_abs_proxy_m']:.1e} m at {run_s:g} s)",
                    xy=(1.68, -0.75 * _FIG7_YCLIP_MM),
                    xytext=(3.4, -0.9 * _FIG7_YCLIP_MM),
                    fontsize=10,
                    color="darkred",
                    arrowprops={"arrowstyle": "->", "color": "darkred", "lw": 1.2},
                    bbox={"boxstyle": "round", "fc": "white", "ec": "darkred", "alpha": 0.9},
                )
            verdict = "stable" if c["stable"] else "unstable"
            ax.set_title(
                f"({name}) $K_o$ = {k_o / 1e3:g} N/mm ({k_o:g} N/m), "
                f"$K_h$ = {k_h / 1e3:g} N/mm ({k_h:g} N/m)\n"
                f"{verdict}, spectral radius {c['spectral_radius']:.2f}",
                fontsize=11,
            )
            _style(ax, "time [s]", "position [mm]")
            ax.set_xlim(0.0, run_s)
            ax.legend(loc="upper right", framealpha=0.95)
        fig.suptitle(
            "Fig. 7: linear spring response to a probe step, proportional local model "
            f"(servo {SERVO_RATE_HZ:g} Hz, simulation {SIM_RATE_HZ:g} Hz)",
            fontsize=13,
        )


# --------------------------------------------------------------------------------------------
# Fig. 8
# --------------------------------------------------------------------------------------------


def plot_fig8(data: Fig8Data, path: pathlib.Path) -> None:
    """Draw Fig. 8 (the PI stability region, normalised and in N/m) into the PNG ``path``.

    Left: the numeric verdict on the (K_h/K_o, I N T/K_o) grid, shaded by spectral radius, with
    the boundary lines of eq. 15. Right: the stable region for each slice K_o, in N/m.

    Parameters
    ----------
    data : haptic_collab.research.reproduce.Fig8Data
        From :func:`haptic_collab.research.reproduce.fig8_data`.
    path : pathlib.Path
        The PNG file written (its folder must exist).

    Raises
    ------
    ModuleNotFoundError
        matplotlib (the ``plots`` extra) is not installed.
    """
    from matplotlib import colormaps
    from matplotlib.colors import ListedColormap
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    kh_r, nti_r = data.kh_over_ko, data.nti_over_ko
    KH, NI = np.meshgrid(kh_r, nti_r, indexing="ij")
    rho, numeric = data.spectral_radius, data.stable
    fraction = data.result["agreement_fraction"]
    kh_max, nti_max = float(kh_r[-1]), float(nti_r[-1])
    with _figure((15.0, 6.4), path) as fig:
        ax, ax2 = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.15, 1.0]})
        # -- left: normalised plane, numeric verdict shaded, eq. 15 boundaries drawn
        rho_plot = np.clip(rho, 0.0, 1.0)
        ext = (kh_r[0], kh_r[-1], nti_r[0], nti_r[-1])
        img = ax.imshow(
            np.where(numeric, rho_plot, np.nan).T,
            origin="lower",
            extent=ext,
            aspect="auto",
            cmap=ListedColormap(colormaps["Blues_r"](np.linspace(0.0, 0.75, 256))),
            vmin=0.0,
            vmax=1.0,
            interpolation="nearest",
        )
        cbar = fig.colorbar(img, ax=ax, fraction=0.05, pad=0.02)
        cbar.set_label("spectral radius of the slow-rate loop (stable points)")
        ax.contour(KH, NI, rho, levels=[0.25, 0.5, 0.75], colors="white", linewidths=0.8)
        x = np.linspace(0.0, kh_max, 200)
        ax.plot(x, x + 1.0, color="tab:red", lw=2.2)
        ax.plot(x, x - 1.0, color="tab:orange", lw=2.2)
        ax.plot(x, 2.0 * x - 2.0, color="tab:purple", lw=2.2, ls="--")
        ax.text(0.6, 1.75, r"$INT - K_h = K_o$", color="tab:red", rotation=33, fontsize=10.5)
        ax.text(2.15, 1.28, r"$INT - K_h = -K_o$", color="tab:orange", rotation=33, fontsize=10.5)
        ax.text(1.72, 1.02, r"$INT - 2K_h = -2K_o$", color="tab:purple", rotation=50, fontsize=10.5)
        ax.plot([1.0], [1.0], "k*", ms=11)
        ax.annotate(
            "deadbeat $K_h = INT = K_o$\n(spectral radius 0)",
            xy=(1.0, 1.0),
            xytext=(1.35, 0.25),
            fontsize=9.5,
            arrowprops={"arrowstyle": "->", "lw": 0.8},
        )
        f9 = data.fig9_gains
        ax.plot(*f9, "o", color="gold", mec="k", ms=8)
        ax.annotate(
            "Fig. 9 gains",
            xy=f9,
            xytext=(0.12, 1.45),
            fontsize=9.5,
            arrowprops={"arrowstyle": "->", "lw": 0.8},
        )
        ax.set_xlim(0.0, kh_max)
        ax.set_ylim(0.0, nti_max)
        handles = [
            Patch(facecolor="tab:blue", alpha=0.8, label="stable (spectral radius < 1)"),
            Line2D([], [], color="0.6", lw=0.8, label="radius 0.25 / 0.5 / 0.75 (contours)"),
            Line2D([], [], color="tab:red", lw=2.2, label=r"eq. 15: $|INT - K_h| = K_o$ (upper)"),
            Line2D(
                [], [], color="tab:orange", lw=2.2, label=r"eq. 15: $|INT - K_h| = K_o$ (lower)"
            ),
            Line2D(
                [], [], color="tab:purple", lw=2.2, ls="--", label=r"eq. 15: $INT - 2K_h = -2K_o$"
            ),
        ]
        ax.legend(handles=handles, loc="upper left", framealpha=0.95)
        ax.set_title(
            "Fig. 8: PI local model stability region (eq. 15)\n"
            f"numeric verdict on {numeric.size} points, agrees with eq. 15 on "
            f"{100.0 * fraction:.2f} %",
            fontsize=11.5,
        )
        _style(ax, r"$K_h / K_o$", r"$I\,N\,T / K_o$")

        # -- right: slices of the stability volume in absolute units
        slices = data.slices_spectral_radius
        colors = ("tab:green", "tab:blue", "tab:purple")
        for (ko, r), col in zip(slices.items(), colors, strict=True):
            ax2.contourf(
                KH * ko, NI * ko, r, levels=[0.0, 1.0 - STABILITY_TOL], colors=[col], alpha=0.22
            )
            ax2.contour(KH * ko, NI * ko, r, levels=[1.0], colors=[col], linewidths=2.0)
        handles2 = [
            Patch(facecolor=col, edgecolor=col, alpha=0.45, label=f"$K_o$ = {ko:g} N/m")
            for ko, col in zip(slices, colors, strict=True)
        ]
        ax2.legend(handles=handles2, loc="upper left", title="stable region for")
        ax2.set_xlim(0.0, 3.1 * max(slices))
        ax2.set_ylim(0.0, 4.2 * max(slices))
        ax2.set_title(
            "Slices of the stability volume: the region scales with $K_o$\n"
            "(stiffer objects are easier to stabilise)",
            fontsize=11.5,
        )
        _style(ax2, r"$K_h$ [N/m]", r"$I\,N\,T$ [N/m]")


# --------------------------------------------------------------------------------------------
# Fig. 9
# --------------------------------------------------------------------------------------------


def plot_fig9(data: Fig9Data, path: pathlib.Path) -> None:
    """Draw Fig. 9 (probe and proxy depth [mm] vs time [s], PI and P panels) into the PNG ``path``.

    Parameters
    ----------
    data : haptic_collab.research.reproduce.Fig9Data
        From :func:`haptic_collab.research.reproduce.fig9_data`.
    path : pathlib.Path
        The PNG file written (its folder must exist).

    Raises
    ------
    ModuleNotFoundError
        matplotlib (the ``plots`` extra) is not installed.
    """
    result = data.result
    k_o, k_h = result["k_o"], result["k_h"]
    run_s = result["run_s"]
    with _figure((13.5, 5.0), path) as fig:
        axes = fig.subplots(1, 2, sharey=True)
        panels = (
            (
                axes[0],
                "pi",
                "PI local model",
                f"$K_h$ = {k_h / 1e3:g} N/mm, $I$ = {result['i_gain']:g} N/(m s), "
                rf"$\theta$ = {result['theta_m'] * 1e3:g} mm",
            ),
            (axes[1], "p_only", "P local model", f"$K_h$ = {k_h / 1e3:g} N/mm, $I$ = 0"),
        )
        for ax, key, label, gains in panels:
            tr = data.traces[key]
            c = result[key]
            t = tr.t_s
            ax.plot(t, tr.probe_m * 1e3, **_PROBE_STYLE)
            ax.plot(t, tr.proxy_m * 1e3, **_PROXY_STYLE)
            ax.axhline(0.0, color="0.5", lw=0.8, ls=":", label="undeformed surface")
            t_mark = run_s - 0.9
            yp = c["final_probe_mm"]
            yo = c["final_proxy_mm"]
            ax.annotate(
                "",
                xy=(t_mark, yo),
                xytext=(t_mark, yp),
                arrowprops={
                    "arrowstyle": "<->",
                    "color": "k",
                    "lw": 1.3,
                    "shrinkA": 0,
                    "shrinkB": 0,
                },
            )
            err = c["steady_state_error_mm"]
            what = "offset = \u03b8" if c["i_gain"] > 0 else "eq. 11 error"
            small = abs(yp - yo) < 8.0
            ax.text(
                t_mark - 0.1,
                yo - 3.0 if small else 0.5 * (yo + yp),
                f"{what} = {err:.1f} mm" if small else f"{what}\n{err:.1f} mm",
                ha="right" if not small else "center",
                va="top" if small else "center",
                fontsize=10.5,
                bbox={"boxstyle": "round", "fc": "white", "ec": "0.6", "alpha": 0.9},
            )
            ax.set_title(
                f"{label}: {gains}\nsteady-state error {err:.1f} mm, "
                f"settles (2 %) in {c['settling_time_s']:.2f} s",
                fontsize=11,
            )
            _style(ax, "time [s]", "position (depth) [mm]")
            ax.set_xlim(0.0, run_s)
            ax.set_ylim(-15.0, 37.0)
            ax.legend(loc="lower right")
        fig.suptitle(
            f"Fig. 9: probe and proxy, spring object $K_o$ = {k_o / 1e3:g} N/mm "
            f"({k_o:g} N/m), servo {SERVO_RATE_HZ:g} Hz, simulation {SIM_RATE_HZ:g} Hz",
            fontsize=13,
        )


# --------------------------------------------------------------------------------------------
# haptic reproduce fig7 | fig8 | fig9 | all
# --------------------------------------------------------------------------------------------


def plot_figure(data: FigureData, path: pathlib.Path) -> None:
    """Draw one figure's data into the PNG ``path``: :func:`plot_fig7`, ``8`` or ``9``.

    Raises
    ------
    ModuleNotFoundError
        matplotlib (the ``plots`` extra) is not installed.
    """
    if isinstance(data, Fig7Data):
        plot_fig7(data, path)
    elif isinstance(data, Fig8Data):
        plot_fig8(data, path)
    else:
        plot_fig9(data, path)


def reproduce_figures(figure: FigureName, out_dir: pathlib.Path) -> dict[str, dict[str, Any]]:
    """Recompute the paper's Fig. 7, 8 and/or 9 and write ``<fig>.png`` and ``<fig>.json``.

    The data come from :func:`haptic_collab.research.reproduce.figure_data`, the JSON text from
    :func:`haptic_collab.research.reproduce.json_text`, the PNG from :func:`plot_figure`.

    Parameters
    ----------
    figure : {"fig7", "fig8", "fig9", "all"}
        Which figure(s) to reproduce (see :func:`haptic_collab.research.reproduce.figure_data`).
    out_dir : pathlib.Path
        Output directory, created if missing.

    Returns
    -------
    dict
        The JSON objects written, keyed by figure name (SI units: m, s, N, N/m, N/(m*s)).

    Raises
    ------
    ValueError
        Unknown figure name.
    ModuleNotFoundError
        matplotlib (the ``plots`` extra) is not installed; raised before anything is computed
        or written.
    AssertionError
        If a simulated response and the stability analysis disagree (they never should).
    """
    names = figure_names(figure)
    import matplotlib  # noqa: F401  (the plots extra: fail before the work, not after it)

    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict[str, Any]] = {}
    for name in names:
        data = figure_data(name)
        plot_figure(data, out_dir / f"{name}.png")
        with open(out_dir / f"{name}.json", "w", encoding="utf-8") as fh:
            fh.write(json_text(data.result))
        results[name] = data.result
    return results
