"""`vehjax reproduce berntorp2018` (paper 004) at a reduced size, and a smoke test of
`vehjax bench marginalized`. The marginalized PF takes tens of seconds to compile on CPU, so
each test compiles it as few times as it can."""

import contextlib
import io
import re

import jax.numpy as jnp
import numpy as np
import pytest

from vehjax.reproduce import berntorp2018, load


def _run(argv):
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = berntorp2018.main(argv)
    return rc, buf.getvalue()


def _links_exist(out):
    report = (out / "report.md").read_text()
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report)
    for name in links:
        assert (out / name).stat().st_size > 0, name
    return report, links


def _row(text, label):
    line = next(ln for ln in text.splitlines() if ln.startswith(f"| {label}"))
    return line.split("|")[2:-1]


def test_registered_with_a_citation():
    assert load("berntorp2018") is berntorp2018
    assert "Berntorp" in berntorp2018.PAPER and "2018" in berntorp2018.PAPER
    assert berntorp2018.parser().get_default("runs") == 100


def test_citation_as_published():
    assert ("Noise-statistics learning of automotive-grade sensors using adaptive marginalized "
            "particle filtering") in berntorp2018.PAPER
    assert "Journal of Dynamic Systems, Measurement, and Control" in berntorp2018.PAPER
    assert "TR2018-181" in berntorp2018.PAPER
    assert "Noise-statistics learning" in berntorp2018.parser().description


@pytest.mark.slow  # a reduced study: `pytest -m slow` (README)
def test_simulation_study(tmp_path):
    rc, text = _run(["--runs", "3", "--duration", "20", "--particles", "50", "--seed", "1",
                     "--out", str(tmp_path)])
    assert rc == 0
    report, links = _links_exist(tmp_path)
    assert len(links) == 5 and "Steady-state" in report
    mean, worst, _ = _row(text, "steering offset error [deg]")
    assert np.isfinite(float(mean)) and float(worst) < 0.28  # better than ignoring the offset
    for s in ("ay", "r", "roll_rate"):
        rel = float(_row(text, f"{s} std relative error")[0])
        assert -0.9 < rel < 1.0, (s, rel)  # started at +1 (twice the truth)
    assert float(_row(text, "bank phi RMS error")[0]) < 1.0  # deg; the bank reaches 6 deg
    assert float(_row(text, "r RMS error")[0]) < 0.3  # deg/s, the gyro's own noise


@pytest.mark.slow  # a reduced study: `pytest -m slow` (README)
def test_drive_study(tmp_path):
    rc, text = _run(["--drive", "--runs", "2", "--duration", "15", "--particles", "50",
                     "--pmmh-iters", "8", "--pmmh-particles", "16", "--pmmh-duration", "5",
                     "--pmmh-likelihood", "bootstrap", "--rvirt-scale", "online",
                     "--out", str(tmp_path)])  # online: its rows are checked below
    assert rc == 0
    report, links = _links_exist(tmp_path)
    assert len(links) == 3 and "EKF" in report  # Fig. 8, 9, 10 (bank)
    roll = _row(text, "bank angle - pose roll")
    assert float(roll[0].split()[1]) < 2.0  # deg: the bank estimate follows the car's roll
    off = float(_row(text, "steering offset, road wheel")[0])
    assert abs(off) < 1.0  # deg at the road wheel
    for label in ("raw gyro", "gyro - MPF bias", "gyro - EKF bias", "MPF yaw-rate estimate",
                  "EKF yaw-rate estimate"):
        rms, mx, share = (float(v) for v in _row(text, label))
        assert 0 < rms < 1.0 and mx < 3.0 and 0 <= share <= 1, label
    eps = float(re.search(r"rolling-radius mismatch eps = ([-+0-9.e]+)", text)[1])
    assert -8e-4 < eps < -1e-4                       # 15 s of it; -4.0e-4 from the whole segment
    for label in ("MPF vy estimate", "EKF vy estimate", "vy = 0"):
        rms, mx = (float(v) for v in _row(text, label))
        assert 0 < rms < 0.5 and mx < 1.0, label
    assert "Virtual yaw rate's scale" in report
    # the scale learnt online: negative, about the offline value's size (15 s of data only)
    for label in ("online, causal recursive least squares", "augmented EKF online, eps a state"):
        e = float(_row(text, label)[0])
        assert -10 < e < -1, (label, e)                               # [1e-4]; offline -4.0
    # smoothed offset, biases, eps and bank over the drive (#29), with their 2-std bands
    for label in ("smoothed steering offset", "smoothed ay bias", "smoothed yaw-gyro bias",
                  "smoothed eps", "smoothed bank angle", "smoothed roll-gyro bias"):
        mean, span, two_sd, _ = _row(text, label)
        lo, hi = (float(v) for v in re.findall(r"[-+][0-9]+\.[0-9]+", span))
        assert lo <= float(mean) <= hi and float(two_sd) > 0, label
    r = _row(text, "smoothed yaw rate (extended RTS)")
    assert 0 < float(r[0]) < 1.0
    # the MPF's own smoother beside it (#29 item 4): offset, biases, stds and bank over the drive
    for label in ("MPF-smoothed steering offset", "MPF-smoothed ay bias",
                  "MPF-smoothed yaw-gyro bias", "MPF-smoothed roll-gyro bias",
                  "MPF-smoothed steering std", "MPF-smoothed ay std", "MPF-smoothed yaw-gyro std",
                  "MPF-smoothed roll-gyro std", "MPF-smoothed bank angle"):
        mean, span, two_sd, end = _row(text, label)
        lo, hi = (float(v) for v in re.findall(r"[-+][0-9]+\.[0-9]+", span))
        assert lo <= float(mean) <= hi and float(two_sd) > 0 and np.isfinite(float(end)), label
        if "std" in label:
            assert lo > 0, label
    assert abs(float(_row(text, "MPF-smoothed steering offset")[0])) < 1.0  # deg, road wheel
    roll_s = _row(text, "MPF-smoothed bank - pose roll")
    assert float(roll_s[0].split()[1]) < 2.0  # deg, as the filter's bank
    assert "MPF smoother (filter + backward simulation" in text
    assert "distinct particles at t = 0" in report and "backward ESS" in report
    # the PMMH offline reference: one row per quantity with R-hat and ESS
    assert "particle marginal Metropolis-Hastings" in report and "PMMH likelihood: bootstrap" in report
    for name in ("delta_offset [deg]", "eps [1e-4]", "bias[ay]", "bias[r]", "R[ay]", "R[r] [",
                 "R[r_virt]", "input[delta]"):
        mean, sd, interval, rhat, ess = _row(text, name)
        assert np.isfinite(float(mean)) and float(sd) >= 0 and float(rhat) > 0 and float(ess) > 0


