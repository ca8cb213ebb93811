"""Whether the model and the data disagree, at a fit's optimum and without a refit: score
(Lagrange-multiplier) tests of the model parameters held fixed, and per-output innovation checks
(:mod:`vehjax.tune.innovations`).

A parameter held at a wrong value (a spec-sheet yaw inertia the car does not have) is not
visible in the fitted parameters' standard errors, which are conditional on it, nor in a NIS
that the fitted noise has absorbed. The score test (Rao 1948; Silvey 1959, "The Lagrangian
multiplier test"; Engle 1984, "Wald, likelihood ratio and Lagrange multiplier tests in
econometrics", sec. 4) asks whether the likelihood would rise if the parameter were freed, from
its derivatives at the fit alone: with ``s_j = d logL / d theta_j`` at the optimum (the fitted
coordinates' score is zero there) and ``I`` the observed information (minus the Hessian of
logL) over the block (fitted coordinates, theta_j)::

    LM_j = s_j^2 [I^-1]_jj,    gain_j ~ LM_j / 2,    p_j = P(chi2_1 > LM_j) = erfc(sqrt(LM_j / 2))

``gain_j`` is the log-likelihood a Newton step of the block (the fitted quantities and theta_j
together) predicts, ``one_step`` where that step takes theta_j (physical units). Under the
hypothesis that the held value is right LM_j is about chi-square with one degree of freedom.
Coordinates: the fitted quantities in the fit's unconstrained ones (:mod:`vehjax.tune`), the
tested parameter in its physical one (:func:`physical_block`). At the optimum (the fitted
coordinates' score zero) the statistic does not depend on the fitted quantities'
parameterisation, but a map theta_j = g(z_j) adds ``-s_j g''`` to the observed information's
(j, j) entry: in log theta a large positive score could make the block indefinite where it is
not in theta itself. Where the observed block is still not positive definite (the likelihood
is not concave along theta_j there) the outer product of the per-step scores
(:func:`vehjax.tune.score_outer_product`, the BHHH form of the information, positive
semi-definite) takes its place. Far from the held value the quadratic model of the likelihood
is rough: the gain and the one-step value are then indications of direction and size, the
rejection itself stays valid.

Cost (:func:`score_tests`): the fit's objective with the held parameters added to ``params``
(:func:`vehjax.tune.likelihood.prepare_fit`) needs its own program. In forward mode the fit runs
on it (:func:`compile_shared`: the tangents along the fit's n coordinates, the held ones read
relative to their held values, so that the fit's arithmetic is that of its own program, bit for
bit; no second compile, and an evaluation costs what the fit's own does), and the tests take
its gradient n directions at a time, ceil((n + k) / n) evaluations a point; else it is compiled
once more. Then its gradient at the optimum and at the points of the Hessian's forward
differences: k along the held coordinates beside the fit's own Hessian (:func:`_held_columns`),
or n + k (:func:`vehjax.tune.information.difference_hessian`), side by side on the host's cores;
n fitted coordinates and k held parameters.

A held parameter whose value the transform cannot take (on or outside its declared domain) or
whose block has no positive-definite information (neither form) gets NaN, not an error.

The report (:func:`rejected`, :func:`score_text`): a held value is called contradicted when
p < :data:`REJECT_P` and the gain exceeds :data:`REJECT_GAIN` log-likelihood units.
"""

from __future__ import annotations

import functools
import warnings
from typing import NamedTuple

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

from .. import execution
from ..filters import input_noise as inoise
from ..lib import whiteness
from . import innovations as inn
from . import program
from .information import FORWARD_REL, RCOND, difference_hessian
from .likelihood import prepare_fit
from .options import Fitted
from .parameterisation import param_transform
from .quantities import coordinates

__all__ = ["ScoreTest", "Checks", "Start", "Ahead", "compile_augmented", "compile_shared",
           "shared_extra",
           "compile_innovations",
           "compile_ahead", "testable", "lm_statistic", "score_p_value", "score_tests", "augmented_information",
           "physical_block", "fit_innovations",
           "fit_diagnostics", "rejected", "score_text", "diagnostics_text", "REJECT_P",
           "REJECT_GAIN"]

