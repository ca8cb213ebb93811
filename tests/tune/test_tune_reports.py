"""What a fit's report says: a quantity on a bound of its domain is reported on its bound (with
the bound and the derivative of the log-likelihood pointing out of the box), not "not determined
by the data"; standard errors come from the curvature of the likelihood, x0's too; a fit on one
step does not fail after fitting.

References nobody here wrote: the exact Kalman likelihood of a scalar linear-Gaussian model
written out in numpy, maximised with ``scipy.optimize.minimize`` (L-BFGS-B with the same bounds),
and its derivatives in physical units by numpy central finite differences. Data drawn here with
numpy.
"""

import warnings

import numpy as np
import pytest
import scipy.optimize

import vehjax as vj
from _linear import fd_hessian as _fd_hessian, scalar_kalman_loglik
import vehjax.tune as vt
from vehjax.tune import boundaries

A_TRUE, Q_TRUE, R_TRUE = 0.8, 0.3, 0.5
P0 = np.eye(1)
T = 300


def model(a=0.5):
    """x' = a x + u + w, y = x + v."""
    return vj.models.Model(
        transition=lambda x, u, th: th[0] * x + u[0], observe=lambda x, u, th: x, dt=0.1,
        state_names=("x",), param_names=("a",), input_names=("u",), output_names=("y",),
        theta=[a], units={"x": "m", "u": "m", "y": "m", "a": "-"})


def simulate(seed, T=T, x0=0.0):
    rng = np.random.default_rng(seed)
    us = rng.normal(size=(T, 1))
    x = x0 + rng.normal()
    ys = np.zeros((T, 1))
    for t in range(T):
        x = A_TRUE * x + us[t, 0] + rng.normal() * np.sqrt(Q_TRUE)
        ys[t, 0] = x + rng.normal() * np.sqrt(R_TRUE)
    return ys, us


def loglik(a, q, r, ys, us, x0=0.0):
    """Exact log p(y_1:T) of x' = a x + u + w (var q), y = x + v (var r), x_0 ~ N(x0, 1)."""
    return scalar_kalman_loglik(a, q, r, ys, us, x0, P0[0, 0])


def fd_hessian(fn, p, rel=1e-4):
    """Central finite-difference Hessian of fn at p (numpy), steps rel * max(|p_i|, 1e-2)."""
    return _fd_hessian(fn, p, rel, floor=1e-2)


def fd_std_errors(fn, p):
    """Standard errors from the inverse of minus the Hessian of the log-likelihood fn."""
    return np.sqrt(np.diag(np.linalg.inv(-fd_hessian(fn, p))))


def scipy_fit(ys, us, a_bounds):
    """Bounded maximum likelihood of (a, q, r) by scipy's L-BFGS-B on the numpy likelihood."""
    res = scipy.optimize.minimize(
        lambda p: -loglik(p[0], p[1], p[2], ys, us), x0=[0.5, 0.3, 0.5], method="L-BFGS-B",
        bounds=[a_bounds, (1e-8, None), (1e-8, None)],
        options=dict(ftol=1e-15, gtol=1e-10, maxiter=2000))
    return res.x


