"""vehjax.metrics on hand-checkable arrays and against scipy.stats."""

import numpy as np
import pytest
from scipy import stats

import vehjax  # noqa: F401
from vehjax import metrics as M

# errors: run 0 -> [1, 3], run 1 -> [0, 4] (one component); a second component of zeros
EST = np.array([[[1.0, 5.0], [3.0, 5.0]], [[0.0, 5.0], [4.0, 5.0]]])
TRUTH = np.array([0.0, 5.0])  # constant truth, broadcast


def test_rmse_mae_by_hand():
    np.testing.assert_allclose(M.rmse(EST, TRUTH), [np.sqrt(26 / 4), 0.0])
    np.testing.assert_allclose(M.rmse(EST, TRUTH, axis="run"), [[np.sqrt(5), 0], [np.sqrt(8), 0]])
    np.testing.assert_allclose(M.rmse(EST, TRUTH, axis="time"), [[np.sqrt(0.5), 0], [np.sqrt(12.5), 0]])
    np.testing.assert_allclose(M.mae(EST, TRUTH), [2.0, 0.0])
    np.testing.assert_allclose(M.mae(EST, TRUTH, axis="run"), [[2.0, 0], [2.0, 0]])
    np.testing.assert_allclose(M.mae(EST, TRUTH, axis="time"), [[0.5, 0], [3.5, 0]])


def test_mask_excludes_runs():
    keep = np.array([True, False])
    np.testing.assert_allclose(M.rmse(EST, TRUTH, mask=keep), [np.sqrt(5), 0.0])
    per_run = M.rmse(EST, TRUTH, axis="run", mask=keep)
    np.testing.assert_allclose(per_run[0], [np.sqrt(5), 0])
    assert np.isnan(per_run[1]).all()
    assert np.isnan(M.mae(EST, TRUTH, mask=np.array([False, False]))).all()


def test_truth_broadcasting_forms_agree():
    rng = np.random.default_rng(0)
    est = rng.normal(size=(3, 4, 2))
    truth_rt = rng.normal(size=(3, 4, 2))
    full = M.rmse(est, truth_rt, axis="run")
    ref = np.sqrt(((est - truth_rt) ** 2).mean(axis=1))
    np.testing.assert_allclose(full, ref)
    per_run_const = rng.normal(size=(3, 2))
    np.testing.assert_allclose(
        M.mae(est, per_run_const[:, None, :]), np.abs(est - per_run_const[:, None, :]).mean(axis=(0, 1))
    )


@pytest.mark.parametrize(
    "call, arg",
    [
        (lambda: M.rmse(EST[0], TRUTH), "estimates"),
        (lambda: M.rmse(EST, np.zeros(3)), "truth"),
        (lambda: M.rmse(EST, TRUTH, axis=0), "axis"),
        (lambda: M.mae(EST, TRUTH, mask=[1, 0]), "mask"),
        (lambda: M.nees(EST, np.zeros((2, 2, 2)), TRUTH), "covariances"),
        (lambda: M.chi2_bounds(2, prob=1.5), "prob"),
        (lambda: M.chi2_bounds(-1), "dof"),
        (lambda: M.chi2_bounds(2, n_runs=0), "n_runs"),
        (lambda: M.consistency(np.zeros(3), 1), "values"),
        (lambda: M.consistency(np.zeros((2, 3)), np.ones(2)), "dof"),
        (lambda: M.convergence_time(EST, TRUTH, 1.0, dt=0.0), "dt"),
        (lambda: M.convergence_time(EST, TRUTH, [1.0, 1.0, 1.0], dt=0.1), "tol"),
        (lambda: M.final_error(EST, TRUTH, window=3), "window"),
        (lambda: M.confidence_interval(np.ones(3), level=95), "level"),
        (lambda: M.confidence_interval(np.ones(3), axis=2), "axis"),
    ],
)
def test_bad_arguments_raise(call, arg):
    with pytest.raises(ValueError, match=arg):
        call()


def test_nees_by_hand_and_against_solve():
    x = np.array([[[1.0, 2.0]]])
    P = np.array([[[[1.0, 0.0], [0.0, 4.0]]]])
    np.testing.assert_allclose(M.nees(x, P, np.zeros(2)), [[2.0]])
    rng = np.random.default_rng(1)
    A = rng.normal(size=(2, 3, 3, 3))
    P = A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(3)
    e = rng.normal(size=(2, 3, 3))
    ref = np.einsum("rti,rti->rt", e, np.linalg.solve(P, e[..., None])[..., 0])
    np.testing.assert_allclose(M.nees(e + 1.0, P, 1.0), ref, rtol=1e-10)
    P[0, 1] = -np.eye(3)
    assert np.isnan(M.nees(e, P, 0.0)[0, 1]) and np.isfinite(M.nees(e, P, 0.0)[1]).all()


