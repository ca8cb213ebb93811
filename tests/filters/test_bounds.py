"""Parameter domains (issue #17): the ``bounds=`` of the parameter-estimating filters
(vehjax.filters.bounds; the transforms themselves are tested in tests/lib/test_transforms.py),
and the ``at_bound`` flag of vehjax.filter / vehjax.run."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax import engine
from vehjax import filters as F
from vehjax.lib.transforms import Transform

INF = np.inf

# ---- a scalar model with a gain b: x' = 0.9 x + b u + w, y = x + v ------------------------------
A, QV, RV = 0.9, 0.05, 0.1


def _gain_model(b_nominal):
    return vj.models.Model(
        transition=lambda x, u, th: A * x + th[0] * u, observe=lambda x, u, th: x, dt=0.1,
        state_names=("x",), param_names=("b",), input_names=("u",), theta=[b_nominal],
    )


def _gain_data(b_true, T, runs=2, seed=0):
    rng = np.random.default_rng(seed)
    us = rng.normal(size=(runs, T, 1))
    ys = np.empty((runs, T, 1))
    for r in range(runs):
        x = 0.0
        for t in range(T):
            x = A * x + b_true * us[r, t, 0] + rng.normal() * np.sqrt(QV)
            ys[r, t, 0] = x + rng.normal() * np.sqrt(RV)
    return ys, us


# ---- (b) the scenario --------------------------------------------------------------------
KIN = vj.models.KinematicBicycle(dt=0.05)  # truth lf = lr = 1.5 m


def _checked(model):
    """The model, whose transition is NaN when called with lf or lr <= 0 (a run that calls it
    so diverges): every sigma point of both the state and the parameter filter goes through it."""
    def transition(x, u, th):
        return jnp.where(jnp.all(th > 0), model.transition(x, u, th), jnp.nan)

    return vj.models.Model(transition=transition, observe=lambda x, u, th: model.observe(x, u, th),
                           dt=model.dt,
                           state_names=model.state_names, param_names=model.param_names,
                           input_names=model.input_names, output_names=model.output_names,
                           theta=model.theta)


def _kinematic_data(runs, T, seed):
    """Inputs (T, 2) of a steering sine and a slow speed swing from 5 m/s (as in Dutta et al.'s
    kinematic study) and (runs, T, 4) measurements: process noise std 0.1 sqrt(dt) per step,
    measurement noise std 0.1 (a plain scan: vehjax.simulate's driver would cost more to
    compile than the test runs)."""
    t = np.arange(T) * KIN.dt
    us = np.stack([0.5 * np.sin(2 * np.pi * 0.05 * t), 0.3 * np.sin(2 * np.pi * 0.5 * t)], 1)
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(runs, T, 4)) * 0.1 * np.sqrt(KIN.dt)
    v = rng.normal(size=(runs, T, 4)) * 0.1

    @jax.jit
    def states(w):
        def step(x, wu):
            x = KIN.transition(x, wu[1], KIN.theta) + wu[0]
            return x, x

        return jax.vmap(lambda wr: jax.lax.scan(step, X0_KIN, (wr, jnp.asarray(us)))[1])(w)

    return np.asarray(states(jnp.asarray(w))) + v, us


X0_KIN = jnp.array([0.0, 0.0, 0.0, 5.0])


@pytest.mark.slow  # a study: `pytest -m slow` (README)
def test_dual_ukf_keeps_lf_lr_positive_under_a_wide_prior():
    """The issue: kinematic bicycle, wide prior P_theta0 = diag(3, 3) m^2 from guesses drawn in
    [0.5, 2.5] m (truth 1.5 m), the loose noise settings of Dutta et al. 2019 (Q_theta = 1.25^2
    m^2 per step). With the default domains (lf, lr > 0) no sigma point leaves them (the checked
    model would make the run diverge) and the final estimates spread less over the runs than
    with ``bounds={}``, whose parameter sigma points go far negative."""
    runs, T = 8, 200
    ys, us = _kinematic_data(runs, T, seed=3)
    th0 = np.random.default_rng(3).uniform(0.5, 2.5, size=(runs, 2))
    q_theta = np.array([1.25, 1.25]) ** 2
    kw = dict(Q=np.array([0.5, 0.5, 0.2, 1.0]) ** 2, R=np.array([1.0, 1.0, 1.5, 0.1]) ** 2,
              Q_theta=q_theta, estimate=("lf", "lr"), theta_decay=0.99)
    prior = dict(x0=np.asarray(X0_KIN), P0=np.array([1.0, 1.0, 0.2, 2.0]), theta0=th0,
                 P_theta0=np.diag([3.0, 3.0]))
    out = vj.run(F.dual_ukf(_checked(KIN), **kw), ys, us, **prior)
    assert not out.diverged.any() and np.all(np.isfinite(out.params))
    assert np.all(out.params > 0) and not out.at_bound.any()
    old = vj.run(F.dual_ukf(KIN, **kw, bounds={}), ys, us, **prior, return_covariances=True)
    # the old filter's parameter sigma points of each next step, mean +- sqrt(2) chol(P + Q_t)
    Q_t = 0.99 ** np.arange(1, T + 1)[:, None, None] * np.diag(q_theta)
    L = np.linalg.cholesky(old.params_cov + Q_t)
    points = old.params[..., None] + np.sqrt(2) * np.concatenate([L, -L], axis=-1)
    lowest = points.min(axis=(1, 3))  # (runs, 2)
    assert np.all(lowest.min(axis=1) < 0)
    spread, spread_old = np.ptp(out.params[:, -1], axis=0), np.ptp(old.params[:, -1], axis=0)
    print(f"\nfinal (lf, lr) spread (max - min) over {runs} runs: default bounds "
          f"{spread.round(2)} m, bounds={{}} {spread_old.round(2)} m; std "
          f"{out.params[:, -1].std(axis=0).round(2)} m, {old.params[:, -1].std(axis=0).round(2)} m;"
          f" lowest estimate {out.params.min():.2f} m, {old.params.min():.2f} m; lowest sigma "
          f"point of bounds={{}} {lowest.min():.1f} m")
    assert spread.max() < spread_old.max()


# ---- (c) at_bound ------------------------------------------------------------------------------


def test_at_bound_rule():
    """On a finite bound (within AT_BOUND_RTOL of its scale) on more than AT_BOUND_FRACTION of the
    steps; the scale of a box is its width, of a one-sided bound max(|bound|, |theta0|)."""
    T = 100
    n_on = int(engine.AT_BOUND_FRACTION * T)
    tol = engine.AT_BOUND_RTOL

    def flag(on_steps, value, bounds, theta0=(2.0,)):
        params = np.full((T, 1), 2.0)
        params[:on_steps] = value
        return bool(engine.on_bound(jnp.asarray(params), jnp.asarray(theta0), bounds))

    box = ((1.0,), (3.0,))  # width 2
    assert flag(n_on + 1, 1.0 + 0.9 * tol * 2, box)
    assert not flag(n_on, 1.0 + 0.9 * tol * 2, box)  # not more than the fraction
    assert not flag(n_on + 1, 1.0 + 1.1 * tol * 2, box)  # not close enough
    assert flag(n_on + 1, 3.0 - 0.9 * tol * 2, box)  # the upper bound too
    lower = ((0.0,), (INF,))  # scale |theta0| = 4
    assert flag(n_on + 1, 0.9 * tol * 4, lower, theta0=(4.0,))
    assert not flag(n_on + 1, 1.1 * tol * 4, lower, theta0=(4.0,))
    assert not flag(T, 1e-9, ((-INF,), (INF,)))  # no finite bound
    assert not flag(T, 1e-9, None)


def test_pinned_run_is_flagged_and_a_free_one_is_not():
    """Truth b = 1 outside the domain (1.2, 3): the dual EKF's estimate is pressed against 1.2
    and the runs are flagged at_bound (not diverged); with the default domain (0, inf) they are
    not. vehjax.filter flags the same."""
    ys, us = _gain_data(1.0, T=300)
    kw = dict(Q=[QV], R=[RV], Q_theta=[1e-6], estimate="b")
    prior = dict(x0=[0.0], P0=[1.0], theta0=[2.0], P_theta0=[[0.3]])
    model = _gain_model(2.0)
    pinned = F.dual_ekf(model, **kw, bounds={"b": (1.2, 3.0)})
    out = vj.run(pinned, ys, us, **prior)
    assert out.at_bound.tolist() == [True, True] and not out.diverged.any()
    assert np.all(out.params > 1.2) and np.all(out.params[:, -1, 0] < 1.2 + 0.02)
    assert "2 at a parameter bound" in repr(out)
    one = vj.filter(pinned, ys[0], us[0], x0=[0.0], P0=[1.0], theta0=[2.0], P_theta0=[[0.3]])
    assert bool(one.at_bound)
    free = vj.run(F.dual_ekf(model, **kw), ys, us, **prior)
    assert free.at_bound.tolist() == [False, False]
    assert np.all(np.abs(free.params[:, -1, 0] - 1.0) < 0.1)
    assert "bound" not in repr(free)


@pytest.mark.slow  # a Liu-West compile (the box rule's maths is tested on its own): `pytest -m slow` (README)
def test_liu_west_particles_stay_in_the_box():
    """Truth b = 1 outside the prior box [1.2, 3]: with the box as the domain no particle ever
    leaves it; with the default domain of a positive box, (0, inf), none becomes negative;
    with bounds={} (Liu and West's kernel on b itself) the kernel moves particles out of the
    box."""
    ys, us = _gain_data(1.0, T=150, runs=1)
    ys, us = jnp.asarray(ys[0]), jnp.asarray(us[0])

    def extremes(est):
        to_physical = Transform(*est.bounds).to_physical

        def body(state, yu):
            state, _ = est.step(state, *yu)
            b = to_physical(state.particles, axis=0)
            return state, (b.min(), b.max())

        state0 = est.init(jnp.zeros(1), jnp.eye(1), key=jax.random.key(0))
        return jax.jit(lambda s: jax.lax.scan(body, s, (ys, us))[1])(state0)

    kw = dict(Q=[QV], R=[RV], n_particles=100, estimate="b", theta_low=[1.2], theta_high=[3.0])
    lo, hi = extremes(F.liu_west_ukf(_gain_model(2.0), **kw, bounds={"b": (1.2, 3.0)}))
    assert np.all(np.asarray(lo) >= 1.2) and np.all(np.asarray(hi) <= 3.0)
    lo_pos, _ = extremes(F.liu_west_ukf(_gain_model(2.0), **kw))
    assert np.all(np.asarray(lo_pos) > 0.0)
    lo_old, _ = extremes(F.liu_west_ukf(_gain_model(2.0), **kw, bounds={}))
    assert np.mean(np.asarray(lo_old) < 1.2) > 0.5


# ---- (d) bad bounds ----------------------------------------------------------------------------
KIN_KW = dict(Q=np.full(4, 1e-4), R=np.full(4, 1e-2), Q_theta=[1e-4, 1e-4], estimate=("lf", "lr"))
LW_KW = dict(Q=np.full(4, 1e-4), R=np.full(4, 1e-2), n_particles=10, estimate=("lf", "lr"),
             theta_low=[0.5, 0.5], theta_high=[2.5, 2.5])
BUILDERS = {
    "dual_ekf": lambda **b: F.dual_ekf(KIN, **KIN_KW, **b),
    "dual_ukf": lambda **b: F.dual_ukf(KIN, **KIN_KW, **b),
    "joint_ekf": lambda **b: F.joint_ekf(KIN, **KIN_KW, **b),
    "joint_ukf": lambda **b: F.joint_ukf(KIN, **KIN_KW, **b),
    "liu_west_ukf": lambda **b: F.liu_west_ukf(KIN, **LW_KW, **b),
}


@pytest.mark.parametrize("name", list(BUILDERS))
@pytest.mark.parametrize("bounds", [
    {"m": (0.0, None)},  # not an estimated parameter
    {"lf": 0.0},  # not a pair
    {"lf": (0.0, 1.0, 2.0)},
    {"lf": (2.0, 1.0)},  # low >= high
    {"lf": (1.0, 1.0)},
    {"lf": (0.0, np.inf)},  # an open end is None
    {"lf": (np.nan, None)},
    {"lf": ("a", None)},
    [("lf", (0.0, None))],  # not a dict
], ids=lambda b: repr(b)[:24])
def test_bad_bounds_raise_naming_bounds(name, bounds):
    with pytest.raises(ValueError, match=r"^bounds\b"):
        BUILDERS[name](bounds=bounds)


def test_declared_bounds_and_defaults():
    inf = float("inf")
    for name, build in BUILDERS.items():
        default = build().bounds
        # positive nominal values (Liu-West: a positive prior box): positive
        assert default == ((0.0, 0.0), (inf, inf))
        assert build(bounds={}).bounds == ((-inf, -inf), (inf, inf))
        assert build(bounds={"lf": (0.1, None)}).bounds == ((0.1, -inf), (inf, inf))
    assert F.ukf(KIN, np.full(4, 1e-4), np.full(4, 1e-2)).bounds is None
    with pytest.raises(ValueError, match="^bounds"):  # the domain must contain the prior box
        F.liu_west_ukf(KIN, **LW_KW, bounds={"lf": (1.0, None)})


@pytest.mark.parametrize("name", ["dual_ekf", "joint_ukf"])
def test_theta0_outside_the_domain_raises_naming_theta0(name):
    est = BUILDERS[name]()
    x0, P0 = np.zeros(4), np.eye(4)
    with pytest.raises(ValueError, match="^theta0"):
        est.init(x0, P0, np.array([1.5, -0.2]), np.eye(2))
    with pytest.raises(ValueError, match="^theta0"):
        est.init(x0, P0, np.array([0.0, 1.5]), np.eye(2))  # on the bound
    ys, us = np.zeros((2, 3, 4)), np.zeros((3, 2))
    with pytest.raises(ValueError, match="^theta0"):  # before tracing, per-run theta0 too
        vj.run(est, ys, us, x0=x0, P0=P0, theta0=[[1.5, 1.5], [1.5, -1.0]], P_theta0=np.eye(2))
    with pytest.raises(ValueError, match="^theta0"):
        vj.filter(est, ys[0], us, x0=x0, P0=P0, theta0=np.array([-1.0, 1.5]), P_theta0=np.eye(2))
    # without domains a negative theta0 is a value like any other
    F.dual_ekf(KIN, **KIN_KW, bounds={}).init(x0, P0, np.array([1.5, -0.2]), np.eye(2))


# ---- (e) far bounds change nothing but the second order ----------------------------------------


@pytest.mark.parametrize("builder", [F.dual_ukf, F.joint_ekf])
def test_far_bounds_agree_with_no_bounds(builder):
    """b = 1.5 with a tight prior (std 0.01, 0.7 % of b) and the default domain (0, inf): the
    filter on log b agrees with the one on b to the delta method's order. Estimates differ by
    O(sigma_rel^2) = 4e-5 relative (the mean of a log-normal), the covariance by
    O(sigma_rel) = 7e-3 relative (J is taken after the update, at an estimate that moved by up
    to about a standard deviation); the tolerances are 3-5 times that."""
    ys, us = _gain_data(1.5, T=100)
    kw = dict(Q=[QV], R=[RV], Q_theta=[1e-6], estimate="b")
    prior = dict(x0=[0.0], P0=[1.0], theta0=[1.45], P_theta0=[[1e-4]], return_covariances=True)
    model = _gain_model(1.5)
    a = vj.run(builder(model, **kw), ys, us, **prior)
    b = vj.run(builder(model, **kw, bounds={}), ys, us, **prior)
    np.testing.assert_allclose(a.params, b.params, rtol=2e-4)
    np.testing.assert_allclose(a.params_cov, b.params_cov, rtol=2e-2)
    np.testing.assert_allclose(a.states, b.states, rtol=0, atol=2e-3 * np.abs(b.states).max())
    np.testing.assert_allclose(a.covariances, b.covariances, rtol=1e-3)
    np.testing.assert_allclose(a.loglik, b.loglik, rtol=1e-4)
    assert not a.params.tolist() == b.params.tolist()  # they are different filters
