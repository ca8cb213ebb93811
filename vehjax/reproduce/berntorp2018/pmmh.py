"""Paper 004's offline reference (sec. 5, ref. [28]): particle marginal Metropolis-Hastings and
particle Gibbs on the planar model of :func:`vehjax.models.bank_scale.offset_scale_model` over
the drive's first ``--pmmh-duration`` s.

Steering offset, eps, ay and gyro biases, the three sensor stds and the steering-noise std, with
the bootstrap PF's likelihood, the marginalized PF's (``mpf``: paper 004's filter with its noise
statistics held at the chain's values by a prior of negligible spread and no forgetting, every
state in each particle's Kalman filter and the steering noise in the transition only, so it
estimates the same model's likelihood without bias: :func:`vehjax.calibrate.fixed_noise_mpf`)
and (the reference) the exact Kalman likelihood of this linear model; chains vmapped, split R-hat
and ESS reported, and the MPF chain's posterior against the exact one's. Beside them particle
Gibbs with ancestor sampling (ref. [29], :func:`vehjax.calibrate.particle_gibbs`): a trajectory
from the conditional PF, then random-walk moves of the values given it. It takes additive noise
only, so the steering noise becomes per-state process stds of vy and r (:func:`pg_process_std`,
their correlation dropped) with priors of their own (:func:`pg_priors`); its moves are
:data:`PG_STEP` of each prior's scale, since given a whole trajectory the values are known far
better than the PMMH likelihood tells them. ``cpm``: the bootstrap PF's likelihood with
correlated random numbers (correlated pseudo-marginal, Deligiannidis, Doucet & Pitt 2018;
``pmmh(Correlated(bootstrap_pf, PMMH_CORRELATION))``), at the bootstrap chain's N and iterations.

Every sampler adapts its random walk over the warm-up (:func:`vehjax.calibrate.pmmh`: windows of
doubling length, the pooled draws' covariance and a scale tuned toward the optimal acceptance)
and runs :data:`PMMH_ITERS` iterations by default, the exact-likelihood chain first; the
bootstrap and marginalized PFs' log-likelihood stds are measured at that chain's posterior mean
(:func:`vehjax.calibrate.log_likelihood_spread`) and set their acceptance targets. Measurements
behind the defaults: ``benchmarks/results/notes_berntorp2018.md``.
"""

from __future__ import annotations

import functools
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from vehjax import calibrate
from vehjax.studies.banked_road import DEG, RVIRT_STD
from vehjax.calibrate import LogNormal, Normal
from vehjax.filters import bootstrap_pf, gaussian
from vehjax.models.bank_scale import offset_scale_model

#: the offline reference's model (the planar model with the steering offset and eps as
#: parameters); kept under the study's name
pmmh_model = offset_scale_model


def pmmh_priors():
    """The offline reference's priors, SI units: steering offset N(0, (0.5 deg)^2), eps
    N(0, 1e-3^2), ay bias N(0, 0.5^2) m/s^2, gyro bias N(0, (0.5 deg/s)^2), and log-normal
    (sigma 1, i.e. a factor e either way) stds: ay 0.3 m/s^2, gyro 0.3 deg/s, r_virt 0.5 deg/s
    (the paper's value), steering 0.1 deg."""
    return {"delta_offset": Normal(0.0, 0.5 * DEG), "eps": Normal(0.0, 1e-3),
            "bias[ay]": Normal(0.0, 0.5), "bias[r]": Normal(0.0, 0.5 * DEG),
            "R[ay]": LogNormal(0.3, 1.0), "R[r]": LogNormal(0.3 * DEG, 1.0),
            "R[r_virt]": LogNormal(RVIRT_STD, 1.0), "input[delta]": LogNormal(0.1 * DEG, 1.0)}


#: Units and scale of the PMMH quantities in the report.
PMMH_UNITS = {"delta_offset": ("deg", DEG), "eps": ("1e-4", 1e-4), "bias[ay]": ("m/s^2", 1.0),
              "bias[r]": ("deg/s", DEG), "R[ay]": ("m/s^2", 1.0), "R[r]": ("deg/s", DEG),
              "R[r_virt]": ("deg/s", DEG), "input[delta]": ("deg", DEG),
              "Q[vy]": ("m/s", 1.0), "Q[r]": ("deg/s", DEG)}
PMMH_Q = np.array([0.01, 0.01 * DEG]) ** 2  # vy [m/s], r [rad/s] per step
PMMH_P0 = np.array([0.1, 0.5 * DEG]) ** 2


