"""Matplotlib figures of simulations and studies. Every function writes a PNG and returns its path."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def plot_simulation(sim, path, max_runs: int = 20, title: str | None = None) -> Path:
    """True states and measurements of up to ``max_runs`` runs against time, one panel each.

    Args:
        sim: a :class:`vehjax.Simulation`.
        path: PNG file to write.
    """
    states = np.asarray(sim.states)[:max_runs]
    meas = np.asarray(sim.measurements)[:max_runs]
    t = np.asarray(sim.t)
    names = [f"state {n}" for n in sim.state_names] + [f"measured {n}" for n in sim.output_names]
    series = [states[..., i] for i in range(states.shape[-1])] + [meas[..., i] for i in range(meas.shape[-1])]
    ncol = 2
    nrow = int(np.ceil(len(series) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(10, 2.2 * nrow), sharex=True, squeeze=False)
    for ax, name, data in zip(axes.flat, names, series):
        ax.plot(t, data.T, lw=0.6, alpha=0.6)
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(series):]:
        ax.axis("off")
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    fig.suptitle(title or f"{states.shape[0]} of {np.asarray(sim.states).shape[0]} runs")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
