"""The marginalized PF's likelihood with its noise statistics held fixed: a builder for PMMH.

:func:`fixed_noise_mpf` is paper 004's marginalized PF (Berntorp & Di Cairano,
:func:`vehjax.filters.marginalized_pf` with ``kalman_states="all"``) with its noise statistics
held at the chain's values: each particle a sequence of input-noise draws with a Kalman filter
over every state given them, whose likelihood estimate varies far less than the bootstrap PF's
where the model is affine in the states.
"""

from __future__ import annotations

from typing import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from .. import validation
from ..filters import NiW, Resampling, marginalized_pf, smc
from ..filters.base import Dims, Estimator, Runtime, StepOutput
from ..models import Model

__all__ = ["FIXED_GAMMA0", "FIXED_NU0", "fixed_noise_mpf"]


#: :func:`fixed_noise_mpf`'s NiW prior: gamma0 (the offset's and biases' prior variance over the
#: noise variance) and nu0 (degrees of freedom), so small and so large that the statistics stay
#: at the given values over a drive (forgetting 1: a datum moves gamma by a relative 1e-12 and a
#: covariance by about 1 / nu0 of itself); the Student-t predictive is then Gaussian to ~1 / nu0.
FIXED_GAMMA0, FIXED_NU0 = 1e-12, 1e8


def _fixed_noise_model(model, noisy_input: str):
    """The model :func:`fixed_noise_mpf` runs the marginalized PF on: states ``("_const",) +
    model.state_names`` (a constant, unobserved first state: the filter needs a particle
    state; every model state is a Kalman state), inputs ``model.input_names + ("_<input>_h",)
    + model.param_names``: the noisy input enters the transition, its noise-free copy the
    observation (so the input noise is process noise only, as the Gaussian filters'
    ``input_noise``), and the model's parameters arrive as inputs (they may be traced values
    of a PMMH chain). No parameters of its own."""
    nu = len(model.input_names)
    i = model.input_names.index(noisy_input)

    def f(X, U, th):
        del th
        return jnp.concatenate([X[:1], model.transition(X[1:], U[:nu], U[nu + 1:])])

    def h(X, U, th):
        del th
        return model.observe(X[1:], U[:nu].at[i].set(U[nu]), U[nu + 1:])

    return Model(f, h, model.dt, ("_const",) + tuple(model.state_names),
                 input_names=tuple(model.input_names) + (f"_{noisy_input}_h",)
                 + tuple(f"_theta_{n}" for n in model.param_names),
                 output_names=tuple(model.output_names), fast_math=False)


def _fixed_noise_filter(aug, n_particles, name, q_std, resampling):
    """:func:`vehjax.filters.marginalized_pf` on :func:`_fixed_noise_model`'s ``aug`` with
    the statistics held (placeholder stds 1: :func:`fixed_noise_mpf`'s ``init`` sets them)."""
    states = aug.state_names[1:]
    return marginalized_pf(
        aug, n_particles, noisy_input=name, sensors=tuple(aug.output_names),
        linear_states=states, Q=q_std ** 2,
        niw=NiW(std0={k: 1.0 for k in (name,) + tuple(aug.output_names)}, forgetting=1.0,
                gamma0=FIXED_GAMMA0, nu0=FIXED_NU0), kalman_states="all",
        resampling=resampling)


