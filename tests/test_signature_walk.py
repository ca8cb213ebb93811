"""Every public callable's options fed wrong values, found by walking the signatures.

For each callable of the ``__all__`` of ``vehjax``, ``vehjax.tune``, ``vehjax.filters`` and
``vehjax.data``, each argument whose default is a bool, int, float or str gets values of the
wrong kind: a list, a truthy string for a flag, NaN and inf for a number, a string for a
number, an unknown string for a choice; and every callable an unknown keyword. Each must raise
ValueError or TypeError naming the argument, before JAX traces or compiles anything (counted by
:mod:`jax.monitoring`'s compile events). A callable with no such argument is not walked; one
that has them is either built here (:data:`CALLS`) or exempt with its reason
(:data:`EXEMPT`), so that a new public function is walked when it is written.
"""

import importlib
import inspect
import math

import jax
import jax.monitoring
import numpy as np
import optax
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import vehjax as vj
from vehjax.models import SingleTrack, SingleTrackBank
from vehjax.tune import parameterisation, program, staged

MODULES = ("vehjax", "vehjax.tune", "vehjax.filters", "vehjax.data", "vehjax.smoothers",
           "vehjax.calibrate")

#: the compile events of JAX (tracing a function, lowering it, compiling it)
_EVENTS = ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/backend_compile_duration")
_compiles = []
jax.monitoring.register_event_duration_secs_listener(
    lambda name, *a, **k: _compiles.append(name) if name in _EVENTS else None)


class _Accepted(Exception):
    """Raised where a fit would start: the bad value got past every check."""


# -- one tiny problem shared by every call --------------------------------------------------
M = SingleTrack(dt=0.01)
T = 6
YS = np.zeros((T, 2))
US = np.tile([0.0, 20.0], (T, 1))
Q, R = np.array([1e-4, 1e-4]), np.array([0.04, 1e-4])
X0, P0 = np.zeros(2), np.array([0.1, 0.01])
KEY = jax.random.key(0)


def _fit(fn):
    return lambda: (fn, (vj.filters.ekf, M, Q, R, YS, US),
                    dict(x0=X0, P0=P0, params=("cf",)))


def _stop_every_fit(monkeypatch):
    """Where a fit would start (its first stage, its program, its objective) it raises
    :class:`_Accepted` instead: a value that got past every check costs nothing."""
    def accepted(*a, **k):
        raise _Accepted

    for mod, name in ((staged, "_nested_stage"), (staged, "fit_start"),
                      (staged, "compile_objective"), (program, "compiled_loss")):
        monkeypatch.setattr(mod, name, accepted)


