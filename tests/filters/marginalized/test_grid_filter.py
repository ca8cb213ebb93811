"""The marginalized PF with the noise means as Kalman states (``marginalized_pf_grid``,
issue #33 item 2) against independent references: the augmented model
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
from vehjax.filters.marginalized.means import augment_prior, map_estimates, with_noise_means
from vehjax.studies.banked_road import MATCHED, matched_inputs, simulate_matched
from vehjax.models import with_input_offset
from vehjax.filters.marginalized import (InputStdGrid, MeanStates, NiW, marginalized_pf,
                                         marginalized_pf_grid)
from vehjax.models.bank import SingleTrackBank

from _bank_ref import (discrete_matrices, mpf_kwargs, simulate_linear_bank, user_bank_case,
                       user_linear_bank)

DT = 0.01
MODEL = SingleTrackBank(dt=DT)
SENSORS = ("ay", "r", "roll_rate")
KNOWN = {"phi": math.radians(0.5), "r_virt": math.radians(0.3)}
STD0 = {"delta": math.radians(0.3), "ay": 0.2, "r": math.radians(0.6),
        "roll_rate": math.radians(0.6)}


def _kw(**over):
    kw = dict(known_std=KNOWN, Q=0.05 ** 2, std0=STD0)
    kw.update(over)
    return mpf_kwargs(**kw)


# ----------------------------------------------------------------------------------------------
# the pieces


def test_augmented_model_is_the_model_with_the_biases_and_the_offset_added():
    """with_noise_means: transition f(x, u + offset) with b and the offset kept; observe
    h(x, u + offset) + b on the sensor rows; the bank gain zero on the added states."""
    aug = with_noise_means(MODEL, SENSORS, "delta")
    assert aug.state_names == tuple(MODEL.state_names) + (
        "ay_bias", "r_bias", "roll_rate_bias", "delta_offset")
    rng = np.random.default_rng(0)
    x = rng.normal(0, 0.1, 5)
    b = np.array([0.1, -0.02, 0.03])
    off = 0.004
    u = np.array([20.0, 0.02])
    uo = u + np.array([0.0, off])  # delta is the second input
    assert MODEL.input_names[1] == "delta"
    xa = np.r_[x, b, off]
    th = MODEL.theta
    np.testing.assert_allclose(aug.transition(xa, u, th),
                               np.r_[MODEL.transition(x, uo, th), b, off],
                               rtol=1e-14, atol=1e-15)
    rows = [MODEL.output_names.index(s) for s in SENSORS]
    y = np.asarray(MODEL.observe(x, uo, th)).copy()
    y[rows] += b
    np.testing.assert_allclose(aug.observe(xa, u, th), y, rtol=1e-14, atol=1e-15)
    np.testing.assert_array_equal(aug.bank_noise_gain(),
                                  np.r_[np.asarray(MODEL.bank_noise_gain()), np.zeros(4)])
    with pytest.raises(ValueError, match="inputs"):
        with_input_offset(MODEL, ("delta", "delta"))


def test_prior_and_estimates_are_mapped_as_documented():
    """augment_prior appends the biases then the offset with variance gamma0 std^2;
    map_estimates reads the offset and the biases (and their covariance, cross terms
    included) from those states, the stds from the statistics, with zero cross-covariance
    between the two groups."""
    ns = 3
    theta = jnp.array([0.1, 0.2, 1.0, 2.0, 3.0, 0.4, 0.5, 0.6])
    xa, Pa = augment_prior(np.zeros(5), np.arange(1.0, 6.0), theta, 2.0, ns)
    np.testing.assert_allclose(xa, [0, 0, 0, 0, 0, 1.0, 2.0, 3.0, 0.1])
    np.testing.assert_allclose(np.diag(Pa), np.r_[np.arange(1.0, 6.0),
                                                  2.0 * np.array([0.4, 0.5, 0.6, 0.2]) ** 2])
    assert np.count_nonzero(Pa - np.diag(np.diag(Pa))) == 0
    rng = np.random.default_rng(1)
    A = rng.normal(size=(9, 9))
    cov = A @ A.T
    mean = rng.normal(size=9)
    B = rng.normal(size=(8, 8))
    pcov = B @ B.T
    params = rng.normal(size=8)
    p, pc = map_estimates(jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(params),
                          jnp.asarray(pcov), 5, ns)
    mi, si, oi = [0, 2, 3, 4], [8, 5, 6, 7], [1, 5, 6, 7]
    np.testing.assert_array_equal(np.asarray(p)[mi], mean[si])
    np.testing.assert_array_equal(np.asarray(p)[oi], params[oi])
    np.testing.assert_array_equal(np.asarray(pc)[np.ix_(mi, mi)], cov[np.ix_(si, si)])
    np.testing.assert_array_equal(np.asarray(pc)[np.ix_(oi, oi)], pcov[np.ix_(oi, oi)])
    np.testing.assert_array_equal(np.asarray(pc)[np.ix_(mi, oi)], 0.0)


@pytest.mark.parametrize("arg, over", [
    ("gamma0", dict(gamma0=0.0)),
    ("nu0", dict(nu0=4.0)),
    ("forgetting", dict(forgetting=1.5)),
    ("sensors", dict(sensors=("ay", "gps"))),
    ("noisy_input", dict(noisy_input="steer")),
    ("std0", dict(std0={"delta": 0.01})),
    ("bias_walk", dict(bias_walk={"gps": 0.1})),
    ("bias_walk", dict(bias_walk={"ay": -0.1})),
    ("bias_walk", dict(bias_walk=[0.1])),
    ("input_std_range", dict(input_std_range=(0.01,))),
    ("input_std_range", dict(input_std_range=(0.02, 0.01))),
    ("input_std_range", dict(input_std_range=(0.0, 0.01))),
    ("input_std_prior", dict(input_std_prior="flat")),
    ("input_std_prior", dict(input_std_prior="log-uniform")),
    ("input_std_prior", dict(input_std_prior="inverse-wishart", input_std_range=(0.01, 0.02))),
    ("sensor_variances", dict(sensor_variances="fisher")),
])
def test_bad_options_raise_naming_them(arg, over):
    with pytest.raises(ValueError, match=arg):
        marginalized_pf_grid(MODEL, 100, **_kw(**over))


@pytest.mark.parametrize("arg", ["bias_walk", "mean_std0", "input_std_range", "input_std_prior",
                                 "sensor_variances", "means", "grid", "noise_means"])
def test_the_papers_filter_takes_no_grid_option(arg):
    """The grid filter is its own builder: marginalized_pf has none of its options (they were
    refused with a ValueError while they were keywords of one builder)."""
    with pytest.raises(TypeError, match=arg):
        marginalized_pf(MODEL, 100, **_kw(), **{arg: None})


def test_default_is_the_papers_filter():
    """marginalized_pf is the paper's filter: the NiW learns the means (the parameters'
    prior is mean0 with gamma0 std0^2), the particles' Kalman filters cover the bank only
    ("linear"), and it declares its Rao-Blackwell structure for smoothing."""
    est = marginalized_pf(MODEL, 100, **_kw())
    default = marginalized_pf(MODEL, 100, known_std=KNOWN, Q=0.05 ** 2,
                              niw=NiW(std0=STD0))
    for e in (est, default):
        assert e.rao_blackwell is not None and not e.rao_blackwell.gauss
        assert e.rao_blackwell.nz == 3
        assert e.param_prior[1][0, 0] == 1.0 * STD0["delta"] ** 2  # gamma0 = 1
    variant = marginalized_pf_grid(MODEL, 100, **_kw())
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


def _simulate(R, T, offset, bias, sig_phi, seed, sig_w=0.0):
    """Data of the linear SingleTrackBank at the study's inputs: steering with a constant
    offset and white noise of std ``sig_w``, white bank jerk, constant sensor biases, white
    noise of the stds STD0 / KNOWN. Returns (truth (R, T, 5), Y (R, T, 5), U (T, 2))."""
    U = matched_inputs(T)
    F, B, H, D = _matrices(float(U[0, 0]))
    gain = np.r_[np.asarray(MODEL.bank_noise_gain()), np.zeros(3)]
    std = np.array([STD0.get(n, KNOWN.get(n)) for n in MODEL.output_names])
    rng = np.random.default_rng(seed)
    x = np.tile(np.r_[np.zeros(5), bias], (R, 1))
    X, Y = np.zeros((R, T, 5)), np.zeros((R, T, 5))
    for t in range(T):
        d = U[t, 1] + offset
        if sig_w:
            d = d + sig_w * rng.normal(size=(R, 1))
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
    est = marginalized_pf_grid(MODEL, N, sensors=SENSORS, known_std=KNOWN,
                               Q=sig_phi ** 2,
                               niw=NiW(std0=std0, mean0={"delta": offset}, forgetting=1.0, nu0=1e7,
                                       gamma0=1.0))
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


def _input_noise_loglik(Y, U, offset, sig_w, x0, P0, Pb0, bank_std):
    """numpy: the exact log-likelihood (R,) of Y under the linear SingleTrackBank (:func:
    `_matrices`) with white noise of stds ``bank_std`` (3,) on the bank states, the steering
    noise of std ``sig_w`` (process noise B w and measurement noise D w, correlated), the
    biases states of prior N(0, Pb0), the offset and every covariance known. Also returns the
    predictive covariances S_t (T, 5, 5), the same for every run."""
    import scipy.stats

    F, B, H, D = _matrices(float(U[0, 0]))
    Q = np.diag(np.r_[0.0, 0.0, bank_std, np.zeros(3)] ** 2)
    Rm = np.diag([STD0.get(n, KNOWN.get(n)) ** 2 for n in MODEL.output_names])
    runs, T, _ = Y.shape
    m = np.tile(np.r_[x0, np.zeros(3)], (runs, 1))
    P = np.zeros((8, 8))
    P[:5, :5], P[5:, 5:] = P0, Pb0
    s2 = sig_w ** 2
    ll = np.zeros(runs)
    Ss = []
    for t in range(T):
        d = U[t, 1] + offset
        m = m @ F.T + B * d
        P = F @ P @ F.T + Q + s2 * np.outer(B, B)
        Csy = P @ H.T + s2 * np.outer(B, D)  # Cov(s_t, y_t)
        S = H @ Csy + s2 * np.outer(D, B) @ H.T + s2 * np.outer(D, D) + Rm
        S = 0.5 * (S + S.T)
        Ss.append(S)
        e = Y[:, t] - m @ H.T - D * d
        ll += scipy.stats.multivariate_normal(np.zeros(5), S).logpdf(e)
        K = np.linalg.solve(S, Csy.T).T
        m = m + e @ K.T
        P = P - K @ S @ K.T
        P = 0.5 * (P + P.T)
    return ll, np.array(Ss)


def _s_information(S, dS):
    """numpy: sum over t of 0.5 tr((S_t^-1 dS_t)^2), S and dS (T, n, n)."""
    A = np.linalg.solve(S, dS)
    return 0.5 * np.einsum("tij,tji->", A, A)


@pytest.mark.slow  # one MPF compile each (about a minute on 2 cores): `pytest -m slow` (README)
@pytest.mark.parametrize("prior, variances", [("log-uniform", None), ("jeffreys", None),
                                               ("log-uniform", "inverse-wishart")])
def test_input_std_grid_is_the_exact_posterior_of_the_steering_std(prior, variances):
    """On the linear SingleTrackBank written as a user would
    (:func:`_bank_ref.user_linear_bank`, white noise on each bank state), with the offset and
    the sensor covariances known (nu0 = 1e10, forgetting 1) and the steering std on a grid
    (``input_std_range``): each particle is the exact Kalman filter at its std, so the filter's
    weights are the exact posterior over the grid: the reported std (sqrt of the posterior mean
    of sigma_w^2), its reported variance (the posterior spread) and the log-likelihood equal
    those computed from numpy Kalman likelihoods at each grid value (flat prior over the grid;
    with ``input_std_prior="jeffreys"`` times sqrt of the covariance part of the Fisher
    information of log sigma_w^2, sum_t 0.5 tr((S_t^-1 dS_t)^2), dS_t by central differences of
    the numpy S_t over the grid). The grid's differences are also checked against the derivative
    itself (numpy S_t at sigma_w^2 (1 +- 1e-4)): the information within 10 %. Where the grid
    does not resolve the posterior (6 points), the reported std and spread are the Laplace
    approximation's from the three largest numpy log weights (:mod:`vehjax.filters.marginalized.grid`,
    written out here again). The sensor variances scored (the default) or the inverse-Wishart
    mean (``sensor_variances="inverse-wishart"``), their prior as good as known either way."""
    # 6 points: the grid does not resolve the posterior (the Laplace branch of
    # vehjax.filters.marginalized.grid); 12 with Jeffreys' prior: it does (the weighted moments)
    T, R, N = 150, 2, 12 if prior == "jeffreys" else 6
    offset, sig_w = math.radians(0.28), math.radians(0.3)
    bank_std = np.array([1e-5, 1e-4, 0.002])
    U = matched_inputs(T)
    std = np.array([STD0.get(n, KNOWN.get(n)) for n in MODEL.output_names])
    _, Y = simulate_linear_bank(MODEL.theta, DT, U, R, offset, sig_w, bank_std, np.zeros(5),
                                std, 4)
    x0, P0 = np.zeros(5), np.array([1e-30, 1e-30, 1e-6, 1e-6, 1e-6])
    lo, hi = sig_w / 1.5, sig_w * 1.5
    est = marginalized_pf_grid(user_linear_bank(MODEL.theta, float(U[0, 0]), DT), N,
                               sensors=SENSORS, known_std=KNOWN, Q=bank_std ** 2,
                               sensor_variances=variances,
                               niw=NiW(std0=STD0, mean0={"delta": offset}, forgetting=1.0,
                                       nu0=1e10),
                               means=MeanStates(mean_std0={"delta": 1e-9}),
                               grid=InputStdGrid(input_std_range=(lo, hi), input_std_prior=prior))
    out = vj.run(est, Y, U, x0=x0, P0=P0, key=jax.random.key(5), return_covariances=True)
    assert not out.diverged.any()
    grid = np.exp(np.linspace(math.log(lo), math.log(hi), N))
    Pb0 = np.diag([STD0[s] ** 2 for s in SENSORS])
    ref = [_input_noise_loglik(Y, U, offset, g, x0, np.diag(P0), Pb0, bank_std) for g in grid]
    L = np.stack([r[0] for r in ref], 1)  # (R, N)
    Lmax = L.max(1, keepdims=True)
    w = np.exp(L - Lmax)
    if prior == "jeffreys":
        S = np.stack([r[1] for r in ref])  # (N, T, 5, 5)
        info = np.array([_s_information(S[i], dS) for i, dS in
                         enumerate(np.gradient(S, 2.0 * np.log(grid), axis=0))])
        exact = []
        for g in grid[[1, N // 2, N - 2]]:
            Sp, Sm = (_input_noise_loglik(Y[:1], U, offset, g * math.sqrt(1.0 + e), x0,
                                          np.diag(P0), Pb0, bank_std)[1] for e in (1e-4, -1e-4))
            exact.append(_s_information(0.5 * (Sp + Sm), (Sp - Sm) / 2e-4))
        np.testing.assert_allclose(info[[1, N // 2, N - 2]], exact, rtol=0.1)
        w = w * np.sqrt(info)
    w /= w.sum(1, keepdims=True)
    std_w = np.sqrt(w @ grid ** 2)
    spread = np.sum(w * (grid[None] - std_w[:, None]) ** 2, 1)
    t = 2.0 * np.log(grid)  # log sigma_w^2, the grid's spacing h
    h = t[1] - t[0]
    narrow = 0
    for r in range(R):  # a posterior the grid does not resolve: the parabola (_grid)
        k = int(np.argmax(w[r]))
        lm, l0, lp = np.log(w[r, k - 1:k + 2]) if 0 < k < N - 1 else (0.0, 0.0, 0.0)
        second = lm - 2.0 * l0 + lp
        if second < 0.0 and -h * h / second < (0.6 * h) ** 2:
            m, V = t[k] + 0.5 * h * (lm - lp) / second, -h * h / second
            std_w[r] = math.exp(0.5 * m + 0.25 * V)
            spread[r] = 2.0 * math.exp(m + 0.5 * V) - 2.0 * math.exp(m + 0.375 * V)
            narrow += 1
    j = est.param_names.index("delta_std")
    np.testing.assert_allclose(out.params[:, -1, j], std_w, rtol=1e-6)
    np.testing.assert_allclose(out.params_cov[:, -1, j, j], spread, rtol=1e-5)
    if prior == "log-uniform":  # the marginal likelihood (with Jeffreys' prior, which
        total = Lmax[:, 0] + np.log(np.mean(np.exp(L - Lmax), 1))  # changes, it is not one)
        np.testing.assert_allclose(np.asarray(out.loglik).reshape(R, -1).sum(1), total,
                                   rtol=1e-8, atol=1e-4)
    assert np.max(w) < 0.99  # the posterior is spread over the grid: not a trivial check
    assert narrow == (0 if prior == "jeffreys" else R), narrow  # each branch as meant


def test_static_grid_carries_the_inverse_wishart_prior_of_the_input_variance():
    """static_prior_grid: the weighted grid of sigma_w^2 reproduces the prior's marginal
    Lambda_w / chi^2_dof, inverse-gamma(dof / 2, Lambda_w / 2) (scipy): its mean, the mean of
    log sigma^2 (log Lambda_w - digamma(dof / 2) - log 2) and the cdf at the quartiles, and it
    reaches into both tails."""
    import scipy.special
    import scipy.stats

    from vehjax.filters.marginalized.niw import static_prior_grid

    lam, dof = 3.0e-4, 5.0
    v, lw = static_prior_grid(jnp.asarray(lam), dof, 400)
    v, w = np.asarray(v), np.exp(np.asarray(lw))
    ig = scipy.stats.invgamma(dof / 2, scale=lam / 2)
    assert abs(w.sum() - 1.0) < 1e-12 and np.all(np.diff(v) > 0)
    np.testing.assert_allclose(w @ v, ig.mean(), rtol=0.01)
    ref_log = math.log(lam) - scipy.special.digamma(dof / 2) - math.log(2.0)  # E log(lam / c)
    np.testing.assert_allclose(w @ np.log(v), ref_log, atol=0.01)
    for q in (0.25, 0.5, 0.75):
        np.testing.assert_allclose(np.sum(w[v <= ig.ppf(q)]), q, atol=0.01)
    assert ig.cdf(v[0]) < 1e-3 and ig.sf(v[-1]) < 1e-3


def test_input_noise_kalman_step_is_the_kalman_update_with_the_input_error_as_a_state():
    """input_noise_kalman_step on the augmented SingleTrackBank (offset and biases as states):
    the predicted joint of (s_t, w) and its conditioning on the observed components of y_t,
    and the weight log N(o; 0, S), equal a numpy Kalman step on the model's Jacobians with w
    appended as a state (scipy for the density), one component missing."""
    import scipy.stats

    from vehjax.lib.entrywise import entries
    from vehjax.filters.marginalized.kalman import input_noise_kalman_step
    from vehjax.filters.marginalized.linearise import lin_entries, linearise

    aug = with_noise_means(MODEL, SENSORS, "delta")
    nx = len(aug.state_names)
    nl, li = np.array([0, 1]), np.arange(2, nx)
    rng = np.random.default_rng(4)
    A = rng.normal(size=(nx, nx)) * 1e-2
    P = A @ A.T + 1e-6 * np.eye(nx)  # (sampled, linear) order, as the filter keeps it
    x, m = np.array([0.1, 0.02]), rng.normal(0, 0.01, nx - 2)
    u = np.array([20.0, 0.01])
    y = rng.normal(0, 0.1, 5)
    obs = np.array([True, True, False, True, True])
    Rn = np.diag([0.04, 1e-4, 1e-4, 1e-4, 2e-4])
    Qn = 1e-8 * np.eye(nx - 2)
    sw2 = 3e-7
    f = lambda X, u_, th: aug.transition(X, u_, th)  # noqa: E731
    h = lambda X, u_, th: aug.observe(X, u_, th)  # noqa: E731
    lin = linearise(f, h, jnp.asarray(x), jnp.asarray(m), jnp.asarray(u), aug.theta, nl, li, 1)
    post, C, o, ll, S = input_noise_kalman_step(
        lin_entries(lin), entries(jnp.asarray(P)), sw2, entries(jnp.asarray(y)), list(obs),
        [0.0] * 5, entries(jnp.asarray(Rn)), entries(jnp.asarray(Qn)))
    # numpy: the Jacobians by finite differences of the model itself, in (sampled, linear) order
    order = np.r_[nl, li]
    X0 = np.zeros(nx)
    X0[nl], X0[li] = x, m

    def fo(v):  # (deviations of the states in filter order, w) -> (f in filter order, h)
        X = X0.copy()
        X[order] += v[:nx]
        uu = u + np.array([0.0, v[nx]])
        return np.asarray(f(X, uu, aug.theta))[order], np.asarray(h(X, uu, aug.theta))

    eps = 1e-6
    J = np.stack([(fo(e)[0] - fo(-e)[0]) / (2 * eps) for e in eps * np.eye(nx + 1)], 1)
    Phi, g = J[:, :nx], J[:, nx]
    xb = fo(np.zeros(nx + 1))[0]

    def ho(v):  # y at the predicted point xb plus deviations (filter order), input error v[nx]
        return np.asarray(h(_shift(X0, order, xb, v[:nx]), u + np.r_[0.0, v[nx]], aug.theta))

    Hh = np.stack([(ho(e) - ho(-e)) / (2 * eps) for e in eps * np.eye(nx + 1)], 1)
    yb = ho(np.zeros(nx + 1))
    Pa = np.zeros((nx + 1, nx + 1))
    Pa[:nx, :nx] = Phi @ P @ Phi.T + sw2 * np.outer(g, g)
    Pa[nx - len(li):nx, nx - len(li):nx] += Qn
    Pa[:nx, nx] = Pa[nx, :nx] = sw2 * g
    Pa[nx, nx] = sw2
    Ho, ro, Ro = Hh[obs], (y - yb)[obs], Rn[np.ix_(obs, obs)]
    Sn = Ho @ Pa @ Ho.T + Ro
    K = np.linalg.solve(Sn, Ho @ Pa).T
    np.testing.assert_allclose(np.array(post, float), K @ ro, rtol=1e-5, atol=1e-12)
    Cn = Pa - K @ Sn @ K.T
    np.testing.assert_allclose(np.array(C, float), Cn, rtol=1e-5, atol=1e-14)
    np.testing.assert_allclose(np.array(S, float)[np.ix_(obs, obs)], Sn, rtol=1e-6)
    ref = scipy.stats.multivariate_normal(np.zeros(obs.sum()), Sn).logpdf(ro)
    np.testing.assert_allclose(float(ll), ref, rtol=1e-7)


def _shift(X0, order, xb, dev):
    """The state vector (model order) at the predicted point xb (filter order) plus dev."""
    X = X0.copy()
    X[order] = xb + dev
    return X


# ----------------------------------------------------------------------------------------------
# Jeffreys' prior over the grid (vehjax.filters.marginalized.jeffreys)


def test_covariance_information_is_half_the_trace_of_the_squared_relative_derivative():
    """A scalar variance component S = a s + c (s = sigma^2): 0.5 (dS / dlog s / S)^2 =
    0.5 (a s / (a s + c))^2, exact; a 3-D case with one component missing against numpy's
    0.5 tr((S^-1 dS)^2) over the observed block."""
    from vehjax.filters.marginalized.jeffreys import covariance_information

    a, c = 2.0, 0.5
    s = np.array([1e-3, 0.1, 1.0, 10.0])
    S = (a * s + c)[None, None, :]
    info = covariance_information(jnp.asarray(S), jnp.asarray((a * s)[None, None, :]),
                                  jnp.array([True]))
    np.testing.assert_allclose(info, 0.5 * (a * s / (a * s + c)) ** 2, rtol=1e-12)
    rng = np.random.default_rng(0)
    M = rng.normal(size=(3, 3, 2))
    S = np.einsum("ikn,jkn->ijn", M, M) + 0.3 * np.eye(3)[:, :, None]
    dS = rng.normal(size=(3, 3, 2))
    dS = dS + dS.transpose(1, 0, 2)
    obs = np.array([True, False, True])
    got = covariance_information(jnp.asarray(S), jnp.asarray(dS), jnp.asarray(obs))
    for n in range(2):
        o = np.ix_(obs, obs)
        A = np.linalg.solve(S[..., n][o], dS[..., n][o])
        np.testing.assert_allclose(got[n], 0.5 * np.trace(A @ A), rtol=1e-10)


def test_grid_derivative_is_second_order_and_the_prior_normalised():
    """Central differences of S(theta) = a e^theta + c on a uniform grid: the relative error
    inside is sinh(h) / h - 1 (about h^2 / 6), so it falls 4x when the spacing halves; log_prior
    is 0.5 log I normalised, equal before any datum."""
    from vehjax.filters.marginalized.jeffreys import grid_derivative, log_prior

    errs = []
    for n in (11, 21):
        th = jnp.linspace(-2.0, 2.0, n)
        S = 3.0 * jnp.exp(th) + 1.0
        d = grid_derivative(S[None, None, :], th)[0, 0]
        errs.append(float(jnp.max(jnp.abs(d / (3.0 * jnp.exp(th)) - 1.0)[1:-1])))
        h = 4.0 / (n - 1)
        np.testing.assert_allclose(errs[-1], math.sinh(h) / h - 1.0, rtol=1e-6)
    assert 3.9 < errs[0] / errs[1] < 4.1
    info = jnp.array([0.0, 1.0, 4.0, 16.0])
    lp = np.asarray(log_prior(info))
    np.testing.assert_allclose(np.exp(lp).sum(), 1.0, rtol=1e-12)
    np.testing.assert_allclose(np.exp(lp[1:]) / np.exp(lp[1]), [1.0, 2.0, 4.0], rtol=1e-12)
    assert np.exp(lp[0]) < 1e-100
    np.testing.assert_allclose(log_prior(jnp.zeros(4)), np.full(4, -math.log(4)), rtol=1e-12)


# ----------------------------------------------------------------------------------------------
# the sensor variances by Fisher scoring (vehjax.filters.marginalized.sensor_scoring)


def _nested(A):
    return [[jnp.asarray(A[i, j]) for j in range(A.shape[1])] for i in range(A.shape[0])]


def _spd(rng, n):
    M = rng.normal(size=(n, n))
    return M @ M.T + 0.5 * np.eye(n)


def test_innovation_score_against_numpy_with_a_sensor_missing():
    """s_i = 0.5 ((G nu)_i^2 - G_ii), W_ij = 0.5 G_ij^2 with G the inverse of the observed block
    of S (numpy), on the learnt rows; a missing sensor's row and column zero."""
    from vehjax.filters.marginalized.sensor_scoring import innovation_score

    rng = np.random.default_rng(1)
    S, nu = _spd(rng, 5), rng.normal(size=5)
    obs = np.array([True, True, False, True, True])
    rows = [0, 2, 3]
    s, W = innovation_score(_nested(S), [jnp.asarray(v) for v in nu], list(jnp.asarray(obs)),
                            rows)
    G = np.zeros((5, 5))
    G[np.ix_(obs, obs)] = np.linalg.inv(S[np.ix_(obs, obs)])
    a = G @ nu
    ok = obs[rows]
    np.testing.assert_allclose(np.array(s), np.where(ok, 0.5 * (a[rows] ** 2 - G[rows, rows]), 0),
                               rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(np.array([[float(w) for w in r] for r in W]),
                               0.5 * G[np.ix_(rows, rows)] ** 2, rtol=1e-10, atol=1e-14)


def test_the_score_is_unbiased_for_the_true_variances():
    """Innovations drawn with the sensors' true variances R where the step used r: the mean
    score over 400,000 draws is W (R - r) within its Monte-Carlo error, so z = r + W^-1 s is
    an unbiased pseudo-observation of R (the module docstring's claim)."""
    from vehjax.filters.marginalized.sensor_scoring import innovation_score

    rng = np.random.default_rng(2)
    rows = [0, 1, 3]
    Sx = _spd(rng, 4)
    r = np.array([0.5, 0.2, 0.0, 1.0])
    R = np.array([1.0, 0.1, 0.0, 1.5])
    S_used, S_true = Sx + np.diag(r), Sx + np.diag(R)
    nu = np.linalg.cholesky(S_true) @ rng.normal(size=(4, 400_000))
    obs = [jnp.asarray(True)] * 4
    s, W = innovation_score(_nested(S_used), [jnp.asarray(v) for v in nu], obs, rows)
    s = np.array([np.asarray(v) for v in s])
    W = np.array([[float(w) for w in row] for row in W])
    expect = W @ (R - r)[rows]
    se = s.std(axis=1) / math.sqrt(nu.shape[1])
    assert np.all(np.abs(s.mean(axis=1) - expect) < 4 * se)
    assert np.all(np.abs(expect) > 10 * se)  # the test can tell a biased score apart


def test_scored_variances_of_a_sensor_seen_alone_are_the_inverse_wishart_mean():
    """S_x = 0 (each sensor seen alone): whatever variances r_t each step used, the scored
    estimate after n steps is (count v_0 + sum e_t^2) / (count + n), the inverse-Wishart mean;
    with the weights' reference at the variances used, the sandwich is J^-1."""
    from vehjax.filters.marginalized.sensor_scoring import prior_terms, scored_variances, scoring_terms

    rng = np.random.default_rng(3)
    v0, count, n = np.array([0.04, 1e-4]), 3.0, 40
    J, h = prior_terms(jnp.asarray(v0), count)
    H = J
    e2 = np.zeros(2)
    for _ in range(n):
        r = v0 * rng.uniform(0.3, 3.0, size=2)
        e = rng.normal(size=2) * np.sqrt(v0)
        e2 += e ** 2
        Wb, Wz, Ht = scoring_terms(_nested(np.diag(r)), _nested(np.diag(r)),
                                   [jnp.asarray(x) for x in e], [jnp.asarray(True)] * 2, [0, 1],
                                   list(jnp.asarray(v0)))
        J = J + jnp.array([[jnp.asarray(w) for w in row] for row in Wb])
        h = h + jnp.array([jnp.asarray(w) for w in Wz])
        H = H + jnp.array([[jnp.asarray(w) for w in row] for row in Ht])
    v, C = scored_variances(J, h, H)
    np.testing.assert_allclose(v, (count * v0 + e2) / (count + n), rtol=1e-10)
    Jr, hr = prior_terms(jnp.asarray(v0), count)
    Wb, Wz, Ht = scoring_terms(_nested(np.diag(v0) + 0.1 * _spd(rng, 2)),
                               _nested(np.diag(v0)), [jnp.asarray(0.3), jnp.asarray(-0.1)],
                               [jnp.asarray(True)] * 2, [0, 1], list(jnp.asarray(v0)))
    Jr = Jr + jnp.array([[jnp.asarray(w) for w in row] for row in Wb])
    Hr = prior_terms(jnp.asarray(v0), count)[0] + jnp.array(
        [[jnp.asarray(w) for w in row] for row in Ht])
    _, C = scored_variances(Jr, hr, Hr)
    np.testing.assert_allclose(C, np.linalg.inv(np.asarray(Jr)), rtol=1e-10)





def test_ridge_sensitivity_and_the_plug_in_variance_against_numpy():
    """ridge_sensitivity is J_w Cov_w(v, theta) (numpy weighted moments); on an exact ridge
    v = v0 + b theta it is J_w b Var_w(theta); plug_in_variance is g C g^T, 0 where C is NaN."""
    from vehjax.filters.marginalized.sensor_scoring import plug_in_variance, ridge_sensitivity

    rng = np.random.default_rng(4)
    theta = np.linspace(-1.0, 1.0, 40)
    w = np.exp(-0.5 * (theta - 0.2) ** 2 / 0.05)
    w /= w.sum()
    b = np.array([0.3, -0.02])
    v = np.array([1.0, 0.5])[:, None] + b[:, None] * theta
    J = np.stack([_spd(rng, 2) for _ in range(40)], axis=-1)
    g = np.asarray(ridge_sensitivity(jnp.asarray(w), jnp.asarray(theta), jnp.asarray(v),
                                     jnp.asarray(J)))
    var = w @ (theta - w @ theta) ** 2
    np.testing.assert_allclose(g, (J * w).sum(-1) @ b * var, rtol=1e-10)
    C = np.stack([_spd(rng, 2), np.full((2, 2), np.nan)], axis=-1)
    got = plug_in_variance(jnp.asarray(g), jnp.asarray(C))
    np.testing.assert_allclose(got[0], g @ C[..., 0] @ g, rtol=1e-12)
    assert float(got[1]) == 0.0


def test_a_sensor_seen_beside_the_input_noise_is_learnt_from_a_wrong_guess():
    # one MPF compile, 27 s on 2 cores: the default suite's one end-to-end run of the scored
    # sensor variances
    """The consistency study's data (``vehjax reproduce consistency``: the steering noise
    reaches ay directly, d sigma_w about 0.35 m/s^2 beside ay's 0.2), 20 runs x 300 steps, the
    steering std known, every sensor std guessed at twice the truth: the scored sensor
    variances (the default, vehjax.filters.marginalized.sensor_scoring) bring the ay std to within 15 % of
    the truth on average and its 95 % interval holds the truth in at least 0.8 of the runs.
    The inverse-Wishart mean alone (``sensor_variances="inverse-wishart"``) stayed at +45 %
    with no interval holding the truth (100 runs, seed 0)."""
    X, Y, U = simulate_matched(MODEL, 20, 300, 7)
    std0 = {"delta": MATCHED.steer_std, **{k: 2.0 * v for k, v in MATCHED.sensor_std.items()}}
    est = marginalized_pf_grid(MODEL, 3, sensors=SENSORS, known_std=MATCHED.known_std,
                               Q=MATCHED.bank_jerk_std ** 2,
                               niw=NiW(std0=std0, mean0={"delta": MATCHED.offset, **MATCHED.bias},
                                       forgetting=1.0),
                               grid=InputStdGrid(input_std_prior="log-uniform",
                                                 input_std_range=(MATCHED.steer_std,
                                                                  MATCHED.steer_std * (1 + 1e-9))))
    out = vj.run(est, Y, U, x0=np.zeros(5), P0=np.full(5, 1e-12), key=jax.random.key(0),
                 return_covariances=True)
    assert not out.diverged.any()
    i = est.param_names.index("ay_std")
    est_ay = np.asarray(out.params[:, -1, i])
    sd = np.sqrt(np.asarray(out.params_cov[:, -1, i, i]))
    rel = est_ay.mean() / MATCHED.sensor_std["ay"] - 1.0
    assert abs(rel) < 0.15, rel
    assert np.mean(np.abs(est_ay - MATCHED.sensor_std["ay"]) <= 1.96 * sd) >= 0.8


def test_the_gyros_scored_variances_match_the_oracle():
    # one MPF compile, about 30 s on 2 cores
    """The consistency study's data, 20 runs x 300 steps, the steering std known and every
    guess at the truth: the scored stds of the gyros (r and the roll rate, which the
    steering noise does not reach directly) average within 0.6 % of the oracle's, each run's
    sample std of its true noise (states and biases known). With the inverse-Wishart
    statistics' correlations kept beside the scored variances they ended 1.1-1.4 % above it
    (100 runs, seeds 0-3; ``benchmarks/mpf_k_param_bias.py``)."""
    X, Y, U = simulate_matched(MODEL, 20, 300, 11)
    est = marginalized_pf_grid(MODEL, 3, sensors=SENSORS, known_std=MATCHED.known_std,
                               Q=MATCHED.bank_jerk_std ** 2, sensor_variances="scored",
                               niw=NiW(std0={"delta": MATCHED.steer_std, **MATCHED.sensor_std},
                                       mean0={"delta": MATCHED.offset, **MATCHED.bias},
                                       forgetting=1.0),
                               grid=InputStdGrid(input_std_prior="log-uniform",
                                                 input_std_range=(MATCHED.steer_std,
                                                                  MATCHED.steer_std * (1 + 1e-9))))
    out = vj.run(est, Y, U, x0=np.zeros(5), P0=np.full(5, 1e-12), key=jax.random.key(0))
    assert not out.diverged.any()
    u0 = jnp.asarray([MATCHED.speed, 0.0])
    clean = np.asarray(jax.vmap(jax.vmap(lambda x: MODEL.observe(x, u0, MODEL.theta)))(X))
    for s in ("r", "roll_rate"):
        j = MODEL.output_names.index(s)
        oracle = np.sqrt(np.mean((Y[..., j] - clean[..., j] - MATCHED.bias[s]) ** 2, axis=1))
        got = np.asarray(out.params[:, -1, est.param_names.index(f"{s}_std")])
        assert abs(got.mean() / oracle.mean() - 1.0) < 0.006, (s, got.mean() / oracle.mean())


@pytest.mark.slow  # one MPF compile (about a minute on 2 cores): `pytest -m slow` (README)
def test_a_user_written_model_learns_every_noise_with_honest_intervals():
    """The linear SingleTrackBank written as a user would (:func:`_bank_ref.user_linear_bank`: two
    plain jnp functions, white noise on each bank state), data simulated in numpy with other
    values than the consistency study's (steering offset 0.4 deg, noise 0.25 deg; ay bias
    -0.15 m/s^2; sensor stds 1.5 x STD0), 100 runs x 400 steps, the filter's defaults learning
    everything (offset and biases as Kalman states, the steering std on Jeffreys' grid from a
    guess twice the truth, the sensor variances scored from guesses twice the truth), 25 grid
    points over a decade either side of the guess (19 % apart in sigma_w, where the data pin
    it to about 6 %: the grid does not resolve its posterior, vehjax.filters.marginalized.grid): each
    learnt parameter's mean error is within 15 % of the truth (stds) or 2 mean reported stds
    (offset, biases), its 95 % interval holds the truth in at least 0.85 of the runs, and the
    NEES of (vy, r) averages 0.7-1.4 per dof over the last half. Measured (``python
    benchmarks/mpf_grid_resolution.py 100 22 25``): coverage 0.95-1.00 (the steering std's
    0.95; with the grid's weighted moments, before _grid, 0.80: ``... weighted``), NEES 0.98
    per dof."""
    T = 400
    est, X, Y, U, truth, run_kw = user_bank_case(100, 22, 25, steps=T)
    out = vj.run(est, Y, U, **run_kw)
    assert not out.diverged.any()
    for name, value in truth.items():
        j = est.param_names.index(name)
        got = np.asarray(out.params[:, -1, j])
        sd = np.sqrt(np.asarray(out.params_cov[:, -1, j, j]))
        if name.endswith("_std"):
            assert abs(got.mean() / value - 1.0) < 0.15, (name, got.mean() / value)
        else:
            assert abs(got.mean() - value) < 2.0 * sd.mean(), (name, got.mean(), value)
        assert np.mean(np.abs(got - value) <= 1.96 * sd) >= 0.85, name
    from vehjax import metrics

    nees = metrics.nees(np.asarray(out.states)[:, T // 2:, :2],
                        np.asarray(out.covariances)[:, T // 2:, :2, :2], X[:, T // 2:, :2])
    assert 0.7 < np.mean(nees) / 2 < 1.4, np.mean(nees) / 2
