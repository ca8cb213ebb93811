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
* ``Estimator.runtime.batch`` (``est.batch``): ``batch(per_run_inputs: bool, dtype, default_theta: bool) ->
  Batch(prepare, step, prefetch)``, the same step for a whole batch of runs at once with the
  runs axis last in every leaf of the state, of y and of the StepOutput (see
  :mod:`vehjax.filters.runs_last`). ``prepare`` maps the whole input sequence, (T, nu) shared or
  (T, nu, R) when ``per_run_inputs``, to what the batch ``step`` takes in place of u at each
  time; ``dtype`` is the filter's float dtype and ``default_theta`` says that every run was
  started with ``theta0=None``. ``vehjax.run`` uses it instead of ``vmap``-ing ``step``. It is a
  field of ``Estimator.runtime``: ``est._replace(step=...)`` keeps it, so replace it by None too
  when the new step computes something else.
* ``Estimator.params.bounds`` (``est.bounds``): ``(low, high)``, two tuples of p Python floats (static under ``jit``),
  the domain of each estimated parameter in physical units (-inf / +inf for an open end), which
  the filter keeps its estimate in (:mod:`vehjax.lib.transforms`); None for state-only filters
  and filters without domains.
  :func:`vehjax.engine.finish` reads it to flag a run whose estimate sits on a bound
  (``at_bound``), and ``run`` to check ``theta0``.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax.numpy as jnp

from .. import validation


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


class GaussianSmoother(NamedTuple):
    """A Gaussian filter's own moments, what the smoothers of :mod:`vehjax.smoothing` need (the
    backward pass of the extended / unscented / cubature RTS, the parallel-in-time and iterated
    smoothers). All functions are pure and of one point; ``S`` below is the covariance P (n, n),
    or its lower Cholesky factor L when ``sqrt``; n = nx, or nx + p for a joint filter (state
    and unconstrained parameters).

    Attributes:
        split: ``split(state) -> (m (n,), S, aux)``: the filtered Gaussian held in a filter
            state and ``aux``, the pytree the filter's step runs with besides it (theta; the
            joint filters' random-walk covariance).
        predict: ``predict(m, S, u, aux)``: the step's prediction from N(m, S) with input u
            (nu,): ``(m- (n,), P- (n, n), C (n, n))``, C = Cov(x_t, x_{t+1}); when ``sqrt``
            ``(m-, L11, L21, L22)``, the lower factor [[L11, 0], [L21, L22]] of the joint
            covariance [[P-, C^T], [C, P]] of (x_{t+1}, x_t): L11 the factor of P-, L21 = C L11^-T,
            L22 that of P - C P-^-1 C^T, the covariance of x_t given x_{t+1}.
        measure: ``measure(m, S, u, aux) -> Measurement(y_hat, S_y, C_xy, H)``: the step's
            measurement moments at N(m, S), S_y with the measurement noise (H None for
            sigma points).
        taylor: the linearisation does not depend on the covariance (the EKF's Jacobians), so
            the smoothers may linearise with an identity covariance.
        sqrt: ``S`` is a Cholesky factor and ``predict`` returns the joint factor.
        report: ``report(m, P) -> (x (nx,), P_x (nx, nx), params (p,), params_cov (p, p))`` in
            physical units; None: the state is all of m (no parameters).
    """

    split: Callable[..., Any]
    predict: Callable[..., Any]
    measure: Callable[..., Any]
    taylor: bool = False
    sqrt: bool = False
    report: Callable[..., Any] | None = None


class Dims(NamedTuple):
    """What a filter's ``step`` and ``init`` expect, checked by ``run`` and ``filter`` against the
    data before tracing.

    Attributes:
        nx: state dimension; the width of ``StepOutput.mean`` and of ``x0``.
        ny: measurement width ``step`` expects (the model's outputs); None: not checked.
        nu: input width ``step`` expects (the model's inputs); None: not checked.
        n_theta: length of the model's parameter vector, which a state-only filter's ``theta0``
            replaces; None: a state-only filter takes no theta0 in ``run``.
        theta_domains: the model's :class:`vehjax.models.domains.ParamDomains`, which a
            state-only filter's ``theta0`` must lie in; None: not checked.
    """

    nx: int
    ny: int | None = None
    nu: int | None = None
    n_theta: int | None = None
    theta_domains: Any = None


class ParamSpec(NamedTuple):
    """The parameters a filter estimates besides the state (empty for state-only filters).

    Attributes:
        names: names of the p parameters (``StepOutput.params`` (p,)); ``run``, ``filter`` and
            the results read them.
        prior: ``(theta0 (p,), P_theta0 (p, p))`` in physical units that ``run`` and ``filter``
            use when the caller gives none; None: the caller must give them.
        bounds: ``(low, high)``, two tuples of p floats in physical units (-inf / +inf open),
            which the filter keeps its estimate in; ``run`` checks ``theta0`` against them and
            flags runs whose estimate sits on one (``at_bound``). None: no domains.
    """

    names: tuple[str, ...] = ()
    prior: tuple | None = None
    bounds: tuple | None = None


