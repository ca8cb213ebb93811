"""The optimisers of a fit, each on the fit's one compiled loss program
(:class:`vehjax.tune.program.CompiledLoss`), minimising the negative mean log-likelihood per
step over the unconstrained coordinates:

* :func:`scoring`: BHHH / the method of scoring (the outer product of the per-step scores as
  curvature, :func:`scoring_direction`) with Levenberg damping and a backtracking line search;
* :func:`lbfgs`: ``optax.lbfgs`` with its zoom line search (``optax.scale_by_zoom_linesearch``,
  strong Wolfe conditions), driven with ``optax.value_and_grad_from_state``; the line search
  evaluates the compiled program through a host callback, so a fit still compiles the filter
  once;
* :func:`first_order`: adam or any ``optax.GradientTransformation``
  (:func:`first_order_optimizer`), keeping the best point;
* :func:`newton`: one Newton step on the Hessian's determined directions, the polish after
  scoring and L-BFGS.

Every optimiser reports its iterations to ``report(i, loss, best)`` (the progress bar) and
returns the history of the loss at the start of each iteration.
"""

from __future__ import annotations

import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .. import validation
from .information import RCOND

__all__ = ["scoring", "scoring_direction", "lbfgs", "first_order", "first_order_optimizer",
           "newton", "GTOL"]

ADAM_LR = 0.05
ADAM_STEPS = 300
LBFGS_STEPS = 100
GTOL = 1e-6  # L-BFGS: max |d loss / dz| at convergence (loss per step, z unconstrained)


def finite(*arrays) -> bool:
    """Whether every entry of every array is finite."""
    return all(bool(np.all(np.isfinite(np.asarray(a)))) for a in arrays)


def check_start(f, *derivatives):
    """FloatingPointError unless the loss ``f`` and its ``derivatives`` at the starting values
    are finite."""
    if not (np.isfinite(f) and finite(*derivatives)):
        raise FloatingPointError(
            "vehjax.tune: the log-likelihood or its gradient is not finite at the starting "
            "values; check Q0, R0, x0, P0 and the measurements")


def first_order_optimizer(optimizer, learning_rate, steps):
    """The optax transformation of a first-order fit: ``"adam"`` (peak rate ``learning_rate``,
    default 0.05, cosine decay to 5 % over ``steps``) or the caller's own transformation, each
    skipping updates whose gradient is not finite (``optax.apply_if_finite``)."""
    if optimizer == "adam":
        lr = ADAM_LR if learning_rate is None else learning_rate
        sched = optax.cosine_decay_schedule(lr, max(steps, 1), alpha=0.05)
        return optax.apply_if_finite(optax.adam(sched), max_consecutive_errors=10)
    if isinstance(optimizer, optax.GradientTransformation):
        if learning_rate is not None:
            raise ValueError("learning_rate: set it inside your own optax optimizer, not here")
        return optax.apply_if_finite(optimizer, max_consecutive_errors=10)
    raise ValueError(f"optimizer: expected 'adam', 'lbfgs' or an optax.GradientTransformation, "
                     f"got {optimizer!r}")


def scoring_direction(g, B, scales, damping: float = 0.0):
    """The BHHH / scoring step ``-(B + damping lam_max I)^-1 g`` in the scaled coordinates
    ``S z`` (S = diag(scales), the coordinates' natural sizes), over the directions where the
    scaled B has curvature above 1e-10 of its largest eigenvalue (a step of zero along the
    others): g (n,) gradient, B (n, n) positive semi-definite curvature, damping >= 0.
    Returns (n,)."""
    damping = validation.number("damping", damping, 0.0, low_open=False)
    scales = validation.shaped("scales", scales, (None,))
    g = validation.shaped("g", g, scales.shape)
    B = validation.shaped("B", B, scales.shape * 2)
    Bs = B * np.outer(scales, scales)
    lam, V = np.linalg.eigh(0.5 * (Bs + Bs.T))
    top = max(float(lam.max()), np.finfo(float).tiny)
    keep = lam > 1e-10 * top
    gs = V[:, keep].T @ (scales * g)
    return -scales * (V[:, keep] @ (gs / (lam[keep] + damping * top)))


