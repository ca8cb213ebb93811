"""Tyre force laws: linear and the Pacejka-89 magic formula.

Pacejka '89 (Bakker, Pacejka & Lidner, SAE 890087) writes every pure-slip force as

    y(x) = D sin(C arctan(B x - E (B x - arctan(B x))))      (Wang et al. 2016, eq. 15)
    Y(X) = y(x) + Sv,     x = X + Sh                          (eq. 16-17)

with B, C, D, E, Sh, Sv functions of the vertical load Fz **in kN**, and the slip input X in
**degrees** of slip angle for the lateral force and in **percent** of longitudinal slip for the
longitudinal force. D and Sv come out in N. A stiffness factor B per degree therefore means a
slope B C D per degree: the paper's B = 0.237 /deg, C = 1.65, D = 3610.5 N give
B C D = 1412 N/deg = 80.9 kN/rad of cornering stiffness (and 141 kN per unit slip when read with
X in percent).

Coefficient sets (module constants, not estimated parameters):

* :data:`LATERAL_89` (a0..a13) is the widely circulated Pacejka '89 example set (it ships as
  the example of many Pac89 implementations, together with b0..b10 = 2.37272, -9.46, 1490, 130,
  276, 0.0886, 0.00402, -0.0615, 1.2, 0.0299, -0.176 and an aligning-moment set c0..c17).
  At Fz = 3.16 kN and camber 0.5 deg it gives exactly the values that Wang et al. 2016 print
  (B = 0.2366 -> 0.237, C = 1.65, D = 3610.49 -> 3610.5, E = 0.7075 -> 0.707,
  Sv = 40.3786 -> 40.379, Sh = 0.04733 -> 0.0473); Sv and Sh are only reproduced with the camber
  terms at 0.5 deg, hence :data:`CAMBER_DEG`.
* :data:`LONGITUDINAL_89` (b0..b12) is ours. The paper quotes one "unified" set for all forces,
  so the longitudinal law is built to give the same B, C, D, E, Sh, Sv at 3.16 kN: C, D, E, Sh
  and Sv follow the lateral laws (camber terms folded in at 0.5 deg), and the slip stiffness
  BCD = (b3 Fz^2 + b4 Fz) exp(-b5 Fz) keeps the load dependence of the published longitudinal
  example (130, 276, 0.0886) scaled by 0.8592122658 so that it equals the lateral BCD for
  Fz = 3.16 kN.
  Sv = b11 Fz + b12 is the '94-style vertical shift ('89 has Sv = 0 for Fx).
"""

from __future__ import annotations

import jax.numpy as jnp

from ..lib.elementary import arctan, sin

#: Pacejka '89 lateral-force coefficients a0..a13 (Fz in kN, alpha and camber in deg, Fy in N).
LATERAL_89 = (
    1.65,  # a0   C, shape factor
    -34.0,  # a1  D = (a1 Fz + a2) Fz: load influence on the friction coefficient [1/kN]
    1250.0,  # a2  friction coefficient x 1000
    3036.0,  # a3  BCD = a3 sin(2 arctan(Fz / a4)) (1 - a5 |camber|): maximum stiffness [N/deg]
    12.8,  # a4   load at maximum stiffness [kN]
    0.00501,  # a5  camber influence on stiffness [1/deg]
    -0.02103,  # a6  E = a6 Fz + a7 [1/kN]
    0.77394,  # a7
    0.0022890,  # a8  Sh = a8 camber + a9 Fz + a10 [deg/deg]
    0.013442,  # a9  [deg/kN]
    0.003709,  # a10 [deg]
    19.1656,  # a11 Sv = a11 Fz camber + a12 Fz + a13 [N/(kN deg)]
    1.21356,  # a12 [N/kN]
    6.26206,  # a13 [N]
)

#: Camber angle [deg] at which :data:`LATERAL_89` reproduces Wang et al.'s values at 3.16 kN.
CAMBER_DEG = 0.5

