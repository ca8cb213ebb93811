"""The vehjax command."""

import importlib.metadata
import subprocess
import sys

import numpy as np
import pytest

from vehjax import cli


def test_help_runs_as_a_program():
    out = subprocess.run([sys.executable, "-m", "vehjax.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "simulate" in out.stdout and "models" in out.stdout


def test_version_prints_the_installed_version():
    out = subprocess.run([sys.executable, "-m", "vehjax.cli", "--version"], capture_output=True,
                         text=True)
    assert out.returncode == 0
    assert out.stdout.strip() == f"vehjax {importlib.metadata.version('vehjax')}"


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


def test_simulate_takes_one_noise_std_per_output_and_notes_identical_runs(tmp_path, capsys):
    # the sizes of test_simulate_writes_npz_and_png, so that the compiled simulation is reused
    assert cli.main(["simulate", "KinematicBicycle", "step_steer", "--runs", "3",
                     "--meas-std", "0.1,0.2,0.01,0.05", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "measurement noise std: x 0.1 m, y 0.2 m, psi 0.01 rad, v 0.05 m/s" in out
    assert "process noise 0" in out and "same true states" in out
    data = np.load(tmp_path / "KinematicBicycle_step_steer.npz")
    np.testing.assert_array_equal(data["states"][0], data["states"][1])
    noise = (data["measurements"] - data["states"]).std(axis=(0, 1))
    np.testing.assert_allclose(noise, [0.1, 0.2, 0.01, 0.05], rtol=0.2)
    assert (tmp_path / "KinematicBicycle_step_steer.png").stat().st_size > 10_000
    # a wrong count is a clear error naming the outputs
    assert cli.main(["simulate", "KinematicBicycle", "step_steer", "--meas-std", "0.1,0.2",
                     "--out", str(tmp_path)]) == 2
    assert "x, y, psi, v" in capsys.readouterr().err


def _help_text(capsys, argv):
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 0
    return capsys.readouterr().out


def _documented(parser):
    """(option string, help) of every option but --help."""
    return [(a.option_strings[-1], a.help or "") for a in parser._actions
            if a.option_strings and a.dest != "help"]


def _assert_listed_with_defaults(text, command, parsers):
    """Every sub-command of ``vehjax <command>`` is in ``text`` with each of its options, and
    each option's help states its default."""
    for name, parser in parsers.items():
        assert f"vehjax {command} {name}" in text
        for opt, helptext in _documented(parser):
            assert opt in text, (name, opt)
            assert "default" in helptext, (name, opt)


def test_reproduce_help_lists_every_study_option_with_its_default(capsys):
    from vehjax import reproduce

    text = _help_text(capsys, ["reproduce", "--help"])
    _assert_listed_with_defaults(text, "reproduce",
                                 {n: reproduce.load(n).parser() for n in reproduce.REGISTRY})
    assert "(default 100)" in text and "(default 1000)" in text  # --runs, dutta2019 --particles


def test_bench_help_lists_every_option_with_its_default(capsys):
    text = _help_text(capsys, ["bench", "--help"])
    _assert_listed_with_defaults(text, "bench",
                                 {w: cli.load_benchmark(w).parser() for w in cli.BENCHMARKS})


def test_bad_input_is_a_clear_error(capsys):
    assert cli.main(["simulate", "Dynamic3DOF", "sine_steer", "--runs", "0"]) == 2
    assert "runs" in capsys.readouterr().err


# ---- user errors: one line on stderr, exit code 2, never a traceback, before any work ---------

def _user_error(capsys, argv):
    """Exit code and stderr of ``vehjax argv``, which must fail at once as a user error."""
    code = cli.main(argv)  # returns 2 also when argparse refused the option
    return code, capsys.readouterr()


@pytest.mark.parametrize(
    "argv, words",
    [
        (["simulate", "KinematicBicycle", "step_steer", "--out", "{file}"], ["--out", "not a folder"]),
        (["simulate", "KinematicBicycle", "step_steer", "--out", "{file}/sub"], ["--out", "not a folder"]),
        (["simulate", "KinematicBicycle", "step_steer", "--runs", "0"], ["--runs", ">= 1"]),
        (["simulate", "KinematicBicycle", "step_steer", "--runs", "2.5"], ["--runs", "integer"]),
        (["simulate", "KinematicBicycle", "step_steer", "--speed", "inf"], ["--speed", "finite"]),
        (["simulate", "KinematicBicycle", "step_steer", "--dt", "nan"], ["--dt", "finite"]),
        (["simulate", "KinematicBicycle", "step_steer", "--dt", "-0.01"], ["--dt", "> 0"]),
        (["simulate", "KinematicBicycle", "step_steer", "--meas-std", "0.1,inf"], ["--meas-std"]),
        (["simulate", "KinematicBicycle", "step_steer", "--process-std", "x"], ["--process-std"]),
        (["simulate", "NoSuchModel", "step_steer"], ["NoSuchModel"]),
        (["simulate", "KinematicBicycle", "no_such_scenario"], ["no_such_scenario"]),
        (["reproduce", "no_such_paper"], ["no_such_paper"]),
        (["reproduce", "wang2016", "--duration", "inf"], ["--duration", "finite"]),
        (["reproduce", "wang2016", "--out", "{file}"], ["--out", "not a folder"]),
        (["reproduce", "wang2016", "--filters", "NOPE"], ["--filters"]),
        (["reproduce", "wang2016", "--speed", "-inf"], ["--speed"]),
        (["reproduce", "dutta2019", "--kinematic-duration", "inf"], ["--kinematic-duration"]),
        (["reproduce", "dutta2019", "--dt", "0"], ["--dt", "> 0"]),
        (["reproduce", "dutta2019", "--settings", "bogus"], ["--settings"]),
        (["reproduce", "dutta2019", "--out", "{file}"], ["--out", "not a folder"]),
        (["reproduce", "consistency", "--models", "NoSuchModel"], ["--models", "NoSuchModel"]),
        (["reproduce", "consistency", "--duration", "nan"], ["--duration"]),
        (["reproduce", "consistency", "--out", "{file}"], ["--out", "not a folder"]),
        (["reproduce", "berntorp2018", "--particles", "0"], ["--particles"]),
        (["reproduce", "berntorp2018", "--duration", "inf"], ["--duration"]),
        (["reproduce", "berntorp2018", "--out", "{file}"], ["--out", "not a folder"]),
        (["bench", "no_such_bench"], ["no_such_bench"]),
        (["bench", "all", "--bogus"], ["bench all", "--bogus"]),
        (["bench", "device", "--repeat", "x"], ["bench device", "--repeat"]),
        (["bench", "smooth", "--runs", "two"], ["bench smooth", "--runs"]),
    ],
)
def test_user_errors_are_one_line_and_exit_code_2(tmp_path, capsys, argv, words):
    a_file = tmp_path / "a_file"
    a_file.write_text("not a folder")
    argv = [a.replace("{file}", str(a_file)) for a in argv]
    code, io = _user_error(capsys, argv)
    assert code == 2, (argv, io.err)
    lines = io.err.splitlines()
    assert len(lines) == 1 and "Traceback" not in io.err, io.err
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert io.out == ""  # refused before any work (nothing printed, nothing written)
    assert a_file.read_text() == "not a folder" and sorted(tmp_path.iterdir()) == [a_file]


def test_user_error_as_a_program_is_one_line_exit_2(tmp_path):
    a_file = tmp_path / "f"
    a_file.write_text("")
    for argv in (["reproduce", "wang2016", "--duration", "inf"],
                 ["simulate", "KinematicBicycle", "step_steer", "--out", str(a_file)]):
        out = subprocess.run([sys.executable, "-m", "vehjax.cli", *argv], capture_output=True,
                             text=True)
        assert out.returncode == 2 and len(out.stderr.splitlines()) == 1, out.stderr
        assert "Traceback" not in out.stderr


@pytest.mark.slow  # a study: `pytest -m slow` (README)
def test_bench_gaussian_smoke(capsys):
    """Tiny sizes: the three libraries must agree before any timing is printed."""
    assert cli.main(["bench", "gaussian", "--runs", "2", "--steps", "30", "--filterpy-runs", "1",
                     "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    assert "dynamax" in out and "filterpy" in out and "same estimates" in out
    assert "vehjax/x: vehjax's run time divided by this library's" in out  # the ratio column


@pytest.mark.slow  # a study: `pytest -m slow` (README)
def test_bench_liu_west_bias_smoke(capsys):
    """Tiny sizes, the scalar skewed-posterior piece: both kernel timings are compared with the
    exact posterior mean; an unknown piece is refused naming --parts."""
    assert cli.main(["bench", "liu_west_bias", "--parts", "skewed", "--small-runs", "4"]) == 0
    out = capsys.readouterr().out
    lines = [line for line in out.splitlines() if "(estimate - exact mean) / std" in line]
    assert len(lines) == 4 and all(np.isfinite(float(line.split("mean ")[1].split()[0]))
                                   for line in lines)
    assert sum("move=every" in line for line in lines) == 2
    with pytest.raises(SystemExit, match="--parts"):
        cli.main(["bench", "liu_west_bias", "--parts", "bogus"])


@pytest.mark.slow  # a study: `pytest -m slow` (README)
def test_bench_all_smoke(capsys):
    """Tiny sizes, the EKF row (vehjax, dynamax, cuthbert): the estimates are checked equal
    before any timing, and the table has a line per library and the row's ratio. One row only:
    each row compiles five to eight studies, about 20 s here; the ukf, pf and liu_west rows
    take as long each (``vehjax bench all`` runs them all)."""
    assert cli.main(["bench", "all", "--runs", "2", "--steps", "20", "--repeat", "1",
                     "--rows", "ekf"]) == 0
    out = capsys.readouterr().out
    assert "[EKF] check: max |vehjax - peer| of the filtered means: dynamax" in out
    assert "cuthbert" in out and "(tol 1e-06): ok" in out
    table = [line for line in out.splitlines() if line.startswith("EKF ")]
    assert [line.split()[1] for line in table] == ["vehjax", "dynamax", "cuthbert"]
    assert "ratio EKF: vehjax / fastest peer" in out
    assert "every row at most 0.5x the fastest peer:" in out


def test_simulate_too_large_for_memory_is_one_line_before_the_scenario_is_driven(monkeypatch, capsys):
    import functools

    from vehjax import scenarios

    driven = []

    @functools.wraps(scenarios.step_steer)  # the same signature, so the same default duration
    def step_steer(*a, **k):
        driven.append(a)
        return scenarios.step_steer(*a, **k)

    monkeypatch.setitem(scenarios.REGISTRY, "step_steer", step_steer)
    code, io = _user_error(capsys, ["simulate", "KinematicBicycle", "step_steer",
                                    "--runs", "100000000000"])
    assert code == 2 and len(io.err.splitlines()) == 1 and io.out == "", io.err
    assert io.err.startswith("vehjax simulate: error: --runs, --dt: 100000000000 runs x 600 steps")
    assert "fewer runs" in io.err and not driven


def test_out_of_memory_at_run_time_is_one_line_other_runtime_errors_propagate(monkeypatch, capsys):
    import importlib

    sim_mod = importlib.import_module("vehjax.simulate")

    def oom(*a, **k):
        raise RuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 9 GiB.\n"
                           "BufferAssignment details ...")

    monkeypatch.setattr(sim_mod, "simulate", oom)
    code, io = _user_error(capsys, ["simulate", "KinematicBicycle", "step_steer", "--runs", "2"])
    assert code == 2 and io.err.splitlines() == [
        "vehjax: error: out of memory: RESOURCE_EXHAUSTED: Out of memory while trying to allocate "
        "9 GiB.; use fewer runs, steps or particles"], io.err

    def other(*a, **k):
        raise RuntimeError("something else")

    monkeypatch.setattr(sim_mod, "simulate", other)
    with pytest.raises(RuntimeError, match="something else"):
        cli.main(["simulate", "KinematicBicycle", "step_steer", "--runs", "2"])