#: "module.name" -> () -> (the callable, its positional arguments, its keyword arguments):
#: valid values for everything but the argument under test (built before the count starts)
CALLS = {
    # the stamps are checked before the file is opened: no bag is needed
    "vehjax.data.read_ros2": lambda: (vj.data.read_ros2, ("no_such_bag",),
                                      dict(fields={"r": "/imu.angular_velocity.z"})),
    "vehjax.simulate": lambda: (vj.simulate, (M, vj.scenarios.from_inputs(M, US, X0)),
                                dict(key=KEY)),
    "vehjax.filter": lambda: (vj.filter, (vj.filters.ekf(M, Q, R), YS, US), dict(x0=X0, P0=P0)),
    # vehjax.smooth's options are the fields of its method's record (vehjax.smoothers)
    **{f"vehjax.smoothers.{name}": (lambda name=name: (getattr(vj.smoothers, name), (), {}))
       for name in ("RTS", "IEKS", "IPLS", "FFBSi", "RejectionSampling", "AncestorPaths")},
    "vehjax.run": lambda: (vj.run, (vj.filters.ekf(M, Q, R), YS[None], US), dict(x0=X0, P0=P0)),
    "vehjax.compile_run": lambda: (vj.compile_run, (vj.filters.ekf(M, Q, R), YS[None], US),
                                   dict(x0=X0, P0=P0)),
    "vehjax.tune.fit": _fit(vj.tune.fit),
    "vehjax.tune.fit_from_theta": _fit(vj.tune.fit_from_theta),
    "vehjax.tune.objective": lambda: (vj.tune.objective, (vj.filters.ekf, M, Q, R, YS, US),
                                      dict(x0=X0, P0=P0)),
    "vehjax.tune.stop_gradient_pf": lambda: (vj.tune.stop_gradient_pf, (M, Q, R), {}),
    # the fit's option records check their own fields when made
    **{f"vehjax.tune.{r}": (lambda r=r: (getattr(vj.tune, r), (), {}))
       for r in ("Fitted", "Options", "Start", "Adam", "LBFGS", "Scoring")},
    "vehjax.tune.FirstOrder": lambda: (vj.tune.FirstOrder, (optax.sgd(0.1),), {}),
    "vehjax.tune.uncertainty": lambda: (vj.tune.uncertainty,
                                        (np.eye(2), np.eye(2), np.ones(2), ("a", "b")), {}),
    "vehjax.tune.scoring_direction": lambda: (vj.tune.scoring_direction,
                                              (np.ones(2), np.eye(2), np.ones(2)), {}),
    **{f"vehjax.filters.{b}": (lambda b=b: (getattr(vj.filters, b), (M, Q, R), {}))
       for b in ("ukf", "ckf", "ackf", "bootstrap_pf")},
    **{f"vehjax.filters.{b}": (lambda b=b: (getattr(vj.filters, b),
                                            (M, Q, R),
                                            dict(Q_theta=np.array([1e-2]), estimate=("cf",))))
       for b in ("dual_ekf", "dual_ukf", "joint_ekf", "joint_ukf")},
    "vehjax.filters.liu_west_ukf": lambda: (vj.filters.liu_west_ukf, (M, Q, R),
                                            dict(estimate=("cf",), theta_low=[5e4],
                                                 theta_high=[2e5])),
    **{f"vehjax.filters.{b}": (lambda b=b: (getattr(vj.filters, b), (M, Q, R), dict(
        augment=vj.filters.Augmentation(biases=("ay",), input_offsets=("delta",)))))
       for b in ("vbakf_r", "vbakf_pr")},
    # the option records check their own fields when made
    **{f"vehjax.filters.{r}": (lambda r=r: (getattr(vj.filters, r), (), {}))
       for r in ("SigmaPoints", "Resampling", "LiuWestKernel")},
    "vehjax.filters.Augmentation": lambda: (vj.filters.Augmentation, (),
                                            dict(biases=("ay",), input_offsets=("delta",))),
    "vehjax.filters.marginalized_pf": lambda: (
        vj.filters.marginalized_pf, (SingleTrackBank(dt=0.01),),
        dict(Q=0.05 ** 2, known_std={"phi": 0.01, "r_virt": 0.005},
             niw=vj.filters.NiW(std0={"delta": 0.01, "ay": 0.4, "r": 0.02, "roll_rate": 0.02}))),
    "vehjax.filters.marginalized_pf_grid": lambda: (
        vj.filters.marginalized_pf_grid, (SingleTrackBank(dt=0.01),), dict(Q=0.1 ** 2)),
    # particle MCMC: the samplers' options are the fields of their records
    **{f"vehjax.calibrate.{r}": (lambda r=r: (getattr(vj.calibrate, r), (), {}))
       for r in ("Chains", "Adaptation", "Sweep")},
    "vehjax.calibrate.log_likelihood_spread": lambda: (
        vj.calibrate.log_likelihood_spread, (vj.filters.ekf, M, YS, US),
        dict(x0=X0, P0=P0, Q=Q, R=R, values={"cf": 8e4}, key=KEY)),
    "vehjax.calibrate.log_likelihood_difference_spread": lambda: (
        vj.calibrate.log_likelihood_difference_spread,
        (vj.calibrate.Correlated(vj.filters.bootstrap_pf, 0.9), M, YS, US),
        dict(x0=X0, P0=P0, Q=Q, R=R, values={"cf": 8e4}, key=KEY)),
    "vehjax.calibrate.fixed_noise_mpf": lambda: (vj.calibrate.fixed_noise_mpf, (M, Q, R),
                                                 dict(input_noise={"delta": 0.01})),
    "vehjax.calibrate.target_acceptance": lambda: (vj.calibrate.target_acceptance, (2,), {}),
    "vehjax.data.online_virtual_scale": lambda: (
        vj.data.online_virtual_scale, (np.zeros(T), np.zeros(T), np.full(T, 20.0), 1.6), {}),
}