def _at_gradient_tolerance(history: list, i: int, f: float, g, gtol: float, report) -> bool:
    """The head of a second-order iteration: record the loss, report progress, and whether the
    gradient is within ``gtol`` (max |grad|), the convergence test of every optimiser here."""
    history.append(f)
    report(i, f, f)
    return bool(np.max(np.abs(g)) <= gtol)


#: BHHH hands over to the Newton polish when a step gains less than this (log-likelihood units,
#: the loss times the run-steps), more than TAIL_RATE of the step before and less than
#: TAIL_RATE of its first-order prediction: a slow tail of steps that overshoot (the outer
#: product of the scores is not the Hessian where the model does not fit the data exactly)
LINEAR_TAIL = 1.0
TAIL_RATE = 0.3
#: ... and whenever a step gains less than this (log-likelihood units) and less than 1e-6 of
#: the loss (a long fit): what is left is a Newton step away, and the Newton polish forms the
#: curvature the standard errors need anyway
SMALL_GAIN = 0.01
#: a full scoring step that gains more than this fraction of its first-order prediction -g.d
#: is taken as too short (:func:`_expand`)
EXPAND_RATIO = 0.8
#: such a step is lengthened at most 2**EXPAND_MAX times
EXPAND_MAX = 5


def _expand(loss, x, d, dg: float, f: float, new):
    """(t, the evaluation at x + t d) after a full step ``new`` of the direction d was accepted
    that gained more than :data:`EXPAND_RATIO` of its first-order prediction ``-g.d``: one
    longer step, to the minimum of the parabola through the loss at 0 and 1 with slope g.d at
    0 (between 2 and ``2**EXPAND_MAX``), kept where it lowers the loss further. Far from the
    optimum, where large scores make the outer product of the scores much larger than the
    Hessian (a misfit explained by a small noise variance), the scoring step is many times too
    short; a quadratic model whose curvature is right gains half the prediction, so a gain near
    all of it says the curvature was overestimated, and by how much."""
    if not f - new[0] > EXPAND_RATIO * -dg:
        return 1.0, new
    bend = new[0] - f - dg  # the parabola's quadratic coefficient, times 1
    t = float(np.clip(-dg / (2.0 * bend), 2.0, 2.0**EXPAND_MAX)) if bend > 0 else 2.0**EXPAND_MAX
    cand = loss.vgo(x + t * d)
    if np.isfinite(cand[0]) and finite(cand[2], cand[3]) and cand[0] < new[0]:
        return t, cand
    return 1.0, new


def scoring(loss, steps: int, gtol: float, report, scales, n_steps: int = 1,
            c1: float = 1e-4):
    """BHHH (method of scoring with the outer product of the per-step scores,
    :func:`score_outer_product`) with Levenberg damping and a backtracking (Armijo) line search
    that lengthens a full step that gains nearly its first-order prediction (:func:`_expand`),
    every trial one evaluation of the forward-mode program (value, gradient and curvature
    together). Stops, converged, when max |grad| <= gtol; hands over (not converged) to the
    Newton polish when a step gains less than 1e-11 max(1, |loss|) or no step decreases the
    loss: BHHH converges linearly where the observed and the expected curvature differ, Newton
    quadratically from there; also when the steps' gains fall slower than by :data:`TAIL_RATE`
    per step while each is below :data:`LINEAR_TAIL` log-likelihood units and below
    :data:`TAIL_RATE` of its first-order prediction (``n_steps``: the run-steps the loss is
    averaged over). Returns (x, aux, history, iterations, converged)."""
    x = loss.x0
    f, aux, g, B = loss.vgo(x)
    check_start(f, g, B)
    history, converged, i, damping, previous = [], False, 0, 0.0, np.inf
    for i in range(1, steps + 1):
        if _at_gradient_tolerance(history, i, f, g, gtol, report):
            converged = True
            break
        d = scoring_direction(g, B, scales, damping)
        dg = float(g @ d)
        if not dg < 0:
            d, dg = -g * scales**2, -float(g @ (g * scales**2))
        t, new = 1.0, None
        for _ in range(30):
            cand = loss.vgo(x + t * d)
            if np.isfinite(cand[0]) and finite(cand[2], cand[3]) and \
                    cand[0] <= f + c1 * t * dg:
                new = cand
                break
            t *= 0.25 if not np.isfinite(cand[0]) else 0.5
        if new is None:
            break
        if t == 1.0:
            t, new = _expand(loss, x, d, dg, f, new)
        damping = damping / 10.0 if t >= 1.0 else max(10.0 * damping, 1e-3)
        gain = f - new[0]
        x, (f, aux, g, B) = x + t * d, new
        if gain < 1e-11 * max(1.0, abs(f)) or (
                gain * n_steps < SMALL_GAIN and gain < 1e-6 * max(1.0, abs(f))) or (
                gain * n_steps < LINEAR_TAIL and gain > TAIL_RATE * previous
                and gain < TAIL_RATE * t * -dg):
            break
        previous = gain
    return x, aux, history, i, converged


