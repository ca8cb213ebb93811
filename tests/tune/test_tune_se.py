"""vehjax.tune.fit: the optimum (L-BFGS by default, Newton polish), standard errors from the
observed information, and the quantities the data do not determine.

References nobody here wrote: the exact Kalman likelihood of a scalar linear-Gaussian model
written out in numpy, maximised with scipy.optimize, and its Hessian in physical units by numpy
central finite differences (the inverse observed information). Data drawn here with numpy.
"""

import functools
import warnings

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import vehjax as vj
from _linear import fd_hessian, scalar_kalman_loglik
import vehjax.tune as vt

A_TRUE, Q_TRUE, R_TRUE, SU_TRUE = 0.8, 0.3, 0.5, 0.6
X0, P0 = np.zeros(1), np.eye(1)
T = 300


def scalar_model(extra=False):
    """x' = a x + u (+ b u2), y = x; ``extra`` adds a parameter b on an input that is zero in the
    data (b does not enter the likelihood)."""
    def f(x, u, th):
        out = th[0] * x + u[0]
        return out + th[1] * u[1] if extra else out

    return vj.models.Model(
        transition=f, observe=lambda x, u, th: x, dt=0.1, state_names=("x",),
        param_names=("a", "b") if extra else ("a",), input_names=("u", "u2") if extra else ("u",),
        output_names=("y",), theta=[0.5, 1.0] if extra else [0.5],
        units={"x": "m", "u": "m", "u2": "m", "y": "m", "a": "-", "b": "-"})


def simulate(seed, q, T=T):
    """One run: inputs (T, 1) N(0, 1), measurements (T, 1); process noise variance q."""
    rng = np.random.default_rng(seed)
    us = rng.normal(size=(T, 1))
    x = X0[0] + rng.normal() * np.sqrt(P0[0, 0])
    ys = np.zeros((T, 1))
    for t in range(T):
        x = A_TRUE * x + us[t, 0] + rng.normal() * np.sqrt(q)
        ys[t, 0] = x + rng.normal() * np.sqrt(R_TRUE)
    return ys, us


def loglik(a, q, r, ys, us):
    """Exact log p(y_1:T) of x' = a x + u + w (var q), y = x + v (var r), numpy."""
    return scalar_kalman_loglik(a, q, r, ys, us, X0[0], P0[0, 0])


def hessian_fd(fn, p, rel=1e-4):
    """Central finite-difference Hessian of fn at p (steps rel * |p_i|)."""
    return fd_hessian(fn, p, rel)


def reference(fn, p0):
    """scipy maximum likelihood on log coordinates: (physical optimum, its covariance)."""
    ref = scipy.optimize.minimize(lambda l: -fn(np.exp(l)), np.log(p0), method="BFGS",
                                  options=dict(gtol=1e-9, maxiter=1000))
    p = np.exp(ref.x)
    cov = np.linalg.inv(-hessian_fd(fn, p))
    return p, cov


def test_fit_with_input_noise_equals_scipy_ml_and_inverse_information():
    """a, the input std and R fitted (Q = 0: the process noise comes through the input) by the
    default optimiser (L-BFGS, then Newton): within 1e-3 relative of scipy's maximum of the
    exact likelihood; standard errors and correlation within 2 % of the numpy inverse observed
    information in physical units (a, std of u in m, R in m^2)."""
    ys, us = simulate(0, q=SU_TRUE**2)
    fn = lambda p: loglik(p[0], p[1] ** 2, p[2], ys, us)  # noqa: E731
    p_ml, cov = reference(fn, np.array([0.5, 0.3, 1.0]))

    res = vt.fit(functools.partial(vj.filters.ekf, input_noise={"u": 0.3}), scalar_model(),
                 np.zeros(1), [1.0], ys, us, x0=X0, P0=P0,
                 params=vt.Fitted(("a",), noise=("R", "input")), options=vt.Options(progress=False))
    assert res.converged and res.gradient <= 1e-6 and not res.undetermined
    got = np.array([res.values["a"], res.values["input[u]"], res.values["R[y,y]"]])
    np.testing.assert_allclose(got, p_ml, rtol=1e-3)
    np.testing.assert_allclose(res.loglik, fn(p_ml), rtol=1e-9, atol=1e-6)
    assert res.units["input[u]"] == "m" and res.units["R[y,y]"] == "m^2"
    assert set(res.input_noise) == {"u"} and res.input_noise["u"] == res.values["input[u]"]
    se = np.array([res.std_errors[k] for k in ("a", "input[u]", "R[y,y]")])
    np.testing.assert_allclose(se, np.sqrt(np.diag(cov)), rtol=0.02)
    keys = list(res.values)
    order = [keys.index(k) for k in ("a", "input[u]", "R[y,y]")]
    corr_ref = cov / np.outer(np.sqrt(np.diag(cov)), np.sqrt(np.diag(cov)))
    np.testing.assert_allclose(res.correlations[np.ix_(order, order)], corr_ref, atol=0.02)
    # the fitted estimator carries the fitted input noise: its likelihood is the fit's
    out = vj.filter(res.estimator, ys, us, x0=X0, P0=P0)
    np.testing.assert_allclose(out.loglik.sum(), res.loglik, rtol=1e-9)


