"""``vehjax reproduce dutta2019``: Dutta, Singh & Alam (2019), dual state and parameter
estimation of a four-wheel vehicle, reproduced.

:mod:`~vehjax.reproduce.dutta2019.study` is the study (the paper's settings and ours, the
excitations, the simulated runs, the "tuned" fit, the filters and the two stages);
:mod:`~vehjax.reproduce.dutta2019.report` reads and shows its results (tables, summaries,
figures, ``report.md``) and holds the command line (:func:`main`, :func:`parser`). Both
modules' names can be used from here.
"""

from . import report, study
from .report import *  # noqa: F401,F403  (the presentation and the command line)
from .report import _check_args, _report_settings  # noqa: F401
from .study import *  # noqa: F401,F403  (the study)
from .study import (  # noqa: F401
    _DECAY, _DYN_REL_BOX, _FILTERS, _FREQUENCIES, _KIN_BOX, _SETTINGS,
    _TRAINING_STREAM, _TUNE_DURATION, _TUNE_LR, _TUNE_PATIENCE, _TUNE_RUNS, _TUNE_STEPS,
    _builders, _config, _final, _ok, _stage, _training_keys, _tuned, _window,
    _with_axle_inputs,
)

#: the names the package lends from :mod:`~vehjax.reproduce.dutta2019.report`
_PRESENTATION = (
    "SMOOTHED_NOTE", "NOT_LEARNED_FRACTION", "SAME_RMSE_RTOL", "table_consistency",
    "table_parameters", "learning", "learning_summary", "table_states", "state_rmse",
    "smoothed_summary", "same_rmse_groups", "states_summary", "frequency_table", "table_noise",
    "tuning_summary", "table_settings", "table_settings_states", "plot_parameters",
    "plot_states", "plot_frequency", "parser", "main", "_check_args", "_report_settings",
)
