"""Parameter transforms (vehjax.lib.transforms): round trips, Jacobians against finite
differences, the covariance floor near a bound, extreme coordinates (moved from
tests/filters/test_bounds.py, issue #17), and the log-Jacobian the calibrate priors use."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vehjax.lib import transforms
from vehjax.lib.transforms import Transform

INF = np.inf

# ---- (a) the transforms ----------------------------------------------------------------------
# one parameter of each kind: none, lower, upper, box; scales c for the first three
TF = Transform([-INF, 0.5, -INF, 1.0], [INF, INF, 2.0, 3.0], [2.0, 1.5, 0.5, 7.0])


def test_kinds_and_declared_bounds():
    assert TF.kinds == ("none", "lower", "upper", "box")
    assert TF.bounds == ((-INF, 0.5, -INF, 1.0), (INF, INF, 2.0, 3.0))
    assert all(type(v) is float for v in TF.bounds[0] + TF.bounds[1])  # static under jit


def test_round_trip_and_jacobian_equals_finite_differences():
    s = jnp.asarray(np.random.default_rng(0).uniform(-6.0, 6.0, size=(50, 4)))
    h = 1e-6

    @jax.jit
    def maps(s):
        theta = TF.to_physical(s)
        fd = (TF.to_physical(s + h) - TF.to_physical(s - h)) / (2 * h)
        return (theta, TF.to_unconstrained(theta), TF.to_physical(TF.to_unconstrained(theta)),
                TF.to_physical(s.T, axis=0), TF.jacobian(s), fd)

    theta, s_back, theta_back, theta_t, J, fd = (np.asarray(a) for a in maps(s))
    assert np.all((theta > TF.low) & (theta < TF.high))
    np.testing.assert_allclose(s_back, s, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(theta_back, theta, rtol=1e-13)
    # the parameter axis can be first, as for Liu-West's particles (p, M)
    np.testing.assert_array_equal(theta_t, theta.T)
    np.testing.assert_allclose(J, fd, rtol=1e-7)
    np.testing.assert_allclose(J[:, 0], 2.0)  # none: theta = c s
    np.testing.assert_allclose(J[:, 1], theta[:, 1] - 0.5, rtol=1e-14)  # lower: the distance
    # the delta method: J P J^T, and back (no floor: standard deviations below |J|)
    P = np.diag([0.1, 0.2, 0.05, 0.3]) @ (np.eye(4) + 0.3) @ np.diag([0.1, 0.2, 0.05, 0.3])
    Pp = TF.cov_to_physical(s[3], jnp.asarray(P))
    np.testing.assert_allclose(Pp, np.outer(J[3], J[3]) * P, rtol=1e-14)
    np.testing.assert_allclose(TF.cov_to_unconstrained(s[3], Pp), P, rtol=1e-12)


def test_covariance_into_s_is_floored_at_one_standard_deviation():
    """Within one standard deviation of a bound the delta method is not used: var(s) <= 1."""
    s = TF.to_unconstrained(jnp.array([0.3, 0.5 + 1e-4, 2.0 - 1e-4, 1.0 + 1e-4]))
    C = jnp.diag(jnp.array([1e-2, 1e-2, 1e-2, 1e-2]))
    Cs = np.asarray(TF.cov_to_unconstrained(s, C))
    np.testing.assert_allclose(Cs[0, 0], 1e-2 / 4.0)  # unbounded: exact, (sd / c)^2
    np.testing.assert_allclose(np.diagonal(Cs)[1:], 1.0, rtol=1e-3)
    # far from the bounds it is the delta method
    s = TF.to_unconstrained(jnp.array([0.3, 1.5, 1.0, 2.0]))
    np.testing.assert_allclose(TF.cov_to_unconstrained(s, C),
                               C / np.outer(TF.jacobian(s), TF.jacobian(s)), rtol=1e-14)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_extreme_coordinates_stay_finite_and_inside(dtype):
    s = jnp.array([[1e4, 1e4, 1e4, 1e4], [-1e4, -1e4, -1e4, -1e4], [80.0, 80.0, 80.0, 80.0],
                   [-80.0, -80.0, -80.0, -80.0]], dtype)
    on = jnp.array([0.0, 0.5, 2.0, 3.0], dtype)  # values on the bounds

    @jax.jit
    def maps(s, on):
        theta, J = TF.to_physical(s), TF.jacobian(s)
        g = jax.grad(lambda v: jnp.sum(TF.to_physical(v)))(s)
        return theta, J, g, TF.to_unconstrained(on)

    theta, J, g, s_on = maps(s, on)
    assert theta.dtype == dtype and J.dtype == dtype
    for a in (theta, J, 1.0 / J, J * J, 1.0 / (J * J), g, s_on):
        assert np.all(np.isfinite(np.asarray(a)))
    assert np.all((np.asarray(theta) >= TF.low) & (np.asarray(theta) <= TF.high))


# ---- the scalar maps: the log-Jacobian and precision near a bound ------------------------------
@pytest.mark.parametrize("k, lo, hi, c", [("none", -INF, INF, 2.0), ("lower", 0.5, INF, 1.5),
                                          ("upper", -INF, 2.0, 0.5), ("box", 1.0, 3.0, 1.0)])
def test_log_derivative_is_the_log_of_the_derivative(k, lo, hi, c):
    s = jnp.linspace(-30.0, 30.0, 61)
    np.testing.assert_allclose(transforms.log_derivative(k, lo, hi, c, s),
                               np.log(np.abs(transforms.derivative(k, lo, hi, c, s))),
                               rtol=1e-12, atol=1e-12)


def test_box_keeps_the_distance_to_the_upper_bound():
    """theta = high - span sigmoid(-s) near the upper end: the distance to high is span e^-s
    (1 + O(e^-s)) to full precision, where low + span sigmoid(s) would round it to a multiple
    of span eps; the inverse gets s back from it."""
    lo, hi = -100.0, 1e-3
    s = jnp.array([20.0, 25.0, 30.0])
    theta = transforms.forward("box", lo, hi, 1.0, s)
    dist = (hi - lo) * np.exp(-np.asarray(s)) / (1.0 + np.exp(-np.asarray(s)))
    np.testing.assert_allclose(hi - np.asarray(theta), dist, rtol=1e-4)
    np.testing.assert_allclose(transforms.inverse("box", lo, hi, 1.0, theta), s, rtol=1e-4)