def test_fit_q_r_and_parameter_equals_scipy_ml():
    """a, Q and R by the defaults: within 1e-3 relative of scipy's maximum likelihood, the
    standard errors within 2 % of the inverse observed information."""
    ys, us = simulate(1, q=Q_TRUE)
    fn = lambda p: loglik(p[0], p[1], p[2], ys, us)  # noqa: E731
    p_ml, cov = reference(fn, np.array([0.5, 1.0, 1.0]))
    res = vt.fit(vj.filters.ckf, scalar_model(), [1.0], [1.0], ys, us, x0=X0, P0=P0, params=("a",),
                 options=vt.Options(progress=False))
    got = np.array([res.values["a"], res.values["Q[x,x]"], res.values["R[y,y]"]])
    np.testing.assert_allclose(got, p_ml, rtol=1e-3)
    se = np.array([res.std_errors[k] for k in ("a", "Q[x,x]", "R[y,y]")])
    np.testing.assert_allclose(se, np.sqrt(np.diag(cov)), rtol=0.02)
    assert "+-" in res.summary()


def test_undetermined_parameter_is_named():
    """b multiplies an input that is zero throughout: the likelihood does not depend on it.
    The fit names it (warning and field), its standard error is inf, a stays determined."""
    ys, us = simulate(2, q=Q_TRUE, T=100)
    us2 = np.concatenate([us, np.zeros_like(us)], axis=1)
    with pytest.warns(UserWarning, match=r"do not determine b\b"):
        res = vt.fit(vj.filters.ekf, scalar_model(extra=True), [Q_TRUE], [R_TRUE], ys, us2, x0=X0,
                     P0=P0, params=vt.Fitted(("a", "b"), noise=()),
                     options=vt.Options(progress=False))
    assert res.undetermined == ("b",)
    assert res.std_errors["b"] == np.inf and res.values["b"] == 1.0  # never moved
    assert np.isfinite(res.std_errors["a"]) and 0 < res.std_errors["a"] < 0.1
    assert np.isnan(res.correlations[0, 1])
    assert "not determined by the data: b" in res.summary()


def test_confounded_pair_is_named_and_q_zero_refused_when_fitted():
    """Only the product a b enters the model: both are named. A Q0 of zero is accepted when Q
    is not fitted and refused, naming Q0, when it is."""
    model = vj.models.Model(transition=lambda x, u, th: th[0] * th[1] * x + u,
                            observe=lambda x, u, th: x, dt=0.1, state_names=("x",),
                            input_names=("u",), param_names=("a", "b"), theta=[1.0, 0.7])
    ys, us = simulate(3, q=Q_TRUE, T=100)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        res = vt.fit(vj.filters.ekf, model, [Q_TRUE], [R_TRUE], ys, us, x0=X0, P0=P0,
                     params=vt.Fitted(("a", "b"), noise=()), options=vt.Options(progress=False))
    assert set(res.undetermined) == {"a", "b"}
    assert any("a, b" in str(m.message) for m in w)
    np.testing.assert_allclose(res.values["a"] * res.values["b"], A_TRUE, atol=0.1)
    with pytest.raises(ValueError, match="^Q0"):
        vt.fit(vj.filters.ekf, model, np.zeros(1), [R_TRUE], ys, us, x0=X0, P0=P0,
               params=vt.Fitted(noise=("Q",)), options=vt.Options(progress=False))


