"""The vehjax command."""

import subprocess
import sys

import numpy as np

from vehjax import cli


def test_help_runs_as_a_program():
    out = subprocess.run([sys.executable, "-m", "vehjax.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "simulate" in out.stdout and "models" in out.stdout


def test_models_lists_every_model(capsys):
    assert cli.main(["models"]) == 0
    text = capsys.readouterr().out
    from vehjax.models import REGISTRY

    for name in REGISTRY:
        assert name in text
    assert "m = 1700 [kg]" in text


def test_simulate_writes_npz_and_png(tmp_path, capsys):
    assert cli.main(["simulate", "KinematicBicycle", "step_steer", "--runs", "3", "--out", str(tmp_path)]) == 0
    data = np.load(tmp_path / "KinematicBicycle_step_steer.npz")
    assert data["states"].shape[0] == 3 and list(data["state_names"]) == ["x", "y", "psi", "v"]
    png = (tmp_path / "KinematicBicycle_step_steer.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_input_is_a_clear_error(capsys):
    assert cli.main(["simulate", "Dynamic3DOF", "sine_steer", "--runs", "0"]) == 2
    assert "runs" in capsys.readouterr().err


def test_bench_gaussian_smoke(capsys):
    """Tiny sizes: the three libraries must agree before any timing is printed."""
    assert cli.main(["bench", "gaussian", "--runs", "2", "--steps", "30", "--filterpy-runs", "1",
                     "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    assert "dynamax" in out and "filterpy" in out and "same estimates" in out
