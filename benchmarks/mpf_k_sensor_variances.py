"""How the consistent MPF (``marginalized_pf_grid``) learns the sensor
variances on the consistency study's data (``vehjax reproduce consistency``, where the
steering noise reaches ay directly beside ay's own noise): the numbers behind
docs/sensor_scoring.md (sensor_scoring.py's docstring in short) and the "MPF-K" remarks of
consistency.py.

    python benchmarks/mpf_k_sensor_variances.py statistic RUNS STEPS [NU0]
        the inverse-Wishart statistic's increments per step (the expected second moment of
        each sensor's noise) over the truth's variance, by window, the filter's R the
        statistics' mean (``sensor_variances="inverse-wishart"``): with NU0 = 1e7 (default)
        it is held at the truth; with the default prior (NU0 = 8) it moves
    python benchmarks/mpf_k_sensor_variances.py guess FACTOR STEPS VARIANCES
        100 runs, the steering std known, every sensor std guessed at FACTOR x the truth,
        VARIANCES inverse-wishart or scored (the default): each learnt std's mean relative
        error, spread and mean reported std (over the truth) and 95 % coverage at a third,
        two thirds and the end, and the NEES of the states (share in the band, per dof)
    python benchmarks/mpf_k_sensor_variances.py profile STEPS
        the exact log-likelihood (everything known but the ay std) per run at 0.7..1.6 x the
        true ay std, and the ay std's std per run from its curvature
    python benchmarks/mpf_k_sensor_variances.py toy
        a scalar toy of ay's case, y = x + e with x independent N(0, 3 R), 300 steps, 20,000
        runs: the three ways of weighting the pseudo-observations, started at the truth and at
        twice it (the module docstring's 0.925 / 1.030 / 1.002)

Examples: ``statistic 100 300``; ``statistic 100 300 8``; ``guess 2 300 inverse-wishart``;
``guess 2 300 scored``; ``guess 1 300 scored``; ``profile 300``; ``toy``.
"""

import sys

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import vehjax as vj  # noqa: E402
from vehjax import metrics  # noqa: E402
from vehjax.filters import InputStdGrid, NiW, marginalized_pf_grid  # noqa: E402
from vehjax.studies.banked_road import MATCHED as N, SENSORS, matched_truth, simulate_matched  # noqa: E402,E501

MODEL = vj.models.SingleTrackBank(dt=0.01)
NX = len(MODEL.state_names)


def _filter(points, std0, nu0=None, variances=None):
    """MPF-K as the study builds it, the steering std known (a grid of the true std)."""
    return marginalized_pf_grid(MODEL, points, sensors=SENSORS, known_std=N.known_std,
                                Q=N.bank_jerk_std ** 2,
                                linear_states=("phi", "phi_dot", "phi_ddot"),
                                sensor_variances=variances,
                                niw=NiW(std0={"delta": N.steer_std, **std0},
                                        mean0={"delta": N.offset, **N.bias}, forgetting=1.0,
                                        nu0=nu0),
                                grid=InputStdGrid(input_std_prior="log-uniform",
                                                  input_std_range=(N.steer_std, N.steer_std * (1 + 1e-9))))


def statistic(runs, steps, nu0=1e7):
    _, Y, U = simulate_matched(MODEL, runs, steps, 0)
    est = _filter(3, N.sensor_std, nu0, variances="inverse-wishart")

    def one(y, key):
        st = est.init(jnp.zeros(NX), jnp.diag(jnp.full(NX, 1e-12)), key=key)

        def body(st, yu):
            st2, _ = est.step(st, yu[0], yu[1])
            return st2, jnp.diagonal(st2.lam_e[..., 0] - st.lam_e[..., 0])

        return jax.lax.scan(body, st, (y, jnp.asarray(U)))[1]

    inc = np.asarray(jax.jit(jax.vmap(one))(jnp.asarray(Y),
                                            jax.random.split(jax.random.key(0), runs)))
    d = inc / np.array([N.sensor_std[s] ** 2 for s in SENSORS])
    print(f"{runs} runs x {steps} steps, nu0 {nu0:g}: the statistic's increment / the true "
          f"variance ({', '.join(SENSORS)})")
    for a, b in ((0, 10), (10, 50), (50, 100), (100, steps)):
        if a < steps:
            print(f"  steps {a}-{b}: {np.round(d[:, a:b].mean((0, 1)), 4)}")
    se = d.std((0, 1)) / np.sqrt(d.shape[0] * d.shape[1])
    print(f"  all: {np.round(d.mean((0, 1)), 4)} (se {np.round(se, 4)})")


