"""vehjax.tune.fit with priors= (penalised likelihood, MAP in physical coordinates), the
pulls and the log-prior reported, the same prior dict in calibrate, and bad input.

References nobody here wrote: the exact Kalman likelihood of a scalar linear-Gaussian model
written out in numpy plus scipy.stats' log densities of the priors, maximised with
scipy.optimize.minimize, and its Hessian in physical units by numpy central finite
differences (the inverse of the posterior's curvature: the standard errors).
"""

import math
import warnings

import jax
import jax.flatten_util
import numpy as np
import pytest
import scipy.optimize
import scipy.stats

import vehjax as vj
import vehjax.tune as vt
from _linear import fd_hessian
from vehjax.calibrate.priors import LogNormal, Normal, Uniform

A, B, D, Q, R = 0.9, 0.5, 0.3, 0.04, 0.09
T = 400
X0, P0 = np.zeros(1), np.eye(1)
PRIORS = {"a": Normal(0.85, 0.05), "b": LogNormal(0.45, 0.3)}


def model(theta=(0.8, 0.6, 0.2), domains=None):
    """x' = a x + b u + w, y = x + d + v."""
    return vj.models.Model(
        transition=lambda x, u, th: th[0] * x + th[1] * u, observe=lambda x, u, th: x + th[2],
        dt=0.1, state_names=("x",), param_names=("a", "b", "d"), input_names=("u",),
        output_names=("y",), theta=list(theta), domains=domains,
        units={"x": "m", "u": "m", "y": "m", "a": "-", "b": "-", "d": "m"})


def data(seed=0, n=T):
    rng = np.random.default_rng(seed)
    us = rng.normal(size=(n, 1))
    x, ys = rng.normal(), []
    for t in range(n):
        x = A * x + B * us[t, 0] + math.sqrt(Q) * rng.normal()
        ys.append(x + D + math.sqrt(R) * rng.normal())
    return np.array(ys)[:, None], us


def kalman_loglik(p, ys, us):
    """Exact log p(y_1:T | a, b, d): the scalar Kalman filter (predict with u_t, update y_t)."""
    a, b, d = p
    x, P, total = 0.0, 1.0, 0.0
    for t in range(len(ys)):
        x, P = a * x + b * us[t, 0], a * a * P + Q
        S = P + R
        e = ys[t, 0] - x - d
        total += -0.5 * (e * e / S + math.log(2 * math.pi * S))
        K = P / S
        x, P = x + K * e, (1 - K) * P
    return total


def scipy_log_prior(p, priors):
    total = 0.0
    for name, prior in priors.items():
        x = p["abd".index(name)]
        if isinstance(prior, Normal):
            total += scipy.stats.norm.logpdf(x, prior.mean, prior.std)
        else:
            total += scipy.stats.lognorm.logpdf(x, s=prior.sigma, scale=prior.median)
    return total


def tune_fit(priors, params=("d",), options=vt.Options(progress=False)):
    ys, us = data()
    return vt.fit(vj.filters.ekf, model(), [Q], [R], ys, us, x0=X0, P0=P0,
                  params=vt.Fitted(params, noise=(), priors=priors),
                  options=options)


@pytest.fixture(scope="module")
def map_fit():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no pull beyond 3 sigma here, nothing undetermined
        return tune_fit(PRIORS)


def test_map_matches_scipy(map_fit):
    ys, us = data()

    def neg(p):
        return -(kalman_loglik(p, ys, us) + scipy_log_prior(p, PRIORS))

    ref = scipy.optimize.minimize(neg, [0.8, 0.6, 0.2], method="Nelder-Mead",
                                  options=dict(xatol=1e-11, fatol=1e-13, maxiter=20000))
    est = np.array([map_fit.values[k] for k in ("a", "b", "d")])
    np.testing.assert_allclose(est, ref.x, rtol=1e-5)
    se_ref = np.sqrt(np.diag(np.linalg.inv(fd_hessian(neg, ref.x))))
    se = np.array([map_fit.std_errors[k] for k in ("a", "b", "d")])
    np.testing.assert_allclose(se, se_ref, rtol=1e-3)
    assert map_fit.converged
    # loglik is the plain log-likelihood, log_prior the priors' term, at the estimate
    np.testing.assert_allclose(map_fit.loglik, kalman_loglik(est, ys, us), rtol=1e-9)
    np.testing.assert_allclose(map_fit.log_prior, scipy_log_prior(est, PRIORS), rtol=1e-9)
    np.testing.assert_allclose(map_fit.loglik0, kalman_loglik([0.8, 0.6, 0.2], ys, us),
                               rtol=1e-9)


