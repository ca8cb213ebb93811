"""Physical domains of the built-in models' parameters (issue 46, class 1) and simulate's
divergence flag.

Properties over every built-in model's domain: inside, the model builds and a short simulation
stays finite (and, for values near the nominal car, within the state envelope); outside, the
value is refused naming the parameter at construction, in ``with_theta``, in ``simulate``'s
``theta`` and in ``filter``/``run``'s ``theta0`` of a state-only filter. The expected domains
are written here from the models' docstrings, independently of the declarations.
"""

import math

import jax
import numpy as np
import pytest

from hypothesis import HealthCheck, given, settings, strategies as st

import vehjax as vj
from vehjax.models import (Dynamic3DOF, KinematicBicycle, Model, SevenDOF, SingleTrack,
                           SingleTrackBank, VirtualScaleBank)
from vehjax.models.domains import Interval, ParamDomains, interval

INF = math.inf
POS = ("(", 0.0, INF, ")")

#: name -> model builder; every built-in model (and each tyre law of SingleTrack)
BUILDERS = {
    "KinematicBicycle": lambda **kw: KinematicBicycle(**kw),
    "Dynamic3DOF": lambda **kw: Dynamic3DOF(**kw),
    "SingleTrack-linear": lambda **kw: SingleTrack(tyres="linear", **kw),
    "SingleTrack-pacejka": lambda **kw: SingleTrack(tyres="pacejka", **kw),
    "SingleTrack-brush": lambda **kw: SingleTrack(tyres="brush", **kw),
    "SingleTrackBank": lambda **kw: SingleTrackBank(**kw),
    "VirtualScaleBank": lambda **kw: VirtualScaleBank(**kw),
    "SevenDOF": lambda **kw: SevenDOF(integrator="ros2", **kw),
}

#: the domains the docstrings state, parameter -> (open/closed low, low, high, open/closed high)
EXPECTED = {
    "m": POS, "iz": POS, "lf": POS, "lr": POS, "cf": POS, "cr": POS, "cx": POS, "cy": POS,
    "ca": ("[", 0.0, INF, ")"), "mu": ("(", 0.0, 3.0, ")"), "shape_f": ("(", 0.0, 2.0, ")"),
    "shape_r": ("(", 0.0, 2.0, ")"), "a": POS, "b": POS, "tf": POS, "tr": POS, "h": POS,
    "re": POS, "iw": POS,
}


def _scenario(model):
    return vj.scenarios.sine_steer(model, speed=20.0, amplitude=0.03, duration=0.3)


@pytest.fixture(scope="module", params=list(BUILDERS))
def built(request):
    model = BUILDERS[request.param]()
    return request.param, model, _scenario(model)


def test_every_parameter_declared_as_documented(built):
    name, model, _ = built
    dom = model.param_domains()
    assert isinstance(dom, ParamDomains) and dom.names == tuple(model.param_names)
    for n, iv in zip(dom.names, dom.intervals):
        lo_c, lo, hi, hi_c = EXPECTED[n]
        assert (iv.low, iv.high, iv.low_closed, iv.high_closed) == (lo, hi, lo_c == "[", hi_c == "]"), n
        assert iv.note  # every domain says why
    low, high = dom.bounds()
    np.testing.assert_array_equal(low, [EXPECTED[n][1] for n in dom.names])
    np.testing.assert_array_equal(high, [EXPECTED[n][2] for n in dom.names])
    assert np.all(dom.inside(np.asarray(model.theta)))  # the nominal car is inside
    env = model.state_envelope()
    assert env.shape == (len(model.state_names),) and np.all(env > 0)


def _inside_value(iv, nominal, u, wide):
    """A value inside ``iv``: near ``nominal`` (factor 2^(2u - 1)) or, ``wide``, anywhere over
    six decades around it; clipped into a bounded interval."""
    if math.isfinite(iv.high) and math.isfinite(iv.low):  # bounded: uniform strictly inside
        span = iv.high - iv.low
        return iv.low + span * (0.02 + 0.96 * u) if wide else nominal
    return nominal * (10.0 ** (6.0 * u - 3.0) if wide else 2.0 ** (2.0 * u - 1.0))


