"""benchmarks/bench_fit.py (``vehjax bench fit``): its data come from a fine integrator that
agrees with scipy's solve_ivp of the single-track equations written out here in numpy, and its
--quick form runs (marked slow: it compiles two fits)."""

import numpy as np
import pytest
import scipy.integrate

from vehjax import cli

bench = cli.load_benchmark("fit")


def single_track_rhs(x, delta, vx, m=1500.0, iz=2700.0, lf=1.2, lr=1.5, cf=1.2e5, cr=1.4e5):
    """Linear single-track equations (textbook, small angles): (vy', r')."""
    vy, r = x
    ff = cf * (delta - (vy + lf * r) / vx)
    fr = cr * (lr * r - vy) / vx
    return np.array([(ff + fr) / m - vx * r, (lf * ff - lr * fr) / iz])


def test_fine_rollout_equals_solve_ivp():
    """50 samples of a held steering and speed profile: fine_rollout's states and outputs (ay, r)
    equal solve_ivp (RK45, rtol 1e-10) of the numpy equations to 1e-8."""
    import vehjax as vj

    T = 50
    rng = np.random.default_rng(0)
    us = np.stack([0.03 * rng.standard_normal(T), 15.0 + rng.uniform(0, 5, T)], axis=1)
    model = vj.models.SingleTrack(dt=bench.DT)
    xs, ys = bench.fine_rollout(model, np.zeros(2), us)
    x, ref = np.zeros(2), []
    for t in range(T):
        sol = scipy.integrate.solve_ivp(lambda _, z: single_track_rhs(z, *us[t]), (0, bench.DT),
                                        x, rtol=1e-10, atol=1e-12)
        x = sol.y[:, -1]
        ref.append(x)
    ref = np.array(ref)
    np.testing.assert_allclose(xs, ref, atol=1e-8)
    ay = np.array([single_track_rhs(ref[t], *us[t])[0] + us[t, 1] * ref[t, 1] for t in range(T)])
    np.testing.assert_allclose(ys[:, 0], ay, atol=1e-6)
    np.testing.assert_allclose(ys[:, 1], ref[:, 1], atol=1e-8)


@pytest.mark.parametrize("argv, words", [
    (["--steps", "5"], ["--steps", ">= 10", "'5'"]),
    (["--coverage-steps", "9"], ["--coverage-steps", ">= 10"]),
    (["--runs", "1"], ["--runs", ">= 2"]),
    (["--coverage", "--models", "bogus,3-DOF"], ["--models", "single-track, 3-DOF", "unknown: bogus"]),
])
def test_bad_options_refused_naming_the_option_and_what_it_takes(argv, words, capsys):
    """From Python: a ValueError naming the option; from the command line: that one line on
    stderr, nothing on stdout, exit code 2 (before any work)."""
    with pytest.raises(ValueError) as err:
        bench.main(argv)
    for w in words:
        assert w in str(err.value), (w, str(err.value))
    assert cli.main(["bench", "fit", *argv]) == 2
    io = capsys.readouterr()
    assert io.out == "" and len(io.err.splitlines()) == 1
    assert io.err.startswith("vehjax bench fit: error: argument " + argv[-2])
    for w in words:
        assert w in io.err


@pytest.mark.slow  # a study: `pytest -m slow` (README)
def test_bench_fit_quick(capsys):
    """--quick: the timed fit reports its compile time, evaluations and each fitted number
    against the truth; the coverage table has a row per fitted quantity with a fraction in
    [0, 1]."""
    assert cli.main(["bench", "fit", "--quick"]) == 0
    out = capsys.readouterr().out
    assert "optimizer scoring, derivatives forward" in out and "evaluations" in out
    for k in ("cf", "cr", "input[delta]", "R[ay,ay]", "R[r,r]"):
        rows = [line for line in out.splitlines() if line.strip().startswith(k + " ")]
        assert len(rows) == 2, k  # the fit's line and the coverage line
        cov = float(rows[1].split()[1])
        assert 0.0 <= cov <= 1.0