def test_uncertainty_on_its_own():
    """The delta method and the undetermined rule on a made-up information matrix."""
    Iz = np.diag([400.0, 1e-12, 100.0])
    J = np.diag([2.0, 1.0, 3.0])
    u = vt.uncertainty(Iz, J, np.ones(3), ("p", "q", "r"))
    assert u.undetermined == ("q",)
    np.testing.assert_allclose(u.std_errors[[0, 2]], [2.0 / 20.0, 3.0 / 10.0])
    assert u.std_errors[1] == np.inf
    # scales: a standard error above the quantity's own size is undetermined too
    u2 = vt.uncertainty(np.diag([400.0, 0.25]), np.eye(2), np.array([1.0, 1.0]), ("p", "q"))
    assert u2.undetermined == ("q",)
    u3 = vt.uncertainty(np.diag([400.0, 0.25]), np.eye(2), np.array([1.0, 4.0]), ("p", "q"))
    assert u3.undetermined == () and np.isclose(u3.std_errors[1], 2.0)


def test_jax_hessian_equals_gradient_differences():
    """hessian="jax" (forward over reverse) and the default central differences of the JAX
    gradient give the same standard errors (1e-5 relative). (The particle-filter half of this
    check, which compiles a reverse-mode gradient and a Hessian through the particle filter,
    is the slow test below.)"""
    ys, us = simulate(4, q=Q_TRUE, T=60)
    common = dict(x0=X0, P0=P0, params=("a",))
    quiet = vt.Options(progress=False)
    d = vt.fit(vj.filters.ekf, scalar_model(), [1.0], [1.0], ys, us, options=quiet, **common)
    j = vt.fit(vj.filters.ekf, scalar_model(), [1.0], [1.0], ys, us,
               options=vt.Options(standard_errors=vt.StandardErrors(hessian="jax"),
                                  progress=False), **common)
    for k in ("a", "Q[x,x]", "R[y,y]"):
        np.testing.assert_allclose(j.std_errors[k], d.std_errors[k], rtol=1e-5)


@pytest.mark.slow  # three compiles, two of them through the particle filter: ~25 s CPU
def test_particle_fit_reports_standard_errors_of_the_kalman_size():
    """A particle-filter fit (adam by default, Hessian by JAX) reports finite standard errors
    of the size of the Kalman ones (the EKF fit's, differences of the gradient)."""
    import jax

    ys, us = simulate(4, q=Q_TRUE, T=60)
    common = dict(x0=X0, P0=P0, params=("a",))
    quiet = vt.Options(progress=False)
    d = vt.fit(vj.filters.ekf, scalar_model(), [1.0], [1.0], ys, us, options=quiet, **common)
    pf = vt.fit(functools.partial(vj.filters.bootstrap_pf, n_particles=256), scalar_model(),
                [Q_TRUE], [R_TRUE], ys, us,
                options=vt.Options(optimizer=vt.Adam(steps=3), progress=False,
                                   key=jax.random.key(0)),
                params=vt.Fitted(("a",), noise=("R",)),
                x0=X0, P0=P0)
    assert pf.iterations == 3 and np.isfinite(pf.std_errors["a"])
    np.testing.assert_allclose(pf.std_errors["a"], d.std_errors["a"], rtol=0.5)


def per_step_loglik(a, q, r, ys, us):
    """log p(y_t | y_1:t-1) per step (T,) of the scalar model, numpy (as ``loglik``)."""
    x, P, out = X0[0], P0[0, 0], np.zeros(len(ys))
    for t in range(len(ys)):
        x, P = a * x + us[t, 0], a * a * P + q
        S = P + r
        e = ys[t, 0] - x
        out[t] = -0.5 * (e * e / S + np.log(2 * np.pi * S))
        K = P / S
        x, P = x + K * e, (1 - K) * P
    return out


