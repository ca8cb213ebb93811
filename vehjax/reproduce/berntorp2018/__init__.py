"""Berntorp & Di Cairano 2018 (paper 004): noise-statistics learning with the adaptive
marginalized particle filter, in simulation (sec. 4, Fig. 3-7) and on a recorded drive (sec. 5,
Fig. 8-9, Remark 1).

    vehjax reproduce berntorp2018 [--runs 100] [--particles 100] [--duration 180] [--seed 0]
                                  [--out out/berntorp2018]
    vehjax reproduce berntorp2018 --drive [--runs 100] [--particles 500] [--out ...]

The package: :mod:`.study` (the simulation study), :mod:`.drive` (the drive study, in named
steps), :mod:`.pmmh` (the offline reference's set-up), :mod:`.report` (tables, figures,
verdicts), :mod:`.cli` (options and ``main``). What a user needs outside this study is public
elsewhere: the simulated scenario and the paper's filter set-ups in :mod:`vehjax.studies.banked_road`,
the drive's preparation (burst gate, the virtual yaw rate's scale) in
:mod:`vehjax.data.prepare`, the eps-carrying models in :mod:`vehjax.models.bank_scale`.
Measurements behind the choices below: ``benchmarks/results/notes_berntorp2018.md``.

Simulation (sec. 4): the scenario of :mod:`vehjax.studies.banked_road` (the shipped comma2k19 RAV4
segment's speed and steering looped to ``--duration`` s, the 0.28 deg offset, a piecewise-linear
bank, random-walk sensor biases), the filter ``build_sim_filter`` (N = ``--particles``,
lambda = 0.995, initial std guesses twice the truth); steady state: the last third of the drive.

Drive (sec. 5, ``--drive``):

* Filter variant (``--variant``, default ``bank``): the paper's filter with the bank in a
  Kalman filter per particle, sensors ay, yaw gyro and roll gyro with unknown bias and std, the
  bank angle phi as a known-std output that is NaN at every step (the log has no bank sensor:
  the roll gyro and the vehicle model carry the bank), the virtual yaw rate with known std
  0.5 deg/s. ``planar`` is Remark 2's filter (ay, r; r_virt known; no bank states: the
  model's bank states are held at zero by a negligible P0, see ``marginalized_pf``'s
  ``linear_states``; a spread of 1e-3 let the particles' constant bank accelerations integrate
  into a bank that ay read as a bias).
* N = 500, lambda = 0.999, 100 executions in one :func:`vehjax.run` call (the same measurements
  tiled over runs, a different key each).
* No steering-offset ground truth exists for this drive (the paper's came from an offline
  PMCMC fit); the table gives the executions' mean and spread after the transient.
* The virtual yaw rate's scale: eq. 10 with linear wheel speeds reads
  r_virt = r + eps vx / l_T when the rear rolling radii differ by the fraction eps
  (:func:`vehjax.models.virtual_yaw_reading`). The paper takes r_virt as unbiased; on this car
  it reads about -0.24 deg/s off the pose. ``--rvirt-scale offline`` (default): eps from
  :func:`vehjax.data.virtual_yaw_scale` (least squares of gyro - r_virt on (1, -vx / l_T) over
  the drive, the gyro's constant bias the other unknown; the yaw rate itself cancels; the
  sensors only, not the pose) is removed from r_virt before the filters. ``online``: a causal
  recursive least-squares estimate of eps (:func:`vehjax.data.online_virtual_scale`) corrects
  r_virt for the MPF, the augmented EKF carries eps as a state. ``state``: eps also a constant
  state in each MPF particle's Kalman filter beside the bank
  (:class:`vehjax.models.VirtualScaleBank`: eps enters r_virt affinely, has no process noise
  and is not forgotten). ``none``: the paper's reading. Offline is the default: the online eps,
  poorly determined early in the drive, pulls the ay bias and the bank off the pose.
  :func:`vehjax.data.pose_virtual_scale` gives the pose's eps. The wheel speeds of this log
  have bursts (|r_virt - gyro| up to 20 deg/s; the core of r_virt's noise is about 1 deg/s):
  ``--rvirt-gate`` (default 5 deg/s) makes those samples missing for every filter
  (:func:`vehjax.data.gate_virtual_yaw`); without it the bootstrap PF of the PMMH loses all
  its weights early in the drive. The least squares of eps (offline and the causal one) use
  every sample: the bursts are one-sided, and gating first moves the offline eps away from the
  pose's; the augmented EKF, which sees the gated r_virt, inherits that sensitivity.
* Offline reference (sec. 5, ref. [28]): :mod:`.pmmh` (PMMH with the bootstrap PF's, the
  marginalized PF's and the exact Kalman likelihood, correlated PMMH, particle Gibbs with
  ancestor sampling; ``--pmmh-likelihood``); the report states for each sampler whether split
  R-hat < ``RHAT_MAX`` and ESS >= ``ESS_MIN`` for every quantity (:func:`.report.pmmh_check`).
* Smoothing: ``vehjax.smooth`` (extended RTS) of the augmented EKF gives the offset,
  biases, eps and (variant ``bank``) the bank over the drive given the whole drive. Beside
  it the MPF's own smoother (:mod:`vehjax.smoothers.marginalized`; ``--mpf-smooth-paths`` M,
  default 100, 0 skips it; ``--mpf-smoother``): one more execution of the drive's filter (its
  ``kalman_states``), M trajectories by backward simulation over all its particles (``ffbsi``,
  the default with ``kalman_states="linear"``) or its M ancestral paths (``ancestor``), each
  trajectory's Kalman states (the bank, eps) by an RTS given it, the noise statistics as the
  trajectories' estimates at each time; its offset, biases, stds and bank over the drive and
  the smoothed bank against the pose roll.
* The yaw gyro: its estimated bias is compared with ``drive.gyro_offset_vs_reference``; the
  bias-corrected yaw rate (gyro minus the estimated bias) and each filter's yaw-rate estimate
  with the pose reference yaw rate, after 15 s; the filters' lateral velocity vy with the
  pose's (the camera's velocity in the car frame; the camera's lever arm times r, < 0.01 m/s
  here, is not removed).
* Remark 1's "common approach": an EKF on the single-track model augmented with the steering
  offset and the ay and yaw-gyro biases as random-walk states
  (:func:`vehjax.models.bank_scale.augmented_model`), with fixed noise covariances (the MPF's
  initial guesses) on the same measurements.
"""

