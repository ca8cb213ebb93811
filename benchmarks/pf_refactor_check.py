"""Bitwise check that a refactor of the particle filters changed no output (issue #32).

Runs bootstrap_pf (4 schemes x 3 ESS thresholds, diagonal R, input noise, an underflowing run),
liu_west_ukf (default, recurrent=False, likelihood="measurement", move="every", gamma=0.9,
bounds={}, residual resampling at threshold 1) and the stop-gradient PF (values and two
gradients) on fixed data, and saves every output (``save``) or compares them bit for bit with a
saved file (``compare``: prints "compared 25 bad 0" when nothing changed).

    git worktree add /tmp/old <rev> && (cd /tmp/old && python /path/to/this save /tmp/ref.pkl)
    python benchmarks/pf_refactor_check.py compare /tmp/ref.pkl

(at 72fcc4f, before resample= existed, tune.stop_gradient_pf built the stop-gradient PF too,
so the same script runs on both sides.)
"""
import sys, pickle
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import vehjax as vj
from vehjax.filters import Resampling, bootstrap_pf, liu_west_ukf

mode, path = sys.argv[1], sys.argv[2]
DT = 0.1
A = np.array([[1.0, DT], [0.0, 0.95]])
lin = vj.models.Model(transition=lambda x, u, th: jnp.asarray(A) @ x + u, observe=lambda x, u, th: x,
                      dt=DT, state_names=("p", "v"), input_names=("up", "uv"), output_names=("yp", "yv"))
rng = np.random.default_rng(0)
T = 40
ys = rng.normal(size=(T, 2)); ys[5, 0] = np.nan; ys[9] = np.nan
us = rng.normal(size=(T, 2)) * 0.1
Q = np.array([[0.02, 0.005], [0.005, 0.05]]); Rf = np.array([[0.09, 0.02], [0.02, 0.16]])
out = {}
def rec(name, est, ys_, us_, x0, P0, key, **kw):
    r = jax.jit(lambda k: vj.filter(est, ys_, us_, x0=x0, P0=P0, key=k, **kw))(key)
    out[name] = jax.tree.map(np.asarray, (r.states, r.covariances, r.params, r.loglik, r.nis, r.diverged, r.state))
k = jax.random.key(5)
for thr in (0.0, 0.5, 1.0):
    for scheme in ("systematic", "multinomial", "residual", "stratified"):
        rec(f"pf-{scheme}-{thr}", bootstrap_pf(lin, Q, Rf, n_particles=64,
                                               resampling=Resampling(scheme=scheme,
                                                                     ess_threshold=thr)), ys, us, np.zeros(2), np.eye(2), k)
rec("pf-diagR", bootstrap_pf(lin, Q, np.diag([0.09, 0.16]), n_particles=50), ys, us, np.zeros(2), np.eye(2), k)
rec("pf-inoise", bootstrap_pf(lin, Q * 0, Rf, n_particles=50, input_noise={"up": 0.1, "uv": 0.2}), ys, us, np.zeros(2), np.eye(2), k)
rec("pf-underflow", bootstrap_pf(lin, Q, Rf * 1e-6, n_particles=30), ys * 50, us, np.zeros(2), np.eye(2), k)
# Liu-West on the kinematic bicycle
m = vj.models.KinematicBicycle(dt=0.05)
scn = vj.scenarios.sine_steer(m, speed=10.0, duration=30 * m.dt)
sim = vj.simulate(m, scn, runs=1, key=jax.random.key(1), process_std=np.full(len(m.state_names), 0.01), meas_std=np.full(len(m.output_names), 0.05))
ysb = np.array(sim.measurements[0]); ysb[4, 0] = np.nan; ysb[7] = np.nan
usb = np.asarray(sim.inputs)
nx, ny = len(m.state_names), len(m.output_names)
names = ("lf", "lr")
th = np.asarray(m.theta)[[m.param_names.index(n) for n in names]]
for kw in (dict(), dict(recurrent=False), dict(likelihood="measurement"), dict(move="every"), dict(gamma=0.9),
           dict(bounds={}), dict(ess_threshold=1.0, resampling="residual")):
    est = liu_west_ukf(m, np.eye(nx) * 1e-4, np.eye(ny) * 0.0025, n_particles=100, estimate=names, theta_low=th * 0.7, theta_high=th * 1.3, **kw)
    rec("lw-" + repr(sorted(kw.items())), est, ysb, usb, np.asarray(scn.x0), np.eye(nx) * 1e-2, k)
# stop-gradient PF: values and gradient
import vehjax.tune as vt
def sgpf():
    try:
        return vt.stop_gradient_pf(lin, Q, Rf, 64)
    except Exception:
        raise
est = sgpf()
rec("sg", est, ys, us, np.zeros(2), np.eye(2), k)
def ll(x0):
    return vj.filter(sgpf(), ys, us, x0=x0, P0=np.eye(2), key=k).loglik.sum()
out["sg-grad"] = np.asarray(jax.jit(jax.grad(ll))(jnp.asarray([0.1, -0.2])))
def llq(s):
    e = vt.stop_gradient_pf(lin, Q * s, Rf, 64)
    return vj.filter(e, ys, us, x0=jnp.zeros(2), P0=np.eye(2), key=k).loglik.sum()
out["sg-gradQ"] = np.asarray(jax.jit(jax.grad(llq))(1.3))
if mode == "save":
    pickle.dump(out, open(path, "wb"))
    print("saved", len(out))
else:
    ref = pickle.load(open(path, "rb"))
    bad = 0
    for name in ref:
        a, b = jax.tree.leaves(ref[name]), jax.tree.leaves(out[name])
        for x, y in zip(a, b):
            if not np.array_equal(x, y, equal_nan=True):
                bad += 1
                print("DIFF", name, np.nanmax(np.abs(np.asarray(x, float) - np.asarray(y, float))))
    print("compared", len(ref), "bad", bad)
