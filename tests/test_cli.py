"""Commands refuse bad input with a clear message and a non-zero exit status."""

import inspect
import subprocess
import sys


def _run(*args):
    return subprocess.run([sys.executable, "-m", "hdjax.fit", *args], capture_output=True, text=True, timeout=120)


def test_fit_missing_target_fails_with_message(tmp_path):
    r = _run(str(tmp_path / "nope"), "--out", str(tmp_path / "out"))
    assert r.returncode != 0
    assert "nope" in r.stderr
    assert not (tmp_path / "out" / "fit.json").exists()


def test_fit_bad_dataset_names_file_and_field(tmp_path):
    (tmp_path / "dataset.yaml").write_text("name: x\nexperiments:\n  - file: a.csv\n    mode: sideways\n")
    (tmp_path / "a.csv").write_text("time,current\n0,0\n")
    r = _run(str(tmp_path), "--out", str(tmp_path / "out"))
    assert r.returncode == 2
    assert "dataset.yaml" in r.stderr and "mode" in r.stderr


# ---------------------------------------------------------------------------------------------
# The `hdjax` command: one parser, strict configs, run.log, report.html, --quiet

import pathlib

import pytest

from hdjax import ConfigError
from hdjax._workflows import cli as _cli
from hdjax._workflows.config import check_keys, section_options


def _help(capsys, argv):
    with pytest.raises(SystemExit) as e:
        _cli.main(argv)
    assert e.value.code == 0
    return " ".join(capsys.readouterr().out.split())  # help text wraps with the terminal width


def test_help_lists_commands_and_every_option_with_its_default(capsys):
    top = _help(capsys, ["--help"])
    for cmd in ("fit", "diagnose", "sensitivity", "tune"):
        assert cmd in top
    fit = _help(capsys, ["fit", "--help"])
    for opt in ("TARGET", "--out DIR", "--quiet", "default: results/<TARGET name>", "default: off"):
        assert opt in fit, opt
    # the config file's options, with their defaults
    for line in ("fit.alpha = 0.5", "fit.Tss2 = 0.1", "fit.trajectory.max_steps = 20", "fit.trajectory.rtol = 1e-05"):
        assert line in fit, line
    sens = _help(capsys, ["sensitivity", "--help"])
    assert "--fit FIT_JSON" in sens and "sensitivity.rtol = 0.0001" in sens
    assert "results/<TARGET name>-sensitivity" in sens
    tune = _help(capsys, ["tune", "--help"])
    assert "tune.plants = 6" in tune and "--fit FIT_JSON" in tune
    diag = _help(capsys, ["diagnose", "--help"])
    assert "diagnose.max_findings = 3" in diag