from __future__ import annotations

# the names the tests, the notebook checks and readers of the study reach through the package
from vehjax.studies.banked_road import (BANK_DEG, BANK_JERK_STD, BIAS_WALK, DEG, DRIVE_STD0, OFFSET,
                                PHI_STD, RVIRT_STD, SENSOR_STD, SENSOR_UNIT, SENSORS, STEER_STD,
                                bank_profile, build_drive_filter, build_sim_filter,
                                looped_inputs, simulate_truth)
from vehjax.data.prepare import (gate_virtual_yaw, online_virtual_scale, pose_virtual_scale,
                                 virtual_yaw_scale)
from vehjax.models.bank_scale import (TRACK, VirtualScaleBank, augmented_model,
                                      virtual_yaw_reading)

from .cli import main, parser
from .drive import MPF_SMOOTH_PATHS, ekf_noise, main_drive, run_drive
from .pmmh import (PG_MOVES, PG_STEP, PMMH_CORRELATION, PMMH_ITERS, PMMH_MIN_TARGET, PMMH_P0,
                   PMMH_PARTICLES, PMMH_Q, PMMH_UNITS, SAMPLER, pg_priors, pg_process_std,
                   pmmh_model, pmmh_priors, run_pmmh)
from .report import (ESS_MIN, LOGLIK_STD_BAND, PAPER, RHAT_MAX, pmmh_check, pmmh_rows,
                     posterior_agreement)
from .study import main_simulation, run_simulation

__all__ = ["PAPER", "parser", "main", "main_simulation", "run_simulation", "main_drive",
           "run_drive", "ekf_noise", "run_pmmh", "pmmh_model", "pmmh_priors", "pmmh_check",
           "pmmh_rows", "posterior_agreement", "pg_priors", "pg_process_std"]
