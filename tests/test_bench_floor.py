"""benchmarks/bench_floor.py (``vehjax bench floor``): its scalar C EKF, written independently
of vehjax's filters, gives vehjax.filter's log-likelihood on the same drive (so the floor times
the same work), and the benchmark runs on a short drive."""

import shutil

import jax.numpy as jnp
import numpy as np
import pytest

import vehjax
from vehjax import cli

bench = cli.load_benchmark("floor")
needs_cc = pytest.mark.skipif(shutil.which("gcc") is None and shutil.which("cc") is None,
                              reason="no C compiler on the PATH")


@needs_cc
@pytest.mark.parametrize("cf_scale", [1.0, 0.6])
def test_c_floor_equals_vehjax_filter(cf_scale):
    """Another car (the stiffness scaled), a held-out realisation of the drive: the C EKF's
    log-likelihood equals vehjax.filter's to 1e-10 relative, and differs from it with
    another R (the comparison can fail)."""
    drive = vehjax.studies.limit_drive.limit_drive("B", duration=10.0, seed=3)
    ys, us = np.asarray(drive.measurements), np.asarray(drive.inputs)
    th = np.array(tuple(drive.body.values()) + tuple(np.asarray(vehjax.models.SingleTrack().theta)[4:]))
    th[4] *= cf_scale
    model = vehjax.models.SingleTrack(tyres="linear", theta=tuple(th))
    floor = bench.c_floor()
    ll = float(jnp.sum(vehjax.filter(vehjax.filters.ekf(model, bench.Q, bench.R), ys, us,
                                     x0=bench.X0, P0=bench.P0).loglik))
    other = float(jnp.sum(vehjax.filter(vehjax.filters.ekf(model, bench.Q, 2 * bench.R), ys, us,
                                        x0=bench.X0, P0=bench.P0).loglik))
    c = floor(model, ys, us)
    assert abs(c - ll) <= 1e-10 * abs(ll)
    assert abs(c - other) > 1e-3 * abs(ll)


@pytest.mark.slow  # every row compiled, the reverse-mode gradient's 13 s among them
@needs_cc
def test_bench_floor_runs(capsys):
    assert bench.main(["--duration", "2", "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    for row in ("C floor", "filter EKF", "loss+grad fwd"):
        assert row in out


@needs_cc
def test_c_floor_of_the_3dof_model_equals_vehjax_filter():
    """The second C EKF (Dynamic3DOF, its Jacobian by hand and through RK4's stages by the
    chain rule), on another realisation and another car (cornering stiffness 0.7x): the
    log-likelihood equals vehjax.filter's (jacfwd Jacobians) to 1e-10 relative, and differs
    from it with another R."""
    _, model, ys, us, Q, R, x0, P0, source = bench.three_dof_problem(5.0, seed=4)
    th = np.asarray(model.theta).copy()
    th[2] *= 0.7
    model = vehjax.models.Dynamic3DOF(dt=model.dt, theta=tuple(th))
    floor = bench.c_floor(source, Q, R, x0, P0)

    def ll(R_):
        return float(jnp.sum(vehjax.filter(vehjax.filters.ekf(model, Q, R_), ys, us, x0=x0,
                                           P0=P0).loglik))

    c = floor(model, ys, us)
    assert abs(c - ll(R)) <= 1e-10 * abs(ll(R))
    assert abs(c - ll(2 * R)) > 1e-3 * abs(ll(R))


@needs_cc
def test_c_ukf_of_the_3dof_model_equals_vehjax_ukf():
    """The C UKF (seven unscented points through RK4, fresh points for the update) on another
    realisation and car (cornering stiffness 1.3x, a wider prior): its log-likelihood equals
    vehjax.filters.ukf's to 1e-10 relative, and differs from the EKF's (a UKF, not an EKF, is
    what it times) and from the UKF's with another Q."""
    _, model, ys, us, Q, R, x0, P0, source = bench.three_dof_problem(5.0, seed=7)
    th = np.asarray(model.theta).copy()
    th[2] *= 1.3
    model = vehjax.models.Dynamic3DOF(dt=model.dt, theta=tuple(th))
    P0 = 4.0 * P0
    floor = bench.c_floor(source, Q, R, x0, P0, symbol="ukf_loglik")

    def ll(build, Q_):
        return float(jnp.sum(vehjax.filter(build(model, Q_, R), ys, us, x0=x0, P0=P0).loglik))

    c, ukf = floor(model, ys, us), ll(vehjax.filters.ukf, Q)
    assert abs(c - ukf) <= 1e-10 * abs(ukf)
    assert abs(c - ll(vehjax.filters.ekf, Q)) > 1e-8 * abs(ukf)
    assert abs(c - ll(vehjax.filters.ukf, 3 * Q)) > 1e-3 * abs(ukf)


def test_bench_floor_runs_on_a_users_model_without_a_floor(capsys):
    """``--model user`` (a Model of plain jnp functions): the filter and run rows, no C row."""
    assert bench.main(["--model", "user", "--duration", "2", "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    assert "a user's Model" in out and "C floor" not in out
    assert all(row in out for row in ("filter EKF", "filter UKF", "run EKF"))
