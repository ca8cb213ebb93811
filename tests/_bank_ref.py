"""Shared by the bank tests: SingleTrackBank's equations (eq. 1-3) written out in numpy, an
independent reference for the jax model, and the exact Kalman filter of its linear-Gaussian
form with paper 004's noise (the reference for the marginalized PF with known noise)."""

import math

import numpy as np

from vehjax.models.bank import G


def continuous_matrices(vx, th):
    """Continuous x' = A x + B delta of the linear single-track model with road bank at speed
    vx [m/s], th = (m, iz, lf, lr, cf, cr); states (vy, r, phi, phi_dot, phi_ddot)."""
    m, iz, lf, lr, cf, cr = th
    a = np.zeros((5, 5))
    a[0, 0] = -(cf + cr) / (m * vx)
    a[0, 1] = -vx + (lr * cr - lf * cf) / (m * vx)
    a[0, 2] = -G
    a[1, 0] = (lr * cr - lf * cf) / (iz * vx)
    a[1, 1] = -(lf**2 * cf + lr**2 * cr) / (iz * vx)
    a[2, 3] = a[3, 4] = 1.0
    b = np.array([cf / m, lf * cf / iz, 0.0, 0.0, 0.0])
    return a, b


def discrete_matrices(th, vx, dt):
    """Exact RK4 discretisation of the linear SingleTrackBank at speed vx, step dt, in numpy:
    X+ = Ad X + Bd delta, y = C X + Dd delta (eq. 1-3 and the ay, r, roll_rate, phi, r_virt
    outputs)."""
    m, iz, lf, lr, cf, cr = np.asarray(th)
    a, b = continuous_matrices(vx, (m, iz, lf, lr, cf, cr))
    M = dt * a
    Ad = sum(np.linalg.matrix_power(M, k) / math.factorial(k) for k in range(5))
    Bd = dt * sum(np.linalg.matrix_power(M, k) / math.factorial(k + 1) for k in range(4)) @ b
    C = np.zeros((5, 5))
    C[0, 0], C[0, 1] = -(cf + cr) / (m * vx), (lr * cr - lf * cf) / (m * vx)
    C[1, 1] = C[4, 1] = 1.0
    C[2, 3] = C[3, 2] = 1.0
    Dd = np.array([cf / m, 0.0, 0.0, 0.0, 0.0])
    return Ad, Bd, C, Dd


def exact_kalman(th, vx, dt, Y, delta, mu_w, sig_w, sigma_phi, bias, std, x0, P0, bank_gain,
                 innovations=False):
    """Kalman filter of the linear-Gaussian SingleTrackBank at speed vx with the white steering
    error w_t ~ N(mu_w, sig_w^2) entering the transition and the observation alike (eq. 6-9),
    white bank jerk of std sigma_phi through ``bank_gain`` (eq. 3), outputs with constant
    ``bias`` and white noise of std ``std`` (5 each). State (x_t, w_t); components NaN in every
    run are skipped. Y (R, T, 5), delta (T,) the measured steering. Returns the filtered means
    (R, T, 5) and covariances (T, 5, 5) of x_t; with ``innovations`` also the innovations
    (R, T, 5) and their covariances (T, 5, 5), NaN on the skipped components."""
    Ad, Bd, C, Dd = discrete_matrices(th, vx, dt)
    F = np.zeros((6, 6))
    F[:5, :5] = Ad
    G = np.zeros((6, 2))
    G[:5, 0], G[5, 0], G[:5, 1] = Bd * sig_w, sig_w, np.asarray(bank_gain) * sigma_phi
    Q = G @ G.T
    H = np.concatenate([C, Dd[:, None]], 1)
    Rm = np.diag(np.asarray(std, float) ** 2)
    b = np.asarray(bias, float)
    runs, T, _ = Y.shape
    m = np.tile(np.r_[x0, mu_w], (runs, 1))
    P = np.zeros((6, 6))
    P[:5, :5] = P0
    means, covs = np.zeros((runs, T, 5)), np.zeros((T, 5, 5))
    nus, Ss = np.full((runs, T, 5), np.nan), np.full((T, 5, 5), np.nan)
    for t in range(T):
        m = m @ F.T + np.r_[Bd * (delta[t] + mu_w), mu_w]
        P = F @ P @ F.T + Q
        o = ~np.isnan(Y[0, t])  # the same components missing in every run
        Ho = H[o]
        S = Ho @ P @ Ho.T + Rm[np.ix_(o, o)]
        K = np.linalg.solve(S, Ho @ P).T
        nu = Y[:, t, o] - m @ Ho.T - Dd[o] * delta[t] - b[o]
        m = m + nu @ K.T
        P = P - K @ S @ K.T
        P = 0.5 * (P + P.T)
        means[:, t], covs[t] = m[:, :5], P[:5, :5]
        nus[:, t, o], Ss[t][np.ix_(o, o)] = nu, S
    return (means, covs, nus, Ss) if innovations else (means, covs)


def user_linear_bank(th, vx, dt):
    """The linear SingleTrackBank at speed vx written as a user would: a
    :class:`vehjax.models.Model` of two plain jnp functions over its discrete matrices, inputs
    (vx, delta), no ``bank_noise_gain``."""
    import jax.numpy as jnp

    from vehjax.models import Model
    from vehjax.models.bank import SingleTrackBank

    Ad, Bd, C, Dd = (jnp.asarray(a) for a in discrete_matrices(th, vx, dt))
    names = SingleTrackBank(dt=dt)
    return Model(lambda x, u, _: Ad @ x + Bd * u[1], lambda x, u, _: C @ x + Dd * u[1], dt=dt,
                 state_names=names.state_names, input_names=("vx", "delta"),
                 output_names=names.output_names)


