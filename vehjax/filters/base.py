"""The Estimator contract shared by every filter and by :func:`vehjax.run`.

An estimator is a pair of pure functions, like optax's ``GradientTransformation``::

    init(x0, P0, theta0, P_theta0, key) -> state      # x0 (nx,), P0 (nx, nx); theta0 (p,) or None
    step(state, y, u) -> (state, StepOutput)          # y (ny,) with NaN for missing, u (nu,)

``state`` is any pytree of arrays (filters that draw random numbers carry their key in it).
Everything that configures a filter (model, Q, R, tuning) is closed over, so ``run`` treats
every filter alike and ``jax.vmap``/``jax.lax.scan`` see only arrays.

Three optional parts of the contract are declared fields too, so that ``run`` reads nothing else:

* ``StepOutput.reinit``: the filter had to re-initialise this step (a particle filter whose
  weights all underflowed). ``run`` reports such a run as diverged but does not freeze it.
* ``Estimator.batch``: ``batch(per_run_inputs: bool, dtype, default_theta: bool) ->
  Batch(prepare, step)``, the same step for a whole batch of runs at once with the runs axis
  last in every leaf of the state, of y and of the StepOutput (see
  :mod:`vehjax.filters.runs_last`). ``prepare`` maps the whole input sequence, (T, nu) shared or
  (T, nu, R) when ``per_run_inputs``, to what the batch ``step`` takes in place of u at each
  time; ``dtype`` is the filter's float dtype and ``default_theta`` says that every run was
  started with ``theta0=None``. ``vehjax.run`` uses it instead of ``vmap``-ing ``step``. It is a
  field: ``est._replace(step=...)`` keeps it, so replace ``batch=None`` too when the new step
  computes something else.
* ``Estimator.bounds``: ``(low, high)``, two tuples of p Python floats (static under ``jit``),
  the domain of each estimated parameter in physical units (-inf / +inf for an open end), which
  the filter keeps its estimate in (:mod:`vehjax.filters._bounds`); None for state-only filters
  and filters without domains.
  :func:`vehjax.filtering.finish` reads it to flag a run whose estimate sits on a bound
  (``at_bound``), and ``run`` to check ``theta0``.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax.numpy as jnp


class StepOutput(NamedTuple):
    """What one filter step reports for the current time.

    Attributes:
        mean: filtered state estimate, (nx,).
        cov: its covariance, (nx, nx).
        loglik: log p(y_t | y_{1:t-1}) of the observed components, scalar.
        nis: normalised innovation squared of the observed components, scalar.
        n_obs: how many measurement components were observed (not NaN), scalar int.
        params: parameter estimate, (p,); shape (0,) for state-only filters.
        params_cov: its covariance, (p, p); shape (0, 0) for state-only filters.
        reinit: bool scalar, the filter re-initialised at this step (its weights all
            underflowed); always False for the Gaussian filters.
    """

    mean: jnp.ndarray
    cov: jnp.ndarray
    loglik: jnp.ndarray
    nis: jnp.ndarray
    n_obs: jnp.ndarray
    params: jnp.ndarray
    params_cov: jnp.ndarray
    reinit: jnp.ndarray | bool = False


def state_output(x, P, loglik, nis, n_obs) -> StepOutput:
    """StepOutput of a state-only filter that never re-initialises (params (0,), params_cov
    (0, 0), reinit False)."""
    return StepOutput(
        mean=x, cov=P, loglik=loglik, nis=nis, n_obs=n_obs,
        params=jnp.zeros((0,), x.dtype), params_cov=jnp.zeros((0, 0), x.dtype),
        reinit=jnp.zeros((), bool),
    )


class ParticleTransition(NamedTuple):
    """A particle filter's transition density, what backward simulation over its particles
    needs: x_t = transition(x_{t-1}, u_t, theta) + v_t, v_t ~ N(0, chol_Q chol_Q^T), in the
    filter's time convention (step t predicts with u_t, then updates with y_t).

    Attributes:
        transition: ``f(x, u, theta) -> x'`` for one point, x (nx,), u (nu,), theta (np,),
            returning (nx,) in x's dtype.
        chol_Q: (nx, nx) lower-triangular Cholesky factor of the process-noise covariance Q
            (state units per step); None when Q is only positive semi-definite (no density).
    """

    transition: Callable[..., Any]
    chol_Q: Any


class Estimator(NamedTuple):
    """``Estimator(init, step)``: see the module docstring for the signatures.

    Attributes:
        init: builds the filter state from the prior.
        step: predicts with ``u`` then updates with ``y``; returns the new state and a StepOutput.
        nx: state dimension the filter estimates.
        param_names: names of the parameters it estimates (empty for state-only filters).
        name: short label used in tables and plots.
        needs_key: whether ``init`` needs a PRNG key (particle filters).
        param_prior: ``(theta0, P_theta0)`` in physical units, what ``run`` and ``filter`` use
            when the caller gives none; None when a parameter-estimating filter requires them.
        batch: optional runs-last form of ``step`` (module docstring); None to ``vmap`` it.
        ny: measurement width the filter expects (the model's outputs); None: not checked.
        nu: input width the filter expects (the model's inputs); None: not checked.
        bounds: ``(low, high)`` domains of the estimated parameters, two tuples of p floats in
            physical units with -inf / +inf for open ends; None: no domains.
        particle_transition: :class:`ParticleTransition`, set by a particle filter whose
            particles move by the model's transition plus Gaussian noise (``bootstrap_pf``),
            for backward simulation over its particles (:mod:`vehjax.smoothers.particle`);
            its state then has ``particles`` (nx, N), ``log_weights`` (N,), ``ancestors``
            (N,) and ``theta``. None for every other filter (and for a bootstrap PF with
            input noise, whose transition density is not that Gaussian).
        compiler_options: ``((name, value), ...)`` XLA options that :func:`vehjax.run` compiles
            this filter's studies with, where a filter measured them to be faster than XLA's
            defaults; a ``compiler_options`` given to ``run`` overrides them name by name.
            Empty: XLA's defaults. Under your own ``jax.jit``, pass
            ``compiler_options=dict(est.compiler_options)`` to get the same.
    """

    init: Callable[..., Any]
    step: Callable[..., tuple[Any, StepOutput]]
    nx: int
    param_names: tuple[str, ...] = ()
    name: str = "estimator"
    needs_key: bool = False
    param_prior: tuple | None = None
    batch: Callable | None = None
    ny: int | None = None
    nu: int | None = None
    bounds: tuple | None = None
    particle_transition: ParticleTransition | None = None
    compiler_options: tuple = ()


#: ``Estimator.compiler_options`` of the Gaussian, dual, joint, Liu-West and marginalized
#: filters: XLA:CPU's classic elemental emitter instead of its fusion emitters. Measured on the
#: 3-DOF user model of ``vehjax bench all`` (100 runs x 1000 steps, ad hoc A/B in one process):
#: compile times halve (EKF 3.9 -> 1.8 s, UKF 4.5 -> 2.4 s, CKF 4.4 -> 2.3 s, dual UKF 10.7 ->
#: 6.3 s), run times within the machine's noise (0.87-1.11x); the marginalized PF runs about
#: twice as fast (``vehjax bench marginalized`` prints both). Not the bootstrap PF, which runs
#: 1.2-1.3x slower with it. The EKF's runs-last step: compile 2.5-4.0 s against 3.3-4.9 s with
#: the fusion emitters, run time within noise (20 x 500 and 100 x 1000, alternated in one
#: process). On other platforms the option is ignored; an XLA that no longer knows it is
#: skipped (:func:`vehjax.run`).
ELEMENTAL_EMITTER = (("xla_cpu_use_fusion_emitters", False),)


def check_estimate(model, estimate) -> tuple[tuple[str, ...], tuple[int, ...]]:
    """Names of the parameters to estimate and their indices in ``model.param_names``.

    ``estimate`` is one name or a sequence of unique names of the model's parameters. Raises
    ValueError naming ``estimate`` when it is missing, empty, not strings, repeated or unknown.
    """
    from .. import _validate

    known = tuple(model.param_names)
    if estimate is None:
        raise ValueError(f"estimate: required, the names of the parameters to estimate from {known}")
    names = _validate.names("estimate", estimate, known)
    return names, tuple(known.index(n) for n in names)
