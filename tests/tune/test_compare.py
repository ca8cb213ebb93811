"""vehjax.tune.compare: information criteria by hand, the warning where two structures fit alike
but disagree about the unmeasured state (and not where they agree), bad input."""

import math
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import vehjax
import vehjax.tune

T, MISSING = 300, 10
P0 = np.array([1.0])


def gain_model(c: float):
    """A random walk h observed as y = c h: models of different c explain y alike (Q scales
    with 1 / c^2) but estimate different h."""
    return vehjax.models.Model(transition=lambda x, u, th: x, observe=lambda x, u, th: th[0] * x,
                               dt=0.1, state_names=("h",), param_names=("c",),
                               input_names=("u",), output_names=("y",), theta=[c])


@pytest.fixture(scope="module")
def data():
    rng = np.random.default_rng(5)
    h = np.cumsum(0.1 * rng.standard_normal(T))
    ys = (h + 0.05 * rng.standard_normal(T))[:, None]
    ys[rng.choice(T, MISSING, replace=False), 0] = np.nan
    return ys, np.zeros((T, 1))


def fit(c, ys, us, q0=1e-2):
    return vehjax.tune.fit_noise(vehjax.filters.ekf, gain_model(c), np.array([q0]),
                                 np.array([1e-2]), ys, us, x0=np.zeros(1), P0=P0,
                                 options=vehjax.tune.Options(progress=False))


@pytest.fixture(scope="module")
def fits(data):
    ys, us = data
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return {"c=2": fit(2.0, ys, us), "c=1": fit(1.0, ys, us), "c=1 again": fit(1.0, ys, us,
                                                                                  q0=4e-2)}


def scalar_kf_loglik(ys, c, q, r):
    """log-likelihood of the random walk observed as c h, by hand (NaN skipped)."""
    x, p, ll = 0.0, P0[0], 0.0
    for y in ys[:, 0]:
        p = p + q
        if np.isnan(y):
            continue
        s = c * c * p + r
        e = y - c * x
        ll += -0.5 * (math.log(2 * math.pi * s) + e * e / s)
        k = p * c / s
        x, p = x + k * e, (1 - k * c) * p
    return ll


def compare_under(action: str, fits, ys, us, **kw):
    """vehjax.tune.compare with warnings ``action``-ed ("ignore" or "error")."""
    with warnings.catch_warnings():
        warnings.simplefilter(action)
        return vehjax.tune.compare(fits, ys, us, P0=P0, state="h", **kw)


def test_criteria_by_hand(data, fits):
    ys, us = data
    two = {k: fits[k] for k in ("c=2", "c=1")}
    cmp = compare_under("ignore", two, ys, us)
    assert cmp.n == T - MISSING
    for name, c in (("c=2", 2.0), ("c=1", 1.0)):
        res = two[name]
        ll = scalar_kf_loglik(ys, c, res.Q[0, 0], res.R[0, 0])
        assert res.loglik == pytest.approx(ll, rel=1e-9)
        assert cmp.k[name] == 2
        assert cmp.aic[name] == pytest.approx(2 * 2 - 2 * ll, rel=1e-9)
        assert cmp.bic[name] == pytest.approx(2 * math.log(T - MISSING) - 2 * ll, rel=1e-9)
    # the two structures are observationally alike: Q scales by 1 / c^2
    assert two["c=2"].Q[0, 0] * 4 == pytest.approx(two["c=1"].Q[0, 0], rel=1e-3)
    assert "AIC" in cmp.summary() and "c=2" in cmp.summary()


def test_warns_where_structures_fit_alike_but_disagree(data, fits):
    ys, us = data
    two = {k: fits[k] for k in ("c=2", "c=1")}
    with pytest.warns(UserWarning, match="cannot choose between 'c=2' and 'c=1'"):
        cmp = vehjax.tune.compare(two, ys, us, P0=P0, state="h",
                                  held_out=(ys[::-1].copy(), us))
    assert cmp.undecided == (("c=2", "c=1"),)
    assert abs(cmp.aic["c=2"] - cmp.aic["c=1"]) < 10.0
    assert cmp.rms_difference[("c=2", "c=1")] > 3 * max(cmp.mean_std.values())
    assert cmp.on == "held_out" and set(cmp.held_out_loglik) == {"c=2", "c=1"}
    assert "warning:" in cmp.summary()


def test_quiet_where_structures_agree(data, fits):
    ys, us = data
    same = {k: fits[k] for k in ("c=1", "c=1 again")}
    cmp = compare_under("error", same, ys, us)
    assert cmp.undecided == () and cmp.warnings == ()
    assert cmp.rms_difference[("c=1", "c=1 again")] < 0.1 * cmp.mean_std["c=1"]


def test_function_of_the_state(data, fits):
    ys, us = data
    two = {k: fits[k] for k in ("c=1", "c=1 again")}
    by_name = vehjax.tune.compare(two, ys, us, P0=P0, state="h")
    doubled = vehjax.tune.compare(two, ys, us, P0=P0, state=lambda x, u: 2.0 * jnp.sin(x[0]))
    np.testing.assert_allclose(doubled.estimates["c=1"], 2 * np.sin(by_name.estimates["c=1"]))
    np.testing.assert_allclose(doubled.std["c=1"],
                               2 * np.abs(np.cos(by_name.estimates["c=1"])) * by_name.std["c=1"],
                               rtol=1e-9)


def test_bad_input_names_the_argument(data, fits):
    ys, us = data
    two = {k: fits[k] for k in ("c=1", "c=1 again")}
    with pytest.raises(ValueError, match="fits"):
        vehjax.tune.compare([fits["c=1"]], ys, us, P0=P0)
    with pytest.raises(ValueError, match="fits"):
        vehjax.tune.compare({"a": fits["c=1"]}, ys, us, P0=P0)
    with pytest.raises(ValueError, match="fits"):
        vehjax.tune.compare({"a": fits["c=1"], "b": 3}, ys, us, P0=P0)
    with pytest.raises(ValueError, match="state"):
        vehjax.tune.compare(two, ys, us, P0=P0, state="vy")
    with pytest.raises(ValueError, match="held_out"):
        vehjax.tune.compare(two, ys, us, P0=P0, state="h", held_out=(np.zeros((5, 2)), us))
    with pytest.raises(ValueError, match="measurements"):
        vehjax.tune.compare(two, ys[:, 0], us, P0=P0, state="h")
    with pytest.raises(ValueError, match="measurements"):
        vehjax.tune.compare(two, ys + 1.0, us, P0=P0, state="h")   # not the fits' data
    with pytest.raises(ValueError, match="margin"):
        vehjax.tune.compare(two, ys, us, P0=P0, state="h", margin=0.0)
