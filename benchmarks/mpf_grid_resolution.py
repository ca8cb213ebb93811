"""The consistent MPF's steering std where its grid does not resolve the posterior: the numbers
behind vehjax/filters/marginalized/grid.py's docstring and
tests/filters/marginalized/test_grid_filter.py's user-model test.

    python benchmarks/mpf_grid_resolution.py RUNS SEED POINTS [known] [weighted]

The linear SingleTrackBank written as a user would (tests/_bank_ref.py's user_linear_bank),
data simulated in numpy at other values than the consistency study's (steering offset 0.4 deg,
noise 0.25 deg, biases ay -0.15 m/s^2, r 0.3 deg/s, roll rate -0.2 deg/s, sensor stds 1.5 x
the test module's STD0), RUNS runs x 400 steps, seed SEED; ``marginalized_pf_grid``
at its defaults with POINTS grid points over a decade either side of the steering
guess (twice the truth), the sensor stds guessed at twice the truth; ``known``: the sensor
covariances known instead (guesses at the truth, nu0 = 1e10); ``weighted``: the grid's
weighted moments everywhere (``vehjax.filters.marginalized.grid.RESOLVED = 0``, as before that module).
Prints per learnt parameter the mean estimate over the truth (stds) or its mean error in mean
reported stds (offset, biases), the spread over runs / mean reported std, the reported std
over the truth (mean and least) and the 95 % intervals' coverage; then the NEES of (vy, r)
over the last half, per dof and its share in the band.

Examples (the docstrings' numbers): ``100 22 25 known``; ``100 22 25 known weighted``;
``100 22 100 known``; ``100 22 25``; ``100 22 100``; ``100 21 25``; ``100 21 100``.
"""

import sys

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, "tests")

import vehjax as vj  # noqa: E402
from vehjax import metrics  # noqa: E402
from vehjax.filters.marginalized import grid as _grid  # noqa: E402

from _bank_ref import user_bank_case  # noqa: E402

STEPS = 400


def main(runs, seed, points, known=False, weighted=False):
    if weighted:
        _grid.RESOLVED = 0.0
    est, X, Y, U, truth, run_kw = user_bank_case(runs, seed, points, known, STEPS)
    out = vj.run(est, Y, U, progress=False, **run_kw)
    print(f"{runs} runs x {STEPS} steps, seed {seed}, {points} points"
          f"{', sensor covariances known' if known else ''}"
          f"{', weighted moments everywhere' if weighted else ''}:")
    for name, value in truth.items():
        j = est.param_names.index(name)
        got = np.asarray(out.params[:, -1, j])
        sd = np.sqrt(np.asarray(out.params_cov[:, -1, j, j]))
        err = (f"mean / truth {got.mean() / value:.3f}" if name.endswith("_std") else
               f"mean error / sd {(got.mean() - value) / sd.mean():+.2f}")
        print(f"  {name:15s} {err}, spread / sd {got.std() / sd.mean():.2f}, sd / truth "
              f"{sd.mean() / abs(value):.4f} (least {sd.min() / abs(value):.4f}), coverage "
              f"{np.mean(np.abs(got - value) <= 1.96 * sd):.2f}")
    half = slice(STEPS // 2, None)
    nees = metrics.nees(np.asarray(out.states)[:, half, :2],
                        np.asarray(out.covariances)[:, half, :2, :2], X[:, half, :2])
    print(f"  NEES (vy, r), last half: {np.mean(nees) / 2:.3f} per dof, in band "
          f"{metrics.consistency(nees, 2).inside:.3f}")


if __name__ == "__main__":
    if len(sys.argv) < 4:
        raise SystemExit(__doc__)
    main(int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), "known" in sys.argv[4:],
         "weighted" in sys.argv[4:])
