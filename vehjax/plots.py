"""Matplotlib figures of simulations and studies. Every function writes a PNG and returns its path.

Conventions shared by every figure vehjax writes:

* axis labels carry units, ``name [unit]``, taken from the model's ``state_units``,
  ``input_units``, ``param_units``, ``output_units`` (:func:`label`);
* titles say how many Monte-Carlo runs the figure summarises;
* a spread over runs is a 5-95 % band with the mean on it, one panel per filter (small
  multiples sharing their y axis), so that filters never hide each other;
* the truth is drawn last, in black, on top of everything else.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

#: line colour of the truth, drawn on top of estimates
TRUTH_COLOR = "k"
_TRUTH_Z = 10


def colors() -> list:
    """The colour cycle; filter k of a study gets ``colors()[k % len(colors())]`` everywhere."""
    return plt.rcParams["axes.prop_cycle"].by_key()["color"]


def label(name: str, unit: str | None = None, scale: float = 1.0) -> str:
    """Axis label ``name [unit]``; a scale s != 1 reads ``name [s unit]`` (values divided by s),
    e.g. ``label("cx", "N", 1e4) == "cx [1e4 N]"``. Dimensionless units ("-", "", None) give
    ``name [-]``."""
    unit = unit if unit not in (None, "", "-") else ""
    if scale != 1:
        k = np.log10(abs(scale))
        s = f"1e{int(round(k))}" if abs(k - round(k)) < 1e-9 and scale > 0 else f"{scale:g}"
        return f"{name} [{s} {unit}]".replace(" ]", "]")
    return f"{name} [{unit or '-'}]"


def moving_rms(values, window: int):
    """Root mean square over a centred moving window of ``window`` steps along the last axis."""
    values = np.asarray(values, dtype=float)
    window = max(1, min(int(window), values.shape[-1]))
    kernel = np.ones(window)
    sq = np.apply_along_axis(lambda r: np.convolve(r, kernel, "same"), -1, values**2)
    count = np.convolve(np.ones(values.shape[-1]), kernel, "same")
    return np.sqrt(sq / count)


def units_of(model, kind: str, names) -> tuple:
    """Units of ``names`` from ``model.<kind>_units`` (kind: state, input, param, output); "-"
    for any the model does not know (or when ``model`` is None)."""
    if model is None:
        return ("-",) * len(names)
    known = dict(zip(getattr(model, f"{kind}_names", ()), getattr(model, f"{kind}_units", ())))
    return tuple(known.get(n, "-") for n in names)


def band(ax, t, values, color, label: str | None = None, mean: bool = True):
    """5-95 % band over runs (axis 0 of ``values``, NaN runs ignored) with the mean on it."""
    values = np.asarray(values, dtype=float)
    if values.ndim == 1:
        values = values[None]
    lo, hi = np.nanpercentile(values, [5, 95], axis=0)
    ax.fill_between(t, lo, hi, color=color, alpha=0.25, lw=0, label=None if mean else label)
    ax.plot(t, lo, color=color, lw=0.5, alpha=0.8)
    ax.plot(t, hi, color=color, lw=0.5, alpha=0.8)
    if mean:
        ax.plot(t, np.nanmean(values, axis=0), color=color, lw=1.3, label=label)


def truth_line(ax, t, value, label: str | None = "truth"):
    """The truth, a constant or a (T,) series, in black dashes on top of everything."""
    value = np.asarray(value, dtype=float)
    if value.ndim == 0:
        ax.axhline(float(value), color=TRUTH_COLOR, ls="--", lw=1.1, label=label, zorder=_TRUTH_Z)
    else:
        ax.plot(t, value, color=TRUTH_COLOR, ls="--", lw=1.1, label=label, zorder=_TRUTH_Z)


def save(fig, path) -> Path:
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_band_grid(path, t, series, row_labels, col_labels, title: str, truth=None,
                   color_of_col: bool = True, truth_label: str = "truth", xlabel: str = "t [s]",
                   panel_width: float = 3.0, panel_height: float = 2.3, notes=None) -> Path:
    """Small multiples: row i, column j shows the 5-95 % band and mean over runs of
    ``series[i][j]`` (R, T) (None leaves the panel empty); rows share their y axis; ``truth[i]``
    (a constant, a (T,) series or None) is drawn on top of every panel of row i; ``notes[i][j]``
    (optional) is written in the panel's lower left corner. One legend for the figure."""
    n_rows, n_cols = len(row_labels), len(col_labels)
    size = (1.2 + panel_width * n_cols, 1.0 + panel_height * n_rows)
    fig, axes = plt.subplots(n_rows, n_cols, figsize=size,
                             sharex=True, sharey="row", squeeze=False)
    cyc = colors()
    t = np.asarray(t)
    for i in range(n_rows):
        for j in range(n_cols):
            ax = axes[i, j]
            data = series[i][j]
            color = cyc[j % len(cyc)] if color_of_col else cyc[0]
            if data is not None and np.size(data):
                band(ax, t, data, color)
            else:
                ax.text(0.5, 0.5, "no runs", transform=ax.transAxes, ha="center", va="center")
            if truth is not None and truth[i] is not None:
                truth_line(ax, t, truth[i], label=truth_label)
            if notes is not None and notes[i][j]:
                ax.text(0.03, 0.04, notes[i][j], transform=ax.transAxes, fontsize=8,
                        ha="left", va="bottom", zorder=_TRUTH_Z + 1,
                        bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="0.6", alpha=0.85))
            ax.grid(alpha=0.3)
            if i == 0:
                ax.set_title(col_labels[j], fontsize=10)
            if j == 0:
                ax.set_ylabel(row_labels[i])
            if i == n_rows - 1:
                ax.set_xlabel(xlabel)
    figure_legend(fig, axes, title, extra=band_handles())
    return save(fig, path)