def test_module_mains_are_the_same_command():
    from hdjax import diagnose, fit, sensitivity, tune

    for mod in (fit, diagnose, sensitivity, tune):
        assert callable(mod.main)
    r = subprocess.run([sys.executable, "-m", "hdjax.sensitivity", "--help"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and "usage: hdjax sensitivity" in r.stdout and "--fit FIT_JSON" in r.stdout
    assert "sensitivity.max_experiments = 50" in r.stdout


def test_unknown_key_names_the_nearest_valid_one():
    with pytest.raises(ConfigError, match=r"\['plantz'\] \(`plantz`: did you mean `plants`\?\)"):
        check_keys({"plantz": 1}, ["plants", "seed"], "config `tune:`")
    with pytest.raises(ConfigError, match=r"`fit.trajectory:`.*`max_step`: did you mean `max_steps`"):
        section_options({"fit": {"trajectory": {"max_step": 3}}}, "fit",
                        {"alpha": 0.5, "trajectory": {"max_steps": 20}}, nested=("trajectory",))
    opts = section_options({"fit": {"alpha": 0.4}}, "fit", {"alpha": 0.5, "trajectory": {"max_steps": 20}},
                           nested=("trajectory",))
    assert opts == {"alpha": 0.4, "trajectory": {"max_steps": 20}}


@pytest.mark.parametrize(
    "text, key, nearest",
    [
        ("fit:\n  alpah: 0.5\n", "alpah", "alpha"),
        ("fit:\n  trajectory:\n    max_experimnts: 4\n", "max_experimnts", "max_experiments"),
        ("tunee:\n  plants: 3\n", "tunee", "tune"),
        ("diagnose:\n  max_finding: 2\n", "max_finding", "max_findings"),
    ],
)
def test_config_with_unknown_key_is_refused_before_any_work(tmp_path, capsys, text, key, nearest):
    cfg = tmp_path / "configs" / "c.yaml"
    cfg.parent.mkdir()
    cfg.write_text("dataset: ../../../data/hd2\n".replace("../../../data/hd2", str(_repo() / "data" / "hd2")) + text)
    assert _cli.main(["fit", str(cfg), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert f"`{key}`: did you mean `{nearest}`?" in err
    assert not (tmp_path / "out").exists()


def _repo() -> pathlib.Path:
    return pathlib.Path(__file__).resolve().parents[1]


def _fake_run(command, dataset, config, out, log):
    """Stands in for a workflow: logs, shows a bar, writes report.md with a table and a figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from hdjax._workflows.progress import task

    log(f"[1/1] {command} on {dataset.name}")
    with task(log, "work", 3, unit="items") as bar:
        for k in range(3):
            bar.advance(1, info=f"item {k}", line=f"  detail {k}")
    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(4, 3))
    ax.plot([0, 1, 2], [0, 1, 4], color="C3", lw=4)
    fig.savefig(out / "fig1.png", dpi=80)
    plt.close(fig)
    (out / "report.md").write_text(
        "# Report of `x`\n\nSome **text**.\n\n| parameter | value |\n|---|---|\n| K1 | 5970 |\n| Tst | 60.2 |\n\n"
        "## Figures\n\n![fig1.png](fig1.png)\n", encoding="utf-8")


def test_run_log_report_html_and_quiet(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(_cli, "_run_command", _fake_run)
    out = tmp_path / "out"
    assert _cli.main(["tune", str(_repo() / "data" / "hd2"), "--out", str(out), "--quiet"]) == 0
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err == ""
    log = (out / "run.log").read_text()
    assert "[1/1] tune on hd2" in log and "detail 2" in log and "work: 3/3 items" in log and "report.html" in log
    html = (out / "report.html").read_text()
    assert "<table>" in html and "<td>5970</td>" in html and 'src="data:image/png;base64,' in html
    assert "fig1.png\"" not in html.replace('alt="fig1.png"', "")  # embedded, not linked
    # not quiet: the lines are printed too
    assert _cli.main(["tune", str(_repo() / "data" / "hd2"), "--out", str(out)]) == 0
    assert "[1/1] tune on hd2" in capsys.readouterr().out


def test_default_output_folders():
    assert _cli.default_out("fit", "configs/hd2.yaml") == pathlib.Path("results/hd2")
    assert _cli.default_out("diagnose", "data/hd1") == pathlib.Path("results/hd1-diagnosis")
    assert _cli.default_out("sensitivity", "configs/hd2.yaml") == pathlib.Path("results/hd2-sensitivity")
    assert _cli.default_out("tune", "data/hd2/dataset.yaml") == pathlib.Path("results/hd2-tune")


@pytest.mark.parametrize("command", ["diagnose", "tune"])
def test_fit_cutoff_reaches_the_paper_identification_of_every_command(command, monkeypatch, tmp_path):
    """`fit.cutoff_hz` (and alpha, Tss2) of the config reach the paper's regressions in `diagnose`
    and `tune` as they do in `fit` and `sensitivity` (both dropped it before)."""
    from hdjax import load_dataset
    from hdjax._fit import paper as _paper_id
    from hdjax._workflows import diagnose as _diagnose_report, tune as _tune

    seen = {}

    class Stop(Exception):
        pass

    def spy(exps, drive, **kw):
        seen.update(kw)
        raise Stop

    monkeypatch.setattr(_paper_id, "identify_paper", spy)
    monkeypatch.setattr(_diagnose_report, "identify_paper", spy)
    # from an empty folder: `tune` takes results/<dataset>/fit.json from the working directory when
    # there is one (the README's first command writes it), and then runs no paper identification
    monkeypatch.chdir(tmp_path)
    ds = load_dataset(_repo() / "data" / "hd2")
    config = {"fit": {"cutoff_hz": 30.0, "alpha": 0.6, "Tss2": 0.2}}
    run = _diagnose_report.run_diagnose if command == "diagnose" else _tune.run_tune
    with pytest.raises(Stop):
        run(ds, config, tmp_path / "out", log=lambda *a: None)
    assert seen == {"alpha": 0.6, "Tss2": 0.2, "cutoff_hz": 30.0}


def test_fit_trajectory_solver_option_builds_the_named_simulator():
    """`fit.trajectory.solver` picks the trajectory fit's numerics: the fixed-step implicit
    velocity-level stepper with `substeps` (the default), adaptive Rosenbrock-W (`Ros34PW2` with
    the plant's stiff part) or adaptive Rodas3 at `rtol`; a bad value names its key."""
    import hdjax
    from hdjax._workflows.fit import DEFAULTS, trajectory_simulator

    opts = dict(DEFAULTS["trajectory"])
    assert opts["solver"] == "velocity_implicit"
    sim = trajectory_simulator(opts)
    assert isinstance(sim.solver, hdjax.VelocityImplicit) and sim.solver.substeps == opts["substeps"]
    sim = trajectory_simulator({**opts, "solver": "ros34pw2"})
    assert sim.rtol == opts["rtol"] and isinstance(sim.solver, hdjax.Ros34PW2)
    assert sim.solver.stiff_part is hdjax.plant_stiff_part
    sim = trajectory_simulator({**opts, "solver": "rodas3"})
    assert sim.rtol == opts["rtol"] and isinstance(sim.solver, hdjax.Rodas3)
    sim = trajectory_simulator({**opts, "solver": "velocity_implicit", "substeps": 2})
    assert isinstance(sim.solver, hdjax.VelocityImplicit) and sim.solver.substeps == 2
    assert not sim.solver.reversal_quadrature
    sim = trajectory_simulator({**opts, "reversal_quadrature": True})
    assert isinstance(sim.solver, hdjax.VelocityImplicit) and sim.solver.reversal_quadrature
    with pytest.raises(ValueError, match=r"fit\.trajectory\.reversal_quadrature.*true or false"):
        trajectory_simulator({**opts, "reversal_quadrature": "yes"})
    with pytest.raises(ValueError, match=r"fit\.trajectory\.solver.*velocity_implicit"):
        trajectory_simulator({**opts, "solver": "euler"})
    with pytest.raises(ValueError, match=r"fit\.trajectory\.substeps"):
        trajectory_simulator({**opts, "solver": "velocity_implicit", "substeps": 0})
    with pytest.raises(ValueError, match=r"fit\.trajectory\.rtol.*\(0, 0\.1\]"):
        trajectory_simulator({**opts, "solver": "ros34pw2", "rtol": 0.0})


def test_fit_sensor_bandwidth_option_frees_both_sensor_lags():
    """`fit.trajectory.sensor_bandwidth` (default true) makes the joint fit apply a first-order lag
    to the simulated torque and motor velocity and fit both time constants from 0 on the scale of
    the sample period; `breakaway_friction` (default true) switches the breakaway torques on at 0
    for `fit_breakaway_friction`'s grid search (not freed in LM: no derivative) and needs the
    fixed-step solver: set true with an adaptive one it is refused, left to its default it is off
    (and `run_fit` says so); false fits none; anything but true or false names its key."""
    from hdjax._workflows.fit import DEFAULTS, SENSOR_LAGS, _options, fit_model_form

    opts = dict(DEFAULTS["trajectory"])
    assert opts["sensor_bandwidth"] is True and opts["breakaway_friction"] is True
    effects, free = fit_model_form(opts, 1e-3)
    assert effects.active == {"sensor_bandwidth", "breakaway_friction"} and free == {path: 1e-3 for path in SENSOR_LAGS}
    assert float(effects.sensor_bandwidth.torque_lag) == float(effects.sensor_bandwidth.velocity_lag) == 0.0
    assert float(effects.breakaway_friction.breakaway_p) == float(effects.breakaway_friction.breakaway_n) == 0.0
    effects, free = fit_model_form({**opts, "sensor_bandwidth": False, "breakaway_friction": False}, 1e-3)
    assert not effects.active and free == {}
    for key in ("sensor_bandwidth", "breakaway_friction"):
        with pytest.raises(ValueError, match=rf"fit\.trajectory\.{key}.*true or false"):
            _options({"fit": {"trajectory": {key: "on"}}})
    with pytest.raises(ValueError, match=r"breakaway_friction: true.*velocity_implicit"):
        _options({"fit": {"trajectory": {"solver": "rodas3", "breakaway_friction": True}}})
    assert _options({"fit": {"trajectory": {"solver": "rodas3"}}})["trajectory"]["breakaway_friction"] is False
    assert _options({})["trajectory"]["breakaway_friction"] is True


def test_freed_effect_parameters_are_checked_before_any_work():
    """`fit_parameters(free_effects=...)`: a path that names no effect field, a term that `effects`
    does not switch on, or a scale that is not positive is refused with the path named."""
    from hdjax import Effects
    from hdjax._fit.least_squares import make_effect_map
    from hdjax._model.effects import SensorBandwidth

    on = Effects().with_term(SensorBandwidth())
    assert make_effect_map(on, None) is None and make_effect_map(on, {}) is None
    emap = make_effect_map(on.with_values("sensor_bandwidth", torque_lag=2e-4), {"sensor_bandwidth.torque_lag": 1e-3})
    assert emap is not None and emap.fields == ("sensor_bandwidth.torque_lag",)
    assert float(emap.to_vector(on.with_values("sensor_bandwidth", torque_lag=2e-4))[0]) == 0.0  # starts where given
    with pytest.raises(ValueError, match=r"sensor_bandwidth\.torque_delay.*'<term>\.<field>'"):
        make_effect_map(on, {"sensor_bandwidth.torque_delay": 1e-3})
    with pytest.raises(ValueError, match=r"sensor_bandwidth\.torque_lag.*does not switch"):
        make_effect_map(Effects(), {"sensor_bandwidth.torque_lag": 1e-3})
    with pytest.raises(ValueError, match=r"scale > 0"):
        make_effect_map(on, {"sensor_bandwidth.torque_lag": 0.0})


def test_diagnose_solver_option_builds_the_named_simulator():
    """`diagnose.solver` picks the diagnosis's numerics: the fixed-step stepper at `substeps` (the
    default, as the library's `diagnose`) or adaptive Rodas3 at `rtol`, both with the periodic terms
    at the measured angle unless `measured_angle` is off; a bad value names its key."""
    import hdjax
    from hdjax._discrepancy.loop import diagnose
    from hdjax._workflows.diagnose import DEFAULTS, diagnosis_simulator

    opts = dict(DEFAULTS)
    sim = diagnosis_simulator(opts)
    assert isinstance(sim.solver, hdjax.VelocityImplicit) and sim.solver.substeps == opts["substeps"] == 4
    assert sim.measured_angle and sim == inspect.signature(diagnose).parameters["simulator"].default
    sim = diagnosis_simulator({**opts, "solver": "rodas3", "rtol": "1e-5", "measured_angle": False})
    assert isinstance(sim.solver, hdjax.Rodas3) and sim.rtol == 1e-5 and not sim.measured_angle
    with pytest.raises(ValueError, match=r"diagnose\.solver.*velocity_implicit"):
        diagnosis_simulator({**opts, "solver": "ros34pw2"})
    with pytest.raises(ValueError, match=r"diagnose\.substeps"):
        diagnosis_simulator({**opts, "substeps": 0})
    with pytest.raises(ValueError, match=r"diagnose\.rtol"):
        diagnosis_simulator({**opts, "solver": "rodas3", "rtol": 2.0})


def test_sensitivity_solver_option_builds_the_named_simulator():
    """`sensitivity.solver` picks the sensitivity and ablation numerics: the fixed-step stepper at
    `substeps` (the default since 2026-12-05) or adaptive Rodas3 at `rtol` with its step budget
    `max_steps`; a bad value names its key."""
    import hdjax
    from hdjax._workflows.sensitivity import DEFAULTS, workflow_simulator

    opts = dict(DEFAULTS)
    sim = workflow_simulator(opts)
    assert isinstance(sim.solver, hdjax.VelocityImplicit) and sim.solver.substeps == opts["substeps"] == 4
    sim = workflow_simulator({**opts, "solver": "velocity_implicit", "substeps": 8})
    assert isinstance(sim.solver, hdjax.VelocityImplicit) and sim.solver.substeps == 8
    sim = workflow_simulator({**opts, "solver": "rodas3"})
    assert isinstance(sim.solver, hdjax.Rodas3) and sim.rtol == opts["rtol"] == 1e-4 and sim.max_steps == 20_000
    sim = workflow_simulator({**opts, "solver": "rodas3", "rtol": "1e-5", "max_steps": 5000})
    assert sim.rtol == 1e-5 and sim.max_steps == 5000
    with pytest.raises(ValueError, match=r"sensitivity\.solver.*velocity_implicit"):
        workflow_simulator({**opts, "solver": "ros34pw2"})
    with pytest.raises(ValueError, match=r"sensitivity\.substeps"):
        workflow_simulator({**opts, "solver": "velocity_implicit", "substeps": 1.5})
    with pytest.raises(ValueError, match=r"sensitivity\.rtol"):
        workflow_simulator({**opts, "solver": "rodas3", "rtol": 0.0})
    with pytest.raises(ValueError, match=r"sensitivity\.max_steps"):
        workflow_simulator({**opts, "solver": "rodas3", "max_steps": -1})


def test_per_experiment_fits_run_at_their_own_tolerance():
    """The per-experiment fits use the joint fit's numerics, coarser: `per_experiment_substeps`
    (half the joint fit's by default) with the fixed-step stepper, `per_experiment_rtol` (a decade
    looser) with the adaptive ones; a value out of range names its key."""
    import hdjax
    from hdjax._workflows.fit import DEFAULTS, per_experiment_simulator, trajectory_simulator

    opts = dict(DEFAULTS["trajectory"])
    sim, joint = per_experiment_simulator(opts), trajectory_simulator(opts)
    assert isinstance(sim.solver, hdjax.VelocityImplicit) and isinstance(joint.solver, hdjax.VelocityImplicit)
    assert 2 * sim.solver.substeps == joint.solver.substeps == opts["substeps"]
    for bad in (0, 1.5, "2", True, None):
        with pytest.raises(ValueError, match=r"fit\.trajectory\.per_experiment_substeps"):
            per_experiment_simulator({**opts, "per_experiment_substeps": bad})
    adaptive = {**opts, "solver": "ros34pw2"}
    assert adaptive["per_experiment_rtol"] == 10 * adaptive["rtol"]
    sim, joint = per_experiment_simulator(adaptive), trajectory_simulator(adaptive)
    assert sim.rtol == opts["per_experiment_rtol"] and sim.atol == opts["per_experiment_rtol"] * 1e-2
    assert type(sim.solver) is type(joint.solver) and joint.rtol == opts["rtol"]
    assert per_experiment_simulator({**adaptive, "per_experiment_rtol": "3e-4"}).rtol == 3e-4  # YAML's reading of 3e-4
    for bad in (-1e-4, 0.5, "fast", True, None):
        with pytest.raises(ValueError, match=r"fit\.trajectory\.per_experiment_rtol"):
            per_experiment_simulator({**adaptive, "per_experiment_rtol": bad})


def test_read_target_turns_dataset_warnings_into_notes(tmp_path):
    """An extra CSV column (in two files) and an unknown key of the drive block are accepted; the command
    gets each message once as a note for its `warning:` line, and no Python warning escapes
    (`filterwarnings = error` would turn one into a failure here)."""
    folder = tmp_path / "rig"
    folder.mkdir()
    rows = "\n".join(f"{0.01 * i:.2f},0.1,0.2,0.3,25" for i in range(10))
    for name in ("a.csv", "b.csv"):
        (folder / name).write_text("time,current,motor_velocity,torque,temperature\n" + rows + "\n")
    (folder / "dataset.yaml").write_text(
        "name: t\ndrive:\n  gear_ratio: 160\n  torque_constant: 0.1815\n  gearbox: CSD-25\n"
        "experiments:\n  - file: a.csv\n    mode: constrained\n  - file: b.csv\n    mode: constrained\n")
    dataset, config, notes = _cli.read_target(str(folder))
    assert len(dataset.experiments) == 2 and config == {}
    assert len(notes) == 3, notes
    assert sum("temperature" in n for n in notes) == 2
    assert any("a.csv" in n for n in notes) and any("b.csv" in n for n in notes)
    assert any("gearbox" in n and "drive" in n for n in notes)


@pytest.mark.parametrize("value", ["0.01x", 1.5, -0.1, True])
def test_a_bad_drift_trend_level_is_refused_before_any_work(tmp_path, capsys, value):
    """`diagnose.drift_trend_p` (and `untouched_record_change`) must be a number in [0, 1): anything
    else stops the command before the paper identification, naming the option."""
    cfg = tmp_path / "configs" / "c.yaml"
    cfg.parent.mkdir()
    cfg.write_text(f"dataset: {_repo() / 'data' / 'hd2'}\ndiagnose:\n  drift_trend_p: {value!r}\n".replace("'", '"'))
    assert _cli.main(["diagnose", str(cfg), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "`diagnose.drift_trend_p` must be a number in [0, 1)" in err
    assert not (tmp_path / "out" / "diagnosis.json").exists()


@pytest.mark.parametrize("key,value,message", [
    ("friction_uncertainty", "true", "`tune.friction_uncertainty` must be a number in [0, 1)"),
    ("friction_uncertainty", "1.0", "`tune.friction_uncertainty` must be a number in [0, 1)"),
    ("ms_max", "true", "`tune.ms_max` must be a positive number"),
])  # fmt: skip
def test_a_bad_tune_number_is_refused_before_any_work(tmp_path, capsys, key, value, message):
    """Tuning options that must be numbers refuse YAML's `true` (an int to Python) and values out of
    range, naming the option, before the paper identification."""
    cfg = tmp_path / "configs" / "c.yaml"
    cfg.parent.mkdir()
    cfg.write_text(f"dataset: {_repo() / 'data' / 'hd2'}\ntune:\n  {key}: {value}\n")
    assert _cli.main(["tune", str(cfg), "--out", str(tmp_path / "out")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out" / "tune.json").exists()


def test_breakaway_summary_gives_the_sticking_limit_and_the_torques_the_data_allow():
    """fit.json's breakaway entry: a searched torque at or below eq. 9's friction at rest
    (Ts + Tss1) changes nothing, so `effective` is that friction; `consistent_range` brackets the
    run of grid values within the reduced χ² of the best (a plateau where the records hold no stick
    event in that direction; one point where they pin it). Profiles shaped as two of the tuning
    benchmark's HD2 drives gave (2026-12-06)."""
    from types import SimpleNamespace

    from hdjax._workflows.fit import breakaway_summary

    p = SimpleNamespace(Tsp=0.0797, Tssp1=0.0120, Tsn=0.0322, Tssn1=-0.0379)
    grid = [0.0, 0.064, 0.072, 0.080, 0.084, 0.088, 0.092, 0.096, 0.100]
    plateau = [79032.3] * 7 + [83247.4, 818540.6]  # flat up to 0.092, then rising
    s = breakaway_summary(p, "breakaway_p", 0.0, grid, plateau, chi2_reduced=5.0)
    assert s["at_rest_eq9"] == pytest.approx(0.0917) and s["effective"] == pytest.approx(0.0917)
    assert s["consistent_range"] == pytest.approx([0.0917, 0.096])
    v = [30737.4, 30497.7, 29831.9, 26064.3, 18764.8, 6101.3, 0.0, 4049.5, 55755.4]  # a V at 0.092
    s = breakaway_summary(p, "breakaway_n", 0.092, grid, v, chi2_reduced=5.0)
    assert s["at_rest_eq9"] == pytest.approx(-0.0057) and s["effective"] == 0.092
    assert s["consistent_range"] == [0.088, 0.096]
    s = breakaway_summary(p, "breakaway_n", 0.092, grid, [x / 1e3 for x in v], chi2_reduced=5.0)  # shallower: wider
    assert s["consistent_range"] == [0.088, 0.100]
