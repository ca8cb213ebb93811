"""vehjax.tune: maximum-likelihood tuning of Q, R, model parameters and x0.

References nobody here wrote: an exact Kalman likelihood in numpy maximised with
scipy.optimize (linear-Gaussian ML), central finite differences (gradients), the noise
vehjax.simulate drew (vehicle), the exact Kalman score (particle filter's stop-gradient score).
Sizes are small: compilation dominates the time of this file.
"""

import functools

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import vehjax as vj
import vehjax.tune as vt

# ----------------------------------------------------------------------------------------------
# a linear-Gaussian model: x' = A x + B u + w, y = H x + v (two outputs, correlated noise)

DT = 0.1
A = np.array([[1.0, DT], [0.0, 0.95]])
B = np.array([[0.0], [DT]])
H = np.array([[1.0, 0.0], [1.0, 0.5]])
Q_TRUE = np.diag([0.02, 0.05])
R_TRUE = np.array([[0.3, 0.1], [0.1, 0.2]])
X0, P0 = np.zeros(2), np.eye(2)


def linear_model():
    return vj.models.Model(
        transition=lambda x, u, th: jnp.asarray(A) @ x + jnp.asarray(B) @ u,
        observe=lambda x, u, th: jnp.asarray(H) @ x,
        dt=DT, state_names=("p", "v"), input_names=("a",), output_names=("y1", "y2"),
        units={"p": "m", "v": "m/s", "a": "m/s^2", "y1": "m", "y2": "m"},
    )


def linear_data(runs, T, seed=1):
    rng = np.random.default_rng(seed)
    us = rng.normal(size=(T, 1))
    ys = np.zeros((runs, T, 2))
    for r in range(runs):
        x = X0 + rng.multivariate_normal(np.zeros(2), P0)
        for t in range(T):
            x = A @ x + B @ us[t] + rng.multivariate_normal(np.zeros(2), Q_TRUE)
            ys[r, t] = H @ x + rng.multivariate_normal(np.zeros(2), R_TRUE)
    return ys, us


def kalman_loglik(Q, R, ys, us):
    """Exact log p(y_1:T) summed over runs, numpy, runs batched."""
    n_runs, T, _ = ys.shape
    x, P, total = np.tile(X0, (n_runs, 1)), P0.copy(), 0.0
    for t in range(T):
        x, P = x @ A.T + B @ us[t], A @ P @ A.T + Q
        S = H @ P @ H.T + R
        e = ys[:, t] - x @ H.T
        L = np.linalg.cholesky(S)
        w = np.linalg.solve(L, e.T)
        total += -0.5 * np.sum(w * w) - n_runs * (np.sum(np.log(np.diag(L))) + np.log(2 * np.pi))
        K = P @ H.T @ np.linalg.inv(S)
        x, P = x + e @ K.T, P - K @ S @ K.T
    return total


def test_fitted_noise_equals_scipy_maximum_likelihood():
    ys, us = linear_data(runs=4, T=100)

    def unpack(p):  # diagonal Q by log-stds, full R by log-Cholesky
        L = np.array([[np.exp(p[2]), 0.0], [p[3], np.exp(p[4])]])
        return np.diag(np.exp(2 * p[:2])), L @ L.T

    ref = scipy.optimize.minimize(
        lambda p: -kalman_loglik(*unpack(p), ys, us), np.array([-2.3, -2.3, 0.0, 0.0, 0.0]),
        method="L-BFGS-B", options=dict(ftol=1e-15, gtol=1e-10, maxiter=1000))
    Q_ml, R_ml = unpack(ref.x)

    model = linear_model()
    R0 = np.array([[1.0, 0.2], [0.2, 1.0]])
    res = vt.fit_noise(vj.filters.ukf, model, np.array([0.01, 0.01]), R0, ys, us, x0=X0, P0=P0,
                       options=vt.Options(optimizer=vt.LBFGS(steps=60), progress=False))
    # diagonal Q0 fitted as diagonal, full R0 as full
    assert res.Q[0, 1] == 0.0 and res.R[0, 1] != 0.0
    np.testing.assert_allclose(np.diag(res.Q), np.diag(Q_ml), rtol=1e-3)
    np.testing.assert_allclose(res.R, R_ml, rtol=1e-3)
    np.testing.assert_allclose(res.loglik, -ref.fun, rtol=1e-9)
    assert res.loglik > res.loglik0
    assert len(res.history) == res.iterations and res.diverged == 0
    # the record: names, units, and the tuned estimator ready for vehjax.run
    assert set(res.values) == {"Q[p,p]", "Q[v,v]", "R[y1,y1]", "R[y1,y2]", "R[y2,y2]"}
    assert res.units["Q[v,v]"] == "(m/s)^2" and res.units["R[y1,y2]"] == "m^2"
    assert "R[y1,y2]" in res.summary()
    out = vj.run(res.estimator, ys, us, x0=X0, P0=P0)
    np.testing.assert_allclose(out.loglik.sum(), res.loglik, rtol=1e-9)