def band_handles(what: str = "over runs") -> dict:
    """Legend entries (label -> grey proxy artist) explaining a band drawn by :func:`band`."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    return {f"mean {what}": Line2D([], [], color="0.35", lw=1.3),
            f"5-95 % band {what}": Patch(facecolor="0.35", alpha=0.25, edgecolor="0.35", lw=0.5)}


def figure_legend(fig, axes, title: str, extra: dict | None = None, ncol: int = 5):
    """The title, then one legend for the whole figure under it (``extra`` entries first, then
    every distinct label of ``axes``), then ``tight_layout`` below them."""
    seen = dict(extra or {})
    for ax in np.ravel(axes):
        for h, lab in zip(*ax.get_legend_handles_labels()):
            seen.setdefault(lab, h)
    height = fig.get_size_inches()[1]
    n_title = title.count("\n") + 1
    title_in = 0.25 * n_title + 0.1
    fig.suptitle(title, y=1 - 0.08 / height, va="top")
    legend_in = 0.0
    if seen:
        fig.legend(list(seen.values()), list(seen), loc="upper center", ncol=min(ncol, len(seen)),
                   fontsize=8, frameon=False, bbox_to_anchor=(0.5, 1 - title_in / height),
                   borderaxespad=0.0, markerscale=4)
        legend_in = 0.2 * int(np.ceil(len(seen) / min(ncol, len(seen))))
    fig.tight_layout(rect=(0, 0, 1, 1 - max(0.0, title_in + legend_in - 0.15) / height))


def plot_simulation(sim, path, max_runs: int = 20, title: str | None = None, model=None,
                    note: str | None = None) -> Path:
    """True states, measurements and inputs of up to ``max_runs`` runs against time.

    One panel per state (the true state of each run; a measured state also shows run 0's
    measurements, in grey, under the truth), one per output that is not a state, and one per
    input. Labels carry the units of ``model`` when it is given.

    Args:
        sim: a :class:`vehjax.Simulation`.
        path: PNG file to write.
        max_runs: at most this many runs are drawn.
        title: figure title; the number of runs drawn and simulated is appended.
        model: the simulated model, for the units.
        note: a line under the title (e.g. that all runs share one truth).
    """
    states = np.asarray(sim.states)
    meas = np.asarray(sim.measurements)
    inputs = np.asarray(sim.inputs)
    t = np.asarray(sim.t)
    n_runs = states.shape[0]
    shown = min(max_runs, n_runs)
    s_units = units_of(model, "state", sim.state_names)
    y_units = units_of(model, "output", sim.output_names)
    u_units = units_of(model, "input", sim.input_names)
    out_of_state = {n: i for i, n in enumerate(sim.output_names)}
    panels = []  # (kind, index)
    panels += [("state", i) for i in range(len(sim.state_names))]
    panels += [("output", i) for i, n in enumerate(sim.output_names) if n not in sim.state_names]
    by_unit = {}  # inputs sharing a unit share a panel
    for i, u in enumerate(u_units):
        by_unit.setdefault(u, []).append(i)
    panels += [("input", tuple(idx)) for idx in by_unit.values()]
    y_true = None
    if model is not None and any(k == "output" for k, _ in panels):
        import jax

        theta0 = np.asarray(sim.theta)[0]  # run 0's noise-free outputs
        y_true = np.asarray(jax.vmap(lambda x, u: model.observe(x, u, theta0))(states[0], inputs))
    ncol = 2
    nrow = int(np.ceil(len(panels) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(11, 1.0 + 2.2 * nrow), sharex=True, squeeze=False)
    cyc = colors()
    for ax, (kind, i) in zip(axes.flat, panels):
        if kind == "state":
            name = sim.state_names[i]
            if name in out_of_state:
                ax.plot(t, meas[0, :, out_of_state[name]], ".", color="0.65", ms=1.5,
                        label="measured (run 0)", zorder=1)
            for r in range(shown):
                ax.plot(t, states[r, :, i], lw=0.8, alpha=0.7, color=cyc[r % len(cyc)],
                        zorder=_TRUTH_Z, label="true state (one colour per run)" if r == 0 else None)
            ax.set_ylabel(label(name, s_units[i]))
            ax.set_title(f"state {name}" + (" (measured)" if name in out_of_state else ""), fontsize=9)
        elif kind == "output":
            name = sim.output_names[i]
            for r in range(shown):
                ax.plot(t, meas[r, :, i], lw=0.5, alpha=0.5, color=cyc[r % len(cyc)],
                        label="measured (one colour per run)" if r == 0 else None)
            if y_true is not None:
                truth_line(ax, t, y_true[:, i], label="noise-free output (run 0)")
            ax.set_ylabel(label(name, y_units[i]))
            ax.set_title(f"measured {name}", fontsize=9)
        else:
            names = [sim.input_names[k] for k in i]
            styles = ("-", "--", ":", "-.")
            for n_k, k in enumerate(i):
                ax.plot(t, inputs[:, k], color="0.35" if len(i) == 1 else cyc[n_k % len(cyc)],
                        lw=1.0 + 0.6 * (len(i) - 1 - n_k) / max(1, len(i) - 1),
                        ls=styles[n_k % len(styles)], label=sim.input_names[k])
            ax.set_ylabel(label(names[0] if len(i) == 1 else "inputs", u_units[i[0]]))
            ax.set_title(f"input{'s' if len(i) > 1 else ''} {', '.join(names)} "
                         "(the same in every run)", fontsize=9)
            if len(i) > 1:
                ax.legend(fontsize=7, loc="best")
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(panels):]:
        ax.axis("off")
    for ax in axes.flat[max(0, len(panels) - ncol):len(panels)]:
        ax.set_xlabel("t [s]")
        ax.xaxis.set_tick_params(labelbottom=True)
    runs = f"{shown} of {n_runs} runs drawn" if shown < n_runs else f"{n_runs} runs"
    head = f"{title}: {runs}" if title else runs
    data_axes = [ax for ax, (k, _) in zip(axes.flat, panels) if k != "input"]
    figure_legend(fig, data_axes, head + (f"\n{note}" if note else ""))
    return save(fig, path)
