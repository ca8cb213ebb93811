"""`vehjax reproduce wang2016` at a reduced size: table shape, finite numbers, filters that help."""

import csv
import math
import re

import numpy as np
import pytest

from vehjax.reproduce import load, wang2016

FILTERS = ("ukf", "ackf")
QUANTITIES = ("u", "v", "ax", "ay", "r", "beta")


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    out = tmp_path_factory.mktemp("wang2016")
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = wang2016.main(["--runs", "3", "--duration", "4", "--filters", ",".join(FILTERS),
                            "--seed", "1", "--out", str(out)])
    with open(out / "table1.csv") as fh:
        rows = list(csv.DictReader(fh))
    return rc, buf.getvalue(), out, rows


def _value(rows, metric, quantity, column):
    hits = [r for r in rows if (r["metric"], r["quantity"], r["column"]) == (metric, quantity, column)]
    assert len(hits) == 1, (metric, quantity, column)
    return float(hits[0]["mean"]), float(hits[0]["ci95_low"]), float(hits[0]["ci95_high"])


def test_registered_with_a_citation():
    assert load("wang2016") is wang2016
    assert "Wang" in wang2016.PAPER and "2016" in wang2016.PAPER


def test_runs_and_writes_table_and_figures(study):
    rc, text, out, rows = study
    assert rc == 0
    for name in ("table1.md", "table1.csv", "fig3.png", "rmse_time.png", "error_bands.png",
                 "report.md"):
        assert (out / name).stat().st_size > 0
    # report.md holds the table and links every figure written
    report = (out / "report.md").read_text()
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report)
    assert sorted(links) == sorted(p.name for p in out.glob("*.png")) and len(links) == 3
    assert "| MAE | ay [m/s^2] |" in report and "3 Monte-Carlo runs" in report
    # 2 metrics x 6 quantities x 2 filters, plus the raw sensor on the 3 measured quantities
    assert len(rows) == 2 * 6 * len(FILTERS) + 2 * 3
    for metric in ("MAE", "RMSE"):
        for q in QUANTITIES:
            for f in FILTERS:
                mean, low, high = _value(rows, metric, q, f.upper())
                assert math.isfinite(mean) and mean > 0.0 and low <= mean <= high
    # The printed table has one line per metric and quantity, with the paper's numbers beside.
    lines = [ln for ln in text.splitlines() if ln.startswith("| MAE") or ln.startswith("| RMSE")]
    assert len(lines) == 12
    assert "0.226" in text and "0.00765" in text  # Table 1: EKF MAE of ay, ACKF MAE of r
    assert "UKF" in text and "ACKF" in text and "compile" in text


def test_mae_never_exceeds_rmse(study):
    rows = study[3]
    for q in QUANTITIES:
        for f in FILTERS:
            assert _value(rows, "MAE", q, f.upper())[0] <= _value(rows, "RMSE", q, f.upper())[0]


def test_filters_beat_the_raw_sensors(study):
    """On the measured yaw rate and lateral acceleration, every filter's error is well below
    the sensor's own error (the same truth, the same runs)."""
    rows = study[3]
    for q in ("r", "ay"):
        raw = _value(rows, "RMSE", q, "meas.")[0]
        for f in FILTERS:
            assert _value(rows, "RMSE", q, f.upper())[0] < 0.6 * raw, (q, f)


def test_unmeasured_states_estimated_to_a_fraction_of_their_size(study):
    """v and beta are not measured; their RMSE is a small fraction of their RMS value over the
    drive (an estimator that returned zero would score 1)."""
    res = np.load(study[2] / "results.npz")
    truth = res["truth"]
    assert list(res["quantities"]) == list(QUANTITIES)
    assert truth.shape == res["ukf"].shape == (3, 400, 6)
    for f in FILTERS:
        assert not res[f"{f}_diverged"].any()
        for i in (1, 5):  # v, beta
            rms = np.sqrt(np.mean(truth[..., i] ** 2))
            err = np.sqrt(np.mean((res[f][..., i] - truth[..., i]) ** 2))
            assert err < 0.3 * rms, (f, i, err, rms)


def test_bad_options_raise_value_error(tmp_path):
    with pytest.raises(ValueError, match="--filters"):
        wang2016.main(["--filters", "ekf,pf", "--out", str(tmp_path)])
    with pytest.raises(ValueError, match="--runs"):
        wang2016.main(["--runs", "1", "--out", str(tmp_path)])
    with pytest.raises(ValueError, match="--duration"):
        wang2016.main(["--duration", "0", "--out", str(tmp_path)])