@pytest.mark.slow  # a study: `pytest -m slow` (README)
def test_bench_marginalized_smoke(capsys):
    from vehjax.cli import load_benchmark

    bench = load_benchmark("marginalized")
    assert bench.parser().get_default("runs") == 100
    assert bench.main(["--particles", "20,40", "--steps", "20", "--runs", "1", "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    assert "target: 1 run" in out and "linearity" in out
    assert "operations and bytes accessed per particle-step" in out and "GFLOP/s" in out
    assert "compiled with XLA's defaults" in out


def test_online_scale_of_the_ekf_matches_the_offline_estimate_on_the_drive():
    """On the shipped drive the augmented EKF, fed the raw virtual yaw rate, learns the rear
    rolling-radius mismatch online: same sign and size as the offline least squares from the
    sensors (virtual_yaw_scale) and the pose's."""
    import vehjax as vj
    from vehjax.filters import gaussian

    drive = vj.data.load_comma2k19()
    model = vj.models.SingleTrackBank(dt=drive.dt)
    U, Y = drive.inputs(model), np.asarray(drive.measurements(model, track=berntorp2018.TRACK))
    eps_off, _ = berntorp2018.virtual_yaw_scale(Y[:, 1], Y[:, 4], U[:, 0], berntorp2018.TRACK)
    eps_pose = berntorp2018.pose_virtual_scale(Y[:, 4], np.asarray(drive.reference["yaw_rate"]),
                                               U[:, 0], berntorp2018.TRACK)
    am = berntorp2018.augmented_model(model)
    Q, R = berntorp2018.ekf_noise(False)
    D = berntorp2018.DEG
    P0 = np.array([0.1, 0.5 * D, 0.5 * D, 0.5, 0.5 * D, 1e-3]) ** 2
    out = vj.filter(gaussian.ekf(am, Q, R), Y[:, [0, 1, 4]], U, x0=np.zeros(6), P0=P0)
    eps_end = float(out.states[-1, 5])
    sd_end = float(np.sqrt(out.covariances[-1, 5, 5]))
    assert -6e-4 < eps_off < -2e-4 and -6e-4 < eps_pose < -2e-4      # about -4e-4
    assert abs(eps_end - eps_off) < 3 * sd_end + 0.25 * abs(eps_off), (eps_end, sd_end, eps_off)
    assert sd_end < 0.5 * abs(eps_off)                               # learnt, not the prior


def test_particle_gibbs_process_noise_stands_for_the_steering_noise():
    """Particle Gibbs takes additive noise only: the steering-input std enters as per-state
    process stds, sqrt(PMMH_Q + (B s)^2) with B = d f / d delta, here against central finite
    differences of the reference model's transition; the priors swap input[delta] for them."""
    from vehjax.models import SingleTrackBank

    pm = berntorp2018.pmmh_model(SingleTrackBank(dt=0.01))
    U = np.array([[15.0, 0.01], [17.0, -0.01], [np.nan, 0.0]])  # vx [m/s], delta [rad]
    u = np.nanmean(U, axis=0)
    h = 1e-6
    f = [np.asarray(pm.transition(jnp.zeros(2), jnp.asarray(u + [0.0, d]), jnp.asarray(pm.theta)))
         for d in (h, -h)]
    B = (f[0] - f[1]) / (2 * h)
    assert abs(B[1]) > 1e-4  # steering moves the yaw rate within a step
    s = 0.2 * berntorp2018.DEG
    np.testing.assert_allclose(berntorp2018.pg_process_std(pm, U, 0.0),
                               np.sqrt(berntorp2018.PMMH_Q), rtol=1e-12)
    np.testing.assert_allclose(berntorp2018.pg_process_std(pm, U, s),
                               np.sqrt(berntorp2018.PMMH_Q + (B * s) ** 2), rtol=1e-6)
    pr = berntorp2018.pg_priors(pm, U)
    assert "input[delta]" not in pr and {"Q[vy]", "Q[r]"} <= set(pr)
    assert set(pr) - {"Q[vy]", "Q[r]"} == set(berntorp2018.pmmh_priors()) - {"input[delta]"}
    assert all(name in berntorp2018.PMMH_UNITS for name in pr)


def test_pmmh_check_states_what_it_checks():
    """The offline reference's per-sampler sentence: met only when every quantity has split
    R-hat < 1.1 and ESS >= 100, naming those that fail; the bootstrap PF's log-likelihood std
    against Doucet et al.'s 1-1.5 band; the per-sampler defaults reach the CLI."""
    from types import SimpleNamespace

    good = SimpleNamespace(names=("a", "b"), rhat=np.array([1.01, 1.09]), ess=np.array([150, 100]))
    assert "met (max R-hat 1.090, min ESS 100)" in berntorp2018.pmmh_check(good, {})
    bad = SimpleNamespace(names=("a", "b"), rhat=np.array([1.01, 1.2]), ess=np.array([99, 300]))
    text = berntorp2018.pmmh_check(bad, {})
    assert "NOT met for a (R-hat 1.01, ESS 99), b (R-hat 1.20, ESS 300)" in text
    noisy = berntorp2018.pmmh_check(good, {"loglik_std": 7.5, "particles": 64})
    assert "std 7.50 nats" in noisy and "far above it" in noisy
    assert "far above" not in berntorp2018.pmmh_check(good, {"loglik_std": 1.2, "particles": 9})
    args = berntorp2018.parser().parse_args(["--drive"])
    assert args.pmmh_iters is None and args.pmmh_particles is None   # per-sampler defaults
    assert set(berntorp2018.PMMH_ITERS) == {"kalman", "mpf", "bootstrap", "pg", "cpm"}
    assert set(berntorp2018.PMMH_PARTICLES) == {"mpf", "bootstrap", "pg", "cpm"}
    assert berntorp2018.PMMH_ITERS["cpm"] == berntorp2018.PMMH_ITERS["bootstrap"]
    assert berntorp2018.PMMH_PARTICLES["cpm"] == berntorp2018.PMMH_PARTICLES["bootstrap"]
    # the correlated chain: the difference's std beside two independent estimates'
    cpm = berntorp2018.pmmh_check(good, {"loglik_diff_std": 11.0, "loglik_std": 14.0,
                                         "particles": 64, "correlation": 0.999}, "cpm")
    assert "differ by a log-likelihood std of 11.00 nats" in cpm and "against 19.80" in cpm
    assert "far above the 1-2 nats" in cpm
    assert "small enough" in berntorp2018.pmmh_check(
        good, {"loglik_diff_std": 1.5, "loglik_std": 14.0, "particles": 64}, "cpm")
    assert args.pmmh_likelihood == "standard" and args.mpf_smoother == "ffbsi"
    # the marginalized PF's likelihood: its own wording, no "far above" verdict on the bootstrap
    mpf = berntorp2018.pmmh_check(good, {"loglik_std": 2.0, "particles": 256}, "mpf")
    assert "marginalized PF's log-likelihood estimate (N = 256) has std 2.00" in mpf
    assert "above it" in mpf and "far above" not in mpf


def test_posterior_agreement_z_scores():
    """The MPF chain against the exact one: z = difference of means / sqrt(s_a^2 / ESS_a +
    s_b^2 / ESS_b) and the std ratio, in the report's units, written out here."""
    from types import SimpleNamespace

    a = SimpleNamespace(names=("eps", "R[ay]"), mean=np.array([-4e-4, 0.31]),
                        std=np.array([1e-4, 0.01]), ess=np.array([100.0, 400.0]))
    b = SimpleNamespace(names=("R[ay]", "eps"), mean=np.array([0.30, -4.5e-4]),
                        std=np.array([0.02, 2e-4]), ess=np.array([100.0, 25.0]))
    rows = berntorp2018.posterior_agreement(a, b)
    z_eps = (-4e-4 + 4.5e-4) / np.sqrt(1e-8 / 100 + 4e-8 / 25)
    z_ay = 0.01 / np.sqrt(1e-4 / 400 + 4e-4 / 100)
    assert rows[0] == ("eps [1e-4]", "-4", "-4.5", f"{z_eps:+.2f}", "0.500")
    assert rows[1] == ("R[ay] [m/s^2]", "+0.31", "+0.3", f"{z_ay:+.2f}", "0.500")
