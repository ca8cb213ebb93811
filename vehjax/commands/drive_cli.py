"""``vehjax fit`` and ``vehjax estimate``: the two commands on a user's drive file, registered
on the ``vehjax`` parser by :func:`add_commands`.

Building the parsers imports nothing heavy (``vehjax --help`` stays fast); the work's modules
(:mod:`~vehjax.commands.fitting`, :mod:`~vehjax.commands.estimating`, which import JAX) load
when a command runs. Every check of the configuration, the drive and the model comes before
anything is compiled; a refused input is a ValueError that ``vehjax.cli.main`` writes as one
line with exit code 2.
"""

from __future__ import annotations

from pathlib import Path

from . import config

__all__ = ["add_commands"]

_FIT_HELP = ("Fit a model to a drive file by maximum likelihood (vehjax.tune.fit): the "
             "parameters and noise named in the configuration's [fit] section, with standard "
             "errors. Writes DIR/report.txt, DIR/fit.json (the fitted filter, for `vehjax "
             "estimate`), DIR/fitted.png and DIR/innovations.png. The drive file is a CSV, "
             "an MDF4/MDF3 file (.mf4, .mdf, .dat), a ROS 2 bag (its folder, .db3, .mcap) or "
             "a CAN log (.asc, .blf, .log, .trc) with a DBC (each beyond CSV with its optional "
             "extra: vehjax[mdf], vehjax[ros], vehjax[can]). The configuration (TOML): "
             "[drive] how the file is read (units, reference; a CSV's time, columns, ...; an "
             "MDF file's channels; a bag's fields, stamps; a CAN log's dbc, signals, channel) "
             "and mapped onto the model (names: signal -> model name, max_gap, ...); "
             "[model] name (a built-in "
             "model or 'package.module:factory'), dt, options, theta (spec values); [fit] "
             "params, bounds, noise, filter, process_std, meas_std, P0_std, x0, input_noise, "
             "...; [estimate] smooth. See vehjax.commands.config.")
_ESTIMATE_HELP = ("Run a fitted filter (or its smoother) over another drive file: writes "
                  "DIR/estimates.csv (t and each state's mean and standard deviation, units "
                  "in the header), DIR/estimates.parquet (with pyarrow) and DIR/estimates.png. "
                  "The drive is read and mapped as the fit's was (its [drive] section, stored "
                  "in fit.json) unless --config gives another [drive] (a drive file of "
                  "another format or layout needs one; a relative dbc path is taken from the "
                  "configuration file's folder).")


def _names_list(text: str) -> list:
    """``"cf,cr"`` -> ``["cf", "cr"]`` (checked as the file's list is)."""
    return [n.strip() for n in text.split(",")]


def _in_file(work, where):
    """``work()``, a ValueError naming a key (``[fit] params: ...``) prefixed with the file
    the key is in, ``where(message)``: its name, or None for a message that stays as it is."""
    try:
        return work()
    except ValueError as err:
        text = str(err)
        source = where(text) if text.startswith("[") else None
        if source is not None:
            raise ValueError(f"{source} {text}") from None
        raise


def _cmd_fit(args) -> int:
    from . import fitting

    cfg = config.read(args.config)
    cfg = config.override(cfg, "model", "name", args.model, "--model")
    cfg = config.override(cfg, "fit", "params",
                          None if args.params is None else _names_list(args.params), "--params")
    cfg = config.override(cfg, "fit", "filter", args.filter, "--filter")
    name = Path(args.config).name
    config.require(cfg, name)
    def where(text):  # a model named on the command line is not the file's
        return "--model:" if args.model and text.startswith("[model] name") else name

    return _in_file(lambda: fitting.run(args.drive, cfg, args.out,
                                        progress=not args.no_progress), where)


def _cmd_estimate(args) -> int:
    from . import estimating

    cfg = None if args.config is None else config.read(args.config)  # [model], [fit]: the fit's

    def where(text):
        section = text[1:text.index("]")] if "]" in text else ""
        given = cfg is not None and section in ("drive", "estimate") and cfg.get(section)
        return Path(args.config).name if given else Path(args.fit).name

    return _in_file(lambda: estimating.run(args.drive, args.fit, args.out, config=cfg,
                                           smooth=True if args.smooth else None,
                                           family=args.filter), where)


def add_commands(sub, out_folder) -> None:
    """Register ``fit`` and ``estimate`` on ``sub`` (the ``vehjax`` parser's subparsers);
    ``out_folder`` is the argparse type of ``--out``."""
    p = sub.add_parser("fit", help="fit a model to a drive file; writes report, fit.json, "
                       "figures", description=_FIT_HELP)
    p.add_argument("drive", metavar="DRIVE", help="the drive file: a CSV (a header of column "
                   "names, units as 'name [unit]' or in [drive] units), an MDF4/MDF3 file, a "
                   "ROS 2 bag (folder, .db3, .mcap) or a CAN log (.asc, .blf, .log, .trc)")
    p.add_argument("--config", required=True, metavar="TOML", help="the configuration file")
    p.add_argument("--model", help="the model, overriding [model] name: a built-in model "
                   "(`vehjax models`) or 'package.module:factory'")
    p.add_argument("--params", metavar="NAME[,NAME...]",
                   help="the model parameters to fit, overriding [fit] params")
    p.add_argument("--filter", choices=config.FILTERS,
                   help="the filter family, overriding [fit] filter (default ekf)")
    p.add_argument("--out", type=out_folder, default="out", help="output folder (default ./out)")
    p.add_argument("--no-progress", action="store_true",
                   help="no progress on stderr (default: shown)")
    p.set_defaults(func=_cmd_fit)

    p = sub.add_parser("estimate", help="run a fitted filter over a drive file; writes "
                       "estimates (CSV, Parquet) and a figure", description=_ESTIMATE_HELP)
    p.add_argument("drive", metavar="DRIVE", help="the drive file, of any format `vehjax "
                   "fit` reads")
    p.add_argument("--fit", required=True, metavar="FIT.json",
                   help="the fit written by `vehjax fit` (DIR/fit.json)")
    p.add_argument("--out", type=out_folder, default="out", help="output folder (default ./out)")
    p.add_argument("--smooth", action="store_true",
                   help="run the smoother (vehjax.smooth) instead of the filter (default: the "
                        "fit's [estimate] smooth, else the filter)")
    p.add_argument("--filter", choices=config.FILTERS,
                   help="another filter family with the fitted noise (default: the fit's)")
    p.add_argument("--config", metavar="TOML", help="a configuration whose [drive] and "
                   "[estimate] sections replace the fit's (a drive file laid out otherwise); "
                   "its other sections are checked and not used (the model and the filter "
                   "are the fit's)")
    p.set_defaults(func=_cmd_estimate)
