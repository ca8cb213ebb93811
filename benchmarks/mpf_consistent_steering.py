"""How well paper 004's simulation pins the steering-noise std, and how the consistent MPF
(``marginalized_pf_grid``, issue #33) learns it: the numbers behind the MPF
(consistent) row of docs/noise_learning.md (noise_learning.py's docstring in short). The data are
``vehjax reproduce noise-learning``'s (vehjax.studies.banked_road's simulate_truth, seed 0).

    python benchmarks/mpf_consistent_steering.py profile RUNS SECONDS
        exact Kalman log-likelihood summed over RUNS runs at 0.5..4 times the true steering
        std, every other covariance at the truth (the consistent MPF with nu0 = 1e7,
        forgetting 1 and a grid of one std is that Kalman filter), relative to the truth's
    python benchmarks/mpf_consistent_steering.py learn RUNS SECONDS POINTS PRIOR FORGETTING
        the consistent MPF as noise-learning builds it, with POINTS grid points, PRIOR
        "jeffreys" (the default: Jeffreys' prior over a decade either side of the guess, twice
        the true std), "jeffreys:F" (Jeffreys' prior over the guess / F .. the guess x F), "iw"
        (the grid over the inverse-Wishart prior of the guess) or a factor F (equal weights,
        log-uniform over the guess / F .. the guess x F), FORGETTING lambda:
        the steering std's estimate / truth over runs (mean, spread), its reported std and
        95 % coverage at the end of each window, and the NEES of (vy, r) per dof and its share
        in the 95 % band; a last argument ``known`` gives it the true sensor covariances
        (nu0 = 1e7: R known, only sigma_w learnt); ``inverse-wishart`` or ``scored``, the
        sensor variances (``sensor_variances``; neither: the builder's default, scored since
        session 23: the numbers in docstrings measured before then name ``inverse-wishart``)
    python benchmarks/mpf_consistent_steering.py time RUNS SECONDS
        ms per run-step of the paper's MPF (noise-learning's, N = 100) and the consistent MPF
        (25 grid points) with the scored sensor variances (the default) and the
        inverse-Wishart ones (``sensor_variances``), one process, through ``vehjax.run``,
        compiled first, then three rounds interleaved (the best of each)
    python benchmarks/mpf_consistent_steering.py exact RUNS SECONDS
        the NEES of (vy, r) of the Kalman filter with every noise known (the consistent MPF
        with nu0 = 1e7 and a grid of one std, the truth) per window: the ceiling of the NEES
        share in the band that the learning filters are held to
    python benchmarks/mpf_consistent_steering.py early RUNS
        the first 30 s of the consistent MPF learning everything from guesses of twice the
        truth, with the inverse-Wishart sensor variances and the scored ones (the default):
        at 0.1-30 s the NEES of (vy, r) per dof (the run-average over the last 6 steps) and
        the mean over runs of each learnt std / truth
    python benchmarks/mpf_consistent_steering.py information RUNS SECONDS
        the Fisher information of log sigma_w per run at 0.5-4 times the true std, every other
        covariance known: the whole (Monte Carlo: the exact log-likelihood's curvature on data
        simulated at that std) against its covariance part (the filter's Jeffreys prior's)

Examples (the docstrings' numbers): ``profile 20 180``; ``learn 100 180 25 jeffreys 1``;
``learn 100 180 25 jeffreys 1 inverse-wishart``; ``learn 20 180 25 jeffreys:100 1
inverse-wishart``; ``learn 20 180 25 iw 1 inverse-wishart``; ``learn 20 180 25 10 1
inverse-wishart``; ``learn 20 180 25 10 1 known``; ``learn 100 180 25 jeffreys:3 1 known``;
``learn 100 180 25 jeffreys:5 1 known``;
``learn 10 180 100 iw 0.995 inverse-wishart``;
``information 8 180``; ``time 20 30``; ``early 50``; ``exact 100 180``.
"""

import math
import sys

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import vehjax as vj  # noqa: E402
from vehjax import metrics  # noqa: E402
from vehjax.filters.marginalized import InputStdGrid  # noqa: E402
from vehjax.studies import banked_road as road  # noqa: E402

WINDOWS = ((0, 5), (5, 20), (20, 60), (60, 120), (120, 180))


def _nees_vr(out, X):
    """The NEES of (vy, r), (R, T), from a ``vehjax.run`` result with covariances."""
    return metrics.nees(np.asarray(out.states)[..., :2],
                        np.asarray(out.covariances)[..., :2, :2], X[..., :2])


def _nees_cells(nees, digits):
    """'NEES x per dof, in band y' of an (R, T) NEES of 2 dof."""
    return (f"NEES {np.nanmean(nees) / 2:.3f} per dof, in band "
            f"{metrics.consistency(nees, 2).inside:.{digits}f}")