def test_chi2_bounds_table_values_and_scipy():
    # Published table values (e.g. NIST/SEMATECH e-Handbook, table 1.3.6.7.4)
    low, high = M.chi2_bounds(10)
    assert abs(high - 20.483) < 5e-4 and abs(low - 3.247) < 5e-4
    assert abs(M.chi2_bounds(1, prob=0.99)[1] - 7.879) < 5e-4
    for dof, n, prob in [(1, 1, 0.95), (2, 50, 0.95), (3, 100, 0.99), (7, 1000, 0.9), (4, 2500, 0.95)]:
        low, high = M.chi2_bounds(dof, n, prob)
        a = (1 - prob) / 2
        np.testing.assert_allclose(
            [low, high], [stats.chi2.ppf(a, dof * n) / n, stats.chi2.ppf(1 - a, dof * n) / n], rtol=1e-10
        )
    lows, highs = M.chi2_bounds(np.array([0, 2, 6]), np.array([5, 5, 1]))
    np.testing.assert_allclose(lows, [0.0, stats.chi2.ppf(0.025, 10) / 5, stats.chi2.ppf(0.025, 6)], rtol=1e-10)
    np.testing.assert_allclose(highs, [0.0, stats.chi2.ppf(0.975, 10) / 5, stats.chi2.ppf(0.975, 6)], rtol=1e-10)


def test_consistency_regions_with_missing_data():
    values = np.array([[1.0, 2.0, np.nan], [3.0, 0.0, 5.0], [2.0, 4.0, 1.0]])
    dof = np.array([[2, 1, 2], [2, 0, 2], [2, 2, 2]])
    c = M.consistency(values, dof, prob=0.9)
    np.testing.assert_allclose(c.mean, [2.0, 2.0, 3.0])
    D, N = np.array([6, 3, 4]), np.array([3, 3, 2])
    np.testing.assert_allclose(c.low, stats.chi2.ppf(0.05, D) / N, rtol=1e-10)
    np.testing.assert_allclose(c.high, stats.chi2.ppf(0.95, D) / N, rtol=1e-10)
    inside = (c.mean >= c.low) & (c.mean <= c.high)
    assert c.inside == inside.mean()
    masked = M.consistency(values, dof, prob=0.9, mask=np.array([True, False, True]))
    np.testing.assert_allclose(masked.mean, [1.5, 3.0, 1.0])


def test_consistency_of_true_chi_square_samples():
    rng = np.random.default_rng(2)
    values = rng.chisquare(3, size=(50, 400))
    assert 0.9 <= M.consistency(values, 3).inside <= 0.99
    assert M.consistency(values * 1.5, 3).inside < 0.1  # over-confident covariance is caught


def test_convergence_time_by_hand():
    err = np.array([5.0, 0.5, 2.0, 0.5, 0.1])
    est = np.stack([err, -err, np.full(5, 3.0), np.array([0.1, 0.1, np.nan, 0.1, 0.1])])[:, :, None]
    t = M.convergence_time(est, 0.0, tol=1.0, dt=0.5, t0=2.0)
    np.testing.assert_allclose(t[:, 0], [2.0 + 3 * 0.5, 2.0 + 3 * 0.5, np.inf, 2.0 + 3 * 0.5])
    always = M.convergence_time(est[:, 3:], 0.0, tol=1.0, dt=0.5)
    np.testing.assert_allclose(always[[0, 1, 3], 0], [0.0, 0.0, 0.0])
    masked = M.convergence_time(est, 0.0, 1.0, 0.5, mask=np.array([True, False, True, True]))
    assert np.isnan(masked[1, 0]) and masked[0, 0] == 1.5


def test_final_error_by_hand():
    np.testing.assert_allclose(M.final_error(EST, TRUTH), [[3.0, 0.0], [4.0, 0.0]])
    np.testing.assert_allclose(M.final_error(EST, TRUTH, window=2), [[2.0, 0.0], [2.0, 0.0]])
    est = np.array([[[110.0], [90.0]]])
    np.testing.assert_allclose(M.final_error(est, 100.0, relative=True), [[-0.1]])
    np.testing.assert_allclose(M.final_error(est, 100.0, window=2, relative=True), [[0.0]])


def test_confidence_interval_against_scipy():
    rng = np.random.default_rng(3)
    x = rng.normal(2.0, 0.5, size=(12, 3))
    x[4, 1] = np.nan
    ci = M.confidence_interval(x, level=0.9)
    for j in range(3):
        col = x[:, j][~np.isnan(x[:, j])]
        lo, hi = stats.t.interval(0.9, len(col) - 1, loc=col.mean(), scale=stats.sem(col))
        np.testing.assert_allclose([ci.mean[j], ci.low[j], ci.high[j]], [col.mean(), lo, hi], rtol=1e-10)
    np.testing.assert_allclose(ci.high - ci.mean, ci.half_width)
    by_axis = M.confidence_interval(x.T, axis=1, level=0.9)
    np.testing.assert_allclose(by_axis.half_width, ci.half_width)
    keep = np.arange(12) < 6
    masked = M.confidence_interval(x, mask=keep)
    np.testing.assert_allclose(masked.mean[0], x[:6, 0].mean())
    single = M.confidence_interval(np.array([1.0, np.nan]))
    assert single.mean == 1.0 and np.isnan(single.half_width)
