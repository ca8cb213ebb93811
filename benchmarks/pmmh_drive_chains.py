"""Particle-likelihood PMMH chains on the RAV4 drive's first 20 s (issue #30): the bootstrap
PF's independent estimates ("bootstrap") against correlated pseudo-marginal PMMH ("cpm"), through
berntorp2018.run_pmmh with the same N, iterations, key (8), 4 chains, each started at (and its
likelihood spread measured at) the exact Kalman chain's posterior mean (from `vehjax reproduce
berntorp2018 --drive`'s report at 56aac88; the values below). Prints acceptance, the summary
(mean, std, R-hat, ESS) and the report's check line per chain; writes a JSON.

    python benchmarks/pmmh_drive_chains.py bootstrap,cpm 200 64 /tmp/chains.json
        # likelihoods, iterations per chain, particles, output
"""
import sys, time, json
import numpy as np, jax
jax.config.update("jax_enable_x64", True)
import vehjax as vj
from vehjax.reproduce import berntorp2018 as B
DEG = B.DEG
drive = vj.data.load_comma2k19()
model = vj.models.SingleTrackBank(dt=drive.dt)
U, Y = drive.inputs(model), drive.measurements(model, track=B.TRACK)
Y = Y.copy()
Y[:, 4], _ = B.gate_virtual_yaw(Y[:, 1], Y[:, 4], 5.0 * DEG)
T = 2000
at = {"delta_offset": 0.01254 * DEG, "eps": -4.331e-4, "bias:ay": -0.06369, "bias:r": 0.02133 * DEG,
      "R:ay": 0.3051, "R:r": 0.1223 * DEG, "R:r_virt": 1.182 * DEG, "input:delta": 0.1356 * DEG}
out = {}
for lik in sys.argv[1].split(","):
    t0 = time.time()
    res, sec, info = B.run_pmmh(model, Y[:T], U[:T], chains=4, key=jax.random.key(8),
                                likelihood=lik, init=at, spread_at=at, iters=int(sys.argv[2]),
                                particles=int(sys.argv[3]))
    print(lik, f"{sec:.1f} s", info, "acceptance", res.acceptance.round(3), flush=True)
    print(res.summary(), flush=True)
    print(B.pmmh_check(res, info, lik), flush=True)
    out[lik] = dict(sec=sec, info=info, mean=res.mean.tolist(), std=res.std.tolist(),
                    rhat=res.rhat.tolist(), ess=res.ess.tolist(),
                    acc=res.acceptance.tolist(), names=list(res.names))
json.dump(out, open(sys.argv[4], "w"), indent=1)