def data(runs, seconds, steer_factor=1.0, seed=0):
    """noise-learning's simulation; ``steer_factor`` scales the true steering std."""
    drive = vj.data.load_comma2k19()
    model = vj.models.SingleTrackBank(dt=drive.dt)
    T = int(round(seconds / model.dt))
    U = road.looped_inputs(drive.inputs(model), T)
    acc, _ = road.bank_profile(np.arange(1, T + 1) * model.dt, model.dt)
    X, Y, _ = (np.asarray(a) for a in road.simulate_truth(
        model, U, acc, runs, jax.random.key(seed), steer_std=steer_factor * road.STEER_STD))
    return model, X, Y, U


def build(model, points, std0, forgetting, nu0=None, std_range=None, prior=None,
          variances=None):
    return road.build_consistent_filter(
        model, points, std0, forgetting, nu0=nu0, sensor_variances=variances,
        grid=InputStdGrid(input_std_range=std_range, input_std_prior=prior))


def profile(runs, seconds):
    model, _, Y, U = data(runs, seconds)
    facs = (0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0)
    total = []
    for f in facs:
        sd = f * road.STEER_STD
        est = build(model, 2, {"delta": sd, **road.SENSOR_STD}, 1.0, nu0=1e7,
                    std_range=(sd, sd * (1 + 1e-9)), prior="log-uniform")
        out = vj.run(est, Y, U, x0=np.zeros(5), P0=road.P0_SIM, key=jax.random.key(1),
                     progress=False)
        total.append(float(np.sum(out.loglik)))
    ref = total[facs.index(1.0)]
    print(f"exact log-likelihood, {runs} runs x {seconds:g} s, relative to the true std:")
    for f, v in zip(facs, total):
        print(f"  {f:4.2f} x truth: {v - ref:+10.2f} nats")


def time_per_step(runs, seconds):
    import time

    model, _, Y, U = data(runs, seconds)
    paper, P0 = road.build_sim_filter(model, 100), road.P0_SIM  # noise-learning's, N = 100
    std0 = {"delta": 2.0 * road.STEER_STD, **{s: 2.0 * road.SENSOR_STD[s] for s in road.SENSORS}}
    iw = build(model, 25, std0, 1.0, variances="inverse-wishart")
    scored = build(model, 25, std0, 1.0, variances="scored")
    ests = {"MPF (paper), N = 100": (paper, P0),
            "consistent, inverse-Wishart": (iw, road.P0_SIM),
            "consistent, scored": (scored, road.P0_SIM)}

    def go(est, P):
        out = vj.run(est, Y, U, x0=np.zeros(5), P0=P, key=jax.random.key(1), progress=False)
        jax.block_until_ready(out.states)

    for est, P in ests.values():  # compile
        go(est, P)
    best = {k: np.inf for k in ests}
    for _ in range(3):
        for k, (est, P) in ests.items():
            t = time.perf_counter()
            go(est, P)
            best[k] = min(best[k], time.perf_counter() - t)
    print(f"{runs} runs x {seconds:g} s, ms per run-step (best of 3, interleaved):")
    for k, v in best.items():
        print(f"  {k:30s} {1e3 * v / Y.shape[0] / Y.shape[1]:.4f}")


def learn(runs, seconds, points, prior, forgetting, r_known=False, variances=None):
    model, X, Y, U = data(runs, seconds)
    guess = 2.0 * road.STEER_STD
    sf = 1.0 if r_known else 2.0
    kind = {"iw": "inverse-wishart", "jeffreys": "jeffreys"}.get(prior.split(":")[0],
                                                                 "log-uniform")
    factor = prior.split(":")[-1]
    rng = None if prior in ("iw", "jeffreys") else (guess / float(factor), guess * float(factor))
    est = build(model, points, {"delta": guess, **{s: sf * road.SENSOR_STD[s] for s in
                                                   road.SENSORS}}, forgetting, std_range=rng,
                prior=kind, nu0=1e7 if r_known else None, variances=variances)
    out = vj.run(est, Y, U, x0=np.zeros(5), P0=road.P0_SIM, key=jax.random.key(1),
                 return_covariances=True, progress=False)
    j = est.param_names.index("delta_std")
    e = np.asarray(out.params[..., j]) / road.STEER_STD
    sd = np.sqrt(np.asarray(out.params_cov[..., j, j])) / road.STEER_STD
    nees = _nees_vr(out, X)
    print(f"{runs} runs x {seconds:g} s, {points} points, prior {prior}, forgetting "
          f"{forgetting:g}{', R known' if r_known else ''}"
          f"{', sensor variances ' + variances if variances else ''}; steering std / "
          f"truth at the window's end:")
    for a, b in WINDOWS:
        if a >= seconds:
            break
        sl = slice(int(a / model.dt), int(min(b, seconds) / model.dt))
        k = sl.stop - 1
        cover = np.mean(np.abs(e[:, k] - 1.0) <= 1.96 * sd[:, k])
        print(f"  {a:3d}-{b:3d} s: {_nees_cells(nees[:, sl], 2)} | mean {e[:, k].mean():.3f} "
              f"spread {e[:, k].std():.3f} reported sd {sd[:, k].mean():.3f} coverage "
              f"{cover:.2f}")
    print("  all: " + _nees_cells(nees, 3))