def fixed_noise_mpf(model, Q, R, *, input_noise, n_particles: int = 100,
                    resampling: Resampling = Resampling()):
    """A builder for :func:`pmmh` / :func:`log_likelihood_fn`: the marginalized PF of paper 004
    (:func:`vehjax.filters.marginalized_pf`, ``kalman_states="all"``) with its noise statistics
    fixed at the given values, as a state-only estimator of ``model``'s states.

    Model: x_t = f(x_{t-1}, u_t + w_t, theta) + v_t, y_t = h(x_t, u_t, theta) + e_t, with
    w_t ~ N(0, s^2) on the one input named in ``input_noise`` (s its std, input units),
    v_t ~ N(0, diag Q), e_t ~ N(0, diag R): the model of a Gaussian filter given the same Q, R
    and ``input_noise`` (exact for it where f and h are affine in x and u). Every model state is
    in each particle's Kalman filter; a particle is a sequence of input-noise draws w_1:t, each
    drawn from its conditional given y_t, weighted by the predictive of y_t given the
    particle's past (a fully adapted, Rao-Blackwellised PF): its likelihood estimate is
    unbiased, with far less variance than the bootstrap PF's. The NiW statistics start at
    offset 0, biases 0, the stds s and sqrt(diag R), with gamma0, nu0 =
    :data:`FIXED_GAMMA0`, :data:`FIXED_NU0` and forgetting 1, so they stay there.

    Args:
        model: a vehjax model affine in its states and in the noisy input (the filter checks).
        Q: (nx,) variances or (nx, nx) (its diagonal is used) per step, concrete (not
            calibrated: ``Q[...]`` priors are refused).
        R: (ny,) variances or (ny, ny) (its diagonal is used: the outputs' noises independent).
        input_noise: dict with one entry, input name -> std [input units] (may be traced).
        n_particles, resampling: as :func:`vehjax.filters.marginalized_pf` (``resampling`` a
            :class:`vehjax.filters.Resampling`).

    Returns:
        ``Estimator``: state-only (``theta0`` replaces the model's parameters), ``needs_key``.
    """
    n_particles = smc.check_n_particles(n_particles)
    if not isinstance(input_noise, Mapping) or len(input_noise) != 1:
        raise ValueError(f"input_noise: expected one input name -> std, got {input_noise!r}")
    (name, s_u), = input_noise.items()
    if name not in model.input_names:
        raise ValueError(f"input_noise: {name!r} not among the inputs {model.input_names}")
    try:
        Qd = np.asarray(Q, float)
    except jax.errors.TracerArrayConversionError:
        raise ValueError("Q: fixed_noise_mpf takes a fixed Q (its values set the Kalman "
                         "filters' noise when built); drop the 'Q[...]' priors") from None
    Qd = np.asarray(validation.cov("Q", Qd, len(model.state_names), allow_psd=True), float)
    q_std = np.sqrt(np.diag(Qd) if Qd.ndim == 2 else Qd)
    R = jnp.asarray(validation.cov("R", R, len(model.output_names)), float)
    r_std = jnp.sqrt(jnp.diag(R) if R.ndim == 2 else R)
    aug = _fixed_noise_model(model, name)
    ny, nx = len(model.output_names), len(model.state_names)
    # built from concrete values only (its model checks run numerically), also when the
    # builder is called under a PMMH chain's trace
    with jax.ensure_compile_time_eval():
        mpf = _fixed_noise_filter(aug, n_particles, name, q_std, resampling)
    i_u = model.input_names.index(name)
    theta_model = jnp.asarray(model.theta, float)

    def init(x0, P0, theta0=None, P_theta0=None, key=None):
        del P_theta0
        x0 = jnp.asarray(x0, float)
        P0 = jnp.asarray(P0, float)
        P0 = jnp.diag(P0) if P0.ndim == 1 else P0
        Pa = jnp.zeros((nx + 1, nx + 1)).at[0, 0].set(1.0).at[1:, 1:].set(P0)
        stats = jnp.concatenate([jnp.stack([0.0, jnp.asarray(s_u, float)]), jnp.zeros(ny),
                                 r_std])
        th = theta_model if theta0 is None else jnp.asarray(theta0, float)
        return mpf.init(jnp.concatenate([jnp.zeros(1), x0]), Pa, stats, None, key), th

    def step(state, y, u):
        st, th = state
        st, out = mpf.step(st, y, jnp.concatenate([u, u[i_u:i_u + 1], th]))
        return (st, th), StepOutput(
            mean=out.mean[1:], cov=out.cov[1:, 1:], loglik=out.loglik, nis=out.nis,
            n_obs=out.n_obs, params=jnp.zeros((0,), out.mean.dtype),
            params_cov=jnp.zeros((0, 0), out.mean.dtype), reinit=out.reinit)

    return Estimator(
        init=init,
        step=step,
        name="fixed_noise_mpf",
        dims=Dims(nx=nx, ny=ny, nu=len(model.input_names), n_theta=len(model.param_names)),
        runtime=Runtime(needs_key=True, workload="small_dense"),
    )
