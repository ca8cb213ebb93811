"""The figures of ``vehjax fit`` and ``vehjax estimate`` (matplotlib, Agg; the conventions of
:mod:`vehjax.plots`: labels with units, one legend per figure, the measurement drawn last)."""

from __future__ import annotations

import numpy as np

from .. import plots
from ..plots import plt

__all__ = ["fitted", "innovations", "estimates"]


def _figure(path, names, units, title: str, draw, height: float = 2.0):
    """One panel per output or state, stacked over a shared time axis: ``draw(ax, i, colors)``
    draws panel i; labels with units, a grid, one legend; saved to ``path``."""
    fig, axes = plt.subplots(len(names), 1, figsize=(9.0, 1.0 + height * len(names)),
                             sharex=True, squeeze=False)
    axes = axes[:, 0]
    c = plots.colors()
    for i, ax in enumerate(axes):
        draw(ax, i, c)
        ax.set_ylabel(plots.label(names[i], units[i]))
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("t [s]")
    plots.figure_legend(fig, axes, title)
    return plots.save(fig, path)


def fitted(path, t, ys, e, names, units, title: str):
    """Each output measured (t, ys (T, ny)) against the fitted filter's one-step prediction
    ``ys - e`` (e: the innovations (T, ny), NaN where the sample is missing)."""
    def draw(ax, i, c):
        ax.plot(t, ys[:, i] - e[:, i], color=c[0], lw=1.0, label="one-step prediction")
        ax.plot(t, ys[:, i], color=plots.TRUTH_COLOR, lw=0.5, alpha=0.6, label="measured")

    return _figure(path, names, units, title, draw)


def innovations(path, t, e, S, names, units, title: str):
    """Each output's innovations e (T, ny) with the filter's +-2 sigma band (S (T, ny, ny): the
    innovations' covariances), and the share of samples outside it (about 5 % for a filter
    whose noise is right)."""
    def draw(ax, i, c):
        sd = np.sqrt(np.maximum(S[:, i, i], 0.0))
        ax.fill_between(t, -2 * sd, 2 * sd, color=c[1], alpha=0.3, lw=0, label="+-2 sigma")
        ax.plot(t, e[:, i], color=c[0], lw=0.6, label="innovation")
        ok = np.isfinite(e[:, i])
        share = float(np.mean(np.abs(e[ok, i]) > 2 * sd[ok])) if ok.any() else float("nan")
        ax.text(0.01, 0.04, f"{100 * share:.1f} % outside", transform=ax.transAxes, fontsize=8)

    return _figure(path, names, units, title, draw)


def estimates(path, t, means, stds, names, units, title: str):
    """Each state's estimate (means (T, nx)) with its +-2 standard deviation band."""
    def draw(ax, i, c):
        ax.fill_between(t, means[:, i] - 2 * stds[:, i], means[:, i] + 2 * stds[:, i],
                        color=c[0], alpha=0.25, lw=0, label="+-2 std")
        ax.plot(t, means[:, i], color=c[0], lw=1.0, label="estimate")

    return _figure(path, names, units, title, draw)
