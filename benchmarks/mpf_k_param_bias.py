"""Bias and spread of the consistent MPF's learnt noise stds on the consistency study's data
(``vehjax reproduce consistency --filters MPF-K``): the numbers behind its ay-std remark.

    python benchmarks/mpf_k_param_bias.py SEED POINTS [PRIOR [STEER_FACTOR [VARIANCES]]]

runs ``MPF-K`` (100 runs x 300 steps, POINTS grid points, PRIOR of the steering std: jeffreys
(default), inverse-wishart, log-uniform over a tenth to ten times the truth, or known (a grid of
the true std alone); STEER_FACTOR scales the true steering std of the data and the filter,
default 1; VARIANCES the sensor variances, ``marginalized_pf``'s ``sensor_variances``: scored
(default, as the builder's) or inverse-wishart) and prints, per learnt std at steps 100, 200 and
300: mean error / mean reported std, spread of the estimates over runs / mean reported std, mean
relative error, reported std / truth and the coverage of the 95 % interval. Then the oracle for
each sensor whose output does not depend on the (noisy) steering input: the sample std of its
true noise per run (states and bias known, 300 steps), its mean relative error, spread over runs
/ its theoretical std truth / sqrt(2 x 300), and the coverage of that interval: how much of a
filter's spread and coverage is the seed's draws. Last, the scores of the sensor variances under
numpy's exact Kalman filter with every noise known (:func:`exact_scores`): zero but for
Monte-Carlo error where the data are the model's.
"""

import sys

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, "tests")

import vehjax as vj  # noqa: E402
from vehjax.studies.banked_road import MATCHED, matched_setup, matched_truth, simulate_matched  # noqa: E402,E501

from _bank_ref import exact_kalman  # noqa: E402


def main(seed, points, prior="jeffreys", steer_factor=1.0, variances="scored"):
    noise = MATCHED._replace(steer_std=MATCHED.steer_std * float(steer_factor))
    sd0 = noise.steer_std
    model = vj.models.SingleTrackBank(dt=0.01)
    X, Y, U = simulate_matched(model, 100, 300, seed, noise)
    extra = {"jeffreys": {}, "inverse-wishart": dict(input_std_prior="inverse-wishart"),
             "known": dict(input_std_prior="log-uniform",
                           input_std_range=(sd0, sd0 * (1 + 1e-9))),
             "log-uniform": dict(input_std_prior="log-uniform",
                                 input_std_range=(sd0 / 10, sd0 * 10))}[prior]
    options = dict(builder="grid", **extra, sensor_variances=variances)  # the study's MPF-K
    P0 = np.full(len(model.state_names), 1e-12)
    est, x0, P0_f, _ = matched_setup(model, points, options, P0, noise)
    out = vj.run(est, Y, U, x0=x0, P0=P0_f, key=jax.random.key(seed * 101 + 99),
                 return_covariances=True, progress=False)
    th = matched_truth(est.param_names, noise)
    print(f"MPF-K, seed {seed}, {points} points, steering-std prior {prior}, steering std "
          f"{steer_factor} x the study's, sensor variances {variances}:")
    for k in (99, 199, 299):
        e = np.asarray(out.params[:, k]) - th
        sd = np.sqrt(np.diagonal(np.asarray(out.params_cov[:, k]), axis1=-2, axis2=-1))
        print(f"  step {k + 1}:")
        for i, n in enumerate(est.param_names):
            if n.endswith("_std"):
                print(f"    {n:14s} bias/sd {e[:, i].mean() / sd[:, i].mean():+.2f}  spread/sd "
                      f"{e[:, i].std() / sd[:, i].mean():.2f}  rel. bias "
                      f"{e[:, i].mean() / th[i]:+.4f}  sd/truth {sd[:, i].mean() / th[i]:.4f}  "
                      f"coverage {np.mean(np.abs(e[:, i]) <= 1.96 * sd[:, i]):.2f}")
    T = Y.shape[1]
    u0 = jnp.asarray([noise.speed, 0.0])
    ddelta = jax.jacfwd(lambda u: model.observe(jnp.zeros(len(model.state_names)), u,
                                                model.theta))(u0)[:, 1]
    clean = np.asarray(jax.vmap(jax.vmap(lambda x: model.observe(x, u0, model.theta)))(
        jnp.asarray(X)))
    print(f"  oracle (the true noise's sample std per run, {T} steps):")
    for j, n in enumerate(model.output_names):
        if n not in noise.sensor_std or float(ddelta[j]) != 0.0:
            continue
        rel = (np.sqrt(np.mean((Y[..., j] - clean[..., j] - noise.bias[n]) ** 2, axis=1))
               / noise.sensor_std[n])
        half = 1.0 / np.sqrt(2 * T)
        print(f"    {n + '_std':14s} rel. bias {rel.mean() - 1.0:+.4f}  spread/sd "
              f"{rel.std() / half:.2f}  coverage {np.mean(np.abs(rel - 1.0) <= 1.96 * half):.2f}")
    exact_scores(model, Y, U, noise)


def exact_scores(model, Y, U, noise=MATCHED):
    """The scores of the sensor variances under numpy's exact Kalman filter
    (tests/_bank_ref.py's ``exact_kalman``: the linear SingleTrackBank at the study's speed,
    every noise, the offset and the biases known), as the scored filter's pseudo-observations
    see them: the mean over runs and steps of s_i / W_ii (s = 0.5 (a_i^2 - G_ii), W_ii = 0.5
    G_ii^2, a = G nu, G = S^-1) relative to the true variance. Zero up to Monte-Carlo error
    when the filter's predictive covariance S is right."""
    names = model.output_names
    bias = np.array([noise.bias.get(n, 0.0) for n in names])
    std = np.array([noise.sensor_std.get(n, noise.known_std.get(n, 0.0)) for n in names])
    _, _, nus, Ss = exact_kalman(model.theta, noise.speed, model.dt, Y, U[:, 1], noise.offset,
                                 noise.steer_std, noise.bank_jerk_std, bias, std, np.zeros(5),
                                 np.diag(np.full(5, 1e-12)), model.bank_noise_gain(),
                                 innovations=True)
    G = np.linalg.solve(Ss, np.broadcast_to(np.eye(len(names)), Ss.shape))  # S^-1, (T, 5, 5)
    a = np.einsum("tij,rtj->rti", G, nus)
    g = np.diagonal(G, axis1=-2, axis2=-1)  # (T, 5)
    ratio = np.mean(0.5 * (a ** 2 - g), axis=0) / (0.5 * g ** 2)  # (T, 5)
    var = std ** 2
    print("  exact Kalman filter (numpy, every noise known): mean s_i / W_ii / variance:")
    print("    " + "  ".join(f"{n} {v:+.4f}" for n, v in zip(names, ratio.mean(0) / var)
                             if n in noise.sensor_std))


if __name__ == "__main__":
    if len(sys.argv) < 3:
        raise SystemExit(__doc__)
    main(int(sys.argv[1]), int(sys.argv[2]), *sys.argv[3:6])