def first_order(loss, opt, steps: int, tol: float, patience: int, report):
    """adam or a custom optax transformation on the compiled loss: steps with a non-finite
    gradient are skipped (``apply_if_finite``); stops, converged, when the best loss has not
    improved by ``tol * max(1, |best|)`` for ``patience`` iterations. Returns (best x, its aux,
    history, iterations, converged, skipped)."""
    update = jax.jit(opt.update)
    x = jnp.asarray(loss.x0)
    state = jax.tree.map(lambda a: jnp.array(a, dtype=jnp.asarray(a).dtype), opt.init(x))
    history, best, best_x, best_aux = [], np.inf, loss.x0, None
    since = skipped = i = 0
    converged, f = False, np.nan
    for i in range(1, steps + 1):
        f, aux, g = loss.vg(x)
        history.append(f)
        if not (np.isfinite(f) and finite(g)):
            skipped += 1
        if np.isfinite(f) and (not np.isfinite(best) or f < best - tol * max(1.0, abs(best))):
            best, best_x, best_aux, since = f, np.asarray(x), aux, 0
        else:
            since += 1
        report(i, f, best)
        updates, state = update(jnp.asarray(g), state, x)
        x = optax.apply_updates(x, updates)
        if since >= patience:
            converged = True
            break
    if not np.isfinite(best):
        raise FloatingPointError(
            "vehjax.tune: the log-likelihood is not finite at the starting values; check Q0, R0, "
            "x0, P0 and the measurements")
    return best_x, best_aux, history, i, converged, skipped


def newton(loss, x, scales, gtol: float, hessian, free=None, curvature_after: bool = True):
    """The curvature at x and one Newton step on its determined directions, kept when the loss
    does not increase (the curvature is then recomputed where the step was large, unless
    ``curvature_after`` is False: the caller does not use it); ``free`` (n,) bool: step in
    these coordinates only (the others on a bound of their domain, held).
    Returns (x, aux, gradient (n,), Hessian of the mean loss)."""
    f, aux, g = loss.vg(x)
    Hm = hessian(x)
    if not (np.all(np.isfinite(Hm)) and finite(g)):
        return x, aux, g, Hm
    free = np.ones(len(g), bool) if free is None else np.asarray(free, bool)
    s, gf = scales[free], g[free]
    if not np.any(free):
        return x, aux, g, Hm
    lam, V = np.linalg.eigh(Hm[np.ix_(free, free)] * np.outer(s, s))
    keep = lam > RCOND * max(float(lam.max()), np.finfo(float).tiny)
    if np.max(np.abs(gf)) <= 1e-3 * gtol or not np.any(keep):
        return x, aux, g, Hm
    step = np.zeros(len(g))
    step[free] = -s * (V[:, keep] @ ((V[:, keep].T @ (s * gf)) / lam[keep]))
    f_new, aux_new, g_new = loss.vg(x + step)
    if np.isfinite(f_new) and finite(g_new) and f_new <= f + 1e-14 * max(1.0, abs(f)):
        x, aux, g = x + step, aux_new, g_new
        if curvature_after and np.max(np.abs(step / scales)) > 1e-3:  # moved far: curvature there
            Hm = hessian(x)
    return x, aux, g, Hm