#: the offline samplers' names in logs and tables, by --pmmh-likelihood value
SAMPLER = {"bootstrap": "PMMH (bootstrap PF likelihood)", "kalman": "PMMH (Kalman likelihood)",
           "mpf": "PMMH (marginalized PF likelihood)",
           "cpm": "correlated PMMH (bootstrap PF likelihood)",
           "pg": "particle Gibbs (ancestor sampling)"}


#: particle Gibbs's random-walk moves of the values given the trajectory: std as a fraction of
#: each prior's scale (unconstrained units), and moves per sweep
PG_STEP, PG_MOVES = 0.01, 5


def pg_process_std(pm, U, steer_std):
    """Per-state process stds (vy [m/s], r [rad/s]) that particle Gibbs uses in place of the
    steering-input noise (it takes additive noise only): PMMH_Q plus the diagonal of
    B steer_std^2 B^T, B = d f / d delta at the drive's mean inputs and zero state. The
    correlation the input noise gives between vy and r is dropped (an approximation)."""
    B = jax.jacfwd(lambda u: pm.transition(jnp.zeros(2), u, jnp.asarray(pm.theta)))(
        jnp.asarray(np.nanmean(np.asarray(U, float), axis=0)))[:, 1]
    return np.sqrt(PMMH_Q + (np.asarray(B) * steer_std) ** 2)


def pg_priors(pm, U):
    """Particle Gibbs's priors: :func:`pmmh_priors` with the steering-input std replaced by
    log-normal (sigma 1) process stds of vy and r centred on :func:`pg_process_std` at the
    input prior's centre (0.1 deg)."""
    pr = {k: v for k, v in pmmh_priors().items() if not k.startswith("input[")}
    q = pg_process_std(pm, U, 0.1 * DEG)
    return {**pr, "Q[vy]": LogNormal(float(q[0]), 1.0), "Q[r]": LogNormal(float(q[1]), 1.0)}


def _pg_init(pm, U, init):
    """PMMH's starting values for particle Gibbs: the steering-input std, if given, replaced by
    the process stds it stands for (:func:`pg_process_std`)."""
    if init is None:
        return None
    init = dict(init)
    steer = init.pop("input[delta]", None)
    if steer is not None:
        init["Q[vy]"], init["Q[r]"] = map(float, pg_process_std(pm, U, steer))
    return init


#: the offline samplers' default iterations per chain (half warm-up) and particles: the
#: exact-likelihood chain's so that it mixes on the first 20 s of the drive (split R-hat < 1.1,
#: ESS >= 100 for every quantity); the bootstrap PF's likelihood is too noisy there for that at
#: any affordable N (its std is measured and reported), and particle Gibbs's sweeps (a
#: conditional PF over the whole segment each) keep their earlier cost; the report says
#: whether each mixed. The marginalized PF's (mpf) N = 256 brings its log-likelihood std near
#: 2 nats on that segment; at 4 x 400 iterations its chain does not mix, so the report marks it
#: not yet a posterior (measurements: benchmarks/results/notes_berntorp2018.md)
PMMH_ITERS = {"kalman": 4000, "mpf": 400, "bootstrap": 200, "pg": 200, "cpm": 200}
PMMH_PARTICLES = {"mpf": 256, "bootstrap": 64, "pg": 64, "cpm": 64}
#: the correlated chain (cpm: :func:`vehjax.calibrate.pmmh` of a ``Correlated``): the
#: Crank-Nicolson move's rho, and the bootstrap chain's particles and iterations (to compare
#: the two at the same cost). With the 2-state model the particles are Hilbert-sorted
#: (:mod:`vehjax.calibrate.correlated`); the report gives the measured std of the log-likelihood difference the
#: chain's acceptance ratio sees, beside the independent estimates'. It keeps 0.5-0.7 of two
#: independent estimates' difference whatever rho and N (notes_berntorp2018.md), so the chain
#: does not mix better than the independent one and is not in the default (``standard``)
PMMH_CORRELATION = 0.999
#: the lowest acceptance rate the bootstrap chain's scale is tuned toward (Sherlock, Thiery,
#: Roberts & Rosenthal 2015's overall optimum)
PMMH_MIN_TARGET = 0.07