#: "module.name" -> why its options are not walked here
EXEMPT = {
    "vehjax.tune.TuneResult": "a record of results (a NamedTuple), built by the fit",
    "vehjax.tune.ScoreTest": "a record of results (a NamedTuple), built by the fit",
    "vehjax.filters.Estimator": "a record of a filter's functions, built by the builders",
    "vehjax.filters.StepOutput": "a record a filter's step returns, inside the traced scan",
    "vehjax.filters.Runtime": "a part of the Estimator record, built by the builders",
    "vehjax.filters.NiW": "a record of prior statistics, checked by the builders that take it",
    "vehjax.tune.hessian_from_gradients": "takes a compiled gradient function: runs it at once",
    "vehjax.tune.compare": "needs fitted TuneResults (a fit each); tests/tune/test_compare.py",
    "vehjax.data.load_comma2k19": "reads the shipped segment; tests/data/test_comma2k19.py",
    "vehjax.data.prepare_drive": "needs a loaded drive; tests/data/test_prepare.py",
}

#: (callable, argument) -> {repr of a value walked here: why the callable takes it}
ALLOWED = {
    ("vehjax.tune.uncertainty", "max_std"): {"inf": "no limit on the standard errors",
                                             "[1.0]": "one limit per coordinate, broadcast"},
    **{(f"vehjax.smoothers.{name}", arg): {
        "1000000000000000": "a count or a cap with no upper bound (the caller's time and memory)"}
       for name, arg in (("IEKS", "max_iter"), ("IPLS", "max_iter"), ("FFBSi", "n_trajectories"),
                         ("RejectionSampling", "n_trajectories"),
                         ("RejectionSampling", "max_tries"), ("AncestorPaths", "n_trajectories"))},
    **{(f"vehjax.calibrate.{r}", a): {repr(10**15): "a count with no upper bound (the "
                                                   "caller's time and memory)"}
       for r, a in (("Chains", "n"), ("Chains", "samples"), ("Sweep", "moves"),
                    ("Adaptation", "windows"))},
    **{(f"vehjax.tune.{r}", a): {repr(10**15): "an iteration limit: the stopping rules end "
                                               "the fit before it"}
       for r in ("Adam", "LBFGS", "Scoring", "FirstOrder") for a in ("steps", "patience")},
}


def _walked():
    """(qualified name, the callable) of every public callable with an option to walk."""
    out = []
    for modname in MODULES:
        mod = importlib.import_module(modname)
        for name in mod.__all__:
            obj = getattr(mod, name)
            if callable(obj) and _options(obj):
                out.append((f"{modname}.{name}", obj))
    return out


def _options(fn) -> dict:
    """{argument: default} of the arguments whose default is a bool, int, float or str."""
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
        return {}
    return {p.name: p.default for p in params if isinstance(p.default, (bool, int, float, str))}


def _bad_values(default) -> list:
    if isinstance(default, bool):
        return ["no", [True], 2]
    if isinstance(default, int):
        return [[1], "3", 1.5, math.nan, 10**15]
    if isinstance(default, float):
        return [[default], "0.5", math.nan, math.inf]
    return ["no_such_choice_here", 3]