def _outside_value(iv, u):
    """A value outside ``iv`` (the ends that are open included)."""
    if math.isfinite(iv.high) and u > 0.5:
        return iv.high * (1.0 + 2.0 * (u - 0.5)) + (0.0 if not iv.high_closed else 1e-9)
    if iv.low_closed:
        return iv.low - 1e-9 - 1e3 * u
    return iv.low - 1e3 * u  # u = 0: the open end itself


_SETTINGS = settings(max_examples=12, deadline=None, derandomize=True,
                     suppress_health_check=[HealthCheck.function_scoped_fixture])


@_SETTINGS
@given(st.lists(st.floats(0.0, 1.0), min_size=9, max_size=9), st.booleans())
def test_inside_the_domain_builds_and_simulates_finite(built, us, wide):
    """Anywhere inside: builds, and simulate's states are finite (a run that leaves the
    envelope is flagged and frozen, not NaN). Near the nominal car: no run is flagged."""
    _, model, scn = built
    dom = model.param_domains()
    theta = np.array([_inside_value(iv, float(t), u, wide)
                      for iv, t, u in zip(dom.intervals, np.asarray(model.theta), us)])
    assert np.all(dom.inside(theta))
    rebuilt = type(model)(theta=theta, **({"tyres": model.tyres} if hasattr(model, "tyres") else {}))
    np.testing.assert_array_equal(np.asarray(rebuilt.theta), theta)
    sim = vj.simulate(model, scn, runs=1, params=vj.ParamDraw(theta=theta))
    assert np.all(np.isfinite(np.asarray(sim.states)))
    assert np.all(np.isfinite(np.asarray(sim.measurements)))
    if not wide:
        assert not bool(sim.diverged[0]) and int(sim.diverged_at[0]) == -1


def _ekf(model):
    nx, ny = len(model.state_names), len(model.output_names)
    return vj.filters.ekf(model, Q=np.eye(nx) * 1e-4, R=np.eye(ny) * 1e-2)


@_SETTINGS
@given(st.integers(0, 8), st.floats(0.0, 1.0))
def test_outside_the_domain_refused_naming_the_parameter(built, j, u):
    """Outside: refused at construction, by with_theta, in simulate's theta and in filter's
    and run's theta0 of a state-only filter, each naming the argument, the parameter, the
    value and the domain."""
    _, model, scn = built
    dom = model.param_domains()
    j = j % len(dom.names)
    name, iv = dom.names[j], dom.intervals[j]
    theta = np.array(model.theta, dtype=float)
    theta[j] = _outside_value(iv, u)
    assert not dom.inside(theta)[j]
    pattern = rf"parameter '{name}' = .* is outside its domain \{iv.text()[0]}"
    kw = {"tyres": model.tyres} if hasattr(model, "tyres") else {}
    with pytest.raises(ValueError, match=r"^theta: " + pattern):
        type(model)(theta=theta, **kw)
    with pytest.raises(ValueError, match=r"^with_theta: " + pattern):
        model.with_theta(**{name: float(theta[j])})
    with pytest.raises(ValueError, match=r"^params.theta: " + pattern):
        vj.simulate(model, scn, params=vj.ParamDraw(theta=theta))
    with pytest.raises(ValueError,
                       match=r"^params.theta: " + pattern.replace(" = .*", r" = .* \(run 1\)")):
        vj.simulate(model, scn, runs=2,
                    params=vj.ParamDraw(theta=np.stack([np.asarray(model.theta), theta])))
    est = _ekf(model)
    nx, ny = len(model.state_names), len(model.output_names)
    ys = np.zeros((3, ny))
    us = np.asarray(scn.inputs)[:3]
    with pytest.raises(ValueError, match=r"^theta0: " + pattern):
        vj.filter(est, ys, us, x0=np.zeros(nx), P0=np.eye(nx), theta0=theta)
    with pytest.raises(ValueError, match=r"^theta0: " + pattern):
        vj.run(est, ys[None], us, x0=np.zeros(nx), P0=np.eye(nx), theta0=theta)


