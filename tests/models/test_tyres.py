"""Pacejka-89 magic formula against Wang et al. 2016's published values and the '89 forms."""

import jax
import jax.numpy as jnp
import numpy as np

from vehjax.models import tyres

# The Pacejka '89 example lateral set, typed in from the published table (not imported).
A = (1.65, -34.0, 1250.0, 3036.0, 12.8, 0.00501, -0.02103, 0.77394, 0.0022890, 0.013442,
     0.003709, 19.1656, 1.21356, 6.26206)
# Wang et al. 2016, section 2.2: "under vertical load of 3.16 kN".
PAPER = {"B": 0.237, "C": 1.65, "D": 3610.5, "E": 0.707, "Sv": 40.379, "Sh": 0.0473}
DECIMALS = {"B": 3, "C": 2, "D": 1, "E": 3, "Sv": 3, "Sh": 4}


def lateral_coefficients(fz, gamma):
    """Pacejka '89 lateral coefficient laws, written out plainly (Fz in kN, camber in deg)."""
    C = A[0]
    D = (A[1] * fz + A[2]) * fz
    B = A[3] * np.sin(2 * np.arctan(fz / A[4])) * (1 - A[5] * abs(gamma)) / (C * D)
    E = A[6] * fz + A[7]
    Sh = A[8] * gamma + A[9] * fz + A[10]
    Sv = A[11] * fz * gamma + A[12] * fz + A[13]
    return {"B": B, "C": C, "D": D, "E": E, "Sh": Sh, "Sv": Sv}


def mf(X, c):
    Bx = c["B"] * (X + c["Sh"])
    return c["D"] * np.sin(c["C"] * np.arctan(Bx - c["E"] * (Bx - np.arctan(Bx)))) + c["Sv"]


def as_dict(coeffs):
    return dict(zip(("B", "C", "D", "E", "Sh", "Sv"), (float(c) for c in coeffs)))


def assert_matches_paper(c):
    for k, v in PAPER.items():
        half_ulp = 0.5 * 10.0 ** -DECIMALS[k]
        assert abs(c[k] - v) <= half_ulp, (k, c[k], v)


def test_module_lateral_set_is_the_published_one():
    assert tyres.LATERAL_89 == A
    assert tyres.CAMBER_DEG == 0.5


def test_lateral_coefficients_reproduce_paper_at_3_16_kN():
    c = as_dict(tyres.pacejka89_lateral_coefficients(3.16))
    assert_matches_paper(c)
    # Without the 0.5 deg camber the shifts miss the paper's values by far.
    c0 = as_dict(tyres.pacejka89_lateral_coefficients(3.16, camber_deg=0.0))
    assert abs(c0["Sv"] - PAPER["Sv"]) > 30.0 and abs(c0["Sh"] - PAPER["Sh"]) > 1e-3


def test_longitudinal_coefficients_reproduce_paper_at_3_16_kN():
    c = as_dict(tyres.pacejka89_longitudinal_coefficients(3.16))
    assert_matches_paper(c)
    lat = as_dict(tyres.pacejka89_lateral_coefficients(3.16))
    for k in c:
        np.testing.assert_allclose(c[k], lat[k], rtol=1e-9, err_msg=k)


def test_longitudinal_set_follows_its_documented_construction():
    # BCD of the published longitudinal example (b3, b4, b5 = 130, 276, 0.0886), rescaled to the
    # lateral BCD at 3.16 kN; C, D, E, Sh, Sv from the lateral laws with camber 0.5 deg.
    fz, g = 3.16, 0.5
    bcd_lat = A[3] * np.sin(2 * np.arctan(fz / A[4])) * (1 - A[5] * g)
    k = bcd_lat / ((130.0 * fz**2 + 276.0 * fz) * np.exp(-0.0886 * fz))
    expected = (A[0], A[1], A[2], 130.0 * k, 276.0 * k, 0.0886, 0.0, A[6], A[7], A[9],
                A[10] + A[8] * g, A[12] + A[11] * g, A[13])
    np.testing.assert_allclose(tyres.LONGITUDINAL_89, expected, rtol=1e-9, atol=1e-12)


