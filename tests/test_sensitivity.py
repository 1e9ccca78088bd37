"""Sensitivity workflow: AD sensitivities vs central differences, the Fisher/standard-error algebra
on a hand-computed linear example, and the command's outputs on a tiny written dataset."""

import json

import jax.numpy as jnp
import numpy as np
import pytest

import hdjax
from hdjax import load_dataset, write_dataset
from hdjax._fit.sensitivity import fisher_summary, scaled_parameters, sensitivities
from hdjax._workflows.sensitivity import _options, _standard_errors, run_sensitivity, workflow_simulator
from helpers import hd2, sine_experiment


def test_ad_sensitivities_match_central_differences():
    """∂y/∂ln p by jacfwd through the solve (vmapped over a constrained and a free 0.2 s record)
    against 4-point central differences in ln p. A fixed step grid makes the discrete solution a
    smooth function of the parameters (an adaptive controller's step sequence is not)."""
    p, drive = hd2()
    batch = hdjax.stack_experiments([
        sine_experiment("constrained", amplitude=2.0, freq=5.0, duration=0.2),
        sine_experiment("free", amplitude=1.5, freq=4.0, duration=0.2),
    ])
    sim = hdjax.Simulator(fixed_step=1e-4)
    sens = sensitivities(p, drive, batch, simulator=sim)
    assert bool(jnp.all(sens.success))

    def out(s):  # the primal outputs at p·exp(s), through the same compiled function
        return sensitivities(scaled_parameters(p, s), drive, batch, simulator=sim).outputs

    h = 1e-4
    for name in ("K1", "Tst", "Tsp", "Tssn1"):
        k = hdjax.PARAMETER_NAMES.index(name)
        e = jnp.zeros(11).at[k].set(h)
        fd = (8 * (out(e) - out(-e)) - (out(2 * e) - out(-2 * e))) / (12 * h)
        ad = sens.S[..., k]
        for c in range(3):
            for j in range(2):
                if c == 2 and j == 0:
                    continue  # locked output: θo ≡ 0, nothing to compare
                ref = np.asarray(fd[j, c])
                rel = float(np.max(np.abs(np.asarray(ad[j, c]) - ref)) / np.max(np.abs(ref)))
                assert rel < 1e-4, (name, c, j, rel)


def test_fisher_summary_linear_example():
    """J = [[1, 0], [0, 2], [1, 1]]: F = JᵀJ = [[2, 1], [1, 5]], F⁻¹ = [[5, −1], [−1, 2]] / 9."""
    J = np.array([[1.0, 0.0], [0.0, 2.0], [1.0, 1.0]])
    r = fisher_summary(J.T @ J, ["a", "b"], n_directions=2)
    assert r["std_error"]["a"] == pytest.approx(np.sqrt(5.0) / 3.0, rel=1e-12)
    assert r["std_error"]["b"] == pytest.approx(np.sqrt(2.0) / 3.0, rel=1e-12)
    assert r["correlation"][0][1] == pytest.approx(-1.0 / np.sqrt(10.0), rel=1e-12)
    s = np.sort(np.linalg.svd(J, compute_uv=False))
    np.testing.assert_allclose(r["singular_values"], s, rtol=1e-12)
    np.testing.assert_allclose(s**2, [(7 - np.sqrt(13)) / 2, (7 + np.sqrt(13)) / 2], rtol=1e-12)
    weakest = r["directions"][0]
    assert weakest["std_error_along"] == pytest.approx(1.0 / s[0], rel=1e-12)
    v = np.array([weakest["components"]["a"], weakest["components"]["b"]])
    np.testing.assert_allclose(np.linalg.norm(J @ v), s[0], rtol=1e-10)
    # an uninformed parameter: infinite standard error, the rest unaffected
    r3 = fisher_summary(np.pad(J.T @ J, ((0, 1), (0, 1))), ["a", "b", "c"], n_directions=0)
    assert r3["std_error"]["c"] == np.inf
    assert r3["std_error"]["a"] == pytest.approx(np.sqrt(5.0) / 3.0, rel=1e-10)


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    p, drive = hd2()
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 0.3, 1e-3)
    exps, modes = [], []
    runs = (("constrained", 2.0, 5.0), ("free", 1.5, 3.0))
    z = np.zeros_like(t)
    currents = [A * np.sin(2 * np.pi * f * t) * np.minimum(1.0, t / 0.05) for _, A, f in runs]
    batch = hdjax.stack_experiments(
        [hdjax.make_experiment(t, i, z, z, mode=m, output_position=z) for (m, _, _), i in zip(runs, currents)])
    # through the workflow's own compiled function (same shapes and simulator), so it compiles once
    ys = np.asarray(sensitivities(p, drive, batch, simulator=workflow_simulator(_options({}))).outputs)
    for j, ((mode, _, _), i) in enumerate(zip(runs, currents)):
        torque, velocity, position = ys[j]
        pos = np.round(position / 1e-4) * 1e-4 if mode == "free" else None
        exps.append(hdjax.make_experiment(
            t, i, torque + rng.normal(0, 0.1, len(t)), velocity + rng.normal(0, 0.02, len(t)),
            mode=mode, output_position=pos))
        modes.append(mode)
    folder = tmp_path_factory.mktemp("tiny") / "ds"
    write_dataset(folder, "tiny", drive, exps, modes, ["locked_01.csv", "free_01.csv"], truth={"parameters": p.to_dict()})
    return folder, p