#: a held value is contradicted when its score test's p-value is below this ...
REJECT_P = 1e-3
#: ... and freeing it would gain more than this many log-likelihood units (with 10^4 samples a
#: p below 1e-3 is reached by a parameter off by a fraction of a per cent; a gain of 5 units, a
#: likelihood ratio of e^5 ~ 150, is one the fit's other numbers would notice too)
REJECT_GAIN = 5.0


class ScoreTest(NamedTuple):
    """The score test of one model parameter held fixed (module docstring).

    Attributes:
        value: the held value (physical units).
        score: d logL / d theta_j there (logL summed over runs; per unit of the parameter).
        statistic: LM_j = s_j^2 [I^-1]_jj.
        gain: LM_j / 2, the log-likelihood one Newton step of the block predicts.
        p_value: P(chi2_1 > LM_j).
        one_step: theta_j after that Newton step (physical units).
        unit: the parameter's unit ("-" unknown).
    """

    value: float
    score: float
    statistic: float
    gain: float
    p_value: float
    one_step: float
    unit: str = "-"


def lm_statistic(score: float, info) -> tuple[float, float]:
    """(LM, Newton step of the tested coordinate) from the score of the tested coordinate and
    the observed information ``info`` (m, m) of the block whose last coordinate it is, the
    others' scores zero: ``x = I^-1 e_m s``, ``LM = s x_m``, step ``x_m``. By a Cholesky factor
    of the Jacobi-scaled block; (NaN, NaN) where it is not finite or not positive definite, or
    its eigenvalues span more than 1 / :data:`vehjax.tune.information.RCOND` (the rule by which
    the fit calls a direction undetermined)."""
    info = np.asarray(info, dtype=float)
    nan = (float("nan"), float("nan"))
    d = np.diagonal(info)
    if not (np.isfinite(score) and np.all(np.isfinite(info)) and np.all(d > 0)):
        return nan
    D = 1.0 / np.sqrt(d)
    Is = 0.5 * (info + info.T) * np.outer(D, D)
    lam = np.linalg.eigvalsh(Is)
    if not lam[0] > RCOND * lam[-1]:  # singular to the fit's own tolerance
        return nan
    L = np.linalg.cholesky(Is)
    rhs = np.zeros(len(d))
    rhs[-1] = D[-1] * score
    x = D * np.linalg.solve(L.T, np.linalg.solve(L, rhs))
    return float(score * x[-1]), float(x[-1])


def score_p_value(statistic: float) -> float:
    """P(chi2_1 > LM) = erfc(sqrt(LM / 2)) (:func:`vehjax.lib.whiteness.chi2_sf_1`)."""
    return whiteness.chi2_sf_1(statistic)


def _testable(model, held) -> tuple[list, list]:
    """(the held parameters the transform can take at their values, the others)."""
    names, theta = tuple(model.param_names), np.asarray(model.theta, dtype=float)
    ok, bad = [], []
    for p in held:
        try:
            param_transform((p,), None, theta, names, model.param_domains())
            ok.append(p)
        except ValueError:
            bad.append(p)
    return ok, bad


def _augmented(fit, setup, data, bounds, extra, anchored: bool = False):
    """The fit's objective at ``fit``'s values (its ``model``, ``Q``, ``R``, ``input_noise``,
    ``x0``: the optimum's, or the start's for :func:`compile_augmented`) with ``extra``
    parameters fitted too: (obj, setup); penalised by the fit's priors, if any (the optimum's
    free gradient is that objective's); ``anchored``: ``extra`` read relative to an anchor
    (:func:`vehjax.tune.likelihood.anchored_physical`, :func:`compile_shared`)."""
    ys, us, _, P0, _ = data
    kw = dict(setup.builder_options)
    if fit.input_noise is not None:
        kw["input_noise"] = fit.input_noise
    return prepare_fit(functools.partial(setup.builder, **kw), fit.model, fit.Q, fit.R,
                       np.asarray(ys), None if us is None else np.asarray(us),
                       np.asarray(fit.x0), np.asarray(P0),
                       Fitted(tuple(setup.params) + tuple(extra), setup.noise, setup.fit_x0,
                              bounds, setup.priors), None,
                       anchored=tuple(extra) if anchored else ())


