"""The benchmark scripts that are not ``vehjax bench`` commands run, at tiny sizes, and print
what their docstrings say (benchmarks/fit_profile.py, forward_directions.py,
filter_outputs.py, split_directions.py)."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from vehjax import execution

ROOT = Path(__file__).resolve().parents[1]


def _load(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow  # a staged fit of a short drive, its programs compiled
def test_fit_profile_splits_a_fit_into_compiles_tracing_and_the_rest(capsys):
    assert _load("fit_profile").main(["--tyres", "linear", "--duration", "10"]) == 0
    out = capsys.readouterr().out
    assert "linear fit, 1000 steps, side_by_side 1" in out and "summed: compile" in out


@pytest.mark.slow  # ten programs compiled
def test_forward_directions_prints_a_row_per_fit(capsys):
    assert _load("forward_directions").main(["--duration", "2", "--repeat", "1"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("cf")]
    assert [int(ln.split()[-4]) for ln in lines] == [2, 4, 5, 5, 6]


@pytest.mark.slow  # two programs compiled
def test_split_directions_prints_the_split_loss_equal(capsys):
    assert _load("split_directions").main(["--duration", "2", "--models", "linear",
                                           "--repeat", "1"]) == 0
    row = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("linear")][0]
    n, block, equal = row.split()[1], row.split()[2], row.split()[-3]
    assert n == "5" and equal == "True"
    assert int(block) == execution.direction_block(execution.for_platform("cpu"), 5)


def test_filter_outputs_compare_says_equal_bits_and_relative_differences(tmp_path, capsys):
    bench = _load("filter_outputs")
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    np.savez(a, x=np.array([1.0, 2.0, np.nan]), y=np.array([1.0, 4.0]))
    np.savez(b, x=np.array([1.0, 2.0, np.nan]), y=np.array([1.0, 4.0 * (1 + 1e-12)]))
    assert bench.main(["compare", str(a), str(b)]) == 0
    out = capsys.readouterr().out
    assert "x" in out and "equal bits" in out.splitlines()[0]
    assert "max relative difference 1.0e-12" in out.splitlines()[1]