# ----------------------------------------------------------------------------------------------
# gradients against central finite differences, on a nonlinear model with missing measurements


def pendulum_model():
    def f(x, u, th):
        k, c = th
        return jnp.stack([x[0] + DT * x[1], x[1] + DT * (-k * jnp.sin(x[0]) - c * x[1] + u[0])])

    def h(x, u, th):
        return jnp.stack([jnp.sin(x[0]) + x[0], x[1] * jnp.abs(x[1]) + 0.5 * x[1]])

    return vj.models.Model(transition=f, observe=h, dt=DT, state_names=("phi", "omega"),
                           param_names=("k", "c"), input_names=("tau",), theta=[4.0, 0.3])


@pytest.mark.parametrize("builder, kwargs", [
    (vj.filters.ekf, {}),
    (vj.filters.ukf, {"sqrt": True}),
], ids=["ekf", "sr-ukf"])
def test_gradient_matches_central_differences(builder, kwargs):
    model = pendulum_model()
    rng = np.random.default_rng(0)
    T = 15
    us = rng.normal(size=(T, 1))
    ys = rng.normal(size=(2, T, 2)) * 0.5
    ys[0, 3, 1] = ys[1, 7, 0] = ys[1, 9, :] = np.nan  # missing components
    obj = vt.objective(functools.partial(builder, **kwargs), model,
                       np.array([[0.01, 0.003], [0.003, 0.02]]), [0.1, 0.2],
                       ys, us, x0=np.array([[0.3, 0.0], [0.1, -0.2]]), P0=np.diag([0.1, 0.1]),
                       params=vt.Fitted(("k",), bounds={"k": (0.5, 20.0)}, x0=True))
    vg = jax.jit(jax.value_and_grad(lambda z: obj.loss(z, obj.data)[0]))
    z0 = obj.z0
    _, g = vg(z0)
    flat, unravel = jax.flatten_util.ravel_pytree(z0)
    g_flat, _ = jax.flatten_util.ravel_pytree(g)
    assert np.all(np.isfinite(g_flat)) and np.all(g_flat != 0)
    h = 1e-5
    fd = np.array([(float(vg(unravel(flat.at[i].add(h)))[0])
                    - float(vg(unravel(flat.at[i].add(-h)))[0])) / (2 * h)
                   for i in range(flat.size)])
    np.testing.assert_allclose(g_flat, fd, rtol=1e-6, atol=1e-9)


# ----------------------------------------------------------------------------------------------
# a nonlinear vehicle model: R started 10x too large is recovered


@pytest.mark.slow  # a small tuning study: `pytest -m slow` (README)
def test_vehicle_tuning_recovers_simulated_measurement_noise():
    model = vj.models.KinematicBicycle(dt=0.05)
    scn = vj.scenarios.sine_steer(model, speed=10.0, amplitude=0.1, frequency=0.3, duration=5.0)
    q = np.array([0.02, 0.02, 0.003, 0.05])
    r = np.array([0.3, 0.3, 0.02, 0.1])
    sim = vj.simulate(model, scn, runs=20, key=jax.random.key(1), process_std=q, meas_std=r)
    res = vt.fit_noise(vj.filters.ukf, model, q**2, 10 * r**2, sim.measurements, sim.inputs,
                       x0=scn.x0, P0=np.full(4, 1e-2), noise=("R",),
                       options=vt.Options(optimizer=vt.Scoring(steps=100), progress=False))
    ratio = np.diag(res.R) / r**2
    assert np.all(np.abs(ratio - 1) < 0.10), ratio
    np.testing.assert_array_equal(res.Q, np.diag(q**2))  # not fitted
    assert res.units["R[psi,psi]"] == "rad^2"