def tune_fit(ys, us, a_bounds, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = vt.fit(vj.filters.ekf, model(), 0.3 * np.eye(1), 0.5 * np.eye(1), ys, us,
                     x0=np.zeros(1), P0=P0, params=vt.Fitted(("a",), bounds={"a": a_bounds}),
                     options=vt.Options(progress=False), **kw)
    return res, [str(w.message) for w in caught]


def test_fit_away_from_a_bound_equals_scipy_and_finite_difference_standard_errors():
    ys, us = simulate(0)
    ref = scipy_fit(ys, us, (0.0, 0.95))
    res, _ = tune_fit(ys, us, (0.0, 0.95))
    got = np.array([res.values["a"], res.values["Q[x,x]"], res.values["R[y,y]"]])
    assert 0.0 < ref[0] < 0.9  # the maximum is inside the box
    np.testing.assert_allclose(got, ref, rtol=1e-4)
    assert res.on_bound == {} and res.undetermined == () and res.converged
    se = fd_std_errors(lambda p: loglik(p[0], p[1], p[2], ys, us), got)
    np.testing.assert_allclose([res.std_errors[k] for k in ("a", "Q[x,x]", "R[y,y]")], se,
                               rtol=2e-3)
    assert "on its" not in res.summary() and "not determined" not in res.summary()


def test_fit_at_a_bound_is_reported_on_its_bound_with_the_one_sided_derivative():
    ys, us = simulate(0)
    ref = scipy_fit(ys, us, (0.0, 0.6))
    assert ref[0] == pytest.approx(0.6, abs=1e-12)  # scipy's bounded maximum: on the bound
    res, messages = tune_fit(ys, us, (0.0, 0.6))
    np.testing.assert_allclose([res.values["a"], res.values["Q[x,x]"], res.values["R[y,y]"]],
                               ref, rtol=1e-4)
    side, bound, dlogl = res.on_bound["a"]
    assert (side, bound) == ("upper", 0.6) and list(res.on_bound) == ["a"]
    # the derivative of the likelihood at the bound, by numpy differences: positive (outward)
    h = 1e-5
    fd = (loglik(0.6 + h, *ref[1:], ys, us) - loglik(0.6 - h, *ref[1:], ys, us)) / (2 * h)
    assert dlogl > 0 and dlogl == pytest.approx(fd, rel=1e-3)
    assert res.converged and res.undetermined == () and np.isnan(res.std_errors["a"])
    text = res.summary()
    assert "not determined" not in text
    assert f"on its upper bound 0.6 (the likelihood increases beyond it: d logL/d a = " \
           f"{dlogl:.3g})" in text
    assert any("a is on its upper bound 0.6" in m for m in messages)
    assert not any("do not determine" in m for m in messages)
    # the free directions' curvature: standard errors of q and r with a held at its bound
    se = fd_std_errors(lambda p: loglik(0.6, p[0], p[1], ys, us), ref[1:])
    np.testing.assert_allclose([res.std_errors["Q[x,x]"], res.std_errors["R[y,y]"]], se,
                               rtol=2e-3)


def test_fit_x0_standard_errors_are_finite_and_equal_finite_differences():
    ys, us = simulate(3, x0=2.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing named undetermined
        res = vt.fit(vj.filters.ekf, model(A_TRUE), 0.3 * np.eye(1), 0.5 * np.eye(1), ys, us,
                     x0=np.zeros(1), P0=P0, params=vt.Fitted(x0=True),
                     options=vt.Options(progress=False))
    fn = lambda p: loglik(A_TRUE, p[1], p[2], ys, us, x0=p[0])  # noqa: E731
    ref = scipy.optimize.minimize(lambda p: -fn(p), x0=[0.0, 0.3, 0.5], method="L-BFGS-B",
                                  bounds=[(None, None), (1e-8, None), (1e-8, None)],
                                  options=dict(ftol=1e-15, gtol=1e-10, maxiter=2000)).x
    got = np.array([res.values["x0[x]"], res.values["Q[x,x]"], res.values["R[y,y]"]])
    np.testing.assert_allclose(got, ref, rtol=1e-3, atol=1e-6)
    assert res.undetermined == () and res.on_bound == {} and res.converged
    se = fd_std_errors(fn, got)
    got_se = np.array([res.std_errors[k] for k in ("x0[x]", "Q[x,x]", "R[y,y]")])
    assert np.all(np.isfinite(got_se))
    np.testing.assert_allclose(got_se, se, rtol=2e-3)
    assert "not determined" not in res.summary()


@pytest.mark.parametrize("y", [0.0, 3.0])
def test_single_step_fit_with_the_default_optimizer_does_not_fail(y):
    """One step: log p(y_1) = log N(y_1; u, a^2 P0 + Q + R); the maximum over Q, R >= 0 is
    S = y^2 when y^2 > a^2 P0 (Q and R not determined apart), else Q = R = 0 (on their bounds)."""
    a = 0.5
    ys, us = np.array([[y]]), np.zeros((1, 1))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = vt.fit(vj.filters.ekf, model(a), 0.3 * np.eye(1), 0.5 * np.eye(1), ys, us,
                     x0=np.zeros(1), P0=P0, options=vt.Options(progress=False))
    S = max(y * y, a * a * P0[0, 0])
    best = -0.5 * (y * y / S + np.log(2 * np.pi * S))
    assert res.loglik == pytest.approx(best, rel=1e-6, abs=1e-6) and res.converged
    out = vj.filter(res.estimator, ys, us, x0=np.zeros(1), P0=P0)  # the estimator is built
    assert np.all(np.isfinite(np.asarray(out.loglik)))
    if y == 0.0:
        assert {k: v[:2] for k, v in res.on_bound.items()} == {
            "Q[x,x]": ("lower", 0.0), "R[y,y]": ("lower", 0.0)}
        assert "on its lower bound 0" in res.summary()
    else:
        assert res.on_bound == {} and res.undetermined
        # converged: |d loss / d z| <= gtol for z = log std of Q and of R, i.e.
        # (max(Q, R) / S) |1 - y^2 / S| <= gtol with max(Q, R) >= S / 2: S within 2 gtol
        assert res.values["Q[x,x]"] + res.values["R[y,y]"] == pytest.approx(
            y * y - a * a, rel=2 * vt.optimisers.GTOL)


def test_on_bounds_on_its_own():
    """The rule: near a bound and the likelihood increasing beyond it."""
    bnds = {"a": (0.0, 1.0, 0.5), "q": (0.0, np.inf, 2.0)}
    names = ("a", "q", "b")
    J = np.diag([1e-7, 1e-9, 1.0])
    n = 100
    # a near its upper bound, the loss falling beyond it (g < 0); q near 0, loss falling below
    on = boundaries.on_bounds(bnds, names, {"a": 1 - 1e-7, "q": 1e-9, "b": 3.0},
                              np.array([-1e-7, 2e-9, 0.0]), J, names, n)
    assert on == {"a": ("upper", 1.0, pytest.approx(100.0)),
                  "q": ("lower", 0.0, pytest.approx(-200.0))}
    # pointing inward: not on its bound
    assert boundaries.on_bounds(bnds, names, {"a": 1 - 1e-7, "q": 1.0, "b": 3.0},
                                np.array([1e-7, 0.0, 0.0]), J, names, n) == {}
    # far from the bound: not on it
    assert boundaries.on_bounds(bnds, names, {"a": 0.9, "q": 1.0, "b": 3.0},
                                np.array([-1e-7, 0.0, 0.0]), J, names, n) == {}


def test_uncertainty_holds_fixed_coordinates_and_exempts_per_coordinate():
    I = np.array([[4.0, 1.0], [1.0, 2.0]])
    J = np.eye(2)
    u = vt.uncertainty(I, J, np.ones(2), ("p", "q"), fixed=np.array([True, False]),
                       pinned=np.array([True, False]))
    assert np.isnan(u.std_errors[0]) and u.std_errors[1] == pytest.approx(np.sqrt(1 / 2.0))
    # an information below 1 / scale^2 is undetermined by size, unless exempted
    small = np.diag([0.25, 4.0])
    assert vt.uncertainty(small, J, np.ones(2), ("x0", "q")).undetermined == ("x0",)
    u2 = vt.uncertainty(small, J, np.ones(2), ("x0", "q"), max_std=np.array([np.inf, 1.0]))
    assert u2.undetermined == () and u2.std_errors[0] == pytest.approx(2.0)


def test_fitted_parameters_stay_in_the_models_physical_domain_by_default():
    """A built-in model's declared domains are tune.fit's default bounds (issue 47 item 1): the
    friction coefficient of the brush tyres is fitted in its domain (0, 3), a user's bounds
    narrow it, and bounds that leave no room inside it are refused naming ``bounds``."""
    from vehjax.tune.parameterisation import param_transform

    model = vj.models.SingleTrack(tyres="brush")
    names, theta = tuple(model.param_names), np.asarray(model.theta)
    dom = model.param_domains()
    _, tr = param_transform(("mu", "cf"), None, theta, names, dom)
    assert tr.bounds == ((0.0, 0.0), (3.0, np.inf))
    _, tr = param_transform(("mu",), {"mu": (0.5, 5.0)}, theta, names, dom)
    assert tr.bounds == ((0.5,), (3.0,))
    with pytest.raises(ValueError, match="^bounds: mu's bounds .* outside its physical domain"):
        param_transform(("mu",), {"mu": (4.0, 5.0)}, theta, names, dom)
    # a user model without declared domains: as before (positive start: kept positive)
    _, tr = param_transform(("mu",), None, theta, names, None)
    assert tr.bounds == ((0.0,), (np.inf,))