#: Longitudinal-force coefficients b0..b12 (Fz in kN, slip in %, Fx in N); see the module doc.
LONGITUDINAL_89 = (
    1.65,  # b0  C
    -34.0,  # b1 D = (b1 Fz + b2) Fz
    1250.0,  # b2
    111.69759455,  # b3 BCD = (b3 Fz^2 + b4 Fz) exp(-b5 Fz) [N/%/kN^2]  (130 x 0.8592122658)
    237.14258536,  # b4 [N/%/kN]  (276 x 0.8592122658)
    0.0886,  # b5  [1/kN]
    0.0,  # b6   E = b6 Fz^2 + b7 Fz + b8
    -0.02103,  # b7
    0.77394,  # b8
    0.013442,  # b9   Sh = b9 Fz + b10 [%/kN]
    0.0048535,  # b10 [%]  (a10 + a8 x 0.5)
    10.79636,  # b11  Sv = b11 Fz + b12 [N/kN]  (a12 + a11 x 0.5)
    6.26206,  # b12 [N]
)


def linear_force(stiffness, slip):
    """Linear tyre: F = stiffness * slip (longitudinal slip [-] or slip angle [rad]) [N]."""
    return stiffness * slip


def magic_formula(X, B, C, D, E, Sh, Sv):
    """Eq. 15-17: Y = D sin(C arctan(B x - E (B x - arctan(B x)))) + Sv with x = X + Sh.

    Broadcasts over all arguments; X in the unit B refers to (deg or %), Y in the unit of D.
    """
    Bx = B * (X + Sh)
    return D * sin(C * arctan(Bx - E * (Bx - arctan(Bx)))) + Sv


def pacejka89_lateral_coefficients(fz_kn, camber_deg=CAMBER_DEG, a=LATERAL_89):
    """(B [1/deg], C, D [N], E, Sh [deg], Sv [N]) of the lateral force at ``fz_kn`` > 0 [kN]."""
    C = a[0]
    D = (a[1] * fz_kn + a[2]) * fz_kn
    BCD = a[3] * sin(2.0 * arctan(fz_kn / a[4])) * (1.0 - a[5] * jnp.abs(camber_deg))
    B = BCD / (C * D)
    E = a[6] * fz_kn + a[7]
    Sh = a[8] * camber_deg + a[9] * fz_kn + a[10]
    Sv = a[11] * fz_kn * camber_deg + a[12] * fz_kn + a[13]
    return B, C, D, E, Sh, Sv


def pacejka89_longitudinal_coefficients(fz_kn, b=LONGITUDINAL_89):
    """(B [1/%], C, D [N], E, Sh [%], Sv [N]) of the longitudinal force at ``fz_kn`` > 0 [kN]."""
    C = b[0]
    D = (b[1] * fz_kn + b[2]) * fz_kn
    BCD = (b[3] * fz_kn**2 + b[4] * fz_kn) * jnp.exp(-b[5] * fz_kn)
    B = BCD / (C * D)
    E = b[6] * fz_kn**2 + b[7] * fz_kn + b[8]
    Sh = b[9] * fz_kn + b[10]
    Sv = b[11] * fz_kn + b[12]
    return B, C, D, E, Sh, Sv


def pacejka89_lateral(alpha_deg, fz_kn, camber_deg=CAMBER_DEG, a=LATERAL_89):
    """Pure-slip lateral force Fy [N] at slip angle ``alpha_deg`` [deg] and load ``fz_kn`` [kN].

    Positive slip angle gives positive force (the sign convention of eq. 9-10 and 15-17).
    """
    return magic_formula(alpha_deg, *pacejka89_lateral_coefficients(fz_kn, camber_deg, a))


def pacejka89_longitudinal(slip_pct, fz_kn, b=LONGITUDINAL_89):
    """Pure-slip longitudinal force Fx [N] at slip ``slip_pct`` [%] and load ``fz_kn`` [kN]."""
    return magic_formula(slip_pct, *pacejka89_longitudinal_coefficients(fz_kn, b))
