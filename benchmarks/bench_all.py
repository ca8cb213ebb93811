"""Every filter family against its fastest peer: one table, one user-written model, float64, CPU.

The model is the 3-DOF dual-track vehicle (states vx, vy, r; inputs four wheel slips and the
steering angle; RK4 at dt = 0.01 s; H = I), written the way a user would, with ``jnp.arctan2``,
``jnp.sin`` and ``jnp.cos``: vehjax gets it as ``vehjax.models.Model(transition=f, observe=h,
...)``, every JAX peer gets the very same Python function ``f`` (with theta bound). The data:
``--runs`` simulated runs of a sine-steer manoeuvre at 20 m/s (``vehjax.simulate`` on
``Dynamic3DOF``, the same equations), per-run measurements, shared inputs.

Rows (each peer through its public API, ``jax.vmap`` over runs, ``jax.jit``-compiled ahead):

    ekf       vehjax ``filters.ekf``   vs dynamax ``extended_kalman_filter``, cuthbert's Taylor
              filter (``cuthbert.gaussian.taylor.build_filter`` + ``cuthbert.filter``)
    ukf       vehjax ``filters.ukf``   vs dynamax ``unscented_kalman_filter``, kalman-py's JAX
              backend UKF, filterpy ``UnscentedKalmanFilter`` (a Python loop: timed on
              ``--filterpy-runs`` runs and extrapolated)
    pf        vehjax ``filters.bootstrap_pf`` vs cuthbert ``smc.particle_filter`` (its
              ``filter_prepare``/``filter_combine`` in a scan keeping the weighted mean, as
              ``bench particle``'s "cuthbert scan"), smcx ``bootstrap_filter``; particles
              (0.4) is not installable beside jax 0.10 (it needs numpy < 2)
    liu_west  vehjax ``filters.liu_west_ukf`` vs smcx ``liu_west_filter``: different
              algorithms (see the row note); compared per particle-step at the same count

vehjax runs through its public ``vehjax.compile_run`` (compile apart) and is timed calling the
compiled study, which includes copying the results to host memory. Estimates are checked before
any timing: Gaussian filters equal to ``--tol`` (max abs difference of the filtered means);
particle filters, whose random streams differ, by their state RMSE against the true states
(each within 25 % of the best; Liu-West: each below the raw measurements' RMSE). Timing is
interleaved (one call of each contender per round, ``--repeat`` rounds, best kept), so that a
change in machine load hits all alike.

    vehjax bench all                      # or: python benchmarks/bench_all.py
    vehjax bench all --runs 2 --steps 30 --particles 50 --repeat 1 --rows ekf,pf
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import time
from importlib.metadata import PackageNotFoundError, version

import jax
import jax.numpy as jnp
import numpy as np

import vehjax as vj

ROWS = ("ekf", "ukf", "pf", "liu_west")
ALPHA, BETA, KAPPA = 1.0, 2.0, 0.0
ESS_THRESHOLD = 0.5
SHRINKAGE = 0.98
ESTIMATE = ("m", "cx", "cy")  # the Liu-West row's parameters
TARGET = 0.5

# -- the user's model: plain jax.numpy, nothing vehjax-specific -------------------------------

DT = 0.01
PARAM_NAMES = ("m", "cx", "cy", "lf", "lr", "iz", "ca")
THETA = np.array([1700.0, 1.5e5, 4.0e4, 1.5, 1.5, 1700.0 * 1.5**2, 0.5])


def _rhs(x, u, th):
    vx, vy, r = x[0], x[1], x[2]
    m, cx, cy, lf, lr, iz, ca = (th[i] for i in range(7))
    delta = u[4]
    alpha_f = delta - jnp.arctan2(vy + lf * r, vx)
    alpha_r = -jnp.arctan2(vy - lr * r, vx)
    fx_front = cx * (u[0] + u[1])
    fx_rear = cx * (u[2] + u[3])
    fy_front = 2.0 * cy * alpha_f
    fy_rear = 2.0 * cy * alpha_r
    c, s = jnp.cos(delta), jnp.sin(delta)
    fx = fx_front * c - fy_front * s + fx_rear - ca * vx * vx
    fy = fx_front * s + fy_front * c + fy_rear
    mz = lf * (fx_front * s + fy_front * c) - lr * fy_rear
    return jnp.stack([vy * r + fx / m, -vx * r + fy / m, mz / iz])


def transition(x, u, th):
    """One RK4 step of the 3-DOF dual-track model."""
    k1 = _rhs(x, u, th)
    k2 = _rhs(x + 0.5 * DT * k1, u, th)
    k3 = _rhs(x + 0.5 * DT * k2, u, th)
    k4 = _rhs(x + DT * k3, u, th)
    return x + DT / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def observe(x, u, th):
    return x


def user_model():
    return vj.models.Model(transition=transition, observe=observe, dt=DT,
                           state_names=("vx", "vy", "r"), param_names=PARAM_NAMES,
                           input_names=("s_fl", "s_fr", "s_rl", "s_rr", "delta"),
                           output_names=("vx", "vy", "r"), theta=THETA)


def _problem(runs: int, steps: int):
    truth_model = vj.models.Dynamic3DOF(dt=DT, theta=THETA)
    scn = vj.scenarios.sine_steer(truth_model, speed=20.0, amplitude=0.05, frequency=0.5,
                                  duration=steps * DT)
    Q = np.diag([0.05, 0.05, 0.01]) ** 2
    R = np.diag([0.2, 0.2, 0.05]) ** 2
    sim = vj.simulate(truth_model, scn, runs=runs, key=jax.random.key(0),
                      process_std=np.sqrt(np.diag(Q)), meas_std=np.sqrt(np.diag(R)))
    x0 = np.asarray(scn.x0) + np.array([0.5, 0.1, 0.02])
    P0 = np.diag([1.0, 0.2, 0.05]) ** 2
    return dict(sim=sim, Q=Q, R=R, x0=x0, P0=P0, ys=jnp.asarray(sim.measurements),
                us=jnp.asarray(sim.inputs), truth=np.asarray(sim.states))


# -- helpers ------------------------------------------------------------------------------------


def _installed(dist: str, module: str) -> str | None:
    """The installed version of ``dist`` when ``module`` imports, else None."""
    try:
        if importlib.util.find_spec(module) is None:
            return None
    except (ImportError, ValueError, AttributeError):
        return None
    try:
        return version(dist)
    except PackageNotFoundError:
        return "?"


def _compile(jitted, *args):
    """(compile time in s, a call of the compiled function returning numpy estimates)."""
    t0 = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    return compile_s, (lambda: jax.block_until_ready(compiled(*args)))


def _vehjax(est, p, **kw):
    t0 = time.perf_counter()
    prepared = vj.compile_run(est, p["sim"].measurements, p["sim"].inputs, x0=p["x0"], P0=p["P0"],
                              progress=False, **kw)
    compile_s = time.perf_counter() - t0
    return compile_s, (lambda: prepared(progress=False))


def _mvn_logpdf(x, mean, cov):
    return jax.scipy.stats.multivariate_normal.logpdf(x, mean, cov)


def _gauss_sampler(p):
    """Pieces every particle peer shares: Cholesky factors, the Gaussian log-likelihood."""
    LQ = jnp.linalg.cholesky(jnp.asarray(p["Q"]))
    L0 = jnp.linalg.cholesky(jnp.asarray(p["P0"]))
    R_inv = jnp.linalg.inv(jnp.asarray(p["R"]))
    const = -0.5 * float(np.linalg.slogdet(2.0 * np.pi * p["R"])[1])

    def loglik(y, x, u, th):
        e = y - observe(x, u, th)
        return -0.5 * (e @ R_inv @ e) + const

    return LQ, L0, loglik


def _weighted_mean(log_w, particles):
    return jax.nn.softmax(log_w) @ particles


def _rmse(est, truth) -> float:
    return float(np.sqrt(np.mean((np.asarray(est) - np.asarray(truth)) ** 2)))


class Contender:
    def __init__(self, name, compile_s, fn, estimates, note="", scale=1.0):
        self.name, self.compile_s, self.fn, self.note = name, compile_s, fn, note
        self.estimates = estimates  # () -> (R', T, nx) numpy, for the check
        self.scale = scale  # the measured time times this = the time of the whole study
        self.best = math.inf


# -- EKF ----------------------------------------------------------------------------------------


def ekf_row(p, args):
    th = jnp.asarray(THETA)
    f = lambda x, u: transition(x, u, th)  # noqa: E731
    h = lambda x, u: observe(x, u, th)  # noqa: E731
    out = []
    est = vj.filters.ekf(user_model(), Q=p["Q"], R=p["R"])
    c, fn = _vehjax(est, p)
    out.append(Contender("vehjax", c, fn, lambda fn=fn: fn().states))

    if _installed("dynamax", "dynamax"):
        from dynamax.nonlinear_gaussian_ssm import ParamsNLGSSM, extended_kalman_filter

        # dynamax conditions on y_t and then predicts with u_{t+1}; vehjax predicts with u_t and
        # then conditions: dynamax's prior is vehjax's first prediction (one EKF predict).
        x0, P0 = jnp.asarray(p["x0"]), jnp.asarray(p["P0"])
        F = jax.jacfwd(f)(x0, p["us"][0])
        params = ParamsNLGSSM(initial_mean=f(x0, p["us"][0]),
                              initial_covariance=F @ P0 @ F.T + jnp.asarray(p["Q"]),
                              dynamics_function=f, dynamics_covariance=jnp.asarray(p["Q"]),
                              emission_function=h, emission_covariance=jnp.asarray(p["R"]))
        us = p["us"]

        def one(y):
            return extended_kalman_filter(params, y, inputs=us,
                                          output_fields=["filtered_means"]).filtered_means

        c, fn = _compile(jax.jit(jax.vmap(one)), p["ys"])
        out.append(Contender(f"dynamax {version('dynamax')}", c, fn, fn,
                             "extended_kalman_filter, prior = vehjax's first prediction"))
    if _installed("cuthbert", "cuthbert"):
        import cuthbert
        from cuthbert.gaussian import taylor

        Q, R = jnp.asarray(p["Q"]), jnp.asarray(p["R"])
        x0, P0 = jnp.asarray(p["x0"]), jnp.asarray(p["P0"])

        def dyn(state, inputs):
            u, _ = inputs
            log_p = lambda xp, x: _mvn_logpdf(x, f(xp, u), Q)  # noqa: E731
            return log_p, state.mean, f(state.mean, u)

        def obs(state, inputs):
            u, y = inputs
            log_p = lambda x, yy: _mvn_logpdf(yy, h(x, u), R)  # noqa: E731
            return log_p, state.mean, y

        filt = taylor.build_filter(lambda x: _mvn_logpdf(x, x0, P0), x0, dyn, obs)
        us = p["us"]

        def one(y):
            return cuthbert.filter(filt, (us, y), filt.init_prepare()).mean[1:]

        c, fn = _compile(jax.jit(jax.vmap(one)), p["ys"])
        out.append(Contender(f"cuthbert {version('cuthbert')}", c, fn, fn,
                             "Taylor filter (non-associative) + cuthbert.filter; equals the EKF "
                             "for Gaussian noise and a linear h"))
    return out


# -- UKF ----------------------------------------------------------------------------------------


def ukf_row(p, args):
    th = jnp.asarray(THETA)
    f = lambda x, u: transition(x, u, th)  # noqa: E731
    h = lambda x, u: observe(x, u, th)  # noqa: E731
    out = []
    est = vj.filters.ukf(user_model(), Q=p["Q"], R=p["R"],
                         points=vj.filters.SigmaPoints(alpha=ALPHA, beta=BETA, kappa=KAPPA))
    c, fn = _vehjax(est, p)
    out.append(Contender("vehjax", c, fn, lambda fn=fn: fn().states))

    if _installed("dynamax", "dynamax"):
        from dynamax.nonlinear_gaussian_ssm import (ParamsNLGSSM, UKFHyperParams,
                                                    unscented_kalman_filter)

        prior = vj.filters.ukf(user_model(), Q=p["Q"], R=p["R"],
                               points=vj.filters.SigmaPoints(alpha=ALPHA, beta=BETA, kappa=KAPPA))
        nan_y = jnp.full((p["ys"].shape[-1],), jnp.nan)
        _, first = prior.step(prior.init(jnp.asarray(p["x0"]), jnp.asarray(p["P0"])), nan_y,
                              p["us"][0])
        params = ParamsNLGSSM(initial_mean=first.mean, initial_covariance=first.cov,
                              dynamics_function=f, dynamics_covariance=jnp.asarray(p["Q"]),
                              emission_function=h, emission_covariance=jnp.asarray(p["R"]))
        hyper = UKFHyperParams(alpha=ALPHA, beta=BETA, kappa=KAPPA)
        us = p["us"]

        def one(y):
            return unscented_kalman_filter(params, y, hyper, inputs=us,
                                           output_fields=["filtered_means"]).filtered_means

        c, fn = _compile(jax.jit(jax.vmap(one)), p["ys"])
        out.append(Contender(f"dynamax {version('dynamax')}", c, fn, fn,
                             "unscented_kalman_filter, prior = vehjax's first prediction"))
    if _installed("kalman-py", "kalman_py"):
        from kalman_py.backends import jax_backend as kb
        from kalman_py.backends.numpy_backend import sigma_weights

        # kalman-py's models are f(x, dt), h(x): the per-step input rides in the dt slot (its
        # filter scans over dt). UnscentedKalmanFilter.filter(backend="jax") ends in a host-side
        # bool(ok) that cannot be vmapped, so the jitted kernel it calls is vmapped directly.
        w = sigma_weights(3, ALPHA, BETA, KAPPA, np.dtype(np.float64))
        consts = [jnp.asarray(a, jnp.float64) for a in (p["Q"], p["R"], p["x0"], p["P0"],
                                                         w.mean, w.cov, w.gamma)]
        Qc, Rc, x0c, P0c, wm, wc, gamma = consts
        h_kp = lambda x: observe(x, None, th)  # noqa: E731
        us = p["us"]

        def one(y):
            res, _ = kb._ukf_filter(Qc, Rc, x0c, P0c, y, us, wm, wc, gamma, f=f, h=h_kp,
                                    residual=None, square_root=False, vectorized=False,
                                    center_sign=1.0 if float(w.cov[0]) >= 0 else -1.0)
            return res.means

        c, fn = _compile(jax.jit(jax.vmap(one)), p["ys"])
        out.append(Contender(f"kalman-py {version('kalman-py')}", c, fn, fn,
                             "JAX backend kernel (_ukf_filter), input in the dt slot; redraws "
                             "sigma points before the update"))
    if _installed("filterpy", "filterpy"):
        from vehjax.cli import load_benchmark

        gauss = load_benchmark("gaussian")
        n_fp = max(1, min(args.filterpy_runs, args.runs))
        model = user_model()
        cache = {}

        def fp():
            per_run, xs = gauss.bench_filterpy(model, p["sim"], p["Q"], p["R"], p["x0"],
                                               p["P0"], n_fp)
            cache["x"] = xs
            return xs

        c = Contender(f"filterpy {version('filterpy')}", 0.0, fp,
                      lambda: cache["x"] if "x" in cache else fp(),
                      f"NumPy transcription, Python loop: timed on {n_fp} run(s), "
                      f"x{args.runs / n_fp:g}",
                      scale=args.runs / n_fp)
        c.runs_checked = n_fp
        out.append(c)
    return out


# -- bootstrap PF -------------------------------------------------------------------------------


def pf_row(p, args):
    th = jnp.asarray(THETA)
    N = args.particles
    keys = jax.random.split(jax.random.key(1), args.runs)
    LQ, L0, loglik = _gauss_sampler(p)
    x0 = jnp.asarray(p["x0"])
    us, ys = p["us"], p["ys"]
    out = []
    est = vj.filters.bootstrap_pf(user_model(), p["Q"], p["R"], n_particles=N,
                                  resampling=vj.filters.Resampling(scheme="systematic",
                                                                   ess_threshold=ESS_THRESHOLD))
    c, fn = _vehjax(est, p, key=jax.random.key(1))
    out.append(Contender("vehjax", c, fn, lambda fn=fn: fn().states))

    if _installed("cuthbert", "cuthbert"):
        from cuthbert.smc import particle_filter
        from cuthbertlib.resampling import ess_decorator, systematic

        filt = particle_filter.build_filter(
            lambda key: x0 + L0 @ jax.random.normal(key, (3,)),
            lambda key, x, inp: transition(x, inp[0], th) + LQ @ jax.random.normal(key, (3,)),
            lambda xp, x, inp: loglik(inp[1], x, inp[0], th),
            N, ess_decorator(systematic.resampling, ESS_THRESHOLD))
        T = us.shape[0]

        def one(key, y):
            k0, k1 = jax.random.split(key)
            state = filt.init_prepare(key=k0)._replace(model_inputs=(us[0], y[0]))

            def body(state, inp):
                u, yt, k = inp
                state = filt.filter_combine(state, filt.filter_prepare((u, yt), key=k))
                return state, _weighted_mean(state.log_weights, state.particles)

            return jax.lax.scan(body, state, (us, y, jax.random.split(k1, T)))[1]

        c, fn = _compile(jax.jit(jax.vmap(one)), keys, ys)
        out.append(Contender(f"cuthbert {version('cuthbert')}", c, fn, fn,
                             "particle_filter pieces in a scan keeping the mean; "
                             "ess_decorator(systematic, 0.5)"))
    if _installed("smcx", "smcx"):
        import smcx

        def init(key, n, u0):
            k1, k2 = jax.random.split(key)
            xs = x0 + jax.random.normal(k1, (n, 3)) @ L0.T
            xs = jax.vmap(transition, in_axes=(0, None, None))(xs, u0, th)
            return xs + jax.random.normal(k2, (n, 3)) @ LQ.T

        def run(key, y, history):
            return smcx.bootstrap_filter(
                key, init, lambda k, x, u: transition(x, u, th) + LQ @ jax.random.normal(k, (3,)),
                lambda yt, x, u: loglik(yt, x, u, th), y, N, resampling_fn=smcx.systematic,
                resampling_threshold=ESS_THRESHOLD, inputs=us, store_history=history)

        def timed(key, y):  # what is timed: no history (the fastest form), the final state
            post = run(key, y, False)
            return post.marginal_loglik, post.filtered_particles[-1]

        def checked(key, y):  # the check: the same filter keeping its history, the means
            post = run(key, y, True)
            return jax.vmap(_weighted_mean)(post.filtered_log_weights, post.filtered_particles)

        c, fn = _compile(jax.jit(jax.vmap(timed)), keys, ys)
        n_chk = min(args.runs, 4)
        chk = jax.jit(jax.vmap(checked))
        out.append(Contender(f"smcx {version('smcx')}", c, fn,
                             lambda: np.asarray(chk(keys[:n_chk], ys[:n_chk])),
                             "bootstrap_filter, store_history=False (checked with history)"))
        out[-1].runs_checked = n_chk
    return out


# -- Liu-West -----------------------------------------------------------------------------------


def _box():
    idx = [PARAM_NAMES.index(n) for n in ESTIMATE]
    nominal = THETA[idx]
    return idx, 0.75 * nominal, 1.35 * nominal


def liu_west_row(p, args):
    N = args.particles
    idx, low, high = _box()
    keys = jax.random.split(jax.random.key(2), args.runs)
    LQ, L0, loglik = _gauss_sampler(p)
    x0 = jnp.asarray(p["x0"])
    us, ys = p["us"], p["ys"]
    th_nom = jnp.asarray(THETA)
    out = []
    est = vj.filters.liu_west_ukf(user_model(), p["Q"], p["R"], n_particles=N, estimate=ESTIMATE,
                                  theta_low=low, theta_high=high, kernel=vj.filters.LiuWestKernel(a=SHRINKAGE),
                                  resampling=vj.filters.Resampling(ess_threshold=ESS_THRESHOLD), points=vj.filters.SigmaPoints(alpha=ALPHA, beta=BETA, kappa=KAPPA))
    c, fn = _vehjax(est, p, key=jax.random.key(2))
    cache = {}

    def vj_est(fn=fn):
        res = fn()
        cache["vehjax"] = np.asarray(res.params)[:, -1]
        return res.states

    out.append(Contender("vehjax", c, fn, vj_est,
                         f"{N} parameter particles (Liu-West kernel) + one UKF for the state"))

    if _installed("smcx", "smcx"):
        import smcx

        lo, hi = jnp.asarray(low), jnp.asarray(high)
        full = lambda prm: th_nom.at[jnp.asarray(idx)].set(prm)  # noqa: E731

        def param_init(key, n):
            return lo + (hi - lo) * jax.random.uniform(key, (n, len(idx)))

        def state_init(key, n, prm, u0):
            k1, k2 = jax.random.split(key)
            xs = x0 + jax.random.normal(k1, (n, 3)) @ L0.T
            xs = jax.vmap(lambda x, q: transition(x, u0, full(q)))(xs, prm)
            return xs + jax.random.normal(k2, (n, 3)) @ LQ.T

        def step(k, x, prm, u):
            return transition(x, u, full(prm)) + LQ @ jax.random.normal(k, (3,))

        def lik(y, x, prm, u):
            return loglik(y, x, u, full(prm))

        def aux(y, x, prm, u):  # look-ahead at the transition's mean
            return loglik(y, transition(x, u, full(prm)), u, full(prm))

        def run(key, y, history):
            return smcx.liu_west_filter(
                key, None, step, lik, aux, param_init, y, N, shrinkage=SHRINKAGE,
                resampling_fn=smcx.systematic, resampling_threshold=ESS_THRESHOLD,
                parameter_moves="always", inputs=us, param_initial_state_sampler=state_init,
                store_history=history)

        def timed(key, y):
            post = run(key, y, False)
            return post.marginal_loglik, post.filtered_particles[-1], post.filtered_params[-1]

        def checked(key, y):
            post = run(key, y, True)
            means = jax.vmap(_weighted_mean)(post.filtered_log_weights, post.filtered_particles)
            return means, _weighted_mean(post.filtered_log_weights[-1], post.filtered_params[-1])

        c, fn = _compile(jax.jit(jax.vmap(timed)), keys, ys)
        n_chk = min(args.runs, 4)
        chk = jax.jit(jax.vmap(checked))

        def sm_est():
            means, prm = chk(keys[:n_chk], ys[:n_chk])
            cache["smcx"] = np.asarray(prm)
            return np.asarray(means)

        out.append(Contender(f"smcx {version('smcx')}", c, fn, sm_est,
                             f"{N} joint (state, parameter) particles, auxiliary PF with the "
                             "Liu-West kernel, store_history=False"))
        out[-1].runs_checked = n_chk
    out[0].param_cache = cache
    return out


BUILDERS = {"ekf": ekf_row, "ukf": ukf_row, "pf": pf_row, "liu_west": liu_west_row}
TITLES = {"ekf": "EKF", "ukf": "UKF", "pf": "bootstrap PF", "liu_west": "Liu-West"}


# -- checks -------------------------------------------------------------------------------------


def _check(row, contenders, p, args) -> tuple[bool, str]:
    """(same work?, a line saying what was compared)."""
    ests = {c.name: np.asarray(c.estimates()) for c in contenders}
    ref = ests["vehjax"]
    if row in ("ekf", "ukf"):
        parts, ok = [], True
        for c in contenders[1:]:
            n = getattr(c, "runs_checked", args.runs)
            d = float(np.max(np.abs(ref[:n] - ests[c.name])))
            parts.append(f"{c.name.split()[0]} {d:.1e}")
            ok &= d < args.tol
        return ok, (f"max |vehjax - peer| of the filtered means: "
                    f"{', '.join(parts) or 'no peer installed'} "
                    f"(tol {args.tol:g})")
    truth = p["truth"]
    meas = _rmse(p["ys"], truth)
    rm = {}
    for c in contenders:
        n = getattr(c, "runs_checked", args.runs)
        rm[c.name] = _rmse(ests[c.name], truth[:n])
    text = ", ".join(f"{k.split()[0]} {v:.4f}" for k, v in rm.items())
    line = f"state RMSE vs truth: {text} (raw measurements {meas:.4f})"
    if row == "pf":
        best = min(rm.values())
        ok = all(np.isfinite(v) and v < 1.25 * best + 1e-3 for v in rm.values())
        return ok, line + "; each within 25 % of the best"
    ok = all(np.isfinite(v) and v < meas for v in rm.values())
    cache = contenders[0].param_cache
    idx, _, _ = _box()
    for name, prm in cache.items():
        err = 100.0 * (np.asarray(prm) / THETA[idx] - 1.0)
        line += f"; {name} final {'/'.join(ESTIMATE)} error % (mean over runs) " + \
                "/".join(f"{e:+.1f}" for e in err.mean(axis=0))
    return ok, line + "; each below the raw measurements"


# -- driver -------------------------------------------------------------------------------------


def parser() -> argparse.ArgumentParser:
    """The benchmark's options (``vehjax bench all --help``)."""
    p = argparse.ArgumentParser(prog="vehjax bench all", description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=20, help="Monte-Carlo runs (default %(default)s)")
    p.add_argument("--steps", type=int, default=500, help="steps per run (default %(default)s)")
    p.add_argument("--particles", type=int, default=500,
                   help="particles per run, PF and Liu-West rows (default %(default)s)")
    p.add_argument("--repeat", type=int, default=3,
                   help="interleaved timing rounds; the best is reported (default %(default)s)")
    p.add_argument("--rows", default=",".join(ROWS),
                   help="comma list of rows out of %s (default %%(default)s)" % ", ".join(ROWS))
    p.add_argument("--filterpy-runs", type=int, default=1,
                   help="filterpy runs timed, then extrapolated to --runs (default %(default)s)")
    p.add_argument("--tol", type=float, default=1e-6,
                   help="max abs difference of the Gaussian filters' means (default %(default)s)")
    return p


