"""`vehjax reproduce dutta2019` at a reduced size: runs end to end, tables and figures written."""

import re
from types import SimpleNamespace

import jax
import numpy as np
import pytest

import vehjax as vj
from vehjax import cli
from vehjax.reproduce import dutta2019


def _check_tuning(args, tuning):
    """One stage's tuned settings, from the arguments ``tuned_settings`` was called with."""
    paper, model, scn, estimate, truth, box, key = args
    dt = model.dt
    # (b) fitted on training runs drawn for this stage, which are not the study's runs
    ys_t = np.asarray(tuning.sim.measurements)
    np.testing.assert_array_equal(ys_t, dutta2019.training_runs(model, scn, 3, key).measurements)
    ys_s = np.asarray(dutta2019.study_runs(model, scn, 3, key).measurements)
    assert np.abs(ys_t[:, None] - ys_s[None, :]).max(axis=(2, 3)).min() > 0.1  # no run shared
    # (a) Q and R near the simulation's noise, and nearer than the paper's where it is off
    for which, sim_var, factor in (("Q", 0.1**2 * dt, 5.0), ("R", 0.1**2, 2.0)):
        tuned, printed = np.asarray(tuning.settings[which]), np.asarray(paper[which])
        np.testing.assert_allclose(tuned, np.diag(getattr(tuning.fit, which)))
        assert np.all(np.abs(np.log(tuned / sim_var)) < np.log(factor)), (which, tuned)
        off = np.abs(np.log(printed / sim_var)) > np.log(2.0)
        assert off.sum() >= 2
        assert np.all(np.abs(np.log(tuned / sim_var))[off] < np.abs(np.log(printed / sim_var))[off])
    # everything but Q and R as in the matched setting
    matched = dutta2019.matched_settings(paper, model, truth, box)
    for k in ("P0", "P_theta0", "Q_theta"):
        np.testing.assert_allclose(tuning.settings[k], matched[k])
    return tuning


@pytest.mark.slow  # a study: `pytest -m slow` (README)
def test_reduced_study_writes_tables_and_figures(tmp_path, capsys, monkeypatch):
    # the tuned setting: Q, R fitted on training runs, the rest as matched (matched_settings is
    # checked on its own below); the real tuned_settings runs, watched
    calls = []
    real = dutta2019.tuned_settings

    def watched(*args, **kwargs):
        out = real(*args, **kwargs)
        calls.append((args, kwargs, out))
        return out

    monkeypatch.setattr(dutta2019.study, "tuned_settings", watched)  # where the stages call it
    rc = cli.main([
        "reproduce", "dutta2019", "--runs", "3", "--particles", "64", "--settings", "tuned",
        "--filters", "Dual UKF,Particle+UKF",
        "--kinematic-duration", "4", "--dynamic-duration", "3", "--out", str(tmp_path),
    ])
    assert rc == 0
    report = (tmp_path / "report.md").read_text()
    for heading in ("Table I", "Table II", "Table III", "Fig. 6"):
        assert f"### {heading}" in report and f"### {heading}: " in report.split("## tuned")[1]
    assert "(tuned settings)" in report and "(matched settings)" not in report
    # the tuned Q and R of both stages, printed beside the paper's and the simulation's
    assert [c[0][3] for c in calls] == [("lf", "lr"), ("m", "cx", "cy")]
    for (args, kwargs, tuning), stage in zip(calls, ("kinematic model", "dynamic model")):
        _check_tuning(args, tuning)
        part = report.split(f"### Tuned Q and R, {stage}")[1].split("###")[0]
        assert "Training set: 3 runs x" in part and "not the study's runs" in part
        model, paper = args[1], args[0]
        for which, names, sim_var in (("Q", model.state_names, 0.1**2 * model.dt),
                                      ("R", model.output_names, 0.1**2)):
            for n, a, b in zip(names, paper[which], tuning.settings[which]):
                assert re.search(rf"\| {which} {n} \[[^]]+\] \| {a:.3g} \| {b:.3g} \| "
                                 rf"{sim_var:.3g} \|", part), (which, n)
    # the dynamic fit holds lf, lr at what the kinematic fit found
    assert calls[1][1]["fixed"] == calls[0][2].fit.params
    for name in ("Dual UKF", "Particle+UKF"):
        assert f"| {name} (vehjax) |" in report
    assert "| Joint EKF (vehjax) |" not in report and "| Dual EKF (vehjax) |" not in report
    assert "| Dual UKF (paper) | 1.580 | 1.390 |" in report
    assert "| Particle+UKF (paper) | 0.1727 | 0.1566 | 0.0630 |" in report
    assert "nan" not in report.lower()
    # consistency (NEES, NIS, parameter coverage) per filter and stage, shares in [0, 1]
    for stage, n_par in (("kinematic model", 2), ("dynamic model", 3)):
        part = report.split(f"### Consistency, {stage} (tuned settings)")[1].split("###")[0]
        for name in ("Dual UKF", "Particle+UKF"):
            cells = next(ln for ln in part.splitlines() if ln.startswith(f"| {name} |")).split("|")
            shares = [float(cells[2]), float(cells[4])] + [float(v) for v in cells[6].split(",")]
            assert len(shares) == 2 + n_par and all(0.0 <= v <= 1.0 for v in shares), (name, cells)
            assert float(cells[3]) > 0 and float(cells[5]) > 0
    for png in ("fig4_5_kinematic_lf_lr", "fig6_input_frequency", "fig7_9_dynamic_states",
                "fig10_12_dynamic_m_cx_cy"):
        assert (tmp_path / f"{png}_tuned.png").stat().st_size > 10_000
    # report.md links every figure it wrote, and every link is a file
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report)
    assert sorted(links) == pngs and len(pngs) == 4
    # units in the headers, the guesses beside the estimates, the verdict in words
    assert "| filter | lf [m] | lr [m] |" in report and "cx [1e4 N]" in report
    assert "RMSE vx [m/s]" in report and "| raw measurements |" in report
    assert report.count("| initial guess |") == 2
    assert report.count("**What is learned and what is not.**") == 2
    printed = capsys.readouterr().out
    assert "Table III" in printed and "Tuned Q and R, dynamic model" in printed


