"""The model seen by the marginalized PF at one particle, to first order: the forward-mode
linearisation (:class:`Lin`) of the transition and the observation in the noisy input, the
linear states and (with Gaussian particle states) the sampled states, and which of its entries
are constants, functions of the input alone, or per particle (:func:`entry_kinds`). For models
affine in the linear states, the sampled states and the noisy input (SingleTrackBank at a given
speed) it is exact.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ...runtime import hoist
from ...lib.entrywise import entries

__all__ = ["Lin", "linearise", "lin_entries", "entry_kinds", "merge_entries"]


class Lin(NamedTuple):
    """The model at one particle, to first order (exact for affine models).

    xb, zb, yb: x_t, z_t and y_t for w = 0 and z_{t-1} = its Kalman mean.
    g, gz: d x_t / d w, d z_t / d w.  Ab, A: d x_t / d z_{t-1}, d z_t / d z_{t-1}.
    Fx, Fzx: d x_t / d x_{t-1}, d z_t / d x_{t-1} (used with Gaussian particle states only).
    Cx, Cz, d: d y / d x, d y / d z at (xb, zb), and d y / d w directly (eq. 8's d).
    """

    xb: jnp.ndarray
    zb: jnp.ndarray
    yb: jnp.ndarray
    g: jnp.ndarray
    gz: jnp.ndarray
    Ab: jnp.ndarray
    A: jnp.ndarray
    Cx: jnp.ndarray
    Cz: jnp.ndarray
    d: jnp.ndarray
    Fx: jnp.ndarray
    Fzx: jnp.ndarray


def linearise(f, h, x, m, u, theta, nl, li, i_in):
    """:class:`Lin` of the model (f, h) at sampled states x, bank mean m, input u (one point).

    ``nl``, ``li``: indices of the sampled and linear states in the model's state vector;
    ``i_in``: index of the noisy input. Forward mode (``jax.linearize``), 1 + n_z directions
    through f and n_x + 1 through h.
    """
    nx = len(nl) + len(li)
    nz = len(li)
    inv = np.argsort(np.concatenate([nl, li]).astype(int))

    nxs = len(nl)

    def trans(p):  # p = (w, z deviation, x deviation)
        X = jnp.concatenate([x + p[1 + nz:], m + p[1:1 + nz]])[inv]
        return f(X, u.at[i_in].add(p[0]), theta)

    def obs(p):
        return h(p[:nx], u.at[i_in].add(p[nx]), theta)

    # jax.linearize and one tangent per direction rather than jacfwd: no inner vmap, so under
    # the filter's vmap over particles every derivative stays one vector over the particles
    # (directions whose derivatives are not used are compiled away)
    Xn, f_lin = jax.linearize(trans, jnp.zeros(1 + nz + nxs, x.dtype))
    eye = np.eye(1 + nz + nxs)
    J = jnp.stack([f_lin(jnp.asarray(eye[k], x.dtype)) for k in range(1 + nz + nxs)], axis=1)
    yb, h_lin = jax.linearize(obs, jnp.concatenate([Xn, jnp.zeros(1, x.dtype)]))
    eye = np.eye(nx + 1)
    JH = jnp.stack([h_lin(jnp.asarray(eye[k], x.dtype)) for k in range(nx + 1)], axis=1)
    zs, xs = slice(1, 1 + nz), slice(1 + nz, None)
    return Lin(Xn[nl], Xn[li], yb, J[nl, 0], J[li, 0], J[nl, zs], J[li, zs], JH[:, nl],
                JH[:, li], JH[:, nx], J[nl, xs], J[li, xs])


def lin_entries(lin):
    """:class:`Lin` of arrays (one point, or particles last) -> :class:`Lin` of entries
    (:func:`vehjax.lib.entrywise.entries`)."""
    return Lin(*(entries(a) for a in lin))


def entry_kinds(f, h, theta, nl, li, i_in, n_u, rows):
    """:class:`Lin` of nested lists saying how each entry of the linearisation varies, found
    from the traced model (:func:`vehjax.runtime.hoist.dependence`); ``rows``: the output rows the
    filter uses. An entry is

    * a Python float: the same number at every particle, bank mean and input (a structural
      constant: the step's algebra skips zeros and ones and folds the rest);
    * ``"step"``: a function of the input alone, the same for every particle: computed once per
      step at one point and broadcast;
    * None: it depends on the particle (its sampled states or its bank mean).

    For SingleTrackBank 36 of the 60 Jacobian entries are constants (gz, A, most of Cx, Cz and
    d) and the other 24 depend on the speed only (the model is affine in (vy, r), the bank and
    the steering at a given speed): per particle only x_t, z_t and y_t at w = 0 remain."""
    probe = (jnp.zeros(len(nl)), jnp.zeros(len(li)), jnp.ones(n_u))

    def lin_one(x, m, u):
        lin = linearise(f, h, x, m, u, theta, nl, li, i_in)
        return lin._replace(yb=lin.yb[rows], Cx=lin.Cx[rows], Cz=lin.Cz[rows], d=lin.d[rows])

    dep = hoist.dependence(lin_one, probe)
    dep_particle = hoist.dependence(lambda x, m: lin_one(x, m, probe[2]), probe[:2])
    val = hoist.evaluate(lin_one, probe)

    def kinds(d, dp, v):
        if d.ndim == 2:
            return [kinds(di, dpi, vi) for di, dpi, vi in zip(d, dp, v)]
        return [None if dpi else ("step" if di else float(vi))
                for di, dpi, vi in zip(d, dp, np.asarray(v))]

    return Lin(*(kinds(np.asarray(d), np.asarray(dp), v)
                  for d, dp, v in zip(dep, dep_particle, val)))


def merge_entries(per_particle, per_step, kinds):
    """Entries of the linearisation: the constants of ``kinds`` (:func:`entry_kinds`), the
    entries of ``per_step`` (one point) where the kind is "step", those of ``per_particle``
    elsewhere (all nested lists)."""
    def put(e, s, k):
        if isinstance(k, list):
            return [put(ei, si, ki) for ei, si, ki in zip(e, s, k)]
        return e if k is None else (s if k == "step" else k)
    return Lin(*(put(e, s, k) for e, s, k in zip(per_particle, per_step, kinds)))