def test_workflow_writes_sensitivity_json(tiny_dataset, tmp_path):
    folder, p = tiny_dataset
    ds = load_dataset(folder)
    out = tmp_path / "out"
    run_sensitivity(ds, {}, out, log=None)
    d = json.loads((out / "sensitivity.json").read_text())
    assert d["schema"] == "hdjax.sensitivity/1" and d["dataset"] == "tiny"
    assert d["parameter_source"]["kind"] == "paper_identification"
    for key in ("sensitivity", "standard_errors", "correlation", "svd", "identifiability", "ablation", "advice", "timing_s"):
        assert key in d, key
    sens = d["sensitivity"]["parameters"]
    assert set(sens) == set(hdjax.PARAMETER_NAMES)
    assert len(sens["K1"]["information"]) == 2 and sens["K1"]["information"][0] > 0
    assert set(sens["K1"]["rms_over_noise"]) == {"torque", "motor_velocity", "output_position"}
    assert np.array(d["correlation"]["matrix"]).shape == (11, 11)
    assert all(d["standard_errors"][k]["relative"] > 0 for k in ("K1", "Tst", "Jeff"))
    changes = {c["change"]: c for c in d["ablation"]["changes"]}
    assert set(changes) == {"coulomb_zero", "viscous_zero", "K1_div10", "Tst_zero"}
    assert "rms_increase" in changes["coulomb_zero"]["per_mode"]["free"]
    assert d["advice"]["ranking"]["Tssp1"][0]["file"] in ("locked_01.csv", "free_01.csv")
    assert d["timing_s"]["total"] > 0
    for f in ("report.md", "sensitivity_heatmap.png", "sensitivity_curves.png", "correlation.png",
              "fig6_free_ablation.png", "fig7_constrained_ablation.png"):
        assert (out / f).exists(), f

    # parameter values from a fit.json (config key), same shapes: no recompilation
    fit = tmp_path / "fit.json"
    fit.write_text(json.dumps({"dataset": "tiny", "parameters": {k: {"value": v} for k, v in p.to_dict().items()}}))
    d2 = run_sensitivity(ds, {"sensitivity": {"fit_json": str(fit)}}, tmp_path / "out2", log=None)
    assert d2["parameter_source"]["kind"] == "fit.json"
    assert d2["parameters"]["K1"] == pytest.approx(float(p.K1))
    # truth parameters on noisy data simulated from them: the residual is noise (chi2 near 1)
    assert d2["identifiability"]["chi2_per_channel"]["motor_velocity"] < 2.0
    # the terms the fit fitted with the parameters (fit.json's model_form) are simulated with them:
    # a 20 ms tachometer lag the data do not have must show in the velocity channel's misfit
    fit.write_text(json.dumps({"dataset": "tiny", "parameters": {k: {"value": v} for k, v in p.to_dict().items()},
                               "model_form": {"sensor_bandwidth": {"torque_lag": {"value": 0.0},
                                                                   "velocity_lag": {"value": 0.02}}}}))
    d3 = run_sensitivity(ds, {"sensitivity": {"fit_json": str(fit)}}, tmp_path / "out3", log=None)
    assert d3["parameter_source"]["effects"]["sensor_bandwidth"]["velocity_lag"] == pytest.approx(0.02)
    assert d3["identifiability"]["chi2_per_channel"]["motor_velocity"] > 5 * d2["identifiability"]["chi2_per_channel"]["motor_velocity"]


def test_bad_option_is_refused(tiny_dataset, tmp_path):
    folder, _ = tiny_dataset
    with pytest.raises(ValueError, match="unknown option"):
        run_sensitivity(load_dataset(folder), {"sensitivity": {"max_experimnets": 3}}, tmp_path / "o", log=None)


def test_standard_errors_carry_the_fits_own():
    """Beside the noise-only (design) standard errors, sensitivity.json carries the fit's own, relative,
    where the parameters came from a fit.json that has them."""
    p, _ = hd2()
    fs = {"std_error": {"K1": 1e-4, "Tst": 2e-4}}
    se = _standard_errors(["K1", "Tst"], ["K1", "Tst"], fs, fs, p, {"K1": 0.01 * float(p.K1), "Tst": None})
    assert se["K1"]["fit_relative"] == pytest.approx(0.01) and se["Tst"]["fit_relative"] is None
    assert _standard_errors(["K1"], ["K1"], fs, fs, p, {})["K1"]["fit_relative"] is None