def run_pmmh(model, Y, U, *, iters=None, particles=None, chains=4, key, likelihood="bootstrap",
             init=None, spread_at=None, spread_evals=32, proposal_cov=None):
    """PMMH over :func:`pmmh_priors` on one drive (Y (T, 5) SingleTrackBank's measurements,
    raw r_virt; U (T, 2)), half the iterations warm-up. ``likelihood``: "bootstrap"
    (:func:`vehjax.filters.bootstrap_pf` with ``particles``, the particle-MCMC reference) or
    "kalman" (the EKF, exact on this linear model: plain Metropolis-Hastings, a check of the
    particle chain) or "mpf" (:func:`vehjax.calibrate.fixed_noise_mpf`: paper 004's
    marginalized PF with ``particles``, its noise statistics held at the chain's values, on
    the same model as the EKF's: an unbiased estimate of the same likelihood) or "pg":
    particle Gibbs with ancestor sampling
    (:func:`vehjax.calibrate.particle_gibbs`, paper 004's ref. [29]; conditional PF with
    ``particles``; the steering noise as additive process noise, :func:`pg_priors`) or "cpm":
    the bootstrap PF's likelihood with correlated random numbers (correlated pseudo-marginal,
    ``correlation`` :data:`PMMH_CORRELATION`; with ``spread_at`` the std of the log-likelihood
    difference under the Crank-Nicolson move is measured too, ``info["loglik_diff_std"]``, and
    the scale tuned toward the acceptance rate for that noise over sqrt(2)).
    ``init``: starting values by name (physical units), default the priors' centres.
    ``proposal_cov``: the PMMH random walk's starting covariance (unconstrained units, e.g.
    the exact chain's ``proposal_cov``), default 0.1 of each prior's scale.
    ``iters``, ``particles``: default :data:`PMMH_ITERS`, :data:`PMMH_PARTICLES`. A particle
    chain (bootstrap, mpf) first measures its log-likelihood estimate's std over ``spread_evals`` keys at
    ``spread_at`` (values by name; None: not measured; :func:`vehjax.calibrate.
    log_likelihood_spread`) and tunes its scale toward the acceptance rate for that noise
    (:func:`vehjax.calibrate.target_acceptance`). Returns (:class:`vehjax.calibrate.
    PMMHResult`, seconds, info: dict with iters, particles and, for the particle
    likelihoods with ``spread_at``, loglik_std, the estimate's std [nats])."""
    pm = pmmh_model(model)
    R0 = np.array([0.3, 0.3 * DEG, RVIRT_STD]) ** 2
    iters = PMMH_ITERS[likelihood] if iters is None else iters
    particles = PMMH_PARTICLES.get(likelihood, 0) if particles is None else particles
    info = {"iters": iters, "particles": particles if likelihood != "kalman" else None}
    if likelihood == "pg":
        init = _pg_init(pm, U, init)
        priors = pg_priors(pm, U)
        # given a whole trajectory the values are known far better than a PMMH step's scale
        # (0.1 of each prior's): moves of PG_STEP of the prior's scale, PG_MOVES per sweep
        step = [PG_STEP * p.scale for p in priors.values()]
        t0 = time.perf_counter()
        res = calibrate.particle_gibbs(
            pm, Y[:, [0, 1, 4]], U, x0=np.zeros(2), P0=PMMH_P0, Q=np.diag(PMMH_Q), R=R0,
            priors=priors, key=key, sweep=calibrate.Sweep(n_particles=particles, moves=PG_MOVES),
            chains=calibrate.Chains(n=chains, samples=iters - iters // 2, warmup=iters // 2,
                                    init=init),
            proposal=calibrate.RandomWalk(std=step))
        return res, time.perf_counter() - t0, info
    corr = PMMH_CORRELATION if likelihood == "cpm" else None
    if corr is not None:
        info["correlation"] = corr
    if likelihood in ("bootstrap", "cpm"):
        builder = functools.partial(bootstrap_pf, n_particles=particles)
    elif likelihood == "mpf":
        builder = functools.partial(calibrate.fixed_noise_mpf, n_particles=particles)
    else:
        builder = gaussian.ekf
    t0 = time.perf_counter()
    priors = pmmh_priors()
    target = None
    if likelihood in ("bootstrap", "mpf", "cpm"):
        at = spread_at
        if at is not None and corr is not None:
            info["loglik_diff_std"], info["loglik_std"] = \
                calibrate.log_likelihood_difference_spread(
                    calibrate.Correlated(builder, corr), pm, Y[:, [0, 1, 4]], U, x0=np.zeros(2),
                    P0=PMMH_P0, Q=PMMH_Q, R=R0, values={k: at[k] for k in priors},
                    key=jax.random.fold_in(key, 2015), n_evals=spread_evals)
            # the ratio's noise is the difference's: as an estimate of std s / sqrt(2)'s
            target = max(calibrate.target_acceptance(
                len(priors), info["loglik_diff_std"] / math.sqrt(2.0)), PMMH_MIN_TARGET)
        elif at is not None:
            info["loglik_std"], _ = calibrate.log_likelihood_spread(
                builder, pm, Y[:, [0, 1, 4]], U, x0=np.zeros(2), P0=PMMH_P0, Q=PMMH_Q, R=R0,
                values={k: at[k] for k in priors}, key=jax.random.fold_in(key, 2015),
                n_evals=spread_evals)
            # at most Sherlock et al.'s 7 % (their optimum, at a std of 1.8): a noisier
            # estimate would ask for an acceptance near 0 and a scale without bound
            target = max(calibrate.target_acceptance(len(priors), info["loglik_std"]),
                         PMMH_MIN_TARGET)
    res = calibrate.pmmh(
        builder if corr is None else calibrate.Correlated(builder, corr), pm, Y[:, [0, 1, 4]], U,
        x0=np.zeros(2), P0=PMMH_P0, Q=PMMH_Q, R=R0, priors=priors, key=key,
        chains=calibrate.Chains(n=chains, samples=iters - iters // 2, warmup=iters // 2,
                                init=init),
        proposal=calibrate.RandomWalk(cov=proposal_cov,
                                      adaptation=calibrate.Adaptation(acceptance=target)))
    info["acceptance_target"] = target if target is not None else \
        calibrate.target_acceptance(len(priors))
    return res, time.perf_counter() - t0, info


