"""The marginalized PF with the noise means as Kalman states (``marginalized_pf(...,
noise_means="kalman")``, issue #33 item 2) against independent references: the augmented model
against the model written out, the prior and the estimates' mapping against numpy, the filter
with the covariances known against the exact Kalman filter of the augmented linear-Gaussian
SingleTrackBank (written out in numpy), its bad options, and the paper's default left as it
was."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax as vj
from vehjax.filters._mpf_means import augment_prior, map_estimates, with_noise_means
from vehjax.filters.marginalized import marginalized_pf
from vehjax.models.bank import SingleTrackBank

from _bank_ref import discrete_matrices

DT = 0.01
MODEL = SingleTrackBank(dt=DT)
SENSORS = ("ay", "r", "roll_rate")
KNOWN = {"phi": math.radians(0.5), "r_virt": math.radians(0.3)}
STD0 = {"delta": math.radians(0.3), "ay": 0.2, "r": math.radians(0.6),
        "roll_rate": math.radians(0.6)}


def _kw(**over):
    kw = dict(known_std=KNOWN, linear_noise_std=0.05, std0=STD0, noise_means="kalman")
    kw.update(over)
    return kw


# ----------------------------------------------------------------------------------------------
# the pieces


def test_augmented_model_is_the_model_with_the_biases_added():
    """with_noise_means: transition f(x, u) with b kept; observe h(x, u) + b on the sensor
    rows; the bank gain zero on the added states."""
    aug = with_noise_means(MODEL, SENSORS)
    assert aug.state_names == tuple(MODEL.state_names) + ("ay_bias", "r_bias", "roll_rate_bias")
    rng = np.random.default_rng(0)
    x = rng.normal(0, 0.1, 5)
    b = np.array([0.1, -0.02, 0.03])
    u = np.array([20.0, 0.02])
    xa = np.r_[x, b]
    th = MODEL.theta
    np.testing.assert_allclose(aug.transition(xa, u, th), np.r_[MODEL.transition(x, u, th), b],
                               rtol=1e-14, atol=1e-15)
    rows = [MODEL.output_names.index(s) for s in SENSORS]
    y = np.asarray(MODEL.observe(x, u, th)).copy()
    y[rows] += b
    np.testing.assert_allclose(aug.observe(xa, u, th), y, rtol=1e-14, atol=1e-15)
    np.testing.assert_array_equal(aug.bank_noise_gain(),
                                  np.r_[np.asarray(MODEL.bank_noise_gain()), np.zeros(3)])


def test_prior_and_estimates_are_mapped_as_documented():
    """augment_prior appends the biases with variance gamma0 std^2; map_estimates reads the
    biases (and their covariance) from the bias states, the offset and the stds from the
    statistics, with zero cross-covariance."""
    ns = 3
    theta = jnp.array([0.1, 0.2, 1.0, 2.0, 3.0, 0.4, 0.5, 0.6])
    xa, Pa = augment_prior(np.zeros(5), np.arange(1.0, 6.0), theta, 2.0, ns)
    np.testing.assert_allclose(xa, [0, 0, 0, 0, 0, 1.0, 2.0, 3.0])
    np.testing.assert_allclose(np.diag(Pa), np.r_[np.arange(1.0, 6.0),
                                                  2.0 * np.array([0.4, 0.5, 0.6]) ** 2])
    assert np.count_nonzero(Pa - np.diag(np.diag(Pa))) == 0
    rng = np.random.default_rng(1)
    A = rng.normal(size=(8, 8))
    cov = A @ A.T
    mean = rng.normal(size=8)
    B = rng.normal(size=(8, 8))
    pcov = B @ B.T
    params = rng.normal(size=8)
    p, pc = map_estimates(jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(params),
                          jnp.asarray(pcov), 5, ns)
    bi, oi = [2, 3, 4], [0, 1, 5, 6, 7]
    np.testing.assert_array_equal(np.asarray(p)[bi], mean[5:])
    np.testing.assert_array_equal(np.asarray(p)[oi], params[oi])
    np.testing.assert_array_equal(np.asarray(pc)[np.ix_(bi, bi)], cov[5:, 5:])
    np.testing.assert_array_equal(np.asarray(pc)[np.ix_(oi, oi)], pcov[np.ix_(oi, oi)])
    np.testing.assert_array_equal(np.asarray(pc)[np.ix_(bi, oi)], 0.0)


@pytest.mark.parametrize("arg, over", [
    ("noise_means", dict(noise_means="gibbs")),
    ("noise_means", dict(noise_means=None)),
    ("kalman_states", dict(kalman_states="bank")),
    ("gamma0", dict(gamma0=0.0)),
    ("nu0", dict(nu0=4.0)),
    ("forgetting", dict(forgetting=1.5)),
    ("sensors", dict(sensors=("ay", "gps"))),
    ("noisy_input", dict(noisy_input="steer")),
    ("std0", dict(std0={"delta": 0.01})),
    ("bias_walk", dict(bias_walk={"gps": 0.1})),
    ("bias_walk", dict(bias_walk={"ay": -0.1})),
    ("bias_walk", dict(bias_walk=[0.1])),
    ("bias_walk", dict(noise_means="niw", bias_walk={"ay": 0.1})),
])
def test_bad_options_raise_naming_them(arg, over):
    with pytest.raises(ValueError, match=arg):
        marginalized_pf(MODEL, 100, **_kw(**over))


def test_default_is_the_papers_filter():
    """Without noise_means the filter is the paper's: the NiW learns the means (the parameters'
    prior is mean0 with gamma0 std0^2), the particles' Kalman filters cover the bank only
    ("linear"), and it declares its Rao-Blackwell structure for smoothing."""
    est = marginalized_pf(MODEL, 100, **_kw(noise_means="niw"))
    default = marginalized_pf(MODEL, 100, known_std=KNOWN, linear_noise_std=0.05, std0=STD0)
    for e in (est, default):
        assert e.rao_blackwell is not None and not e.rao_blackwell.gauss
        assert e.rao_blackwell.nz == 3
        assert e.rao_blackwell.setup.g0 == 1.0
    variant = marginalized_pf(MODEL, 100, **_kw())
    assert variant.rao_blackwell is None and variant.nx == 5
    assert variant.param_names == default.param_names
    np.testing.assert_array_equal(variant.param_prior[0], default.param_prior[0])
    np.testing.assert_array_equal(variant.param_prior[1], default.param_prior[1])


# ----------------------------------------------------------------------------------------------
# against the exact Kalman filter


def _matrices(vx):
    """The augmented linear SingleTrackBank with bias states (x (5), b (3)) in numpy:
    x_t = Ad x + Bd delta, y = C x + Dd delta + Sb b."""
    Ad, Bd, C, Dd = discrete_matrices(MODEL.theta, vx, DT)
    Sb = np.zeros((5, 3))
    for j, s in enumerate(SENSORS):
        Sb[MODEL.output_names.index(s), j] = 1.0
    F = np.eye(8)
    F[:5, :5] = Ad
    return F, np.r_[Bd, np.zeros(3)], np.concatenate([C, Sb], 1), Dd


def _simulate(R, T, offset, bias, sig_phi, seed):
    """Data of the linear SingleTrackBank at the study's inputs: steering with a constant
    offset (no steering noise), white bank jerk, constant sensor biases, white noise of the
    stds STD0 / KNOWN. Returns (truth (R, T, 5), Y (R, T, 5), U (T, 2))."""
    from vehjax.reproduce.consistency import mpf_inputs

    U = mpf_inputs(T)
    F, B, H, D = _matrices(float(U[0, 0]))
    gain = np.r_[np.asarray(MODEL.bank_noise_gain()), np.zeros(3)]
    std = np.array([STD0.get(n, KNOWN.get(n)) for n in MODEL.output_names])
    rng = np.random.default_rng(seed)
    x = np.tile(np.r_[np.zeros(5), bias], (R, 1))
    X, Y = np.zeros((R, T, 5)), np.zeros((R, T, 5))
    for t in range(T):
        d = U[t, 1] + offset
        x = x @ F.T + B * d + sig_phi * rng.normal(size=(R, 1)) * gain
        X[:, t] = x[:, :5]
        Y[:, t] = x @ H.T + D * d + std * rng.normal(size=(R, 5))
    return X, Y, U


def _augmented_kalman(Y, U, offset, x0, P0, b0, Pb0, sig_phi):
    """numpy Kalman filter of the model of :func:`_simulate` with the biases as states of
    prior N(b0, Pb0) and the offset known. Returns the filtered means (R, T, 8) and
    covariances (T, 8, 8)."""
    F, B, H, D = _matrices(float(U[0, 0]))
    gain = np.r_[np.asarray(MODEL.bank_noise_gain()), np.zeros(3)]
    Q = sig_phi ** 2 * np.outer(gain, gain)
    Rm = np.diag([STD0.get(n, KNOWN.get(n)) ** 2 for n in MODEL.output_names])
    runs, T, _ = Y.shape
    m = np.tile(np.r_[x0, b0], (runs, 1))
    P = np.zeros((8, 8))
    P[:5, :5], P[5:, 5:] = P0, Pb0
    means, covs = np.zeros((runs, T, 8)), np.zeros((T, 8, 8))
    for t in range(T):
        d = U[t, 1] + offset
        m = m @ F.T + B * d
        P = F @ P @ F.T + Q
        S = H @ P @ H.T + Rm
        K = np.linalg.solve(S, H @ P).T
        m = m + (Y[:, t] - m @ H.T - D * d) @ K.T
        P = P - K @ S @ K.T
        P = 0.5 * (P + P.T)
        means[:, t], covs[t] = m, P
    return means, covs


@pytest.mark.slow  # one MPF compile (about a minute on 2 cores): `pytest -m slow` (README)
def test_with_the_noise_known_it_is_the_exact_kalman_filter_of_the_biased_model():
    """The steering offset and all covariances made known (steering std 1e-10 rad, nu0 = 1e7:
    the Student-t is Gaussian and the draws of w_t are the offset to 1e-10), the biases learnt
    from the prior N(mean0, gamma0 std0^2) with gamma0 = 1: the model is linear-Gaussian with
    the biases constant states, and every particle's Kalman filter is the exact Kalman filter of
    that model (written out in numpy). States, biases and their covariances must be that
    filter's; the stds stay the known ones."""
    T, R, N = 150, 2, 50
    offset, bias, sig_phi = math.radians(0.28), np.array([0.1, 0.005, -0.003]), 0.05
    X, Y, U = _simulate(R, T, offset, bias, sig_phi, seed=3)
    # vy, r known at the start: the particles' own spread (a sample of P0) would be Monte-Carlo
    # error; the bank's prior uncertainty is Gaussian in every particle
    x0, P0 = np.zeros(5), np.array([1e-30, 1e-30, 1e-6, 1e-6, 1e-6])
    std0 = dict(STD0, delta=1e-10)
    est = marginalized_pf(MODEL, N, sensors=SENSORS, known_std=KNOWN, linear_noise_std=sig_phi,
                          std0=std0, mean0={"delta": offset}, forgetting=1.0, nu0=1e7,
                          gamma0=1.0, noise_means="kalman")
    out = vj.run(est, Y, U, x0=x0, P0=P0, key=jax.random.key(5), return_covariances=True)
    assert not out.diverged.any()
    Pb0 = np.diag([STD0[s] ** 2 for s in SENSORS])
    km, kc = _augmented_kalman(Y, U, offset, x0, np.diag(P0), np.zeros(3), Pb0, sig_phi)
    sd = np.sqrt(np.diagonal(kc, axis1=1, axis2=2))  # (T, 8)
    np.testing.assert_array_less(np.abs(out.states - km[..., :5]) / sd[:, :5], 1e-3)
    np.testing.assert_allclose(np.diagonal(out.covariances, axis1=2, axis2=3),
                               np.broadcast_to(sd[:, :5] ** 2, (R, T, 5)), rtol=1e-3)
    bi = [2, 3, 4]
    np.testing.assert_array_less(np.abs(out.params[..., bi] - km[..., 5:]) / sd[:, 5:], 1e-3)
    np.testing.assert_allclose(out.params_cov[..., 2:5, 2:5],
                               np.broadcast_to(kc[:, 5:, 5:], (R, T, 3, 3)), rtol=1e-3,
                               atol=1e-3 * float(np.min(sd[:, 5:])) ** 2)
    np.testing.assert_allclose(out.params[:, -1, [5, 6, 7]],
                               np.tile([STD0[s] for s in SENSORS], (R, 1)), rtol=1e-4)
    np.testing.assert_allclose(out.params[:, -1, 0], offset, rtol=1e-6)