#: the compiled losses of the L-BFGS fits running now, by handle: the line search's host callback
#: finds its fit's loss by the handle it is passed as an array, so one compiled L-BFGS step
#: serves every fit with the same number of coordinates (no compile per fit)
_LOSSES: dict = {}
_HANDLES = itertools.count()


def _host_value_grad(handle, f):
    v, _, g = _LOSSES[int(handle)](np.asarray(f))
    return np.asarray(v, dtype=f.dtype), np.asarray(g, dtype=f.dtype)


@jax.custom_vjp
def _callback_loss(f, handle):
    return _callback_value_grad(f, handle)[0]


def _callback_value_grad(f, handle):
    shapes = (jax.ShapeDtypeStruct((), f.dtype), jax.ShapeDtypeStruct(f.shape, f.dtype))
    return jax.pure_callback(_host_value_grad, shapes, handle, f)


def _callback_fwd(f, handle):
    return _callback_value_grad(f, handle)


def _callback_bwd(g, ct):
    return ct * g, None


_callback_loss.defvjp(_callback_fwd, _callback_bwd)


def traced_loss(f, handle):
    """The loss of the fit registered under ``handle`` as a JAX function of the flat
    coordinates f, for optax's line search: value and gradient from the fit's compiled program
    (``CompiledLoss.vg``: one evaluation per point, counted, a repeated point not evaluated
    again) through ``jax.pure_callback``; its derivative is that gradient
    (``jax.custom_vjp``). Nothing of the filter is traced again."""
    return _callback_loss(f, handle)


@functools.lru_cache(maxsize=None)
def _lbfgs_program(memory: int, linesearch_steps: int):
    """(``optax.lbfgs`` with the zoom line search, its step ``(z, state, handle) -> (z',
    state')`` jitted), built once per configuration: the jit cache then holds one program per
    number of coordinates."""
    opt = optax.lbfgs(memory_size=memory, linesearch=optax.scale_by_zoom_linesearch(
        max_linesearch_steps=linesearch_steps, initial_guess_strategy="one"))
    value_and_grad = optax.value_and_grad_from_state(traced_loss)

    @jax.jit
    def step(z, state, handle):
        value, grad = value_and_grad(z, handle, state=state)
        updates, state = opt.update(grad, state, z, value=value, grad=grad,
                                    value_fn=traced_loss, handle=handle)
        return optax.apply_updates(z, updates), state

    return opt, step


def lbfgs(loss, steps: int, gtol: float, report, memory: int = 10, linesearch_steps: int = 40):
    """L-BFGS (``optax.lbfgs``, ``memory`` pairs) with optax's zoom line search (strong Wolfe,
    at most ``linesearch_steps`` trials) on the compiled loss. Stops, converged, when
    max |grad| <= gtol, or (not converged) when an iteration does not lower the loss (the
    line search found no lower point: the numerical optimum, handed to the Newton polish).
    Returns (x, aux, history, iterations, converged)."""
    x = loss.x0
    f, aux, g = loss.vg(x)
    check_start(f, g)
    opt, step = _lbfgs_program(memory, linesearch_steps)
    handle = next(_HANDLES)
    _LOSSES[handle] = loss.vg
    try:
        state = opt.init(jnp.asarray(x))
        history, converged, i = [], False, 0
        for i in range(1, steps + 1):
            if _at_gradient_tolerance(history, i, f, g, gtol, report):
                converged = True
                break
            z, state = step(jnp.asarray(x), state, jnp.asarray(handle, dtype=jnp.int32))
            x_new = np.asarray(z, dtype=float)
            f_new, aux_new, g_new = loss.vg(x_new)  # the line search's last point: cached
            if not (np.isfinite(f_new) and finite(g_new) and f_new < f):
                break
            x, f, aux, g = x_new, f_new, aux_new, g_new
    finally:
        del _LOSSES[handle]
    return x, aux, history, i, converged
