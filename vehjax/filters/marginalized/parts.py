"""The per-particle pieces both marginalized PFs' steps share: the linearisation at every
particle (constants as numbers, entries that depend on the input alone computed once per step),
the noise covariances as entries, the sensor part of the statistics' datum, and the guard that
keeps a particle's old values where its new ones are not finite. Entries over the particles
(:mod:`vehjax.lib.entrywise`), particles last."""

from __future__ import annotations

import jax.numpy as jnp

from ...lib.entrywise import add
from .linearise import lin_entries, linearise, merge_entries
from .niw import impute_missing
from .setup import ModelFns, Setup
from .staging import stage

__all__ = ["linearisation", "linear_noise_entries", "used_noise", "sensor_data",
           "finite_or_old", "measured"]


def linearisation(s: Setup, mdl: ModelFns, x, m, u, theta):
    """The linearisation's entries at every particle (used output rows only): constants as
    numbers, the entries that depend on the input alone computed once at one point."""
    dtype = x.dtype
    rows = s.used_rows

    def used_rows(lin):
        return lin_entries(lin._replace(yb=lin.yb[rows], Cx=lin.Cx[rows], Cz=lin.Cz[rows],
                                        d=lin.d[rows]))

    lin = used_rows(mdl.linearise_all(x, m, u, theta))  # entries not used are compiled away
    lin_step = used_rows(linearise(mdl.transition, mdl.observe, jnp.zeros(s.n_sampled, dtype),
                                   jnp.zeros(s.n_linear, dtype), u, theta, s.sampled_idx,
                                   s.linear_idx, s.input_idx))
    return stage(merge_entries(lin, lin_step, mdl.entry_kinds))


def linear_noise_entries(s: Setup, dtype):
    """The linear states' process noise as entries: structural zeros as 0.0."""
    Q = s.linear_noise
    return [[float(Q[i, j]) if Q[i, j] == 0.0 else jnp.asarray(Q[i, j], dtype)
             for j in range(s.n_linear)] for i in range(s.n_linear)]


def used_noise(s: Setup, R_s):
    """The noise covariance of the used output rows (entries): the sensors' ``R_s``, the known
    variances on the diagonal elsewhere."""
    spos, kvu = s.sensor_of_row, s.known_variances
    nyu = len(s.used_rows)
    return [[R_s[spos[i]][spos[j]] if (i in spos and j in spos) else (kvu[i] if i == j else 0.0)
             for j in range(nyu)] for i in range(nyu)]


def sensor_data(s: Setup, eta_e, V, ob, R_s):
    """The sensor part of the statistics' datum: the residuals ``eta_e`` with missing ones
    imputed from ``R_s`` (the point estimate) and the covariance added to Lambda_e (``V`` on
    the observed pairs plus the imputation's). Returns (eta_e list, extra (ns, ns) entries)."""
    ns = s.n_sensors
    ob_e = [ob[r] for r in s.sensor_rows]
    V = [[jnp.where(ob_e[i] & ob_e[j], V[i][j], 0.0) for j in range(ns)] for i in range(ns)]
    eta_e, V_miss = stage(impute_missing(eta_e, R_s, ob_e))
    return eta_e, [[add(V[i][j], V_miss[i][j]) for j in range(ns)] for i in range(ns)]


def finite_or_old(ll, news, olds):
    """Per particle: where the log-likelihood or any new value is not finite, the weight zero
    (-inf) and the old values kept. ``news``, ``olds``: arrays with particles last."""
    ok = jnp.isfinite(ll)
    for a in news:
        ok = ok & jnp.all(jnp.isfinite(a), axis=tuple(range(a.ndim - 1)))
    return jnp.where(ok, ll, -jnp.inf), [jnp.where(ok, n, o) for n, o in zip(news, olds)]


def measured(s: Setup, mdl: ModelFns, y, u, dtype):
    """The step's measurement on the used rows in ``dtype``, NaN (missing) as 0.0, which rows
    are observed and how many; the input and the model's parameters in ``dtype``. Returns
    (y0, obs, n_obs, u, theta)."""
    y, u = jnp.asarray(y).astype(dtype), jnp.asarray(u).astype(dtype)
    theta = mdl.theta.astype(dtype)
    yu = y[s.used_rows]
    obs = ~jnp.isnan(yu)
    y0 = jnp.where(obs, yu, 0.0)
    return y0, obs, jnp.sum(obs, dtype=jnp.int32), u, theta