#: --pmmh-likelihood's groups of samplers, in the order they run (the exact chain first)
SAMPLER_GROUPS = {"both": ("kalman", "bootstrap"), "standard": ("kalman", "bootstrap", "pg"),
                  "all": ("kalman", "mpf", "bootstrap", "cpm", "pg")}


def chain_start(d, Es, Pm, names, stop):
    """The chains' starting values: the online estimates (the EKF's smoothed offset and biases,
    the causal eps at the segment's end, the MPF's stds, r_virt's residual std): a short
    warm-up."""
    return {"delta_offset": float(Es[0, 2]), "eps": float(d["eps_rls"][stop - 1]),
            "bias[ay]": float(Es[0, 3]), "bias[r]": float(Es[0, 4]),
            "R[ay]": float(Pm[:, -1, names.index("ay_std")].mean()),
            "R[r]": float(Pm[:, -1, names.index("r_std")].mean()), "R[r_virt]": d["rvirt_sd"],
            "input[delta]": float(Pm[:, -1, names.index("delta_std")].mean())}


def run_samplers(args, d, Es, Pm, names, log=print):
    """The drive's offline reference: each sampler of ``--pmmh-likelihood`` on the first
    ``--pmmh-duration`` s of the raw r_virt (``d`` from the drive study's ``load_drive``), the
    exact-likelihood chain first: its posterior mean is where the particle likelihoods'
    noise is measured, and its adapted random walk starts the MPF chain's (a pilot run).
    Returns {likelihood: (PMMHResult, seconds, steps, info)}."""
    model, T, U = d["model"], d["T"], d["U"]
    pm_res = {}
    choice = getattr(args, "pmmh_likelihood", "both")
    for lik in SAMPLER_GROUPS.get(choice, (choice,)):
        if getattr(args, "pmmh_iters", None) == 0:
            break
        seg = slice(0, min(T, int(round(args.pmmh_duration / model.dt))))
        init = chain_start(d, Es, Pm, names, seg.stop)
        at = None
        if lik in ("bootstrap", "mpf", "cpm") and "kalman" in pm_res:
            at = dict(zip(pm_res["kalman"][0].names, map(float, pm_res["kalman"][0].mean)))
        cov0 = pm_res["kalman"][0].proposal_cov if lik == "mpf" and "kalman" in pm_res \
            else None
        r_, sec, info = run_pmmh(model, d["Y_raw"][seg], U[seg],
                                 iters=getattr(args, "pmmh_iters", None),
                                 particles=getattr(args, "pmmh_particles", None),
                                 chains=args.pmmh_chains, key=jax.random.key(args.seed + 7),
                                 likelihood=lik, init=init, spread_at=at, proposal_cov=cov0)
        pm_res[lik] = (r_, sec, seg.stop, info)
        log(f"{SAMPLER[lik]}: {args.pmmh_chains} chains x {info['iters']} iterations over "
            f"{seg.stop} steps, {sec:.1f} s (compile included), max split R-hat "
            f"{np.max(r_.rhat):.3f}, min ESS {np.min(r_.ess):.0f}"
            + (f", log-likelihood std {info['loglik_std']:.2f} at "
               + ("the Kalman chain's posterior mean" if at else "the starting values")
               if "loglik_std" in info else ""))
    return pm_res