def _stage(frozen=(), runs=6, steps=50, same_states=False, seed=0):
    """A synthetic dynamic-model Stage: filters "A", "B", "C"; the parameters named in
    ``frozen`` stay at each run's initial guess, the others converge to the truth."""
    rng = np.random.default_rng(seed)
    truth = np.array([1700.0, 1.5e5, 4.0e4])
    theta0 = truth * (1 + rng.uniform(-0.3, 0.3, (runs, 3)))
    decay = np.exp(-np.arange(steps) / 5.0)[None, :, None]
    states = rng.normal(size=(runs, steps, 3))
    sim = SimpleNamespace(t=np.arange(steps) * 0.02, states=states,
                          measurements=states + 0.1 * rng.normal(size=states.shape),
                          state_names=("vx", "vy", "r"), output_names=("vx", "vy", "r"))
    results = {}
    for k, name in enumerate("ABC"):
        params = truth + (theta0[:, None, :] - truth) * decay
        for j, p in enumerate(("m", "cx", "cy")):
            if (name, p) in frozen or p in frozen:
                params[..., j] = theta0[:, None, j]
        noise = 0.05 if same_states else 0.05 * (k + 1)
        rng_k = np.random.default_rng(seed + (0 if same_states else k))
        est = states + noise * rng_k.normal(size=states.shape)
        results[name] = SimpleNamespace(params=params, states=est, diverged=np.zeros(runs, bool))
    box = np.stack([0.7 * truth, 1.3 * truth], 1)
    return dutta2019.Stage(sim, results, truth, ("m", "cx", "cy"), {}, theta0,
                           ("kg", "N", "N/rad"), ("m/s", "m/s", "rad/s"), box)


def test_a_parameter_left_at_its_guess_is_reported_as_not_learned():
    st = _stage(frozen=("cx",))
    tol = 0.03 * st.truth
    verdicts = dutta2019.learning(st, tol)
    assert {v[0] for v in verdicts["cx"].values()} == {"not learned"}
    assert {v[0] for v in verdicts["m"].values()} == {"learned"}
    text = dutta2019.learning_summary(st, tol, "3 % of the truth", scale=(1, 1e4, 1e4),
                                      digits=(1, 3, 3))
    g = st.theta0[:, 1] / 1e4
    assert "**cx** [1e4 N]" in text and "**not learned by any filter**" in text
    assert f"{g.mean():.3f} +- {g.std():.3f}" in text  # the guesses' mean and spread, from the data
    assert "Particle+UKF" not in text  # no box-prior filter in this study
    assert "**m** [kg]" in text and "learned by A" in text
    assert "not learned" not in text.split("- **m**")[1].split("- **cx**")[0]