class Start(NamedTuple):
    """A fit's starting values, as :func:`_augmented` reads them from a result."""

    model: object
    Q: object
    R: object
    input_noise: object
    x0: object


class Checks(NamedTuple):
    """Which diagnostics a fit makes (:func:`fit_diagnostics`): the score tests of the held
    parameters among ``held`` (None: every one) and, with ``innovations``, the innovation
    checks. :func:`vehjax.tune.fit`'s nested stage tests only what it may release."""

    held: tuple | None = None
    innovations: bool = True


def held_parameters(model, params, only=None) -> list:
    """The parameters of ``model`` not among ``params`` (and among ``only`` unless None)."""
    return [p for p in model.param_names if p not in params and (only is None or p in only)]


def testable(model, params, only=None) -> list:
    """The held parameters of ``model`` (:func:`held_parameters`) that a score test can take."""
    return _testable(model, held_parameters(model, params, only))[0]


def compile_augmented(start: Start, setup, data, bounds=None, only=None):
    """The program of the augmented objective (:func:`augmented_information`), compiled from
    the fit's start (:class:`Start`): its held values are the optimum's and its fitted values
    are the program's argument, so it serves the optimum (:func:`vehjax.tune.fit_from_theta`
    compiles it in a second thread while it fits); None when nothing is held (among
    ``only``, unless None)."""
    extra = testable(start.model, setup.params, only)
    if not extra:
        return None
    obj, aug = _augmented(start, setup, data, bounds, extra)
    return program.compile_program(obj, aug)


def shared_extra(model, setup, only=None) -> tuple:
    """The held parameters of the program :func:`compile_shared` would compile for the fit of
    ``setup`` (its ``z0``) on ``model``: the testable ones (among ``only``, unless None); ()
    where there is none or the fit's derivatives are not forward mode (a particle filter,
    more than :data:`vehjax.tune.program.FORWARD_MAX` coordinates)."""
    n = jax.flatten_util.ravel_pytree(setup.z0)[0].shape[0]
    if setup.stochastic or n > program.FORWARD_MAX:
        return ()
    return tuple(testable(model, setup.params, only))


def compile_shared(start: Start, setup, data, bounds=None, only=None, beside: bool = False):
    """The program of the augmented objective (:func:`compile_augmented`) that serves the fit
    too (:func:`vehjax.tune.program.compile_directed`): forward mode along the fit's n
    coordinates at a time, the held parameters read relative to their values at the start
    (their anchor), so that the fit runs on it with its own program's arithmetic and its score
    tests need no second compile; None where :func:`shared_extra` is empty. ``setup`` the
    fit's; ``beside`` as :func:`vehjax.tune.program.compile_program`'s."""
    extra = shared_extra(start.model, setup, only)
    if not extra:
        return None
    obj, aug = _augmented(start, setup, data, bounds, extra, anchored=True)
    fit_names = list(coordinates(setup, start.model, setup.z0)[0])
    names = list(coordinates(aug, start.model, obj.z0)[0])
    held_pos = np.array([names.index(p) for p in extra], dtype=int)
    theta = np.asarray(start.model.theta, dtype=float)
    layout = program.Layout(
        tuple(extra), tuple(fit_names), np.array([names.index(q) for q in fit_names], dtype=int),
        held_pos, np.asarray(jax.flatten_util.ravel_pytree(obj.z0)[0], dtype=float)[held_pos],
        np.array([theta[list(start.model.param_names).index(p)] for p in extra]), len(names))
    return program.compile_directed(obj, aug, layout, beside)