def test_pulls_and_summary(map_fit):
    a, b = map_fit.values["a"], map_fit.values["b"]
    assert map_fit.priors == PRIORS
    np.testing.assert_allclose(map_fit.pulls["a"], (a - 0.85) / 0.05, rtol=1e-12)
    np.testing.assert_allclose(map_fit.pulls["b"], (math.log(b) - math.log(0.45)) / 0.3,
                               rtol=1e-12)
    assert set(map_fit.pulls) == {"a", "b"}
    text = map_fit.summary()
    line = next(ln for ln in text.splitlines() if ln.strip().startswith("b "))
    assert f"(prior 0.45 to 30 %: pulled {abs(map_fit.pulls['b']):.2g} sigma from it)" in line
    assert "+-" in line and "[-]" in line
    assert "(prior 0.85 +- 0.05: pulled" in text
    assert "prior" not in next(ln for ln in text.splitlines() if ln.strip().startswith("d "))


def test_wide_prior_is_the_plain_fit():
    wide = tune_fit({"a": Normal(0.9, 1e4)})
    plain = tune_fit(None, params=("a", "d"))
    for k in ("a", "d"):
        np.testing.assert_allclose(wide.values[k], plain.values[k], rtol=1e-6)
        np.testing.assert_allclose(wide.std_errors[k], plain.std_errors[k], rtol=1e-4)
    assert plain.priors == {} and plain.pulls == {} and plain.log_prior == 0.0


def test_narrow_prior_holds_the_centre():
    res = tune_fit({"b": LogNormal(0.4, 1e-5)})
    assert abs(math.log(res.values["b"] / 0.4)) < 0.05 * 1e-5
    np.testing.assert_allclose(res.std_errors["b"], 0.4 * 1e-5, rtol=0.01)  # the prior's


def test_contradicting_prior_warns():
    with pytest.warns(UserWarning, match=r"data contradict the stated value of a .*sigma"):
        res = tune_fit({"a": Normal(0.5, 0.01)})
    assert res.pulls["a"] > 3.0
    assert "pulled" in res.summary()


def test_uniform_is_a_box():
    ys, us = data()
    kw = dict(x0=X0, P0=P0, options=vt.Options(progress=False))
    box = vt.fit(vj.filters.ekf, model(), [Q], [R], ys, us,
                 params=vt.Fitted(noise=(), priors={"b": Uniform(0.0, 2.0)}), **kw)
    ref = vt.fit(vj.filters.ekf, model(), [Q], [R], ys, us,
                 params=vt.Fitted(("b",), noise=(), bounds={"b": (0, 2)}), **kw)
    np.testing.assert_allclose(box.values["b"], ref.values["b"], rtol=1e-9)
    assert box.pulls == {} and "(prior uniform on (0, 2))" in box.summary()
    np.testing.assert_allclose(box.log_prior, -math.log(2.0), rtol=1e-12)


def test_same_priors_in_calibrate():
    ys, us = data(n=60)
    res = vj.calibrate.pmmh(vj.filters.ekf, model(theta=(0.85, 0.45, 0.3)), ys, us, x0=X0,
                            P0=P0, Q=[Q], R=[R], priors=PRIORS, key=jax.random.key(0),
                            chains=vj.calibrate.Chains(n=2, samples=4, warmup=4),
                            proposal=vj.calibrate.RandomWalk(adaptation=None))
    assert tuple(res.names) == ("a", "b")