def _cases():
    for qual, fn in _walked():
        if qual in EXEMPT:
            continue
        for arg, default in _options(fn).items():
            for bad in _bad_values(default):
                if repr(bad) in ALLOWED.get((qual, arg), {}):
                    continue
                yield pytest.param(qual, arg, bad, id=f"{qual}-{arg}-{bad!r}")


def test_every_walked_callable_is_built_here_or_exempt_with_a_reason():
    names = {q for q, _ in _walked()}
    assert names - set(CALLS) - set(EXEMPT) == set(), "add a call or an exemption"
    public = {f"{m}.{n}" for m in MODULES for n in importlib.import_module(m).__all__
              if callable(getattr(importlib.import_module(m), n))}
    assert set(CALLS) | set(EXEMPT) <= public, "a listed callable is no longer public"


@pytest.mark.parametrize("qual, arg, bad", list(_cases()))
def test_a_wrong_value_is_refused_naming_it_before_anything_is_compiled(monkeypatch, qual,
                                                                      arg, bad):
    _stop_every_fit(monkeypatch)
    fn, args, kwargs = CALLS[qual]()
    before = len(_compiles)
    with pytest.raises((ValueError, TypeError)) as err:
        fn(*args, **kwargs, **{arg: bad})
    assert arg in str(err.value), (qual, arg, bad, str(err.value))
    assert len(_compiles) == before, (qual, arg, bad, "refused only after compiling")


@pytest.mark.parametrize("qual", sorted(CALLS))
def test_an_unknown_keyword_is_refused_naming_it(monkeypatch, qual):
    """A TypeError as Python raises it, or a ValueError from a callable that passes further
    keywords on (smooth's particle options) naming the keyword."""
    _stop_every_fit(monkeypatch)
    fn, args, kwargs = CALLS[qual]()
    with pytest.raises((TypeError, ValueError), match="no_such_option"):
        fn(*args, **kwargs, no_such_option=1)


def test_smooth_refuses_an_unknown_keyword_naming_it():
    """vehjax.smooth has no option of its own left to walk (they are its method records', walked
    above), so it is not in CALLS; an unknown keyword is still refused naming it."""
    with pytest.raises(TypeError, match="no_such_option"):
        vj.smooth(vj.filters.ekf(M, Q, R), YS, US, x0=X0, P0=P0, no_such_option=1)


# -- where values interact: properties against rules written out here ------------------------
_stamp = st.one_of(st.floats(-1e3, 1e3), st.just(math.nan), st.just(math.inf))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(t=st.lists(_stamp, min_size=0, max_size=6), n=st.integers(0, 7),
       unit=st.sampled_from(["s", "ms", "min", "parsec"]))
def test_drive_from_arrays_takes_exactly_the_stamps_and_columns_that_fit(t, n, unit):
    """A drive is made iff there are at least 2 finite, strictly increasing stamps, a known
    time unit and a column as long as them; then its stamps are the given ones in seconds and
    its column the given values. Otherwise a ValueError naming what is wrong."""
    scale = {"s": 1.0, "ms": 1e-3, "min": 60.0}.get(unit)
    col = np.arange(float(n))
    ts = np.asarray(t, dtype=float)
    ok = (len(ts) >= 2 and np.all(np.isfinite(ts)) and np.all(np.diff(ts) > 0)
          and scale is not None and n == len(ts))
    try:
        d = vj.data.Drive.from_arrays(t, {"y": col}, {"y": "m"}, time_unit=unit)
    except ValueError as err:
        assert not ok, (t, n, unit, str(err))
        assert any(w in str(err) for w in ("t:", "time", "y", "unit")), str(err)
        return
    assert ok, (t, n, unit)
    np.testing.assert_allclose(d.t, ts * scale, rtol=1e-15)
    np.testing.assert_array_equal(d.signals["y"], col)


_end = st.one_of(st.none(), st.floats(-5.0, 6.0), st.just(math.nan))