def test_per_run_theta_names_the_run():
    model = SingleTrack()
    theta = np.tile(np.asarray(model.theta), (3, 1))
    theta[2, 0] = -1.0
    with pytest.raises(ValueError, match=r"^params.theta: parameter 'm' = -1 \(run 2\) is "
                                         r"outside its domain \(0, inf\) in SingleTrack"):
        vj.simulate(model, _scenario(model), runs=3, params=vj.ParamDraw(theta=theta))


@pytest.mark.parametrize("name", ["cf", "cr"])
def test_sae_sign_message_says_how_to_convert(name):
    model = SingleTrack()
    theta = np.array(model.theta, dtype=float)
    j = model.param_names.index(name)
    theta[j] = -theta[j]
    with pytest.raises(ValueError) as err:
        SingleTrack(theta=theta)
    msg = str(err.value)
    assert f"parameter '{name}' = {theta[j]:g}" in msg and "SAE" in msg
    assert f"{name} = {-theta[j]:g}" in msg  # the converted value to pass
    with pytest.raises(ValueError, match=f"SAE.*{name} = {-theta[j]:g}"):
        SingleTrackBank(theta=theta)
    with pytest.raises(ValueError, match="SAE.*cy = 40000"):
        Dynamic3DOF().with_theta(cy=-4e4)


def test_closed_and_open_ends():
    """ca = 0 (no drag) is inside its closed end; mu = 3 and C = 2 are outside their open
    ones."""
    assert float(Dynamic3DOF().with_theta(ca=0.0).theta[6]) == 0.0
    with pytest.raises(ValueError, match=r"'mu' = 3 is outside its domain \(0, 3\)"):
        SingleTrack(tyres="brush").with_theta(mu=3.0)
    with pytest.raises(ValueError, match=r"'shape_r' = 2 is outside its domain \(0, 2\)"):
        SingleTrack(tyres="pacejka").with_theta(shape_r=2.0)
    with pytest.raises(ValueError, match=r"'mu' = nan"):
        SingleTrack(tyres="brush").with_theta(mu=float("nan"))


def test_interval_text_round_trip():
    for text in ("(0, inf)", "[0, inf)", "(0, 3]", "[-1, 2]", "(-inf, inf)"):
        assert interval(text).text() == text
    for bad in ("0, 1", "[0, inf]", "(2, 1)", "(0; 1)"):
        with pytest.raises(ValueError):
            interval(bad)


def _user_model(**kw):
    return Model(lambda x, u, th: th[0] * x, lambda x, u, th: x, dt=0.1, state_names=("x",),
                 param_names=("a",), **kw)


def test_user_model_without_domains_unchanged_with_domains_checked():
    model = _user_model(theta=[-5.0])  # no domains: any finite value
    assert model.param_domains() is None and model.state_envelope() is None
    est = _ekf(model)
    res = vj.filter(est, np.zeros((3, 1)), None, x0=np.zeros(1), P0=np.eye(1), theta0=[-7.0])
    assert not bool(res.diverged)
    sim = vj.simulate(model, vj.scenarios.from_inputs(model, np.zeros((3, 0)), np.ones(1)),
                      params=vj.ParamDraw(theta=[-7.0]))
    assert sim.states.shape == (1, 3, 1)
    with pytest.raises(ValueError, match=r"^theta: parameter 'a' = -5 is outside its domain "
                                         r"\(0, 1\] in Model"):
        _user_model(theta=[-5.0], domains={"a": "(0, 1]"})
    ok = _user_model(theta=[1.0], domains={"a": "(0, 1]"})
    assert ok.param_domains().intervals == (Interval(0.0, 1.0, False, True),)
    with pytest.raises(ValueError, match=r"^theta0: parameter 'a' = 2"):
        vj.filter(_ekf(ok), np.zeros((3, 1)), None, x0=np.zeros(1), P0=np.eye(1), theta0=[2.0])
    with pytest.raises(ValueError, match=r"^domains: unknown name"):
        _user_model(theta=[1.0], domains={"b": "(0, 1)"})
    with pytest.raises(ValueError, match=r"^domains\['a'\]"):
        _user_model(theta=[1.0], domains={"a": "0 to 1"})