def compile_innovations(setup, data):
    """The innovation checks' program (:func:`vehjax.tune.innovations.fitted_innovations`)
    compiled at the fit's start ``setup.z0``: its fitted values are the argument, so it
    serves the optimum (:func:`fit_innovations`)."""
    options = execution.compiler_options(execution.current(), setup.workload)
    return jax.jit(inn.fitted_innovations(setup)).lower(setup.z0, data).compile(
        compiler_options=options)


class Ahead(NamedTuple):
    """The diagnostics' programs compiled ahead (:func:`compile_ahead`), each None where not
    (:func:`fit_diagnostics` then compiles its own)."""

    augmented: object = None
    innovations: object = None


def compile_ahead(start: Start, setup, data, bounds=None, checks: Checks = Checks(),
                  augmented: bool = True) -> Ahead:
    """The programs :func:`fit_diagnostics` runs at the optimum, compiled from the fit's start
    side by side: the score tests' (:func:`compile_augmented`, for the held parameters among
    ``checks.held``; not with ``augmented`` False, where the fit's own program serves them,
    :func:`compile_shared`) here and, with ``checks.innovations``, the innovation checks'
    (:func:`compile_innovations`) in another host thread. :func:`vehjax.tune.fit_from_theta`
    runs this in a second host thread while it fits: the two compiles, which end the fit
    when they finish after it, then use the cores its evaluations leave."""
    if not augmented:
        return Ahead(None, compile_innovations(setup, data) if checks.innovations else None)
    inn = execution.in_thread(compile_innovations, setup, data) if checks.innovations else None
    aug = compile_augmented(start, setup, data, bounds, checks.held)
    return Ahead(aug, None if inn is None else inn.result())


def _held_columns(loss, x, scales, held, free_hessian, names):
    """The observed information of the mean loss (n, n) at x from the fit's Hessian over its
    own coordinates (``free_hessian`` = (their names, (m, m))) and forward differences of the
    gradient along the ``held`` coordinates only (k evaluations, side by side), symmetrised."""
    fit_names, H_fit = free_hessian
    n = len(x)
    free = [names.index(q) for q in fit_names]
    h = FORWARD_REL * np.asarray(scales, dtype=float)[held]
    points = [x + h[i] * np.eye(n)[j] for i, j in enumerate(held)]
    g0 = np.asarray(loss.vg(x)[2], dtype=float)
    cols = (np.stack([np.asarray(r[2], dtype=float) for r in loss.many(points)]) - g0) / h[:, None]
    H = np.zeros((n, n))
    H[np.ix_(free, free)] = H_fit
    H[held, :] = cols
    H[:, held] = cols.T
    H[np.ix_(held, held)] = 0.5 * (cols[:, held] + cols[:, held].T)
    return H


def augmented_information(res, setup, data, bounds, extra, compiled=None, free_hessian=None):
    """The score and curvature at the fit's optimum ``res`` of its objective with the
    parameters ``extra`` fitted too (:func:`vehjax.tune.likelihood.prepare_fit` at the fitted
    values, compiled once or ``compiled`` by :func:`compile_augmented` or
    :func:`compile_shared`; the Hessian by
    :func:`vehjax.tune.information.difference_hessian`, or, given the fit's own Hessian
    ``free_hessian`` = (its coordinate names, the Hessian of the mean loss over them), that
    and differences along the held coordinates only, :func:`_held_columns`).

    Returns:
        (coordinate names (n,), score d logL / dz (n,), observed information -d2 logL / dz2
        (n, n), the outer product of the per-step scores (n, n) or None (reverse mode), the
        augmented set-up, z its starting coordinates); logL summed over the runs, z the
        unconstrained coordinates (:func:`vehjax.tune.quantities.coordinates` order).
    """
    obj, aug = _augmented(res, setup, data, bounds, extra)
    names, scales = coordinates(aug, res.model, obj.z0)
    if compiled is not None and compiled.layout is not None and (
            compiled.layout.extra != tuple(extra) or compiled.layout.size != len(names)):
        compiled = None  # a program over other held parameters: this objective's own
    loss = program.compiled_loss(obj, aug, batch_hessian=program.batched_hessian(obj.n_steps),
                                 compiled=compiled)
    if loss.vgo is not None:
        _, _, g, opg = loss.vgo(loss.x0)
        opg = obj.n_steps * opg
    else:
        (_, _, g), opg = loss.vg(loss.x0), None
    held = [i for i, q in enumerate(names) if free_hessian is None or q not in free_hessian[0]]
    if free_hessian is None or not held or len(held) + len(free_hessian[0]) != len(names):
        info = obj.n_steps * difference_hessian(loss, loss.x0, scales)
    else:
        info = obj.n_steps * _held_columns(loss, np.asarray(loss.x0, dtype=float), scales,
                                           held, free_hessian, list(names))
    return names, -obj.n_steps * np.asarray(g, dtype=float), info, opg, aug, obj.z0


