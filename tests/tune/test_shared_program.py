"""A fit with score tests on one program (vehjax.tune.diagnostics.compile_shared): the score
tests' objective, over the fit's coordinates and the held parameters', evaluated along the fit's
directions serves the fit with the arithmetic of the fit's own program, and a block of
directions at a time gives the tests' full gradient and BHHH matrix.

References: the fit's own program (vehjax.tune.program.compile_program) and the score tests'
own (compile_augmented, every direction at once), each compiled on its own; a transform's
values and derivatives taken by jax directly.
"""

import math
import warnings

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest

import vehjax
from vehjax.filters import bounds as bounds_maps
from vehjax.models import Model
from vehjax.tune import diagnostics, program
from vehjax.tune.likelihood import anchored_physical, prepare

T = 300


def _model(b=0.55, c=2.0):
    # c enters through b * c: held, it is tested like b
    return Model(transition=lambda x, u, th: th[0] * x + th[1] * th[2] * u / 2.0,
                 observe=lambda x, u, th: x, dt=0.1, state_names=("x",),
                 param_names=("a", "b", "c"), input_names=("u",), output_names=("y",),
                 theta=[0.85, b, c])


def _data(seed=0):
    rng = np.random.default_rng(seed)
    u = np.sin(np.arange(T) / 7.0) + 0.5 * rng.standard_normal(T)
    x, ys = 0.0, []
    for k in range(T):
        x = 0.9 * x + 0.5 * u[k] + 0.1 * rng.standard_normal()
        ys.append(x + 0.2 * rng.standard_normal())
    return np.array(ys)[:, None], u[:, None]


def _setup(seed=0):
    ys, us = _data(seed)
    model = _model()
    args = (vehjax.filters.ekf, model, np.array([0.02]), np.array([0.02]), ys, us)
    kw = dict(x0=np.zeros(1), P0=np.ones(1))
    what = vehjax.tune.Fitted(("a",), noise=("Q", "R"))
    obj, setup = prepare(*args, **kw, params=what)
    start = diagnostics.Start(model, args[2], args[3], None, kw["x0"])
    return args, kw, what, obj, setup, start


def test_anchored_physical_is_exact_at_the_anchor_with_the_maps_derivatives():
    tmap = bounds_maps.Transform(np.array([0.0, -np.inf, 0.1]), np.array([np.inf, np.inf, 5.0]))
    held = jnp.array([2760.0, 1.05])
    pos = np.array([0, 2])
    z_anchor = tmap.to_unconstrained(jnp.array([2760.0, 0.3, 1.05]))
    out = anchored_physical(tmap, z_anchor, z_anchor[pos], pos, held)
    assert float(out[0]) == 2760.0 and float(out[2]) == 1.05
    assert float(out[1]) == float(tmap.to_physical(z_anchor)[1])
    f = lambda z: anchored_physical(tmap, z, z_anchor[pos], pos, held)  # noqa: E731
    np.testing.assert_allclose(jax.jacfwd(f)(z_anchor), jax.jacfwd(tmap.to_physical)(z_anchor),
                               rtol=1e-14)
    zs = z_anchor + jnp.array([1e-3, 0.0, -2e-3])
    np.testing.assert_allclose(f(zs), tmap.to_physical(zs), rtol=1e-12)


def test_the_fit_on_the_shared_program_is_its_own_program_bit_for_bit():
    _, _, _, obj, setup, start = _setup()
    shared = diagnostics.compile_shared(start, setup, obj.data)
    assert shared.layout.extra == ("b", "c") and shared.layout.size == 5
    own = program.compiled_loss(obj, setup)
    on_shared = program.compiled_loss(obj, setup, compiled=shared)
    x0 = own.x0
    for step in (np.zeros(3), np.array([0.3, -0.2, 0.1]), np.array([-0.5, 0.4, -0.3])):
        a, b = own.vgo(x0 + step), on_shared.vgo(x0 + step)
        assert a[0] == b[0]
        np.testing.assert_array_equal(a[2], b[2])
        np.testing.assert_array_equal(a[3], b[3])
        np.testing.assert_array_equal(np.asarray(a[1][0]), np.asarray(b[1][0]))


def test_the_score_tests_full_gradient_and_bhhh_match_their_own_program():
    _, _, _, obj, setup, start = _setup(seed=1)
    shared = diagnostics.compile_shared(start, setup, obj.data)
    aobj, aug = diagnostics._augmented(start, setup, obj.data, None, ("b", "c"))
    ref = program.compiled_loss(aobj, aug)  # every direction at once, the held read through g
    full = program.compiled_loss(aobj, aug, compiled=shared)  # 3 directions at a time
    rng = np.random.default_rng(3)
    for _ in range(3):
        f = ref.x0 + 0.2 * rng.standard_normal(ref.x0.shape)
        a, b = ref.vgo(f), full.vgo(f)
        assert b[0] == pytest.approx(a[0], rel=1e-13)
        np.testing.assert_allclose(b[2], a[2], rtol=1e-10, atol=1e-13)
        np.testing.assert_allclose(b[3], a[3], rtol=1e-10, atol=1e-13 * np.max(np.abs(a[3])))
    assert np.all(np.linalg.eigvalsh(b[3]) > 0)


def _fit(args, kw, what):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return vehjax.tune.fit_from_theta(*args, **kw, params=what,
                                          options=vehjax.tune.Options(progress=False))


def test_a_fit_with_score_tests_compiles_no_second_program_and_tests_as_before(monkeypatch):
    args, kw, what, *_ = _setup(seed=2)
    plain = program.compile_program
    with monkeypatch.context() as m:  # the reference: the fit's program and the tests' own
        m.setattr(diagnostics, "shared_extra", lambda *a, **k: ())
        ref = _fit(args, kw, what)
    compiles = []
    monkeypatch.setattr(program, "compile_program",
                        lambda *a, **k: compiles.append(1) or plain(*a, **k))
    res = _fit(args, kw, what)
    assert compiles == []  # one program, compile_directed's
    assert res.loglik == ref.loglik and res.values == ref.values
    assert res.std_errors == ref.std_errors
    assert set(res.score_tests) == {"b", "c"}
    for k, t in res.score_tests.items():
        r = ref.score_tests[k]
        assert t.value == r.value
        assert t.statistic == pytest.approx(r.statistic, rel=1e-6)
        assert t.one_step == pytest.approx(r.one_step, rel=1e-6)
        assert t.score == pytest.approx(r.score, rel=1e-6)
    assert math.isfinite(res.score_tests["b"].statistic)


def test_a_program_for_other_held_values_is_not_taken(monkeypatch):
    args, kw, what, obj, setup, start = _setup()
    other = diagnostics.Start(_model(b=0.6), *start[1:])
    shared = diagnostics.compile_shared(other, setup, obj.data)
    names = diagnostics.coordinates(setup, start.model, obj.z0)[0]
    assert program.serves(shared.layout, names, other.model)
    assert not program.serves(shared.layout, names, start.model)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = vehjax.tune.driver.fit_start(*args, dict(kw, params=what),
                                           vehjax.tune.Options(progress=False), compiled=shared)
    ref = _fit(args, kw, what)
    assert res.loglik == ref.loglik and res.values == ref.values