def test_lateral_coefficients_follow_pacejka89_load_laws():
    for fz in (1.5, 3.16, 4.5, 7.0):
        for gamma in (-1.0, 0.0, 0.5, 2.0):
            got = as_dict(tyres.pacejka89_lateral_coefficients(fz, gamma))
            ref = lateral_coefficients(fz, gamma)
            for k in got:
                np.testing.assert_allclose(got[k], ref[k], rtol=1e-12, err_msg=f"{k} at {fz} kN")


def test_lateral_force_matches_plain_formula():
    alpha = np.linspace(-20.0, 20.0, 81)
    for fz in (2.0, 3.16, 5.0):
        c = lateral_coefficients(fz, 0.5)
        np.testing.assert_allclose(tyres.pacejka89_lateral(jnp.asarray(alpha), fz), mf(alpha, c),
                                   rtol=1e-12, atol=1e-9)


def test_cornering_stiffness_is_about_81_kN_per_rad():
    # B is per degree: the slope of Y(X) at x = 0 (X = -Sh) is BCD N/deg.
    B, C, D, E, Sh, Sv = tyres.pacejka89_lateral_coefficients(3.16)
    slope_deg = jax.grad(lambda X: tyres.pacejka89_lateral(X, 3.16))(-Sh)
    np.testing.assert_allclose(slope_deg, B * C * D, rtol=1e-12)
    slope_rad = jax.grad(lambda a: tyres.pacejka89_lateral(jnp.rad2deg(a), 3.16))(jnp.deg2rad(-Sh))
    assert 80.0e3 < slope_rad < 81.5e3
    # The paper's rounded numbers give the same: 0.237 * 1.65 * 3610.5 N/deg.
    np.testing.assert_allclose(slope_rad, 0.237 * 1.65 * 3610.5 * 180 / np.pi, rtol=2e-3)


def _peak_x(B, C, E):
    """x > 0 where C arctan(B x - E (B x - arctan B x)) = pi / 2, by bisection."""
    target = np.tan(np.pi / (2 * C))
    lo, hi = 1e-9, 200.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        phi = B * mid - E * (B * mid - np.arctan(B * mid))
        lo, hi = (mid, hi) if phi < target else (lo, mid)
    return 0.5 * (lo + hi)


def test_curve_shape_odd_about_minus_sh_and_peak_d_plus_sv():
    for fn, coeffs in ((tyres.pacejka89_lateral, tyres.pacejka89_lateral_coefficients),
                       (tyres.pacejka89_longitudinal, tyres.pacejka89_longitudinal_coefficients)):
        for fz in (2.0, 3.16, 6.0):
            B, C, D, E, Sh, Sv = (float(c) for c in coeffs(fz))
            d = np.linspace(0.0, 30.0, 301)
            up = np.asarray(fn(jnp.asarray(-Sh + d), fz)) - Sv
            down = np.asarray(fn(jnp.asarray(-Sh - d), fz)) - Sv
            np.testing.assert_allclose(up, -down, rtol=1e-12, atol=1e-9)
            X = np.linspace(-Sh - 40.0, -Sh + 40.0, 160001)
            Y = np.asarray(fn(jnp.asarray(X), fz))
            i = np.argmax(Y)
            np.testing.assert_allclose(Y[i], D + Sv, rtol=1e-9)
            np.testing.assert_allclose(Y.min(), -D + Sv, rtol=1e-9)
            np.testing.assert_allclose(X[i] + Sh, _peak_x(B, C, E), atol=2e-3)
            assert 0.0 < X[i] < 15.0  # peak at a few deg / percent, as for a car tyre
            # Past the peak the force falls off towards D sin(C pi / 2) (sliding).
            assert Y[-1] < Y[i] and Y[-1] > D * np.sin(C * np.pi / 2) + Sv


def test_jit_and_vmap_over_loads():
    fz = jnp.linspace(1.0, 8.0, 8)
    f = jax.jit(jax.vmap(tyres.pacejka89_longitudinal, in_axes=(None, 0)))
    out = f(2.0, fz)
    assert out.shape == (8,) and out.dtype == jnp.float64 and bool(jnp.all(jnp.isfinite(out)))
    # More load, more force at the same slip; friction coefficient D / Fz falls with load.
    assert bool(jnp.all(jnp.diff(out) > 0))
    mu = jnp.array([tyres.pacejka89_longitudinal_coefficients(f)[2] / (1000 * f) for f in fz])
    assert bool(jnp.all(jnp.diff(mu) < 0))
