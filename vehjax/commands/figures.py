"""The figures of ``vehjax fit`` and ``vehjax estimate`` (matplotlib, Agg; the conventions of
:mod:`vehjax.plots`: labels with units, one legend per figure, the measurement drawn last)."""

from __future__ import annotations

import numpy as np

from .. import plots
from ..plots import plt

__all__ = ["fitted", "innovations", "estimates"]


def _panels(n: int, height: float = 2.0):
    fig, axes = plt.subplots(n, 1, figsize=(9.0, 1.0 + height * n), sharex=True, squeeze=False)
    return fig, axes[:, 0]


def fitted(path, t, ys, e, names, units, title: str):
    """Each output measured (t, ys (T, ny)) against the fitted filter's one-step prediction
    ``ys - e`` (e: the innovations (T, ny), NaN where the sample is missing)."""
    fig, axes = _panels(len(names))
    c = plots.colors()
    for i, ax in enumerate(axes):
        ax.plot(t, ys[:, i] - e[:, i], color=c[0], lw=1.0, label="one-step prediction")
        ax.plot(t, ys[:, i], color=plots.TRUTH_COLOR, lw=0.5, alpha=0.6, label="measured")
        ax.set_ylabel(plots.label(names[i], units[i]))
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("t [s]")
    plots.figure_legend(fig, axes, title)
    return plots.save(fig, path)


def innovations(path, t, e, S, names, units, title: str):
    """Each output's innovations e (T, ny) with the filter's +-2 sigma band (S (T, ny, ny): the
    innovations' covariances), and the share of samples outside it (about 5 % for a filter
    whose noise is right)."""
    fig, axes = _panels(len(names))
    c = plots.colors()
    for i, ax in enumerate(axes):
        sd = np.sqrt(np.maximum(S[:, i, i], 0.0))
        ax.fill_between(t, -2 * sd, 2 * sd, color=c[1], alpha=0.3, lw=0, label="+-2 sigma")
        ax.plot(t, e[:, i], color=c[0], lw=0.6, label="innovation")
        ok = np.isfinite(e[:, i])
        share = float(np.mean(np.abs(e[ok, i]) > 2 * sd[ok])) if ok.any() else float("nan")
        ax.text(0.01, 0.04, f"{100 * share:.1f} % outside", transform=ax.transAxes, fontsize=8)
        ax.set_ylabel(plots.label(names[i], units[i]))
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("t [s]")
    plots.figure_legend(fig, axes, title)
    return plots.save(fig, path)


def estimates(path, t, means, stds, names, units, title: str):
    """Each state's estimate (means (T, nx)) with its +-2 standard deviation band."""
    fig, axes = _panels(len(names))
    c = plots.colors()
    for i, ax in enumerate(axes):
        ax.fill_between(t, means[:, i] - 2 * stds[:, i], means[:, i] + 2 * stds[:, i],
                        color=c[0], alpha=0.25, lw=0, label="+-2 std")
        ax.plot(t, means[:, i], color=c[0], lw=1.0, label="estimate")
        ax.set_ylabel(plots.label(names[i], units[i]))
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("t [s]")
    plots.figure_legend(fig, axes, title)
    return plots.save(fig, path)
