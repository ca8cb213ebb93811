"""vehjax.data.prepare: a recorded drive's virtual yaw rate made ready for filtering (bursts
gated, the rear rolling-radius scale estimated and removed). Each function on a tiny case whose
answer is written out here, then the statistical checks (moved from the berntorp2018 tests)."""

import math

import numpy as np
import pytest

import vehjax as vj
from vehjax.data import prepare


def test_gate_by_hand():
    gyro = np.array([0.0, 0.1, 0.2, 0.3])
    r_virt = np.array([0.05, 0.5, 0.2, np.nan])          # |diff| 0.05, 0.4, 0, nan
    g, n = prepare.gate_virtual_yaw(gyro, r_virt, 0.1)
    np.testing.assert_array_equal(g, [0.05, np.nan, 0.2, np.nan])
    assert n == 1
    for off in (0.0, -1.0, np.inf):                      # no gate: a copy, nothing counted
        g, n = prepare.gate_virtual_yaw(gyro, r_virt, off)
        assert n == 0 and g is not r_virt
        np.testing.assert_array_equal(g, r_virt)


def test_virtual_yaw_scale_by_hand():
    # noise-free: gyro - r_virt = b - eps vx / l_T exactly, so two speeds fix both unknowns
    track, eps, b = 2.0, -1e-3, 0.01
    vx = np.array([10.0, 20.0, 30.0, np.nan])
    r = np.array([0.1, -0.2, 0.05, 0.0])                  # cancels in the difference
    gyro = r + b
    r_virt = r + eps * vx / track                         # the nan speed's sample is skipped
    e, bias = prepare.virtual_yaw_scale(gyro, r_virt, vx, track)
    assert e == pytest.approx(eps, rel=1e-10) and bias == pytest.approx(b, rel=1e-10)


def test_online_virtual_scale_by_hand():
    # one sample, unit prior and noise: theta = (H^T H + I)^-1 H^T z with H = (1, -vx / l_T)
    z, vx, track = 0.3, 2.0, 1.0                          # H = (1, -2), H^T z = (0.3, -0.6)
    e, b = prepare.online_virtual_scale([z], [0.0], [vx], track, noise_std=1.0,
                                        bias_std=1.0, eps_std=1.0)
    # (H^T H + I) = [[2, -2], [-2, 5]], det 6, inverse [[5, 2], [2, 2]] / 6
    assert b[0] == pytest.approx((5 * 0.3 + 2 * -0.6) / 6)        # 0.05
    assert e[0] == pytest.approx((2 * 0.3 + 2 * -0.6) / 6)        # -0.1


def test_pose_virtual_scale_by_hand():
    vx, track = np.array([10.0, 20.0, np.nan]), 2.0
    ref = np.array([0.1, 0.2, 0.3])
    r_virt = ref + 3e-4 * vx / track                     # the third sample's vx is nan ...
    r_virt[2] = np.nan                                   # ... and its r_virt missing
    assert prepare.pose_virtual_scale(r_virt, ref, vx, track) == pytest.approx(3e-4)


def test_remove_virtual_scale_by_hand():
    out = prepare.remove_virtual_scale(np.array([0.1, 0.2]), 2e-3, np.array([10.0, 20.0]), 4.0)
    np.testing.assert_allclose(out, [0.1 - 0.005, 0.2 - 0.01])
    steps = prepare.remove_virtual_scale(np.array([0.1, 0.2]), np.array([0.0, 1e-3]),
                                         np.array([10.0, 20.0]), 4.0)
    np.testing.assert_allclose(steps, [0.1, 0.2 - 0.005])


class _Tiny:
    """A three-step drive: inputs (vx, delta) and SingleTrackBank measurements, noise-free."""

    def inputs(self, model):
        return np.array([[10.0, 0.0], [20.0, 0.0], [30.0, 0.0]])

    def measurements(self, model, track):
        r = np.array([0.1, 0.0, -0.1])
        vx = self.inputs(model)[:, 0]
        Y = np.zeros((3, 5))
        Y[:, 1] = r + 0.01                              # gyro with a bias
        Y[:, 4] = r + (-1e-3) * vx / track              # r_virt with a scale error
        Y[2, 4] += 1.0                                   # ... and a burst at the last step
        return Y


def test_prepare_drive_by_hand():
    model = vj.models.SingleTrackBank(dt=0.01)
    drive = _Tiny()
    # eps from every sample (the burst included), then the gate, then the scale removed
    Y0 = drive.measurements(model, 2.0)
    eps, _ = prepare.virtual_yaw_scale(Y0[:, 1], Y0[:, 4], drive.inputs(model)[:, 0], 2.0)
    U, Y = prepare.prepare_drive(drive, model, gate=0.5, track=2.0)
    np.testing.assert_array_equal(U, drive.inputs(model))
    assert np.isnan(Y[2, 4])                              # the burst is missing
    np.testing.assert_allclose(Y[:2, 4], Y0[:2, 4] - eps * U[:2, 0] / 2.0)
    np.testing.assert_array_equal(Y[:, :4], Y0[:, :4])   # the other outputs untouched
    U2, Y2 = prepare.prepare_drive(drive, model, seconds=0.02, track=2.0)  # two steps, no gate
    assert U2.shape == (2, 2) and np.all(np.isfinite(Y2[:, 4]))


