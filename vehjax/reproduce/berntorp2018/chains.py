"""Particle-likelihood PMMH chains on the RAV4 drive's first 20 s: the bootstrap
PF's independent estimates ("bootstrap") against correlated pseudo-marginal PMMH ("cpm"), through
:func:`.pmmh.run_pmmh` with the same N, iterations, key (8), 4 chains, each started at (and its
likelihood spread measured at) the exact Kalman chain's posterior mean (:data:`AT`, from
``vehjax reproduce berntorp2018 --drive``'s report; see
``benchmarks/results/notes_berntorp2018.md``). Prints acceptance, the summary (mean, std, R-hat,
ESS) and the report's check line per chain; writes a JSON. Was ``benchmarks/pmmh_drive_chains.py``:
it runs the study's own PMMH set-up, so it lives with the study.

    python -m vehjax.reproduce.berntorp2018.chains bootstrap,cpm 200 64 /tmp/chains.json
        # likelihoods, iterations per chain, particles, output
"""

from __future__ import annotations

import json
import sys

import jax

import vehjax as vj
from vehjax.studies.banked_road import DEG
from vehjax.data.prepare import gate_virtual_yaw
from vehjax.models.bank_scale import TRACK

from .pmmh import run_pmmh
from .report import pmmh_check

#: the exact Kalman chain's posterior mean on the first 20 s (physical units)
AT = {"delta_offset": 0.01254 * DEG, "eps": -4.331e-4, "bias[ay]": -0.06369,
      "bias[r]": 0.02133 * DEG, "R[ay]": 0.3051, "R[r]": 0.1223 * DEG, "R[r_virt]": 1.182 * DEG,
      "input[delta]": 0.1356 * DEG}


def main(argv=None):
    """``LIKELIHOODS ITERS PARTICLES OUT.json``: each chain, printed and written to OUT."""
    argv = sys.argv[1:] if argv is None else argv
    jax.config.update("jax_enable_x64", True)
    drive = vj.data.load_comma2k19()
    model = vj.models.SingleTrackBank(dt=drive.dt)
    U, Y = drive.inputs(model), drive.measurements(model, track=TRACK)
    Y = Y.copy()
    Y[:, 4], _ = gate_virtual_yaw(Y[:, 1], Y[:, 4], 5.0 * DEG)
    T = 2000
    out = {}
    for lik in argv[0].split(","):
        res, sec, info = run_pmmh(model, Y[:T], U[:T], chains=4, key=jax.random.key(8),
                                  likelihood=lik, init=AT, spread_at=AT, iters=int(argv[1]),
                                  particles=int(argv[2]))
        print(lik, f"{sec:.1f} s", info, "acceptance", res.acceptance.round(3), flush=True)
        print(res.summary(), flush=True)
        print(pmmh_check(res, info, lik), flush=True)
        out[lik] = dict(sec=sec, info=info, mean=res.mean.tolist(), std=res.std.tolist(),
                        rhat=res.rhat.tolist(), ess=res.ess.tolist(),
                        acc=res.acceptance.tolist(), names=list(res.names))
    with open(argv[3], "w") as f:
        json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