# ----------------------------------------------------------------------------------------------
# particle filter: the stop-gradient score against the exact Kalman score


@pytest.mark.slow  # a Monte-Carlo check of the PF's score: `pytest -m slow` (README)
def test_particle_filter_stop_gradient_score_matches_kalman_score():
    a = 0.9
    model = vj.models.Model(transition=lambda x, u, th: a * x, observe=lambda x, u, th: x,
                            dt=1.0, state_names=("x",))
    rng = np.random.default_rng(0)
    T, q, r = 10, 0.5, 0.3
    x, ys = 0.0, []
    for _ in range(T):
        x = a * x + rng.normal() * np.sqrt(q)
        ys.append(x + rng.normal() * np.sqrt(r))
    ys = np.array(ys)[None, :, None]
    # score at (2q, 2r), away from the maximum: both components clearly non-zero; the exact
    # Kalman log-likelihood written out in numpy, differentiated by central differences in the
    # fit's coordinates (log std q, log std r)
    common = dict(x0=np.zeros(1), P0=np.eye(1))

    def kalman_loglik(zq, zr):
        qq, rr, m, p, ll = np.exp(2 * zq), np.exp(2 * zr), 0.0, 1.0, 0.0
        for y in ys[0, :, 0]:
            m, p = a * m, a * a * p + qq
            s = p + rr
            ll -= 0.5 * (np.log(2 * np.pi * s) + (y - m) ** 2 / s)
            m, p = m + p / s * (y - m), p - p * p / s
        return ll

    z = np.log(np.sqrt([2 * q, 2 * r]))
    h = 1e-6
    score_kf = np.array([(kalman_loglik(*(z + e)) - kalman_loglik(*(z - e))) / (2 * h)
                         for e in np.eye(2) * h])  # d log p(y) / d (log std q, log std r)

    # forward pass untouched: the same numbers as the bootstrap PF's
    k = jax.random.key(3)
    pf = vj.filters.bootstrap_pf(model, [q], [r], n_particles=64)
    a1 = vj.filter(pf, ys[0], None, key=k, **common)
    a2 = vj.filter(vt.stop_gradient_pf(model, [q], [r], n_particles=64), ys[0], None, key=k,
                   **common)
    np.testing.assert_array_equal(a1.loglik, a2.loglik)
    np.testing.assert_array_equal(a1.states, a2.states)

    S, N = 100, 2000
    obj = vt.objective(functools.partial(vj.filters.bootstrap_pf, n_particles=N), model,
                       [2 * q], [2 * r], ys, None, **common, key=jax.random.key(0))
    ys_, us_, x0_, P0_, _ = obj.data

    def score(key):
        g = jax.grad(lambda z: obj.loss(z, (ys_, us_, x0_, P0_, key[None]))[0])(obj.z0)
        return -T * jnp.concatenate([g["Q"], g["R"]])

    scores = np.asarray(jax.jit(jax.vmap(score))(jax.random.split(jax.random.key(7), S)))
    mean, se = scores.mean(0), scores.std(0, ddof=1) / np.sqrt(S)
    assert np.all(se < 0.1 * np.abs(score_kf)), (se, score_kf)  # a test with teeth
    assert np.all(np.abs(mean - score_kf) < 4 * se), (mean, score_kf, se)


def test_stop_gradient_is_a_builder_choice_not_a_patch():
    """stop_gradient(estimator) refuses (it pointed at a global swap), naming estimator and the
    builder keyword; tune refuses a particle filter's builder without a resample keyword."""
    model = vj.models.Model(transition=lambda x, u, th: 0.9 * x, observe=lambda x, u, th: x,
                            dt=1.0, state_names=("x",))
    pf = vj.filters.bootstrap_pf(model, [0.5], [0.3], n_particles=8)
    with pytest.raises(ValueError, match="^estimator: .*resample=vehjax.filters.smc"):
        vt.stop_gradient(pf)

    def own_pf(model, Q, R):  # a particle filter's builder that takes no resample=
        return vj.filters.bootstrap_pf(model, Q, R, n_particles=8)

    with pytest.raises(ValueError, match="^builder: .*resample"):
        vt.objective(own_pf, model, [0.5], [0.3], np.zeros((1, 5, 1)), None, x0=np.zeros(1),
                     P0=np.eye(1), key=jax.random.key(0))