def guess(factor, steps, variances):
    X, Y, U = simulate_matched(MODEL, 100, steps, 0)
    est = _filter(3, {k: factor * v for k, v in N.sensor_std.items()}, variances=variances)
    out = vj.run(est, Y, U, x0=np.zeros(NX), P0=np.full(NX, 1e-12), key=jax.random.key(0),
                 return_covariances=True, progress=False)
    th = matched_truth(est.param_names)
    print(f"100 runs, guesses {factor:g} x the truth, sensor variances {variances}:")
    for k in sorted({steps // 3 - 1, 2 * steps // 3 - 1, steps - 1}):
        e = np.asarray(out.params[:, k]) - th
        sd = np.sqrt(np.diagonal(np.asarray(out.params_cov[:, k]), axis1=-2, axis2=-1))
        cells = [f"{n}: {e[:, i].mean() / th[i]:+.3f}, spread {e[:, i].std() / th[i]:.3f}, "
                 f"sd {sd[:, i].mean() / th[i]:.3f}, coverage "
                 f"{np.mean(np.abs(e[:, i]) <= 1.96 * sd[:, i]):.2f}"
                 for i, n in enumerate(est.param_names) if n.endswith("_std") and n != "delta_std"]
        print(f"  step {k + 1}: " + " | ".join(cells))
    ne = metrics.nees(out.states[..., :NX], out.covariances[..., :NX, :NX], X)
    ce = metrics.consistency(ne, NX)
    print(f"  NEES in band {ce.inside:.3f}, per dof {float(np.nanmean(ce.mean) / NX):.3f}")


def profile(steps):
    _, Y, U = simulate_matched(MODEL, 100, steps, 0)
    facs = (0.7, 0.85, 1.0, 1.15, 1.3, 1.6)
    ll = []
    for f in facs:
        est = _filter(2, {**N.sensor_std, "ay": f * N.sensor_std["ay"]}, nu0=1e9)
        out = vj.run(est, Y, U, x0=np.zeros(NX), P0=np.full(NX, 1e-12),
                     key=jax.random.key(0), progress=False)
        ll.append(float(np.mean(out.loglik)))
    print(f"exact log-likelihood per run ({steps} steps) relative to the true ay std:")
    for f, v in zip(facs, ll):
        print(f"  {f:4.2f} x truth: {v - ll[2]:+8.3f}")
    curv = 0.5 * ((ll[2] - ll[1]) + (ll[2] - ll[3])) / 0.15 ** 2 * 2.0
    print(f"  the ay std's std per run from the curvature at +-15 %: {curv ** -0.5:.3f} x truth")


def toy(runs=20000, n=300, sx=3.0, nu0=3.0, seed=1):
    rng = np.random.default_rng(seed)
    for v0 in (1.0, 2.0):
        for form in ("first-order (weights F_t)", "Fisher at the estimate", "weights at the guess"):
            v = np.full(runs, v0)
            j0 = 0.5 * nu0 / v0 ** 2
            a = np.zeros(runs)
            b = np.zeros(runs)
            for _ in range(n):
                r = v
                g = 1.0 / (sx + r)
                nu = np.sqrt(sx + 1.0) * rng.standard_normal(runs)
                s = 0.5 * (g * g * nu * nu - g)
                w = 0.5 * g * g
                if form.startswith("first"):
                    f = (r * g) ** 2
                    a += f
                    b += f * r + 2.0 * r * r * s  # the statistic T - r = 2 r^2 s
                    v = (nu0 * v0 + b) / (nu0 + a)
                elif form.startswith("Fisher"):
                    a += w
                    b += w * r + s
                    v = (j0 * v0 + b) / (j0 + a)
                else:
                    wb = 0.5 / (sx + v0) ** 2
                    a += wb
                    b += wb * (r + s / w)
                    v = (j0 * v0 + b) / (j0 + a)
                v = np.where(v > 0, v, 1e-3)
            print(f"started at {v0:g} R, {form}: mean {v.mean():.3f} R, sd {v.std():.3f}")


if __name__ == "__main__":
    mode = sys.argv[1] if len(sys.argv) > 1 else ""
    if mode == "statistic":
        statistic(int(sys.argv[2]), int(sys.argv[3]), *map(float, sys.argv[4:5]))
    elif mode == "guess":
        guess(float(sys.argv[2]), int(sys.argv[3]), sys.argv[4])
    elif mode == "profile":
        profile(int(sys.argv[2]))
    elif mode == "toy":
        toy()
    else:
        raise SystemExit(__doc__)
