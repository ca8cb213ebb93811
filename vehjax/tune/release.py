"""Held values the data reject, fitted under the uncertainty a data sheet has: the release
stage of :func:`vehjax.tune.fit`.

Why. A fit holds every model parameter not named in ``params`` exactly at its given value. A
user takes those values from a data sheet (a car's mass, yaw inertia, centre of gravity), and a
data sheet can be far off: on a car whose yaw inertia was 2.5 times its data sheet's, the fit
of the two cornering stiffnesses moved them 40-50 % away from the truth to make up for it,
reported them to 2 %, and its sideslip estimate was three to five times a textbook observer's,
with the NIS in band. The score test of the held value (:mod:`vehjax.tune.diagnostics`) sees
it at once: freeing the inertia would gain hundreds of log-likelihood units.

What :func:`vehjax.tune.fit` does (``release=True``, the default), for a deterministic filter
with standard errors:

1. after a fit, the score test of every held parameter;
2. a held parameter is *released* when the data reject it by at least :data:`RELEASE_GAIN`
   log-likelihood units (and :func:`vehjax.tune.diagnostics.rejected`), its model declares
   how well a data sheet gives it (:meth:`vehjax.models.BaseModel.spec_priors`: for
   :class:`~vehjax.models.SingleTrack` the yaw inertia, to 30 %), and the data place it
   outside that uncertainty: the score test's one Newton step moves it at least
   :data:`RELEASE_SIGMAS` of the prior's standard deviations;
3. the fit is made again from its own values, the released parameters added to the fitted
   ones under those priors (penalised likelihood, :mod:`vehjax.tune.priors`), each starting at
   its score test's one Newton step (:func:`start_value`);
4. the result says so: ``TuneResult.released`` (the score test that released each), a line of
   the summary and a warning; its prior's pull (``TuneResult.pulls``) says how far the data
   moved it.

Where the model nests a simpler one (``start="data"``), step 1 is made on the nested model's
fit, so that the model's own fit starts from the released values (a saturating tyre model
fitted with a wrong inertia runs to a wrong friction coefficient first); the model's fit is
tested once more, and may release once more. A parameter without a data-sheet prior (a tyre
parameter the user chose to hold) is never released, only reported; a parameter already in
``priors`` is fitted already. ``release=False`` holds every given value as given (the report
still names those the data reject).

What it cannot do: the likelihood can reject a held value because the model lacks a physics
the car has (a tyre lag, a roll mode) that the released parameter then stands in for; the
released value is then an effective one (a test drive with a tyre lag moves the yaw inertia
towards what the lag needs, not to the car's). :func:`vehjax.tune.compare` sets such
structures side by side.

Cost: the score tests (an augmented program's compile and its Hessian) after the first fit,
and, where something is released, a second fit from near its optimum.
"""

from __future__ import annotations

import math

import numpy as np

from ..lib.priors import LogNormal, describe
from .diagnostics import ScoreTest, rejected

__all__ = ["RELEASE_GAIN", "RELEASE_SIGMAS", "to_release", "step_offset", "prior_distance",
           "release_priors", "start_value", "release_text"]

#: a held value is released when freeing it would gain at least this many log-likelihood
#: units: well beyond what an information criterion charges for one parameter (1 unit for
#: AIC, ln(n) / 2 ~ 5 units for BIC at 10^4 samples), so that the small misfit every real
#: model has on a long drive does not refit it
RELEASE_GAIN = 10.0
#: ... and when the score test's one Newton step moves it at least this many of its prior's
#: standard deviations: a value the data place within its data sheet's own uncertainty is kept
#: as given, since a model that lacks some physics of the car (a second track, a load
#: transfer) gains likelihood by moving a body value a little, and the estimates of the states
#: it does not measure can get worse by it (a simulated limit drive whose data sheet was exact:
#: the yaw inertia moved 11 %, 0.4 sigma of its prior, and the sideslip error grew by 40 %)
RELEASE_SIGMAS = 1.0
#: a released parameter starts at its one Newton step, kept within this many of its prior's
#: standard deviations of the given value
START_SIGMAS = 3.0


def step_offset(test: ScoreTest, prior) -> float:
    """The score test's one Newton step from the held value in the prior's own coordinate (log
    for a log-normal prior, the value itself for a normal one): NaN where the step is not
    finite (nothing known), -inf where it leaves a log-normal's support (0 or below)."""
    step = test.one_step
    if not math.isfinite(step):
        return math.nan
    if isinstance(prior, LogNormal):
        if step <= 0.0 or test.value <= 0.0:
            return -math.inf
        return math.log(step / test.value)
    return step - test.value


def prior_distance(test: ScoreTest, prior) -> float:
    """How far the score test's one Newton step moves the held value, in the prior's standard
    deviations (:func:`step_offset`); inf where the step leaves the prior's support (far
    beyond any linear step), 0.0 where it is not finite."""
    offset = step_offset(test, prior)
    return 0.0 if math.isnan(offset) else abs(offset) / prior.scale


def to_release(res, model, fitted) -> dict:
    """``{name: ScoreTest}`` of the held parameters of the fit ``res`` that are released: the
    data reject them by at least :data:`RELEASE_GAIN` units, ``model`` declares a data-sheet
    prior for them, and the score test's step moves them at least :data:`RELEASE_SIGMAS` of
    that prior's standard deviations (:func:`prior_distance`); none of ``fitted`` (names
    fitted already)."""
    spec = model.spec_priors()
    return {k: t for k, t in res.score_tests.items()
            if k in spec and k not in fitted and rejected(t) and t.gain >= RELEASE_GAIN
            and prior_distance(t, spec[k]) >= RELEASE_SIGMAS}


def release_priors(model, names) -> dict:
    """``{name: prior}``: ``model.spec_priors()`` of ``names``."""
    spec = model.spec_priors()
    return {k: spec[k] for k in names}


def start_value(test: ScoreTest, prior) -> float:
    """Where a released parameter starts: its score test's one Newton step, within
    :data:`START_SIGMAS` prior standard deviations of the held value (:func:`step_offset`:
    in the prior's coordinate); the held value where the step is not finite or leaves the
    prior's support."""
    offset = step_offset(test, prior)
    if not math.isfinite(offset):
        return test.value
    width = START_SIGMAS * prior.scale
    clipped = float(np.clip(offset, -width, width))
    return test.value * math.exp(clipped) if isinstance(prior, LogNormal) else test.value + clipped


def release_text(name: str, test: ScoreTest, prior, fitted: float) -> str:
    """What the report says of a released parameter."""
    return (f"{name} = {test.value:.4g} [{test.unit}] was given, and the data reject it "
            f"(freeing it gains about {test.gain:.3g} log-likelihood units): fitted under the "
            f"prior {describe(prior)} instead (model.spec_priors()), to {fitted:.4g}; "
            f"release=False "
            f"holds it")