class Runtime(NamedTuple):
    """How the filter is run, for ``run`` and the execution seam (:mod:`vehjax.execution`).

    Attributes:
        needs_key: ``init`` requires a PRNG key (the particle filters); ``run`` and ``filter``
            refuse a call without one, and :mod:`vehjax.tune` differentiates such a filter with
            stop-gradient resampling.
        batch: optional runs-last form of ``step`` (module docstring), used by ``run`` where the
            strategy says so instead of ``vmap``-ing ``step``; it must give what ``step`` gives
            run by run, to rounding (``tests/_contract.py`` checks it). None: ``run`` vmaps.
        workload: what the step computes, from which the execution seam picks platform options:
            "default", "small_dense" (many small dense operations) or "particles" (long vectors
            over particles). It states no platform rule itself.
    """

    needs_key: bool = False
    batch: Callable | None = None
    workload: str = "default"


class Backward(NamedTuple):
    """The forms a backward pass (:func:`vehjax.smooth`, :mod:`vehjax.smoothers`) reads; None
    where the filter has none.

    Attributes:
        smoother: :class:`GaussianSmoother`, the Gaussian filter's own prediction and
            measurement moments (EKF, UKF, CKF, their square-root forms, the joint filters).
        particle_transition: :class:`ParticleTransition` of a particle filter whose particles
            move by the model's transition plus Gaussian noise (``bootstrap_pf``), for backward
            simulation; its state has ``particles`` (nx, N), ``log_weights`` (N,),
            ``ancestors`` (N,) and ``theta``.
        rao_blackwell: :class:`vehjax.filters.marginalized.RBTransition` of the marginalized PF
            (each particle's Gaussian prediction given its offset draw); its state has
            ``offset`` and ``ancestors``.
    """

    smoother: GaussianSmoother | None = None
    particle_transition: ParticleTransition | None = None
    rao_blackwell: Any = None


class Estimator(NamedTuple):
    """``Estimator(init, step, Dims(nx))``: see the module docstring for the signatures.

    Each field is part of the contract between a filter's builder and what runs it; the
    optional parts are grouped in small records, whose fields read through as attributes
    (``est.nx``, ``est.param_names``, ``est.needs_key``, ``est.smoother``, ...).

    Attributes:
        init: ``init(x0, P0, theta0=None, P_theta0=None, key=None) -> state``: the filter state
            (a pytree of arrays) from the prior, x0 (nx,), P0 (nx, nx); its dtype sets the
            filter's. Must raise ValueError naming the argument for a wrong shape, and for a
            missing ``key`` when ``needs_key``. Read by :func:`vehjax.filter`, :func:`vehjax.run`
            (vmapped over runs), :func:`vehjax.smooth`.
        step: ``step(state, y, u) -> (state, StepOutput)``: predicts with u (nu,), then updates
            with y (ny,), NaN components missing. Pure and traceable (``jit``, ``vmap``,
            ``grad``); the StepOutput has the shapes its class documents (checked by
            ``vehjax.filtering`` when traced). Read by everything that runs a filter.
        dims: :class:`Dims`, the widths ``init`` and ``step`` expect.
        name: short label for tables, plots, messages and the multi-process consistency digest
            of ``run``; not a key to any behaviour.
        params: :class:`ParamSpec`, the parameters estimated besides the state.
        runtime: :class:`Runtime`, how ``run`` executes it (key, runs-last form, workload).
        backward: :class:`Backward`, the forms the smoothers read.

    ``est._replace(step=...)`` keeps ``runtime.batch``: replace it too when the new step computes
    something else (``est._replace(step=s, runtime=est.runtime._replace(batch=None))``).
    """

    init: Callable[..., Any]
    step: Callable[..., tuple[Any, StepOutput]]
    dims: Dims
    name: str = "estimator"
    params: ParamSpec = ParamSpec()
    runtime: Runtime = Runtime()
    backward: Backward = Backward()

    nx = property(lambda self: self.dims.nx, doc="``dims.nx``")
    ny = property(lambda self: self.dims.ny, doc="``dims.ny``")
    nu = property(lambda self: self.dims.nu, doc="``dims.nu``")
    n_theta = property(lambda self: self.dims.n_theta, doc="``dims.n_theta``")
    theta_domains = property(lambda self: self.dims.theta_domains, doc="``dims.theta_domains``")
    param_names = property(lambda self: self.params.names, doc="``params.names``")
    param_prior = property(lambda self: self.params.prior, doc="``params.prior``")
    bounds = property(lambda self: self.params.bounds, doc="``params.bounds``")
    needs_key = property(lambda self: self.runtime.needs_key, doc="``runtime.needs_key``")
    batch = property(lambda self: self.runtime.batch, doc="``runtime.batch``")
    workload = property(lambda self: self.runtime.workload, doc="``runtime.workload``")
    smoother = property(lambda self: self.backward.smoother, doc="``backward.smoother``")
    particle_transition = property(lambda self: self.backward.particle_transition,
                                   doc="``backward.particle_transition``")
    rao_blackwell = property(lambda self: self.backward.rao_blackwell,
                             doc="``backward.rao_blackwell``")


def check_estimate(model, estimate) -> tuple[tuple[str, ...], tuple[int, ...]]:
    """Names of the parameters to estimate and their indices in ``model.param_names``.

    ``estimate`` is one name or a sequence of unique names of the model's parameters. Raises
    ValueError naming ``estimate`` when it is missing, empty, not strings, repeated or unknown.
    """
    known = tuple(model.param_names)
    if estimate is None:
        raise ValueError(f"estimate: required, the names of the parameters to estimate from {known}")
    names = validation.names("estimate", estimate, known)
    return names, tuple(known.index(n) for n in names)