# -- simulate's divergence flag ---------------------------------------------------------------

def test_simulate_flags_an_exploding_user_model_at_the_first_non_finite_state():
    """x_t = a^(t+1) x0 overflows float64; the flag is at the first infinite power (numpy),
    and the states hold the last finite one from there on."""
    model = _user_model(theta=[1e3])
    T = 200
    scn = vj.scenarios.from_inputs(model, np.zeros((T, 0)), np.ones(1))
    with np.errstate(over="ignore"):
        ref = np.cumprod(np.full(T, 1e3))
    first = int(np.argmax(~np.isfinite(ref)))
    sim = vj.simulate(model, scn, runs=2, params=vj.ParamDraw(theta=np.array([[1e3], [0.5]])))
    np.testing.assert_array_equal(np.asarray(sim.diverged), [True, False])
    np.testing.assert_array_equal(np.asarray(sim.diverged_at), [first, -1])
    states = np.asarray(sim.states)
    np.testing.assert_allclose(states[0, :first, 0], ref[:first], rtol=1e-12)
    np.testing.assert_array_equal(states[0, first:, 0], ref[first - 1])  # frozen
    np.testing.assert_array_equal(np.asarray(sim.measurements)[0, first:], ref[first - 1])
    np.testing.assert_allclose(states[1, :, 0], 0.5 ** np.arange(1, T + 1), rtol=1e-12)
    assert np.all(np.isfinite(states))
    d = sim.to_dict()
    assert d["diverged"].tolist() == [True, False] and d["diverged_at"].tolist() == [first, -1]


def _euler_single_track(theta, dt, vx, delta, T):
    """The linear single-track model (module docstring of single_track) by explicit Euler, in
    numpy: (T, 2) states from rest."""
    m, iz, lf, lr, cf, cr = theta
    x = np.zeros(2)
    out = np.empty((T, 2))
    with np.errstate(over="ignore", invalid="ignore"):
        for t in range(T):
            vy, r = x
            ff = cf * (delta - (vy + lf * r) / vx)
            fr = cr * (lr * r - vy) / vx
            x = x + dt * np.array([(ff + fr) / m - vx * r, (lf * ff - lr * fr) / iz])
            out[t] = x
    return out


def test_simulate_flags_a_built_in_model_leaving_its_envelope():
    """Explicit Euler at 0.5 m/s with 50 ms steps is unstable for the nominal car (|lambda h|
    about 17); the run is flagged where |vy| first exceeds 300 m/s or |r| 20 rad/s (numpy's
    rollout of the same equations), long before it overflows; a normal drive is not."""
    model = SingleTrack(dt=0.05, integrator="euler", substeps=1)
    T, vx, delta = 40, 0.5, 0.01
    inputs = np.tile([delta, vx], (T, 1))
    scn = vj.scenarios.from_inputs(model, inputs, np.zeros(2))
    ref = _euler_single_track(np.asarray(model.theta), 0.05, vx, delta, T)
    out = (np.abs(ref[:, 0]) > 300.0) | (np.abs(ref[:, 1]) > 20.0)
    first = int(np.argmax(out))
    assert out.any() and np.all(np.isfinite(ref[:first + 1]))
    sim = vj.simulate(model, scn)
    assert bool(sim.diverged[0]) and int(sim.diverged_at[0]) == first
    states = np.asarray(sim.states[0])
    np.testing.assert_allclose(states[:first], ref[:first], rtol=1e-9)
    np.testing.assert_array_equal(states[first:], np.broadcast_to(states[first - 1], states[first:].shape))

    normal = SingleTrack()
    sim = vj.simulate(normal, _scenario(normal), runs=3, process_std=1e-3, meas_std=0.1)
    assert not np.any(np.asarray(sim.diverged))
    np.testing.assert_array_equal(np.asarray(sim.diverged_at), [-1, -1, -1])
