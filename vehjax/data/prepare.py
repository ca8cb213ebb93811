"""Preparing a recorded drive's virtual yaw rate before filtering (Berntorp & Di Cairano 2018,
eq. 10, on a real car).

Eq. 10 reads the yaw rate from the rear wheel speeds, r_virt = (v_rr - v_rl) / l_T, and the paper
takes it as unbiased with a small known std. On a recorded drive two things break that:

* **Bursts.** Wheel speeds have bursts (on the shipped comma2k19 segment |r_virt - gyro| reaches
  20 deg/s against a noise core of about 1 deg/s): at the paper's 0.5 deg/s they are 40-sigma
  samples that empty a particle filter's weights. :func:`gate_virtual_yaw` makes the samples far
  from the gyro missing (NaN), which every vehjax filter skips.
* **Scale.** Rear rolling radii that differ by the fraction eps make r_virt read
  r + eps vx / l_T (:func:`vehjax.models.virtual_yaw_reading`). The difference gyro - r_virt =
  b - eps vx / l_T + noise holds no yaw rate, so eps and the gyro's constant bias b follow from
  the two sensors alone: :func:`virtual_yaw_scale` (least squares over the drive),
  :func:`online_virtual_scale` (its causal, recursive form), and, for validation against a pose
  reference, :func:`pose_virtual_scale`. :func:`remove_virtual_scale` takes eps vx / l_T out.

:func:`prepare_drive` does both on a :class:`~vehjax.data.Drive` for
:class:`~vehjax.models.SingleTrackBank`: eps from every sample (the bursts are one-sided, so
gating first would bias it), then the gate, then the scale removed.

Limits: eps is identifiable only where vx varies; a constant gyro bias is assumed over the
samples used; the gate needs a gyro that is itself free of bursts.
"""

from __future__ import annotations

import math

import numpy as np

from .. import validation
from ..models.bank_scale import TRACK

__all__ = ["gate_virtual_yaw", "virtual_yaw_scale", "online_virtual_scale", "pose_virtual_scale",
           "remove_virtual_scale", "prepare_drive"]

DEG = math.pi / 180.0

#: SingleTrackBank's measurement columns used here: the yaw gyro and the virtual yaw rate
GYRO, R_VIRT = 1, 4


def gate_virtual_yaw(gyro, r_virt, limit):
    """r_virt with the samples more than ``limit`` [rad/s] from the gyro set to NaN (missing):
    the wheel-speed bursts of a log (|r_virt - gyro| reaches 20 deg/s on the shipped segment; a
    Gaussian noise of the paper's 0.5 deg/s std would make them 40-sigma events that empty a
    particle filter's weights). ``limit`` <= 0 or inf: no gate. Returns (r_virt (T,), number
    gated)."""
    r_virt = np.array(r_virt, float)
    if not limit > 0 or not np.isfinite(limit):
        return r_virt, 0
    bad = np.abs(r_virt - np.asarray(gyro, float)) > limit
    r_virt[bad] = np.nan
    return r_virt, int(bad.sum())


def virtual_yaw_scale(gyro, r_virt, vx, track):
    """(eps, gyro bias [rad/s]): the rear rolling-radius mismatch and the gyro's constant bias
    from the two yaw-rate sensors alone.

    With r_virt = r + eps vx / l_T + noise (eq. 10 from linear wheel speeds whose rolling radii
    differ by the fraction eps) and gyro = r + b + noise, the difference gyro - r_virt =
    b - eps vx / l_T + noise does not contain r: least squares over the samples where all three
    are finite. Identifiable when vx varies (8 to 20 m/s on the shipped segment).

    Args:
        gyro, r_virt: (T,) yaw rates [rad/s]; vx: (T,) speed [m/s]; track: rear track l_T [m].
    """
    gyro = validation.shaped("gyro", gyro, (None,))  # non-finite samples: skipped
    r_virt, vx = (validation.shaped(k, a, gyro.shape) for k, a in (("r_virt", r_virt),
                                                                   ("vx", vx)))
    ok = np.isfinite(gyro) & np.isfinite(r_virt) & np.isfinite(vx)
    A = np.stack([np.ones(ok.sum()), -vx[ok] / track], axis=1)
    (b, eps), *_ = np.linalg.lstsq(A, gyro[ok] - r_virt[ok], rcond=None)
    return float(eps), float(b)