def test_not_learned_names_only_the_filters_that_left_it():
    st = _stage(frozen=(("A", "cy"), ("B", "cy")))
    text = dutta2019.learning_summary(st, 0.03 * st.truth, "3 %")
    line = next(ln for ln in text.splitlines() if ln.startswith("- **cy**"))
    assert "**not learned by A and B**" in line and "learned by C" in line
    assert "not learned" not in text.split("- **cy**")[0].split("- **m**")[1]  # m, cx learned


def test_a_box_prior_filter_starting_at_the_truth_is_not_called_not_learned():
    st = _stage()
    results = dict(st.results)
    res = results.pop("C")
    # the particle filter's prior is the box, centred on the truth: it starts there and stays
    results["Particle+UKF"] = SimpleNamespace(
        params=np.broadcast_to(st.truth, res.params.shape).copy(), states=res.states,
        diverged=res.diverged)
    st = st._replace(results=results)
    verdicts = dutta2019.learning(st, 0.03 * st.truth)
    assert all(verdicts[p]["Particle+UKF"][0] == "learned" for p in st.names)
    drifting = SimpleNamespace(params=results["Particle+UKF"].params * 1.1, states=res.states,
                               diverged=res.diverged)
    moved = dutta2019.learning(st._replace(results={**results, "Particle+UKF": drifting}),
                               0.03 * st.truth)
    assert all(moved[p]["Particle+UKF"][0] == "drifted" for p in st.names)
    text = dutta2019.learning_summary(st, 0.03 * st.truth, "3 %")
    assert "Particle+UKF starts from the centre of its prior box" in text
    assert "not learned" not in text.split("- **m**")[1]
    table = dutta2019.table_parameters(st, {}, 0.02, 0.03 * st.truth, (1, 3, 3))
    assert "| Particle+UKF prior mean (box centre) | 1700.0 (0.0) |" in table


def test_identical_state_rmse_rows_are_said_in_words():
    same = _stage(frozen=(("A", "cx"),), same_states=True)
    text = dutta2019.states_summary(same, 0.03 * same.truth)
    assert "every filter alike" in text and "All 3 filters have the same state RMSE" in text
    assert "learned m, cx and cy differently" in text
    assert "raw-measurement RMSE" in text
    table = dutta2019.table_states(same, {})
    assert "| raw measurements |" in table and "RMSE vx [m/s]" in table
    differ = _stage()
    assert "alike" not in dutta2019.states_summary(differ, 0.03 * differ.truth)
    assert dutta2019.same_rmse_groups(dutta2019.state_rmse(differ)) == []


def test_parameter_figure_has_units_and_runs(tmp_path):
    st = _stage(frozen=("cx",), runs=4, steps=20)
    path = dutta2019.plot_parameters(st, tmp_path / "p.png", "m, cx, cy", scale=(1, 1e4, 1e4),
                                     tol=0.03 * st.truth)
    assert path.stat().st_size > 10_000
    from vehjax import plots

    assert plots.label("cx", "N", 1e4) == "cx [1e4 N]" and plots.label("s", "-") == "s [-]"


def test_chirp_excitation_sweeps_up_around_15_m_s():
    """--excitation chirp's scenario (#17 item 3's second excitation): the speed swings around
    15 m/s and the steering sweeps up in frequency."""
    dyn = vj.models.Dynamic3DOF(dt=0.02)
    scn = dutta2019.chirp_scenario(dyn, duration=60.0)
    sim = vj.simulate(dyn, scn, runs=1, key=jax.random.key(0))
    vx = np.asarray(sim.states)[0, :, 0]
    assert 11.0 < vx.min() < 15.0 < vx.max() < 19.0
    delta = np.asarray(scn.inputs)[:, 4]
    crossings = np.flatnonzero(np.diff(np.sign(delta)) != 0)
    first, last = np.sum(crossings < 1000), np.sum(crossings >= 2000)  # first / last 20 s
    assert last > 3 * first  # 0.1 Hz -> 1.5 Hz
    assert np.all(np.asarray(scn.inputs)[:, 2:4] == 0.0)


def test_bad_options_are_refused():
    with pytest.raises(ValueError, match="--filters"):
        dutta2019.main(["--filters", "Dual KF"])
    with pytest.raises(ValueError, match="--settings"):
        dutta2019.main(["--settings", "tuning"])
    with pytest.raises(ValueError, match="--runs"):
        dutta2019.main(["--runs", "1"])
    # a stage shorter than two steps: named, in seconds and steps, not an internal array
    with pytest.raises(ValueError, match="^--kinematic-duration: expected at least two steps"):
        dutta2019.main(["--kinematic-duration", "0.01"])
    with pytest.raises(ValueError, match="^--dynamic-duration: expected at least two steps"):
        dutta2019.main(["--dynamic-duration", "0.03", "--dt", "0.02"])