def measure(rows, p, args):
    """Build, check and time each row's contenders (interleaved, best of ``args.repeat``):
    ([(row, contenders)], any check failed)."""
    results, failed = [], False
    for row in rows:
        contenders = BUILDERS[row](p, args)
        ok, line = _check(row, contenders, p, args)
        print(f"[{TITLES[row]}] check: {line}: {'ok' if ok else 'FAILED'}")
        if not ok:
            print(f"[{TITLES[row]}] the filters disagree: this row is not timed")
            failed = True
            continue
        for c in contenders:
            c.fn()  # warm
        for _ in range(args.repeat):
            for c in contenders:
                t0 = time.perf_counter()
                c.fn()
                c.best = min(c.best, time.perf_counter() - t0)
        results.append((row, contenders))
    return results, failed


def table(results, n_work) -> list:
    """Print the timing table of :func:`measure`'s results; [(title, vehjax / fastest peer,
    peer name)] per row (NaN when no peer is installed)."""
    print()
    print(f"{'row':<14}{'library':<18}{'compile [s]':>12}{'run [s]':>10}{'ms/run-step':>13}"
          f"{'vehjax/x':>10}  note")
    verdicts = []
    for row, contenders in results:
        vj_t = contenders[0].best * contenders[0].scale
        for c in contenders:
            t = c.best * c.scale
            print(f"{TITLES[row]:<14}{c.name:<18}{c.compile_s:>12.2f}{t:>10.3f}"
                  f"{t / n_work * 1e3:>13.5f}{vj_t / t:>10.3f}  {c.note}")
        peers = [(c.best * c.scale, c.name) for c in contenders[1:]]
        if peers:
            t, name = min(peers)
            verdicts.append((TITLES[row], vj_t / t, name))
        else:
            verdicts.append((TITLES[row], math.nan, "no peer installed"))
    return verdicts


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    for name in ("runs", "steps", "particles", "repeat", "filterpy_runs"):
        if getattr(args, name) < 1:
            print(f"bench all: --{name.replace('_', '-')} must be >= 1")
            return 2
    rows = [r.strip() for r in args.rows.split(",") if r.strip()]
    bad = [r for r in rows if r not in ROWS]
    if bad:
        print(f"bench all: unknown row(s) {', '.join(bad)}; expected some of {', '.join(ROWS)}")
        return 2

    p = _problem(args.runs, args.steps)
    n_work = args.runs * args.steps
    print(f"All filters vs their fastest peer: {args.runs} runs x {args.steps} steps, "
          f"{args.particles} particles (PF, Liu-West), 3-DOF dual-track user model (nx = 3), "
          f"float64, {jax.devices()[0].platform.upper()}, best of {args.repeat} interleaved")
    for dist, mod in (("dynamax", "dynamax"), ("cuthbert", "cuthbert"), ("kalman-py", "kalman_py"),
                      ("filterpy", "filterpy"), ("smcx", "smcx")):
        if not _installed(dist, mod):
            print(f"note: {dist} is not installed: its entries are skipped "
                  f"(pip install 'vehjax[bench]')")

    results, failed = measure(rows, p, args)
    verdicts = table(results, n_work)
    if "pf" in rows:
        print(f"{'bootstrap PF':<14}{'particles 0.4':<18}{'':>12}{'':>10}{'':>13}{'':>10}  "
              "not installable beside jax 0.10 (it requires numpy < 2): not run")
    print("run: compiled run time of the whole study (compile apart); ms/run-step: per run and "
          "step; vehjax/x: vehjax's time / this library's (0.5 = vehjax twice as fast)")
    for title, ratio, name in verdicts:
        if math.isnan(ratio):
            print(f"ratio {title}: no peer installed, not compared")
            continue
        tag = "meets" if ratio <= TARGET else "misses"
        per = " per particle-step (same count, different algorithms)" if title == "Liu-West" else ""
        print(f"ratio {title}: vehjax / fastest peer ({name}) = {ratio:.3f}{per}  "
              f"({tag} <= {TARGET})")
    every = bool(verdicts) and all(r <= TARGET for _, r, _ in verdicts) and not failed
    print(f"every row at most {TARGET}x the fastest peer: {'yes' if every else 'no'}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