def online_virtual_scale(gyro, r_virt, vx, track, *, noise_std=1.0 * DEG, bias_std=0.5 * DEG,
                         eps_std=1e-3):
    """Causal estimates (eps_t, gyro bias b_t [rad/s]), each (T,), from the samples up to t:
    the recursive form of :func:`virtual_yaw_scale`, run online beside the filters.

    A Kalman filter on the constant theta = (b, eps) ~ N(0, diag(bias_std^2, eps_std^2)) with
    the measurement z_t = gyro_t - r_virt_t = b - eps vx_t / l_T + N(0, noise_std^2), which
    does not contain the yaw rate. With constant theta its posterior after t samples is the
    information form Lambda_t = Lambda_0 + sum H_k^T H_k / s^2, eta_t = sum H_k^T z_k / s^2,
    theta_t = Lambda_t^-1 eta_t (a 2 x 2 solve per step); samples with a non-finite z or vx
    add nothing. With a diffuse prior theta_T is the least squares of ``virtual_yaw_scale``.

    Args:
        gyro, r_virt: (T,) yaw rates [rad/s]; vx: (T,) speed [m/s]; track: l_T [m].
        noise_std: std of gyro - r_virt [rad/s] (default 1 deg/s); bias_std, eps_std: prior
            stds [rad/s] (default 0.5 deg/s), [-].
    """
    gyro = validation.shaped("gyro", gyro, (None,))  # non-finite samples: skipped
    r_virt, vx = (validation.shaped(k, a, gyro.shape) for k, a in (("r_virt", r_virt),
                                                                   ("vx", vx)))
    noise_std, bias_std, eps_std = (validation.number(name, v, 0.0, what="a positive std")
                                    for name, v in (("noise_std", noise_std),
                                                    ("bias_std", bias_std), ("eps_std", eps_std)))
    z = gyro - r_virt
    ok = np.isfinite(z) & np.isfinite(vx)
    H = np.stack([np.ones_like(vx), -np.where(ok, vx, 0.0) / track], axis=1) * ok[:, None]
    z = np.where(ok, z, 0.0)
    lam = np.cumsum(H[:, :, None] * H[:, None, :], axis=0) / noise_std**2
    lam += np.diag([bias_std**-2, eps_std**-2])[None]
    eta = np.cumsum(H * z[:, None], axis=0) / noise_std**2
    theta = np.linalg.solve(lam, eta[:, :, None])[:, :, 0]
    return theta[:, 1], theta[:, 0]


def pose_virtual_scale(r_virt, ref_r, vx, track):
    """eps from a pose reference: least squares of r_virt - r_pose on vx / l_T (no intercept)
    [-], over the samples where both yaw rates are finite. For validation only: a user's drive
    rarely has a pose; :func:`virtual_yaw_scale` needs none."""
    ok = np.isfinite(r_virt) & np.isfinite(ref_r)
    a = vx[ok] / track
    return float(a @ (r_virt[ok] - ref_r[ok]) / (a @ a))


def remove_virtual_scale(r_virt, eps, vx, track):
    """r_virt with the rolling-radius mismatch's reading eps vx / l_T removed [rad/s]; ``eps``
    a scalar or (T,) (a causal estimate per step)."""
    return r_virt - eps * vx / track


def prepare_drive(drive, model, *, seconds=None, gate=None, track=TRACK):
    """(U (T, 2), Y (T, 5)): a drive's inputs and SingleTrackBank measurements over its first
    ``seconds`` (None: all), its virtual yaw rate ready for a filter that takes it unbiased.

    In this order: eps by least squares from every sample (:func:`virtual_yaw_scale`; the
    bursts are one-sided, so gating first biases it), the bursts more than ``gate`` [rad/s]
    from the gyro made missing (:func:`gate_virtual_yaw`; None: not gated), eps vx / l_T
    removed (:func:`remove_virtual_scale`).

    Args:
        drive: anything with ``inputs(model)`` and ``measurements(model, track=...)``, e.g.
            :func:`~vehjax.data.load_comma2k19`'s drive.
        model: a :class:`~vehjax.models.SingleTrackBank` (outputs ay, r, roll_rate, phi, r_virt).
        track: the rear track l_T [m] the wheel speeds are read with.
    """
    U, Y = drive.inputs(model), drive.measurements(model, track=track)
    T = len(U) if seconds is None else min(len(U), int(round(seconds / model.dt)))
    U, Y = U[:T], Y[:T].copy()
    eps, _ = virtual_yaw_scale(Y[:, GYRO], Y[:, R_VIRT], U[:, 0], track)
    if gate is not None:
        Y[:, R_VIRT], _ = gate_virtual_yaw(Y[:, GYRO], Y[:, R_VIRT], gate)
    Y[:, R_VIRT] = remove_virtual_scale(Y[:, R_VIRT], eps, U[:, 0], track)
    return U, Y
