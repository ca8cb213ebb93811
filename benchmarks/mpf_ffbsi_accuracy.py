"""Accuracy of the marginalized PF's smoothers (vehjax.smoothers.marginalized, issue #29 item 2)
against the exact RTS smoother, on the linear-Gaussian test model of
tests/smoothers/test_smoothing_mpf.py (_model_lin: the offset drives v, a and y2; noise statistics
known; kalman_states="linear"), 8 keys, T = 25, N = M: method "ffbsi" and "ancestor", smoothed
means' error in units of the smoothed std, its z-RMS over the 8 keys' mean (about 1 when unbiased),
the variance ratio to the RTS's averaged over time, the distinct particles at t = 0.

    python benchmarks/mpf_ffbsi_accuracy.py 400 0.1     # N = M = 400, A_bar = 0.1
    python benchmarks/mpf_ffbsi_accuracy.py 50 0.0      # A_bar = 0: the exact RB filter

With A_bar = 0 the filter is the exact Rao-Blackwellised filter (the slow test
test_ffbsi_converges_to_the_rts_smoother_and_spreads_early checks it); with A_bar != 0 the
linear state feeds the sampled one (as the bank feeds vy) and the filter is approximate itself.
"""
import sys, time
sys.path.insert(0, "tests")
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import vehjax as vj
import test_smoothing_mpf as t
from vehjax.filters.marginalized import NiW, marginalized_pf
AB = float(sys.argv[2]) if len(sys.argv) > 2 else 0.1
T = t.T
rng = np.random.default_rng(3)
us = np.sin(0.3 * np.arange(T))[:, None]
x = rng.multivariate_normal(t.X0, t.P0)
ys = np.empty((T, 2))
for k in range(T):
    w = t.MU_W + t.SIG_W * rng.normal()
    u = us[k, 0] + w
    x = np.array([0.95 * x[0] + AB * x[1] + 0.1 * u,
                  0.05 * x[0] + 0.9 * x[1] + t.GZ * u + t.SIG_Z * rng.normal()])
    ys[k] = [x[0] + t.CA * x[1] + t.B1 + t.SD1 * rng.normal(),
             x[1] + t.DY * u + t.SD2 * rng.normal()]
ys[list(t.NAN_STEPS), 0] = np.nan
F = np.array([[0.95, AB, 0.0], [0.05, 0.9, 0.0], [0.0, 0.0, 0.0]])
g = np.array([0.1, t.GZ, 1.0])
Q = t.SIG_W**2 * np.outer(g, g) + np.diag([0.0, t.SIG_Z**2, 0.0])
H = np.array([[1.0, t.CA, 0.0], [0.0, 1.0, t.DY]])
R = np.diag([t.SD1**2, t.SD2**2])
xx, P = np.r_[t.X0, 0.0], np.zeros((3, 3)); P[:2, :2] = t.P0
xp, Pp, xf, Pf = [], [], [], []
for k in range(T):
    xx, P = F @ xx + g * (us[k, 0] + t.MU_W) - np.r_[0.0, 0.0, us[k, 0]], F @ P @ F.T + Q
    xp.append(xx), Pp.append(P)
    o = np.isfinite(ys[k]); Ho = H[o]
    S = Ho @ P @ Ho.T + R[np.ix_(o, o)]
    K = np.linalg.solve(S, Ho @ P).T
    off = np.array([t.B1, t.DY * us[k, 0]])[o]
    xx, P = xx + K @ (ys[k][o] - off - Ho @ xx), P - K @ S @ K.T
    xf.append(xx), Pf.append(P)
m, Ps, C = t._rts_backward(F, xf, Pf, xp, Pp)
m, Ps = m[:, :2], Ps[:, :2, :2]
sd = np.sqrt(np.diagonal(Ps, axis1=1, axis2=2))
n = int(sys.argv[1])
est = marginalized_pf(t._model_lin(ab=AB), n, noisy_input="u", sensors=("y1",),
                      known_std={"y2": t.SD2}, linear_states=("a",), Q=t.SIG_Z ** 2,
                      kalman_states="linear",
                      niw=NiW(std0={"u": t.SIG_W, "y1": t.SD1}, mean0={"u": t.MU_W, "y1": t.B1},
                              forgetting=1.0, nu0=1e7, gamma0=1e-9))
for meth in ("ffbsi", "ancestor"):
    sm = jax.jit(jax.vmap(lambda k, meth=meth: vj.smooth(
        est, ys, us, x0=t.X0, P0=t.P0, key=k,
        method=vj.smoothers.methods.BY_NAME[meth](n_trajectories=n))))(
        jax.random.split(jax.random.key(5), 8))
    rms = float(np.sqrt(np.mean(((np.asarray(sm.states) - m) / sd) ** 2)))
    vr = (np.asarray(sm.covariances).mean(0).diagonal(axis1=1, axis2=2)
          / Ps.diagonal(axis1=1, axis2=2)).mean(0)
    print(meth, n, "z", round(t._z_rms(sm.states, m), 2), "err/sd", round(rms, 3),
          "var ratio mean over t", np.round(vr, 3), "n_distinct0",
          np.asarray(sm.n_distinct)[:, 0], flush=True)