@settings(max_examples=60, deadline=None)
@given(lo=_end, hi=_end)
def test_bounds_are_refused_exactly_when_they_leave_nothing_of_the_domain(lo, hi):
    """mu's domain is (0, 3): bounds (lo, hi) pass iff both ends are numbers or None, lo < hi,
    and (lo, hi) meets (0, 3) (the interval arithmetic written out here)."""
    model = SingleTrack(tyres="brush")
    a = -math.inf if lo is None else lo
    b = math.inf if hi is None else hi
    ok = not (math.isnan(a) or math.isnan(b)) and a < b and max(a, 0.0) < min(b, 3.0)
    try:
        parameterisation.check_bounds(("mu",), {"mu": (lo, hi)}, model)
    except ValueError as err:
        assert not ok, (lo, hi, str(err))
        assert str(err).startswith("bounds") and "mu" in str(err), str(err)
        return
    assert ok, (lo, hi)


# -- array arguments: a wrong shape, no samples, inf, NaN ----------------------------------
def _array_variants(a: np.ndarray) -> dict:
    return {"extra axis": np.stack([a] * 3), "empty": np.zeros((0,) + a.shape[1:]),
            "inf": np.full(a.shape, np.inf), "nan": np.full(a.shape, np.nan)}


#: (callable, argument, variant) -> why the callable takes it; (callable, "*", "*"): not walked
ARRAY_ALLOWED = {
    **{(q, "measurements", "nan"): "NaN is a missing measurement"
       for q in ("vehjax.filter", "vehjax.smooth", "vehjax.run", "vehjax.compile_run",
                 "vehjax.tune.fit", "vehjax.tune.fit_from_theta", "vehjax.tune.objective",
                 "vehjax.calibrate.log_likelihood_spread",
                 "vehjax.calibrate.log_likelihood_difference_spread")},
    **{(q, "measurements", "extra axis"): "several runs (R, T, ny) fitted together"
       for q in ("vehjax.tune.fit", "vehjax.tune.fit_from_theta", "vehjax.tune.objective")},
    **{("vehjax.tune.uncertainty", a, v): "a fit's information that is not finite gives NaN "
       "standard errors, the fit's report of it" for a in ("info_matrix", "jac", "scales")
       for v in ("nan", "inf")},
    **{("vehjax.tune.scoring_direction", a, v): "a step from a point where the loss is not "
       "finite is the optimiser's to reject" for a in ("g", "B", "scales") for v in ("nan", "inf")},
    **{("vehjax.data.online_virtual_scale", a, v): "a sample that is not finite adds nothing "
       "(a missing one)" for a in ("gyro", "r_virt", "vx") for v in ("nan", "inf")},
}


def _array_cases():
    for qual, make in sorted(CALLS.items()):
        if (qual, "*", "*") in ARRAY_ALLOWED:
            continue
        fn, args, kwargs = make()
        bound = inspect.signature(fn).bind_partial(*args, **kwargs).arguments
        for arg, value in bound.items():
            if isinstance(value, np.ndarray):
                for variant in _array_variants(value):
                    if (qual, arg, variant) not in ARRAY_ALLOWED:
                        yield pytest.param(qual, arg, variant, id=f"{qual}-{arg}-{variant}")


@pytest.mark.parametrize("qual, arg, variant", list(_array_cases()))
def test_a_wrong_array_is_refused_naming_it_before_anything_is_compiled(monkeypatch, qual, arg,
                                                                        variant):
    _stop_every_fit(monkeypatch)
    fn, args, kwargs = CALLS[qual]()
    bound = inspect.signature(fn).bind_partial(*args, **kwargs).arguments
    bound[arg] = _array_variants(bound[arg])[variant]
    before = len(_compiles)
    with pytest.raises((ValueError, TypeError)) as err:
        fn(**bound)
    assert arg in str(err.value), (qual, arg, variant, str(err.value))
    assert len(_compiles) == before, (qual, arg, variant, "refused only after compiling")