def physical_block(score_z: float, info, d1: float, d2: float):
    """(score, information) of a block whose last coordinate z is carried to the physical
    theta = g(z) (g' = ``d1``, g'' = ``d2``), the others' scores zero: ``s = s_z / g'``, the
    last row and column divided by g', its diagonal entry corrected by the curvature of the
    map, ``I_tt = (I_zz + s_z g'' / g') / g'^2``. NaN where g' = 0."""
    info = np.array(info, dtype=float)
    if not (np.isfinite(d1) and d1 != 0):
        return float("nan"), np.full_like(info, np.nan)
    info[-1, -1] += score_z * d2 / d1
    info[-1, :] /= d1
    info[:, -1] /= d1
    return score_z / d1, info


def _map_derivatives(tmap, z):
    """(g'(z), g''(z)) of the parameter map, entry by entry, (p,) each."""
    ones = jnp.ones_like(z)
    d1 = lambda v: jax.jvp(tmap.to_physical, (v,), (ones,))[1]  # noqa: E731
    both = jax.jit(lambda v: (d1(v), jax.jvp(d1, (v,), (ones,))[1]))  # one program
    return tuple(np.asarray(d) for d in both(z))


def _one_test(value, score_z, info, opg, d1, d2, unit):
    """The :class:`ScoreTest` of one held parameter from its block (last coordinate), in its
    physical coordinate; the outer product of the scores where the observed information is not
    positive definite there."""
    s, I = physical_block(score_z, info, d1, d2)
    lm, step = lm_statistic(s, I)
    if not np.isfinite(lm) and opg is not None:
        s, I = physical_block(score_z, opg, d1, 0.0)
        lm, step = lm_statistic(s, I)
    return ScoreTest(value, float(s), lm, 0.5 * lm, score_p_value(lm), value + step, unit)


def score_tests(res, setup, data, bounds=None, held_coordinates=(), compiled=None,
                only=None, free_hessian=None) -> dict:
    """``{name: ScoreTest}`` for every model parameter not among the fit's ``params``
    (module docstring), at the fit's optimum.

    Args:
        res: the fit's :class:`vehjax.tune.TuneResult` (``model``, ``Q``, ``R``,
            ``input_noise``, ``x0`` at the optimum).
        setup: the fit's set-up (:func:`vehjax.tune.likelihood.prepare_fit`).
        data: the fit's ``Objective.data``.
        bounds: the fit's ``bounds=``.
        held_coordinates: names of fitted coordinates held out of the block (on a bound).
        compiled: the augmented program from :func:`compile_augmented`, or None (compiled
            here).
        only: test only the held parameters among these names (None: every one).
        free_hessian: (the fit's coordinate names, the Hessian of its mean loss over them at
            the optimum), reused for that block (:func:`augmented_information`), or None.
    """
    model = res.model
    held = held_parameters(model, setup.params, only)
    ok, bad = _testable(model, held)
    units = dict(zip(model.param_names, getattr(model, "param_units",
                                                ("-",) * len(model.param_names))))
    value = {p: float(model.theta[model.param_names.index(p)]) for p in held}
    nan = float("nan")
    out = {p: ScoreTest(value[p], nan, nan, nan, nan, nan, units[p]) for p in bad}
    if ok:
        names, score, info, opg, aug, z0 = augmented_information(res, setup, data, bounds, ok,
                                                                 compiled, free_hessian)
        block = [i for i, n in enumerate(names) if n not in ok and n not in held_coordinates]
        d1, d2 = _map_derivatives(aug.theta_map, jnp.asarray(z0["theta"]))
        pos = list(aug.params)
        for p in ok:
            j, k = names.index(p), pos.index(p)
            ix = np.ix_(block + [j], block + [j])
            out[p] = _one_test(value[p], score[j], info[ix], None if opg is None else opg[ix],
                               d1[k], d2[k], units[p])
    return {p: out[p] for p in held}


