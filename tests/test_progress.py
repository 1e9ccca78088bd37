"""Progress display: RunLog lines and bars, run.log, the LM-step callback compiled into the fit
only when a command listens, and the diagnosis bars driven by `diagnose`'s log lines."""

import jax

jax.config.update("jax_enable_x64", True)

import io

import numpy as np
from rich.console import Console

import hdjax
from hdjax._workflows.diagnose import DEFAULTS, DiagnosisProgress
from hdjax._workflows.progress import RunLog, current, task
from helpers import hd2, sine_experiment


def _terminal():
    buf = io.StringIO()
    return Console(file=buf, force_terminal=True, width=120), buf


def test_runlog_lines_bars_and_run_log(tmp_path):
    console, buf = _terminal()
    with RunLog(path=tmp_path / "run.log", console=console) as log:
        assert current() is log
        log("[1/2] step one")
        with task(log, "items", 4, unit="items") as bar:
            for k in range(4):
                bar.advance(1, info=f"item {k}", line=f"detail {k}")
    assert current() is None
    text = (tmp_path / "run.log").read_text()
    assert "[1/2] step one" in text and "detail 3" in text and "items: 4/4 items in" in text
    assert "[1/2] step one" in buf.getvalue() and "items" in buf.getvalue()  # the bar was drawn
    # quiet: nothing on the console, the log file still complete
    console, buf = _terminal()
    with RunLog(path=tmp_path / "q.log", console=console, quiet=True) as log:
        log("hidden")
        with task(log, "work", 2) as bar:
            bar.advance(2)
    assert buf.getvalue() == "" and "hidden" in (tmp_path / "q.log").read_text()
    # library use: plain print or None gets a do-nothing bar
    with task(print, "nothing", 3) as bar:
        bar.advance(1)


def test_lm_steps_reported_with_their_cost(tmp_path):
    truth, drive = hd2()
    exps = [sine_experiment("constrained", amplitude=2.0, duration=0.2)]
    exps = [hdjax.make_experiment(np.asarray(e.time), np.asarray(e.current),
                                  np.asarray(hdjax.simulate(truth, drive, e).torque),
                                  np.asarray(hdjax.simulate(truth, drive, e).motor_velocity), mode="constrained")
            for e in exps]
    batch = hdjax.stack_experiments(exps)
    start = truth.replace(K1=truth.K1 * 1.05)
    with RunLog(path=tmp_path / "run.log", quiet=True):
        fit = hdjax.fit_parameters(start, drive, batch, free=("K1",), max_steps=3, sigma=[0.05, 1e-3, 1e-3],
                                   throw=False)
    text = (tmp_path / "run.log").read_text()
    assert "LM step 1: ½χ²" in text and "Gauss–Newton step" in text
    assert f"LM fit (1 parameters, 1 experiments): {fit.steps}/3 LM steps" in text


def test_diagnosis_progress_follows_rounds_and_candidates(tmp_path):
    lines = [
        "diagnose: refining the base model (5 LM steps on 8 experiments)",
        "diagnose: round 1: Jacobian w.r.t. 9 base + 6 effect parameters",
        "  low_speed_friction             held-out gain predicted +0.001",
        "  sensor_offset                  held-out gain predicted -0.002",
        "  sensor_bandwidth               held-out gain predicted +0.000",
        "diagnose: round 2: Jacobian w.r.t. 9 base + 40 effect parameters",
        "  torque_sensor_ripple           held-out gain simulated +0.620 (folds [0.61, 0.62]) significant",
        "    per held-out experiment: +60 +61 % of whitened SSE 100 120",
        "  cogging                        held-out gain predicted +0.010",
        "  accepted torque_sensor_ripple",
        "diagnose: round 3: Jacobian w.r.t. 11 base + 38 effect parameters",
        "  cogging                        held-out gain predicted +0.010",
    ]
    opts = dict(DEFAULTS)
    with RunLog(path=tmp_path / "run.log", quiet=True) as log:
        with DiagnosisProgress(log, opts) as watch:
            for line in lines:
                watch(line)
    text = (tmp_path / "run.log").read_text()
    n_effects = len([c for c in opts["candidates"] if c != "presliding_friction"])
    n_form = len(opts["model_form"])
    assert f"round 1/{opts['max_findings'] + 2}: Jacobian, refit, base-model assumptions: 3/{n_form} candidates" in text
    assert f"round 2/{opts['max_findings'] + 2}: Jacobian, refit, candidate effects: 2/{n_effects} candidates" in text
    assert f"candidate effects: 1/{n_effects - 1} candidates" in text  # one finding: one candidate fewer
    assert all(line in text for line in lines)  # every line passed on
