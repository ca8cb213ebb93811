"""The simulated set-ups of vehjax's studies and checks: each builds the truth, the noise and the
filter settings of one problem, for the reproductions, the benchmarks and the tests to share.

Modules:
    banked_road: the banked-road problem of Berntorp & Di Cairano (2018), sec. 4-5 (truth,
        sensors, the marginalized filters' settings).
    dual_settings: the filter settings and simulated noise of Dutta, Singh & Alam (2019).
    limit_drive: simulated track drives at the friction limit, with a truth none of vehjax's
        fitted models is.
    second_car: a simulated second car (front-wheel-drive saloon) whose truth is richer than any
        fitted model, for checks on a car nothing was tuned to.
"""

from . import banked_road, dual_settings, limit_drive, second_car

__all__ = ["banked_road", "dual_settings", "limit_drive", "second_car"]