@pytest.mark.parametrize("priors, match", [
    ({"zz": Normal(0.0, 1.0)}, r"priors: unknown parameter 'zz'"),
    ({"a": 0.9}, r"priors: 'a'"),
    ({"a": (0.9, 0.1)}, r"priors: 'a'"),
    ("a", r"priors"),
    ({"b": Normal(-1.0, 0.1)}, r"priors: 'b': the prior's centre -1 lies outside"),
    ({"b": Uniform(-3.0, -1.0)}, r"priors: 'b': the prior's support"),
])
def test_bad_priors(priors, match):
    ys, us = data(n=20)
    m = model(domains={"b": "(0, inf)"})
    for fn in (vt.fit, vt.fit_from_theta):
        with pytest.raises(ValueError, match=match):
            fn(vj.filters.ekf, m, [Q], [R], ys, us, x0=X0, P0=P0,
               params=vt.Fitted(noise=(), priors=priors), options=vt.Options(progress=False))


def test_uniform_beside_other_bounds_refused():
    ys, us = data(n=20)
    with pytest.raises(ValueError, match=r"priors: 'b' has a Uniform prior and bounds"):
        vt.fit(vj.filters.ekf, model(), [Q], [R], ys, us, x0=X0, P0=P0,
               params=vt.Fitted(noise=(), bounds={"b": (0.1, 3.0)},
                                priors={"b": Uniform(0.0, 2.0)}),
               options=vt.Options(progress=False))


def test_lognormal_within():
    p = LogNormal.within(2763.0, 0.3)
    assert p == LogNormal(2763.0, 0.3)
    with pytest.raises(ValueError, match="LogNormal.sigma"):
        LogNormal.within(2763.0, 0.0)


def test_objective_and_programs_carry_the_penalty():
    """The loss of vehjax.tune.objective (reverse mode) and the compiled forward-mode program,
    its BHHH matrix and its batched gradients all see the prior."""
    ys, us = data(n=100)
    args = (vj.filters.ekf, model(), [Q], [R], ys, us)
    obj, setup = vt.prepare(*args, x0=X0, P0=P0, params=vt.Fitted(("d",), noise=(),
                                                                  priors=PRIORS))
    p0 = [0.8, 0.6, 0.2]
    ref = -(kalman_loglik(p0, ys, us) + scipy_log_prior(p0, PRIORS)) / len(ys)
    np.testing.assert_allclose(float(obj.loss(obj.z0, obj.data)[0]), ref, rtol=1e-10)
    loss = vt.program.compiled_loss(obj, setup, batch_hessian=True)
    v, _, g, B = loss.vgo(loss.x0)
    np.testing.assert_allclose(v, ref, rtol=1e-10)
    g_rev = jax.flatten_util.ravel_pytree(jax.grad(lambda z: obj.loss(z, obj.data)[0])(
        obj.z0))[0]
    np.testing.assert_allclose(g, np.asarray(g_rev), rtol=1e-8)
    np.testing.assert_allclose(loss.grads(np.stack([loss.x0] * 6))[0], g, rtol=1e-8)
    plain_obj, plain_setup = vt.prepare(*args, x0=X0, P0=P0,
                                        params=vt.Fitted(("d", "a", "b"), noise=()))
    assert plain_setup.log_prior is None and setup.params == ("d", "a", "b")
    # the coordinates: theta = log d, log a, log b (the prior'd parameters after params); the
    # prior's curvature in log a is (a^2 + (a - mean) a) / std^2 and in log b 1 / sigma^2
    # (per step), none in d
    Bp = vt.program.compiled_loss(plain_obj, plain_setup).vgo(loss.x0)[3]
    a = 0.8
    expect = np.diag([0.0, (a * a + (a - 0.85) * a) / 0.05**2, 1 / 0.3**2]) / len(ys)
    np.testing.assert_allclose(B - Bp, expect, rtol=1e-8, atol=1e-12)


def test_jax_hessian_gives_the_same_standard_errors(map_fit):
    res = tune_fit(PRIORS, options=vt.Options(standard_errors=vt.StandardErrors(hessian="jax"),
                                              progress=False))
    for k in ("a", "b", "d"):
        np.testing.assert_allclose(res.std_errors[k], map_fit.std_errors[k], rtol=1e-4)