def test_forward_scores_and_bhhh_equal_numpy_differences():
    """forward_scores' per-step derivatives equal numpy central differences of the exact
    per-step Kalman log-likelihood in the fit's coordinates (Q = exp(2 zQ), R = exp(2 zR),
    a = exp(za), sorted keys Q, R, theta), and score_outer_product is their outer product
    sum / T."""
    import jax
    import jax.flatten_util

    ys, us = simulate(5, q=Q_TRUE, T=40)
    obj, info = vt.prepare(vj.filters.ekf, scalar_model(), [0.4], [0.7], ys, us, x0=X0, P0=P0,
                           params=("a",))
    flat, unravel = jax.flatten_util.ravel_pytree(obj.z0)
    ll, dll, div = vt.forward_scores(lambda g, d: info.per_step(unravel(g), d), flat,
                                     obj.data)
    z = np.asarray(flat)
    phys = lambda z: (np.exp(z[2]), np.exp(2 * z[0]), np.exp(2 * z[1]))  # noqa: E731
    np.testing.assert_allclose(np.asarray(ll)[0], per_step_loglik(*phys(z), ys, us), rtol=1e-10)
    fd = np.zeros((3, len(ys)))
    for i in range(3):
        e = np.zeros(3)
        e[i] = 1e-6
        fd[i] = (per_step_loglik(*phys(z + e), ys, us)
                 - per_step_loglik(*phys(z - e), ys, us)) / 2e-6
    np.testing.assert_allclose(np.asarray(dll)[:, 0], fd, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(vt.score_outer_product(dll, len(ys)), fd @ fd.T / len(ys),
                               rtol=1e-6)
    assert not bool(np.asarray(div)[0])


def test_scoring_direction_solves_the_damped_system():
    """The BHHH step solves (B + damping lam_max I) d = -g in scaled coordinates (numpy solve),
    and drops directions without curvature."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(4, 4))
    B, g, sc = A @ A.T + 0.1 * np.eye(4), rng.normal(size=4), np.array([1.0, 2.0, 0.5, 3.0])
    S = np.diag(sc)
    lam = np.linalg.eigvalsh(S @ B @ S).max()
    want = -S @ np.linalg.solve(S @ B @ S + 0.3 * lam * np.eye(4), S @ g)
    np.testing.assert_allclose(vt.scoring_direction(g, B, sc, 0.3), want, rtol=1e-10)
    d = vt.scoring_direction(np.array([1.0, 5.0]), np.diag([2.0, 0.0]), np.ones(2))
    np.testing.assert_allclose(d, [-0.5, 0.0])


def test_default_is_forward_scoring_and_lbfgs_reaches_the_same_optimum():
    """The default for a deterministic filter with few coordinates: BHHH scoring on forward-mode
    derivatives; L-BFGS (reverse mode beyond 12 coordinates, forward here) reaches the same
    optimum, both within 1e-3 relative of scipy's maximum of the exact likelihood."""
    ys, us = simulate(6, q=Q_TRUE, T=200)
    fn = lambda p: loglik(p[0], p[1], p[2], ys, us)  # noqa: E731
    p_ml, _ = reference(fn, np.array([0.5, 1.0, 1.0]))
    common = dict(x0=X0, P0=P0, params=("a",))
    quiet = vt.Options(progress=False)
    d = vt.fit(vj.filters.ekf, scalar_model(), [1.0], [1.0], ys, us, options=quiet, **common)
    lb = vt.fit(vj.filters.ekf, scalar_model(), [1.0], [1.0], ys, us,
                options=vt.Options(optimizer="lbfgs", progress=False), **common)
    assert (d.optimizer, d.derivatives, lb.optimizer) == ("scoring", "forward", "lbfgs")
    assert d.converged and lb.converged and 0 < d.evaluations and 0 < d.compile_seconds
    assert d.compile_seconds < d.seconds and 0 < d.compile_cpu_seconds
    for r in (d, lb):
        got = np.array([r.values["a"], r.values["Q[x,x]"], r.values["R[y,y]"]])
        np.testing.assert_allclose(got, p_ml, rtol=1e-3)
    with pytest.raises(ValueError, match="^optimizer"):
        vt.fit(vj.filters.bootstrap_pf, scalar_model(), [1.0], [1.0], ys, us,
               options=vt.Options(optimizer="scoring", progress=False,
                                  key=__import__("jax").random.key(0)),
               **common)


def test_hessian_from_gradients_batched_equals_one_by_one_and_the_analytic_hessian():
    """hessian_from_gradients with the 2 n difference points in one call (``grads``, as the
    long forward-mode fits do) gives the Hessian of a made-up smooth function written out by
    hand (1e-7 relative), the same as the points one by one (1e-12)."""
    A = np.array([[4.0, 1.0, 0.5], [1.0, 3.0, -0.2], [0.5, -0.2, 2.0]])
    c = np.array([0.3, -0.1, 0.2])

    def grad(x):  # f(x) = x.A.x / 2 + sum(c exp(x)) + x0^2 x1
        return A @ x + c * np.exp(x) + np.array([2 * x[0] * x[1], x[0] ** 2, 0.0])

    x, scales = np.array([0.2, -0.4, 0.7]), np.array([1.0, 0.5, 2.0])
    want = A + np.diag(c * np.exp(x))
    want[0, 0] += 2 * x[1]
    want[0, 1] += 2 * x[0]
    want[1, 0] += 2 * x[0]
    calls = []

    def grads(F):
        calls.append(F.shape)
        return np.stack([grad(f) for f in F])

    one = vt.hessian_from_gradients(lambda f: (0.0, None, grad(f)), x, scales)
    batched = vt.hessian_from_gradients(None, x, scales, grads=grads)
    assert calls == [(6, 3)]
    np.testing.assert_allclose(batched, want, rtol=1e-7)
    np.testing.assert_allclose(batched, one, rtol=1e-12, atol=1e-12)
    # forward differences from the gradient at x (what fit uses without the batched program):
    # n evaluations, none at x itself, error O(rel)
    points = []

    def vg(f):
        points.append(np.array(f))
        return 0.0, None, grad(f)

    fwd = vt.hessian_from_gradients(vg, x, scales, rel=vt.information.FORWARD_REL, g0=grad(x))
    assert len(points) == 3 and not any(np.array_equal(p, x) for p in points)
    np.testing.assert_allclose(fwd, want, rtol=1e-5)
    assert np.max(np.abs(fwd - want)) > 1e-12  # really one-sided: not the central result
    # the same points handed over at once (CompiledLoss.many: evaluated side by side)
    handed = []

    def many(fs):
        handed.append(len(fs))
        return [vg(f) for f in fs]

    assert np.array_equal(vt.hessian_from_gradients(
        vg, x, scales, rel=vt.information.FORWARD_REL, g0=grad(x), many=many), fwd)
    assert handed == [3]


def test_the_batched_hessian_is_a_platform_rule():
    """Never on the CPU (batched points cost about one evaluation each there); from the GPU
    strategy's run-steps on."""
    cpu, gpu = vj.execution.for_platform("cpu"), vj.execution.for_platform("gpu")
    assert cpu.batched_hessian_steps is None and gpu.batched_hessian_steps == 50000
    with vj.execution.using(cpu):
        assert not vt.program.batched_hessian(10 ** 9)
    with vj.execution.using(gpu):
        assert vt.program.batched_hessian(50000) and not vt.program.batched_hessian(49999)
    with pytest.raises(ValueError, match="batched_hessian_steps"):
        vj.execution.check_strategy(cpu._replace(batched_hessian_steps=0))


def test_fit_with_the_batched_hessian_matches_the_inverse_information():
    """A fit long enough for the batched Hessian (threshold lowered to take this short run):
    its standard errors within 2 % of the numpy inverse observed information at scipy's
    optimum, the optimum within 1e-3, and the Hessian went through the batched program."""
    ys, us = simulate(7, q=Q_TRUE, T=150)
    fn = lambda p: loglik(p[0], p[1], p[2], ys, us)  # noqa: E731
    p_ml, cov = reference(fn, np.array([0.5, 1.0, 1.0]))
    strategy = vj.execution.current()._replace(batched_hessian_steps=1)  # a GPU's rule, lowered
    with vj.execution.using(strategy):
        res = vt.fit(vj.filters.ekf, scalar_model(), [1.0], [1.0], ys, us, x0=X0, P0=P0,
                     params=("a",), options=vt.Options(progress=False))
    assert res.converged and res.hessian_batches >= 1 and res.hessian_compile_seconds > 0
    got = np.array([res.values["a"], res.values["Q[x,x]"], res.values["R[y,y]"]])
    np.testing.assert_allclose(got, p_ml, rtol=1e-3)
    se = np.array([res.std_errors[k] for k in ("a", "Q[x,x]", "R[y,y]")])
    np.testing.assert_allclose(se, np.sqrt(np.diag(cov)), rtol=0.02)
