"""The same option means the same thing and is checked the same way in every function that
takes it (issue 46): each bad value of a shared particle-filter option gives one and the same
error, naming the option, from every builder that takes it, before anything is traced."""

import jax.numpy as jnp
import pytest

import vehjax as vj
from vehjax import filters as F

MODEL = vj.models.Model(
    lambda x, u, th: jnp.stack([th[0] * 0.9 * x[0] + 0.1 * u[0], 0.95 * x[1] + 0.05 * x[0]]),
    lambda x, u, th: jnp.stack([x[0], x[1]]), dt=0.1, state_names=("v", "w"),
    input_names=("u",), output_names=("y", "z"), param_names=("a",), theta=(1.0,))
Q = R = [0.1, 0.1]
MPF = dict(noisy_input="u", sensors=("y",), linear_states=("w",), known_std={"z": 0.2},
           Q=0.05 ** 2, niw=F.NiW(std0={"u": 0.5, "y": 0.3}))
BUILDERS = {
    "bootstrap_pf": lambda **k: F.bootstrap_pf(MODEL, Q, R, **k),
    "liu_west_ukf": lambda **k: F.liu_west_ukf(MODEL, Q, R, estimate=("a",), theta_low=[0.5],
                                               theta_high=[1.5], **k),
    "marginalized_pf": lambda **k: F.marginalized_pf(MODEL, **MPF, **k),
    "marginalized_pf_grid": lambda **k: F.marginalized_pf_grid(MODEL, **MPF, **k),
}
TAKES = {  # which builder takes which option (scheme, ess_threshold: in its Resampling)
    "n_particles": ("bootstrap_pf", "liu_west_ukf", "marginalized_pf", "marginalized_pf_grid"),
    "scheme": ("bootstrap_pf", "liu_west_ukf", "marginalized_pf"),
    "ess_threshold": ("bootstrap_pf", "liu_west_ukf", "marginalized_pf"),
    "resampling": ("bootstrap_pf", "liu_west_ukf", "marginalized_pf"),
}
RECORD_FIELDS = ("scheme", "ess_threshold")  # made into resampling=Resampling(...) in the call
BAD = [("n_particles", 1), ("n_particles", 2.5), ("scheme", "bogus"),
       ("ess_threshold", 2.0), ("ess_threshold", -0.1), ("resampling", "systematic")]


def _call(name, option, value):
    if option in RECORD_FIELDS:
        return BUILDERS[name](resampling=F.Resampling(**{option: value}))
    return BUILDERS[name](**{option: value})


@pytest.mark.parametrize("option, value", BAD)
def test_a_bad_shared_option_gives_the_same_error_everywhere(option, value):
    messages = set()
    for name in TAKES[option]:
        with pytest.raises(ValueError, match=f"^{option}: ") as err:
            _call(name, option, value)
        messages.add(str(err.value))
    assert len(messages) == 1, messages