# ----------------------------------------------------------------------------------------------
# validation: ValueError naming the argument, before anything is traced


class _Counting:
    calls = 0


def _counting_model():
    def f(x, u, th):
        _Counting.calls += 1
        return th[0] * x

    return vj.models.Model(transition=f, observe=lambda x, u, th: x, dt=0.1, state_names=("x",),
                           param_names=("a",), theta=[0.9])


@pytest.mark.parametrize("change, name", [
    (dict(params=("b",)), "params"),
    (dict(measurements=np.zeros((5, 2))), "measurements"),
    (dict(measurements=np.zeros((2, 5, 1)), x0=np.zeros((3, 1))), "x0"),
    (dict(Q0=np.array([-1.0])), "Q0"),
    (dict(R0=np.array([[0.0]])), "R0"),
    (dict(Q0=np.zeros((2, 2))), "Q0"),
    (lambda: dict(options=vt.Options(optimizer=vt.Adam(learning_rate=0.0))),
     "optimizer.learning_rate"),
    (lambda: dict(options=vt.Options(optimizer=vt.Adam(learning_rate=-1e-3))),
     "optimizer.learning_rate"),
    (lambda: dict(options=vt.Options(optimizer=vt.Scoring(steps=0))), "optimizer.steps"),
    (lambda: dict(options=vt.Options(optimizer="sgd")), "optimizer"),
    (dict(params=vt.Fitted(("a",), bounds={"a": (1.0, 2.0)})), "bounds"),
    (lambda: dict(params=vt.Fitted(noise=("P",))), "params.noise"),
    (dict(params=vt.Fitted(noise=())), "params.noise"),
    (dict(builder=vj.filters.bootstrap_pf), "key"),
    (dict(P0=np.array([[-1.0]])), "P0"),
    (dict(builder="ukf"), "builder"),
    (dict(builder=functools.partial(vj.filters.ukf, 1.0)), "builder"),  # options by keyword
    (dict(params=vt.Fitted(noise=("R", "input"))), "params.noise"),  # no input_noise to start
])
def test_bad_arguments_raise_before_tracing(change, name):
    args = dict(builder=vj.filters.ukf, model=_counting_model(), Q0=[0.1], R0=[0.1],
                measurements=np.zeros((5, 1)), inputs=None, x0=np.zeros(1), P0=np.eye(1))
    _Counting.calls = 0
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        args.update(change() if callable(change) else change)  # a record checks itself
        vt.fit(**args)
    assert _Counting.calls == 0


def test_a_builders_options_go_with_it_by_partial_not_by_a_keyword():
    """tune takes a builder's options as vehjax.calibrate does, functools.partial(builder,
    **options): ``builder_kwargs=`` is no keyword of any tune function."""
    args = (vj.filters.ekf, _counting_model(), [0.1], [0.1], np.zeros((5, 1)), None)
    for fn in (vt.fit, vt.fit_from_theta, vt.fit_noise, vt.objective, vt.prepare):
        with pytest.raises(TypeError, match="builder_kwargs"):
            fn(*args, x0=np.zeros(1), P0=np.eye(1), builder_kwargs={"sqrt": True})
    model = vj.models.Model(transition=lambda x, u, th: 0.9 * x + u, observe=lambda x, u, th: x,
                            dt=1.0, state_names=("x",), input_names=("u",))
    us = np.zeros((5, 1))
    obj = vt.objective(functools.partial(vj.filters.ukf, sqrt=True, input_noise={"u": 0.3}),
                       model, np.zeros(1), [0.1], np.zeros((5, 1)), us, x0=np.zeros(1),
                       P0=np.eye(1), params=vt.Fitted(noise=("R", "input")))
    np.testing.assert_allclose(obj.unpack(obj.z0)["input"]["u"], 0.3)  # the partial's start