def test_prepare_drive_on_the_shipped_drive():
    """The shipped segment as ``vehjax reproduce berntorp2018 --drive`` and noise-learning read
    it: the scale estimated from every sample (about -4e-4), bursts gated at 5 deg/s."""
    drive = vj.data.load_comma2k19()
    model = vj.models.SingleTrackBank(dt=drive.dt)
    U, Y = prepare.prepare_drive(drive, model, gate=5.0 * prepare.DEG)
    raw = drive.measurements(model, track=prepare.TRACK)
    assert U.shape[0] == Y.shape[0] == raw.shape[0]
    gated = np.isnan(Y[:, 4]) & np.isfinite(raw[:, 4])
    assert 50 < gated.sum() < 300                          # the wheel-speed bursts
    eps, _ = prepare.virtual_yaw_scale(raw[:, 1], raw[:, 4], U[:, 0], prepare.TRACK)
    assert -6e-4 < eps < -2e-4
    ok = np.isfinite(Y[:, 4])
    np.testing.assert_allclose(Y[ok, 4], raw[ok, 4] - eps * U[ok, 0] / prepare.TRACK)


def test_virtual_yaw_scale_from_the_sensors_alone():
    # synthetic: a yaw rate the estimate never sees, a gyro bias, a rolling-radius mismatch
    rng = np.random.default_rng(0)
    T, track, eps, bias = 6000, 1.61, -4e-4, 6e-4
    t = np.arange(T) * 0.01
    vx = 14.0 + 6.0 * np.sin(2 * np.pi * t / 40.0)
    r = 0.02 * np.sin(2 * np.pi * t / 7.0) + 0.01 * rng.standard_normal(T).cumsum() / 50
    gyro = r + bias + 0.003 * rng.standard_normal(T)
    r_virt = r + eps * vx / track + 0.008 * rng.standard_normal(T)
    r_virt[::97] = np.nan                                           # missing samples skipped
    e, b = prepare.virtual_yaw_scale(gyro, r_virt, vx, track)
    # least-squares standard errors of the two coefficients, from the noise written above
    A = np.stack([np.ones(T), -vx / track], 1)
    se = np.sqrt(np.diag(np.linalg.inv(A.T @ A))) * math.hypot(0.003, 0.008)
    assert abs(b - bias) < 4 * se[0] and abs(e - eps) < 4 * se[1], (b, e, se)


def test_online_virtual_scale_is_recursive_least_squares():
    """The causal estimate at every step equals the regularised least squares over the samples
    so far (numpy lstsq on the stacked prior and data rows), and with a diffuse prior its last
    value equals virtual_yaw_scale's."""
    rng = np.random.default_rng(3)
    T, track = 400, 1.61
    vx = 10.0 + 8.0 * rng.random(T)
    gyro = 0.01 * rng.standard_normal(T) + 7e-4
    r_virt = gyro - 7e-4 + 4e-4 * vx / track + 0.004 * rng.standard_normal(T)
    r_virt[5] = np.nan
    s, pb, pe = 0.004, 1e-3, 2e-3
    eps_t, b_t = prepare.online_virtual_scale(gyro, r_virt, vx, track, noise_std=s,
                                                    bias_std=pb, eps_std=pe)
    for t in (3, 50, T - 1):
        z = (gyro - r_virt)[: t + 1]
        ok = np.isfinite(z)
        A = np.vstack([np.stack([np.ones(ok.sum()), -vx[: t + 1][ok] / track], 1) / s,
                       np.diag([1 / pb, 1 / pe])])
        rhs = np.concatenate([z[ok] / s, [0.0, 0.0]])
        (b, e), *_ = np.linalg.lstsq(A, rhs, rcond=None)
        assert b_t[t] == pytest.approx(b, rel=1e-9, abs=1e-15)
        assert eps_t[t] == pytest.approx(e, rel=1e-9, abs=1e-15)
    e_d, b_d = prepare.online_virtual_scale(gyro, r_virt, vx, track, noise_std=s,
                                                  bias_std=10.0, eps_std=10.0)
    e_ls, b_ls = prepare.virtual_yaw_scale(gyro, r_virt, vx, track)
    assert e_d[-1] == pytest.approx(e_ls, rel=1e-6) and b_d[-1] == pytest.approx(b_ls, rel=1e-6)
    assert eps_t[-1] == pytest.approx(4e-4, abs=1e-4)
    with pytest.raises(ValueError, match="noise_std"):
        prepare.online_virtual_scale(gyro, r_virt, vx, track, noise_std=0.0)
    g, n = prepare.gate_virtual_yaw(gyro, np.where(np.arange(T) == 7, 1.0, r_virt), 0.1)
    assert n == 1 and np.isnan(g[7]) and np.isnan(g[5])