def test_settings_option_accepts_tuned_and_runs_all_three_by_default():
    p = dutta2019.parser()
    assert dutta2019._check_args(p.parse_args([]))[1] == ("paper", "matched", "tuned")
    assert dutta2019._check_args(p.parse_args(["--settings", "tuned"]))[1] == ("tuned",)
    assert "vehjax.tune" in p.format_help()


def test_settings_side_by_side():
    a, b = _stage(), _stage(frozen=("cx",))
    table = dutta2019.table_settings({"matched": a, "tuned": b}, scale=(1, 1e4, 1e4),
                                     digits=(1, 3, 3))
    err = np.abs(b.results["B"].params[:, -5:].mean(axis=1) - b.truth).mean(axis=0) / [1, 1e4, 1e4]
    assert f"| B | tuned | {err[0]:.1f} | {err[1]:.3f} | {err[2]:.3f} | 0/6 |" in table
    assert "| filter | setting | error m [kg] | error cx [1e4 N] |" in table
    assert table.count("| matched |") == table.count("| tuned |") == 3
    states = dutta2019.table_settings_states({"matched": a, "tuned": b})
    assert "| filter | setting | RMSE vx [m/s] |" in states and states.count("| tuned |") == 3
    text = "\n".join(dutta2019._report_settings({"matched": (a, a), "tuned": (b, b)}))
    for heading in ("Table I", "Table II", "Table III"):
        assert f"### {heading}: " in text
    assert table in text and states in text


@pytest.mark.slow  # compiles filters and smoothers: `pytest -m slow` (README)
def test_smoothed_rows_beside_the_joint_filters_and_below_their_rmse():
    """Table II's smoothed rows (issue 29, item 4): the joint filters' own RTS on the same runs
    (``_stage(..., smooth=True)``), a row each beside the filter's, with a state RMSE below the
    filter's in every state (smoothing uses the future too); the dual filter gets none."""
    kin = vj.models.KinematicBicycle(dt=0.05)
    scn = dutta2019.kinematic_scenario(kin, duration=6.0)
    box = [(0.5, 2.5), (0.5, 2.5)]
    cfg = dutta2019.matched_settings(dutta2019.KINEMATIC_SETTINGS, kin, np.asarray(kin.theta), box)
    builders = dutta2019._builders(kin, cfg, ("lf", "lr"), box, particles=8)
    ests = {n: builders[n]() for n in ("Joint EKF", "Joint UKF")}
    assert builders["Dual EKF"]().smoother is None  # no smoothed row for the dual filters
    st = dutta2019._stage(kin, scn, ("lf", "lr"), cfg, box, 3, jax.random.key(3), ests,
                          smooth=True)
    assert sorted(st.smoothed) == ["Joint EKF", "Joint UKF"]
    table = dutta2019.table_states(st, {})
    for name in ("Joint EKF", "Joint UKF"):
        assert f"| {name} RTS-smoothed (vehjax, offline) |" in table
        filt, sm = st.results[name], st.smoothed[name]
        assert not np.any(filt.diverged) and not np.any(sm.diverged)
        assert sm.states.shape == filt.states.shape
        r_f = np.sqrt(np.mean((filt.states - np.asarray(st.sim.states)) ** 2, axis=(0, 1)))
        r_s = np.sqrt(np.mean((sm.states - np.asarray(st.sim.states)) ** 2, axis=(0, 1)))
        assert np.all(r_s < r_f), (name, r_s, r_f)
        # the smoothed estimate at the last step is the filter's (nothing after it)
        np.testing.assert_allclose(sm.states[:, -1], filt.states[:, -1], rtol=1e-9, atol=1e-9)
    assert "Smoothed over filtered state RMSE: Joint EKF" in dutta2019.smoothed_summary(st)
    p = dutta2019.parser()
    assert p.parse_args([]).smooth and not p.parse_args(["--no-smooth"]).smooth


def test_presentation_names_are_lent_by_the_study_module():
    """The tables, figures and CLI live in dutta2019.report; the package lends their names."""
    from vehjax.reproduce.dutta2019 import report

    for name in dutta2019._PRESENTATION:
        assert getattr(dutta2019, name) is getattr(report, name), name
    with pytest.raises(AttributeError, match="no_such_name"):
        dutta2019.no_such_name  # noqa: B018
