"""Resampling schemes: unbiased offspring counts, their known variances, references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax  # noqa: F401
from vehjax.filters import resampling as rs

# A fixed weight vector with a zero weight, a large one and fractional parts of n w all over.
W = np.array([0.31, 0.0, 0.045, 0.12, 0.005, 0.2, 0.07, 0.25])
W = W / W.sum()
N = W.size
K = 20000  # keys per scheme


def _counts(scheme, log_w, n, n_keys=K):
    keys = jax.random.split(jax.random.key(42), n_keys)
    idx = jax.jit(jax.vmap(lambda k: rs.resample(k, log_w, scheme, n)))(keys)
    idx = np.asarray(idx)
    assert idx.shape == (n_keys, n) and idx.dtype == np.int32
    assert idx.min() >= 0 and idx.max() < log_w.shape[0]
    return np.stack([np.bincount(row, minlength=log_w.shape[0]) for row in idx])


@pytest.fixture(scope="module")
def counts():
    with np.errstate(divide="ignore"):
        log_w = jnp.asarray(np.log(W))
    return {s: _counts(s, log_w, N) for s in rs.SCHEMES}


def _multinomial_var(n, w):
    return n * w * (1 - w)


def _systematic_var(n, w):
    f = n * w - np.floor(n * w)
    return f * (1 - f)


def _residual_var(n, w):
    f = n * w - np.floor(n * w)
    return f * (1 - f / f.sum())


@pytest.mark.parametrize("scheme", rs.SCHEMES)
def test_offspring_counts_are_unbiased(counts, scheme):
    c = counts[scheme]
    assert np.all(c.sum(axis=1) == N)
    assert np.all(c[:, 1] == 0)  # the zero-weight particle never survives
    # standard error from the largest variance any of the schemes has (multinomial's)
    se = np.sqrt(_multinomial_var(N, W) / K)
    assert np.all(np.abs(c.mean(axis=0) - N * W) <= 4.5 * se + 1e-12), (c.mean(axis=0), N * W)


def test_offspring_variances_match_theory_and_order(counts):
    var = {s: counts[s].var(axis=0, ddof=1) for s in rs.SCHEMES}
    tol = 0.06  # relative; the sample variance of K = 20000 draws has ~1-2 % relative error
    mult, syst, resid = _multinomial_var(N, W), _systematic_var(N, W), _residual_var(N, W)
    np.testing.assert_allclose(var["multinomial"], mult, rtol=tol, atol=1e-3)
    np.testing.assert_allclose(var["systematic"], syst, rtol=tol, atol=1e-3)
    np.testing.assert_allclose(var["residual"], resid, rtol=tol, atol=1e-3)
    # stratified: no closed form; bounded by systematic's (the least any unbiased integer count
    # can have) and multinomial's (Douc, Cappe & Moulines 2005)
    assert np.all(var["stratified"] >= syst * (1 - tol) - 1e-3)
    assert np.all(var["stratified"] <= mult * (1 + tol) + 1e-3)
    # the known ordering, summed over particles, with room for sampling error
    total = {s: v.sum() for s, v in var.items()}
    assert total["systematic"] < total["stratified"] < total["multinomial"]
    assert total["systematic"] < total["residual"] < total["multinomial"]


def test_systematic_and_residual_counts_are_floor_or_more(counts):
    lo, hi = np.floor(N * W), np.ceil(N * W)
    c = counts["systematic"]
    assert np.all((c >= lo) & (c <= hi))
    assert np.all(counts["residual"] >= lo)


@pytest.mark.parametrize("scheme", rs.SCHEMES)
def test_fewer_indices_than_particles(scheme):
    n = 5
    c = _counts(scheme, jnp.log(jnp.asarray(W) + 1e-300), n, n_keys=8000)
    se = np.sqrt(_multinomial_var(n, W) / 8000)
    assert np.all(c.sum(axis=1) == n)
    assert np.all(np.abs(c.mean(axis=0) - n * W) <= 4.5 * se + 1e-12)


@pytest.mark.parametrize("scheme", rs.SCHEMES)
def test_log_weights_need_not_be_normalised(scheme):
    log_w = jnp.asarray(np.log(np.array([0.5, 0.2, 0.2, 0.1])))
    key = jax.random.key(3)
    a = rs.resample(key, log_w, scheme)
    b = rs.resample(key, log_w + 1000.0, scheme)  # exp would overflow without logsumexp
    c = rs.resample(key, log_w - 1000.0, scheme)  # and underflow
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, c)


def _inverse_cdf(points, w):
    """Plain loop: the k-th point goes to the first particle whose cumulative weight exceeds it."""
    out, j, s = [], 0, w[0]
    for p in points:
        while p >= s and j < w.size - 1:
            j += 1
            s += w[j]
        out.append(j)
    return np.array(out)


def test_cores_match_a_plain_loop_reference():
    rng = np.random.default_rng(0)
    core = jax.jit(rs.indices_from_uniforms, static_argnums=(0, 3))
    for trial in range(30):
        n_part = (1, 2, 9, 40)[trial % 4]
        w = rng.dirichlet(np.full(n_part, 0.4))
        if n_part > 2:
            w[rng.integers(n_part)] = 0.0
            w /= w.sum()
        n = n_part
        u1 = rng.random()
        un = rng.random(n)
        got = core("systematic", jnp.asarray(w), jnp.asarray(u1), n)
        np.testing.assert_array_equal(got, _inverse_cdf((np.arange(n) + u1) / n, w))
        got = core("stratified", jnp.asarray(w), jnp.asarray(un), n)
        np.testing.assert_array_equal(got, _inverse_cdf((np.arange(n) + un) / n, w))
        got = core("multinomial", jnp.asarray(w), jnp.asarray(un), n)
        ref = np.array([_inverse_cdf([p], w)[0] for p in un])
        np.testing.assert_array_equal(got, ref)
        # residual: floor(n w_i) copies in order, then multinomial on the remainders
        got = np.asarray(core("residual", jnp.asarray(w), jnp.asarray(un), n))
        det = np.repeat(np.arange(n_part), np.floor(n * w).astype(int))
        rem = n * w - np.floor(n * w)
        tail = [_inverse_cdf([p], rem / rem.sum())[0] for p in un[det.size:]] if rem.sum() else []
        np.testing.assert_array_equal(got, np.concatenate([det, np.array(tail, int)]))


def test_systematic_matches_cuthbert():
    sysmod = pytest.importorskip("cuthbertlib.resampling.systematic")
    rng = np.random.default_rng(1)
    for i in range(10):
        log_w = jnp.asarray(rng.normal(size=64) * 3.0)
        key = jax.random.key(i)
        ref, _, _ = sysmod.resampling(key, log_w, jnp.zeros(64), 64)
        np.testing.assert_array_equal(rs.systematic(key, log_w), ref)


def test_degenerate_weights_stay_in_range():
    resample = jax.jit(rs.resample, static_argnums=(2,))
    for scheme in rs.SCHEMES:
        idx = resample(jax.random.key(0), jnp.full(5, -jnp.inf), scheme)
        assert idx.shape == (5,) and int(idx.min()) >= 0 and int(idx.max()) < 5
        idx = resample(jax.random.key(0), jnp.array([-jnp.inf, 0.0, -jnp.inf]), scheme)
        np.testing.assert_array_equal(idx, [1, 1, 1])


def test_bad_input_raises_value_error_naming_it():
    lw = jnp.zeros(4)
    valid = "systematic.*stratified.*multinomial.*residual.*bogus"
    with pytest.raises(ValueError, match="^scheme: expected.*" + valid):  # its own argument's name
        rs.resample(jax.random.key(0), lw, "bogus")
    with pytest.raises(ValueError, match="^scheme: "):
        rs.uniforms_needed("sorted", 4)
    with pytest.raises(ValueError, match="n:"):
        rs.systematic(jax.random.key(0), lw, 0)
    with pytest.raises(ValueError, match="n:"):
        rs.multinomial(jax.random.key(0), lw, 2.5)
    with pytest.raises(ValueError, match="log_weights"):
        rs.stratified(jax.random.key(0), jnp.zeros((2, 2)))
    with pytest.raises(ValueError, match="log_weights"):
        rs.residual(jax.random.key(0), jnp.zeros(0))


# ----------------------------------------------------------------------------------------------
# the particle core's resampling functions: plain and stop-gradient, the same forward pass


@pytest.mark.parametrize("scheme", rs.SCHEMES)
def test_stop_gradient_resampling_values_equal_plain_and_gradient_counts_offspring(scheme):
    """Same values as smc.resample (particles, weights, decision); the gradient of the sum of
    the resampled log weights with respect to the log weights is each particle's number of
    offspring (d/d lw_j of sum_i lw_a(i) - stop_gradient(lw_a(i)) = #{i: a(i) = j})."""
    from vehjax.filters import smc

    with np.errstate(divide="ignore"):
        log_w = jnp.asarray(np.log(W))  # one zero weight: its -inf contributes 0
    w = jnp.exp(log_w)
    parts = (jnp.asarray(np.arange(3.0 * N).reshape(3, N)), jnp.arange(N))
    u = smc.uniforms(smc.raw_key(jax.random.key(1)), scheme, N, jnp.float64)
    plain = smc.resample(parts, w, log_w, u, scheme, 1.0)
    sg = smc.resample_stop_gradient(parts, w, log_w, u, scheme, 1.0)
    for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(sg)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert bool(plain[3])  # it did resample
    anc = np.asarray(plain[0][1])
    offspring = np.bincount(anc, minlength=N)

    def total(lw):
        return jnp.sum(smc.resample_stop_gradient(parts, jnp.exp(lw), lw, u, scheme, 1.0)[1])

    grad = np.asarray(jax.grad(total)(log_w))
    np.testing.assert_array_equal(grad, offspring)
    # the plain resampler's weights are constants: no gradient at all
    plain_grad = jax.grad(lambda lw: jnp.sum(smc.resample(parts, jnp.exp(lw), lw, u, scheme,
                                                          1.0)[1]))(log_w)
    np.testing.assert_array_equal(np.asarray(plain_grad), 0.0)


def test_resampling_below_the_threshold_leaves_everything_and_threshold_zero_never():
    from vehjax.filters import smc

    log_w = jnp.full(N, -np.log(N))  # ESS = N
    x = jnp.asarray(np.arange(N, dtype=float))
    u = smc.uniforms(smc.raw_key(jax.random.key(1)), "systematic", N, jnp.float64)
    for fn in (smc.resample, smc.resample_stop_gradient):
        for thr in (0.0, 0.99):
            xs, lw, w, did = fn(x, jnp.exp(log_w), log_w, u, "systematic", thr)
            assert not bool(did)
            np.testing.assert_array_equal(np.asarray(xs), np.asarray(x))
            np.testing.assert_array_equal(np.asarray(lw), np.asarray(log_w))


def test_check_resample():
    from vehjax.filters import smc

    assert smc.check_resample(None) is smc.resample
    assert smc.check_resample(smc.resample_stop_gradient) is smc.resample_stop_gradient
    with pytest.raises(ValueError, match="^resample: expected None or a resampling function"):
        smc.check_resample(0.5)