def exact(runs, seconds):
    model, X, Y, U = data(runs, seconds)
    sd = road.STEER_STD
    est = build(model, 2, {"delta": sd, **road.SENSOR_STD}, 1.0, nu0=1e7,
                std_range=(sd, sd * (1 + 1e-9)), prior="log-uniform")
    out = vj.run(est, Y, U, x0=np.zeros(5), P0=road.P0_SIM, key=jax.random.key(1),
                 return_covariances=True, progress=False)
    nees = _nees_vr(out, X)
    print(f"{runs} runs x {seconds:g} s, every noise known (the Kalman filter):")
    for a, b in WINDOWS:
        if a >= seconds:  # as learn: no empty windows
            break
        sl = slice(int(a / model.dt), int(min(b, seconds) / model.dt))
        print(f"  {a:3d}-{b:3d} s: " + _nees_cells(nees[:, sl], 2))
    print("  all: " + _nees_cells(nees, 3))


def early(runs):
    model, X, Y, U = data(runs, 30)
    std0 = {"delta": 2 * road.STEER_STD, **{s: 2 * road.SENSOR_STD[s] for s in road.SENSORS}}
    truth = {"delta_std": road.STEER_STD, **{f"{s}_std": road.SENSOR_STD[s] for s in road.SENSORS}}
    print(f"{runs} runs, guesses twice the truth; mean estimate / truth:")
    for variances in ("inverse-wishart", "scored"):
        est = build(model, 25, std0, 1.0, variances=variances)
        out = vj.run(est, Y, U, x0=np.zeros(5), P0=road.P0_SIM, key=jax.random.key(1),
                     return_covariances=True, progress=False)
        nees = _nees_vr(out, X)
        print(f"  sensor variances {variances}:")
        for t in (0.1, 0.5, 1, 2, 5, 10, 20, 30):
            k = int(round(t / model.dt)) - 1
            cells = [f"NEES {np.nanmean(nees[:, max(0, k - 5):k + 1]) / 2:.3f}"]
            cells += [f"{nm} {np.mean(out.params[:, k, est.param_names.index(nm)]) / v:.3f}"
                      for nm, v in truth.items()]
            print(f"    {t:4.1f} s: " + ", ".join(cells))


def information(runs, seconds):
    """Fisher information of log sigma_w (per run) at 0.5-4 times the truth, the sensor noise
    known: the whole, by the curvature of the exact log-likelihood over a fine grid on data
    simulated at that std (Monte Carlo over RUNS runs), against its covariance part, which the
    filter's Jeffreys prior uses (the filter's ``info``, per log sigma_w^2, times 4)."""
    pts = 49
    print(f"Fisher information of log sigma_w per run, {runs} runs x {seconds:g} s, R known:")
    for f in (0.5, 1.0, 2.0, 4.0):
        model, _, Y, U = data(runs, seconds, steer_factor=f, seed=7)
        sd = f * road.STEER_STD
        est = build(model, pts, {"delta": sd, **road.SENSOR_STD}, 1.0, nu0=1e7,
                    std_range=(sd / 2.0, sd * 2.0), prior="jeffreys")

        def one(y, u):
            s0 = est.init(jnp.zeros(5), jnp.asarray(road.P0_SIM), key=jax.random.key(1))
            s, _ = jax.lax.scan(lambda c, yu: (est.step(c, *yu)[0], None), s0, (y, u))
            return s.base_log_weights, s.info

        L, info = (np.asarray(a) for a in jax.jit(jax.vmap(one, in_axes=(0, None)))(
            jnp.asarray(Y), jnp.asarray(U)))
        h = 2.0 * math.log(2.0) / (pts - 1)  # grid step in log sigma_w
        k = pts // 2  # the grid's middle: the true std
        whole = -(L[:, k + 1] - 2.0 * L[:, k] + L[:, k - 1]) / h ** 2
        print(f"  {f:3.1f} x truth: whole {whole.mean():9.2f} (sd over runs "
              f"{whole.std():7.2f}), covariance part {4.0 * info[:, k].mean():9.2f}")


if __name__ == "__main__":
    mode = sys.argv[1] if len(sys.argv) > 1 else "learn"
    if mode == "profile":
        profile(int(sys.argv[2]), float(sys.argv[3]))
    elif mode == "information":
        information(int(sys.argv[2]), float(sys.argv[3]))
    elif mode == "exact":
        exact(int(sys.argv[2]), float(sys.argv[3]))
    elif mode == "early":
        early(int(sys.argv[2]))
    elif mode == "time":
        time_per_step(int(sys.argv[2]), float(sys.argv[3]))
    elif mode == "learn":
        learn(int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4]), sys.argv[5],
              float(sys.argv[6]), "known" in sys.argv[7:],
              next((v for v in ("scored", "inverse-wishart") if v in sys.argv[7:]), None))
    else:
        raise SystemExit(__doc__)