def simulate_linear_bank(th, dt, U, runs, offset, sig_w, bank_std, bias, std, seed):
    """Data of the linear SingleTrackBank at the constant speed U[0, 0] in numpy: steering
    U[:, 1] + ``offset`` + white noise of std ``sig_w``, white noise of stds ``bank_std`` (3,)
    on the bank states (phi, phi_dot, phi_ddot), outputs with constant ``bias`` (5,) and white
    noise of stds ``std`` (5,). Returns (states (runs, T, 5), Y (runs, T, 5))."""
    Ad, Bd, C, Dd = discrete_matrices(th, float(U[0, 0]), dt)
    rng = np.random.default_rng(seed)
    x = np.zeros((runs, 5))
    X, Y = np.zeros((runs, len(U), 5)), np.zeros((runs, len(U), 5))
    for t in range(len(U)):
        d = U[t, 1] + offset + sig_w * rng.normal(size=(runs, 1))
        x = x @ Ad.T + Bd * d + np.r_[0.0, 0.0, bank_std] * rng.normal(size=(runs, 5))
        X[:, t] = x
        Y[:, t] = x @ C.T + Dd * d + bias + std * rng.normal(size=(runs, 5))
    return X, Y


def user_bank_case(runs, seed, points, known=False, steps=400):
    """The user-written model's study (tests/filters/marginalized/test_grid_filter.py's user-model
    test, benchmarks/mpf_grid_resolution.py): :func:`user_linear_bank` at the consistency study's
    inputs, data by :func:`simulate_linear_bank` at other values than that study's (steering
    offset 0.4 deg and noise 0.25 deg, biases ay -0.15 m/s^2, r 0.3 deg/s, roll rate -0.2
    deg/s, sensor stds 0.3 m/s^2, 0.9 deg/s, 0.9 deg/s), ``runs`` x ``steps``, ``seed``, and
    ``marginalized_pf_grid`` at its defaults with ``points`` grid points over
    a decade either side of a steering guess twice the truth, the sensor stds guessed at twice
    the truth (``known``: the sensor covariances known, guesses at the truth, nu0 = 1e10).
    Returns (estimator, X, Y, U, truth dict of the learnt parameters, ``vehjax.run``'s keyword
    arguments)."""
    import jax

    from vehjax.filters.marginalized import MeanStates, NiW, marginalized_pf_grid
    from vehjax.models.bank import SingleTrackBank
    from vehjax.studies.banked_road import matched_inputs

    dt, deg = 0.01, math.radians(1.0)
    model = SingleTrackBank(dt=dt)
    sensors = ("ay", "r", "roll_rate")
    known_std = {"phi": 0.5 * deg, "r_virt": 0.3 * deg}
    offset, sig_w, bank_std = 0.4 * deg, 0.25 * deg, np.array([1e-5, 1e-4, 0.002])
    bias = dict(zip(sensors, (-0.15, 0.3 * deg, -0.2 * deg)))
    std = dict(zip(sensors, (0.3, 0.9 * deg, 0.9 * deg)))
    names = model.output_names
    U = matched_inputs(steps)
    X, Y = simulate_linear_bank(model.theta, dt, U, runs, offset, sig_w, bank_std,
                                np.array([bias.get(n, 0.0) for n in names]),
                                np.array([{**std, **known_std}[n] for n in names]), seed)
    factor = 1.0 if known else 2.0
    est = marginalized_pf_grid(
        user_linear_bank(model.theta, float(U[0, 0]), dt), points, sensors=sensors,
        known_std=known_std, Q=bank_std ** 2,
        niw=NiW(std0={"delta": 2 * sig_w, **{n: factor * std[n] for n in sensors}},
                forgetting=1.0, nu0=1e10 if known else None),
        means=MeanStates(mean_std0={"delta": 1.0 * deg, "ay": 0.5, "r": 1.0 * deg,
                                    "roll_rate": 1.0 * deg}))
    truth = {"delta_offset": offset, "delta_std": sig_w,
             **{f"{s}_bias": bias[s] for s in sensors}, **{f"{s}_std": std[s] for s in sensors}}
    run_kw = dict(x0=np.zeros(5), P0=np.array([1e-4, 1e-6, 1e-6, 1e-6, 1e-6]),
                  key=jax.random.key(2), return_covariances=True)
    return est, X, Y, U, truth, run_kw


def mpf_kwargs(**kw):
    """The marginalized PFs' keyword arguments from flat ones: the NiW fields (std0, mean0,
    gamma0, nu0, forgetting) grouped into ``niw=NiW(...)``, mean_std0 and bias_walk into
    ``means=MeanStates(...)``, input_std_range and input_std_prior into
    ``grid=InputStdGrid(...)``, resampling, ess_threshold and resample into
    ``resampling=Resampling(...)``."""
    from vehjax.filters.marginalized import InputStdGrid, MeanStates, NiW
    from _records import grouped

    groups = {"niw": (NiW, ("std0", "mean0", "gamma0", "nu0", "forgetting")),
              "means": (MeanStates, ("mean_std0", "bias_walk")),
              "grid": (InputStdGrid, ("input_std_range", "input_std_prior"))}
    out = grouped(kw, ("resampling",))
    for name, (cls, fields) in groups.items():
        got = {k: out.pop(k) for k in fields if k in out}
        if got:
            out[name] = cls(**got)
    return out