def fit_innovations(setup, data, z, names, compiled=None, lags=None) -> dict:
    """``{output: InnovationCheck}`` of the fitted estimator on the fit's data
    (:mod:`vehjax.tune.innovations`): the filter at the fit's coordinates ``z`` run once more
    with its covariances, on the program ``compiled`` ahead or one compiled here (both
    :func:`compile_innovations`); ``names`` the model's outputs."""
    run = compile_innovations(setup, data) if compiled is None else compiled
    e, S = run(z, data)
    return inn.output_checks(np.asarray(e), np.asarray(S), names, lags)


def rejected(test: ScoreTest) -> bool:
    """Whether a held value is contradicted by the data (module docstring)."""
    return bool(test.p_value < REJECT_P and test.gain > REJECT_GAIN)


def score_text(name: str, test: ScoreTest) -> str:
    """What the report says of a contradicted held value."""
    return (f"{name} = {test.value:.4g} [{test.unit}] (held fixed): the data reject it: "
            f"freeing it would gain about {test.gain:.3g} log-likelihood units "
            f"({inn.p_text(test.p_value)}; one step to {test.one_step:.4g})")


def diagnostics_text(score: dict, checks: dict) -> list:
    """The report's lines: the contradicted held values, then the coloured outputs."""
    lines = [score_text(k, t) for k, t in score.items() if rejected(t)]
    return lines + [inn.coloured_text(k, c) for k, c in checks.items() if inn.coloured(c)]


def fit_diagnostics(res, setup, data, z, bounds=None, held_coordinates=(), ahead=Ahead(),
                    checks: Checks = Checks(), free_hessian=None) -> dict:
    """``{"score_tests": ..., "innovations": ...}`` of a deterministic filter's fit at its
    optimum (``res``, its coordinates ``z``), as ``checks`` asks (:class:`Checks`):
    :func:`score_tests`; :func:`fit_innovations`, in a second host thread beside the score
    tests where the platform has a core to spare (``side_by_side`` of
    :mod:`vehjax.execution`); each on its program compiled ahead (:class:`Ahead`) where
    given; with a warning naming the contradicted held values; ``free_hessian`` as
    :func:`score_tests`."""
    want = checks.innovations
    names = res.model.output_names
    beside = want and execution.current().side_by_side >= 2
    future = execution.in_thread(fit_innovations, setup, data, z, names,
                                 ahead.innovations) if beside else None
    tests = score_tests(res, setup, data, bounds, held_coordinates, ahead.augmented,
                        checks.held, free_hessian)
    checks = future.result() if beside else \
        fit_innovations(setup, data, z, names, ahead.innovations) if want else {}
    bad = [score_text(k, t) for k, t in tests.items() if rejected(t)]
    if bad:
        warnings.warn("vehjax.tune: " + "; ".join(bad) + ": fit it too, or correct it",
                      stacklevel=3)
    return {"score_tests": tests, "innovations": checks}
