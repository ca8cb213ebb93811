"""Flat option keywords grouped into the filter builders' option records (a test's table of
bad values stays flat; the record is made inside the call, so its own checks raise there)."""

from vehjax.filters import Augmentation, LiuWestKernel, Resampling, SigmaPoints

#: record keyword -> (record, {flat keyword: the record's field})
GROUPS = {
    "points": (SigmaPoints, {"alpha": "alpha", "beta": "beta", "kappa": "kappa"}),
    "resampling": (Resampling, {"resampling": "scheme", "ess_threshold": "ess_threshold",
                                "resample": "resample"}),
    "kernel": (LiuWestKernel, {"a": "a", "gamma": "gamma", "move": "move",
                               "likelihood": "likelihood"}),
    "augment": (Augmentation, {k: k for k in ("biases", "input_offsets", "bias_walk",
                                              "offset_walk", "bias_std0", "offset_std0")}),
}


def grouped(kw: dict, only=tuple(GROUPS)) -> dict:
    """``kw`` with the flat options of the records named in ``only`` made into those records
    (a value that already is the record is kept)."""
    out = dict(kw)
    for name in only:
        cls, fields = GROUPS[name]
        if isinstance(out.get(name), cls):
            continue
        got = {f: out.pop(k) for k, f in fields.items() if k in out}
        if got:
            out[name] = cls(**got)
    return out
