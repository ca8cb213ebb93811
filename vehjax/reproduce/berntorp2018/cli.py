"""The command line of ``vehjax reproduce berntorp2018 [--drive]``: its options and ``main``."""

from __future__ import annotations

import math
from pathlib import Path

from .drive import main_drive
from .pmmh import PMMH_ITERS, PMMH_PARTICLES
from .report import PAPER
from .study import main_simulation


def parser():
    """The study's options (``vehjax reproduce berntorp2018 --help``); each help states its
    default."""
    from vehjax import cli as _cli  # one-line user errors, finite numbers in range

    p = _cli.ArgumentParser(
        prog="vehjax reproduce berntorp2018",
        description=f"Adaptive marginalized PF, steering offset and IMU noise statistics: {PAPER}. "
                    "Writes report.md (tables and figures) and results.npz.")
    p.add_argument("--drive", action="store_true",
                   help="the real-drive study (sec. 5) instead of the simulation (default: simulation)")
    p.add_argument("--runs", type=_cli.count, default=100,
                   help="Monte-Carlo runs / executions (default %(default)s)")
    p.add_argument("--particles", type=_cli.count, default=None,
                   help="particles N (default 100 in simulation, 500 with --drive)")
    p.add_argument("--duration", type=_cli.positive, default=None,
                   help="seconds of driving (default 180 in simulation; with --drive the whole "
                        "60 s segment)")
    p.add_argument("--seed", type=_cli.integer, default=0, help="random seed (default %(default)s)")
    p.add_argument("--out", type=_cli.out_folder, default="out/berntorp2018",
                   help="output folder (default %(default)s, with --drive %(default)s_drive)")
    p.add_argument("--variant", choices=("planar", "bank"), default="bank",
                   help="--drive filter: planar (Remark 2) or bank (phi unmeasured) "
                        "(default %(default)s)")
    p.add_argument("--kalman-states", choices=("linear", "all"), default="linear",
                   help="marginalized_pf's kalman_states: linear (the paper's Algorithm 1) or "
                        "all (each particle a Gaussian over all states) (default %(default)s)")
    p.add_argument("--rvirt-scale", choices=("online", "state", "offline", "none"),
                   default="offline",
                   help="--drive: the virtual yaw rate's scale (rear rolling-radius mismatch): "
                        "online (a causal recursive estimate from the two yaw sensors corrects "
                        "r_virt for the MPF; a state of the EKF), state (also a Kalman state of "
                        "each MPF particle), offline (least squares over the drive removed "
                        "beforehand) or none (the paper: unbiased) (default %(default)s)")
    p.add_argument("--rvirt-gate", type=_cli.at_least(float, 0.0), default=5.0,
                   help="--drive: r_virt samples more than this many deg/s from the gyro are "
                        "missing (wheel-speed bursts); 0: none (default %(default)s)")
    p.add_argument("--pmmh-iters", type=_cli.at_least(int, 0), default=None,
                   help="--drive: iterations per chain of every offline sampler, half warm-up; "
                        "0 skips the offline reference (default per sampler: "
                        + ", ".join(f"{k} {v}" for k, v in PMMH_ITERS.items()) + ")")
    p.add_argument("--pmmh-particles", type=_cli.count, default=None,
                   help="--drive: particles of the bootstrap PF (PMMH likelihood) and of "
                        "particle Gibbs's conditional PF (default per sampler: "
                        + ", ".join(f"{k} {v}" for k, v in PMMH_PARTICLES.items()) + ")")
    p.add_argument("--pmmh-chains", type=_cli.count, default=4,
                   help="--drive: PMMH chains, vmapped (default %(default)s)")
    p.add_argument("--pmmh-duration", type=_cli.positive, default=20.0,
                   help="--drive: seconds of the drive PMMH fits, from its start "
                        "(default %(default)s)")
    p.add_argument("--pmmh-likelihood", choices=("bootstrap", "kalman", "mpf", "cpm", "both",
                                                 "pg", "standard", "all"),
                   default="standard",
                   help="--drive: the offline reference's samplers: PMMH with the bootstrap "
                        "PF's likelihood, PMMH with the exact Kalman likelihood (plain MH, a "
                        "check), PMMH with the marginalized PF's likelihood (mpf: paper 004's "
                        "filter with the noise statistics held at the chain's values), the "
                        "bootstrap PF's with correlated random numbers (cpm: correlated "
                        "pseudo-marginal, Deligiannidis et al. 2018), both "
                        "(kalman and bootstrap), particle Gibbs with ancestor sampling (pg; "
                        "--pmmh-particles particles in its conditional PF), standard "
                        "(kalman, bootstrap and pg: the MPF chain does not mix at its default "
                        "size and is the slowest) or all five (default %(default)s)")
    p.add_argument("--mpf-smoother", choices=("ffbsi", "ancestor"), default="ffbsi",
                   help="--drive: the MPF smoother's method (vehjax.smooth's method): "
                        "backward simulation over all the filter's particles (ffbsi; with "
                        "kalman_states linear, else ancestor) or the ancestral paths "
                        "(ancestor) (default %(default)s)")
    p.add_argument("--mpf-smooth-paths", type=_cli.at_least(int, 0), default=100,
                   help="--drive: ancestral paths M of the MPF's smoother (vehjax.smooth, one "
                        "more execution; at most N); 0 skips it (default %(default)s)")
    p.add_argument("--no-plots", action="store_true", help="skip the figures (default: draw them)")
    return p


def main(argv=None) -> int:
    """``vehjax reproduce berntorp2018 [options]``: the simulation study, or with ``--drive`` the
    drive study; 0 on success."""
    args = parser().parse_args(argv)
    if args.runs < 1:
        raise ValueError(f"--runs: expected at least 1, got {args.runs}")
    if args.particles is not None and args.particles < 2:
        raise ValueError(f"--particles: expected at least 2, got {args.particles}")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 1.0):
        raise ValueError(f"--duration: expected more than 1 s, got {args.duration}")
    if args.drive and args.pmmh_iters is not None and 0 < args.pmmh_iters < 8:
        raise ValueError(f"--pmmh-iters: expected 0 (skip) or at least 8 (4 warm-up, 4 kept), "
                         f"got {args.pmmh_iters}")
    out_dir = Path(args.out)
    if args.drive and args.out == parser().get_default("out"):
        out_dir = Path(args.out + "_drive")
    out_dir.mkdir(parents=True, exist_ok=True)
    print(PAPER)
    return main_drive(args, out_dir) if args.drive else main_simulation(args, out_dir)
