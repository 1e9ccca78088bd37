"""The commands' JSON artifacts (`hdjax._workflows.artifacts`): fit.json and extended_model.json as
`sensitivity` and `tune` read them, and the plain-number form of `Effects`."""

import json
import pathlib

import numpy as np
import pytest

from hdjax import PARAMETER_NAMES, Effects, effects_from_dict, effects_to_dict, read_extended_model, read_fit_json
from hdjax._workflows.artifacts import fit_json_dataset
from helpers import hd2


def _fit_doc(p, **extra):
    doc = {"dataset": "hd2-bench", "parameters": {k: {"value": v, "consistency": 0.01, "per_experiment": [v, v]}
                                                   for k, v in p.to_dict().items()},
           "fit": {"noise_levels": {"torque": 0.5, "motor_velocity": 0.02}}}
    doc.update(extra)
    return doc


def test_fit_json_is_read_with_its_consistency_and_noise_levels(tmp_path):
    p, _ = hd2()
    path = tmp_path / "fit.json"
    path.write_text(json.dumps(_fit_doc(p)))
    fit = read_fit_json(path, setting="config `tune.fit`")
    assert fit.parameters.to_dict() == p.to_dict() and fit.dataset == "hd2-bench" == fit_json_dataset(path)
    assert fit.consistency["K1"] == 0.01 and fit.per_experiment["Tst"] == [p.to_dict()["Tst"]] * 2
    assert fit.noise_levels == {"torque": 0.5, "motor_velocity": 0.02}
    assert fit.std_error == {k: None for k in PARAMETER_NAMES}  # a fit.json without standard errors
    doc = _fit_doc(p)
    doc["parameters"]["K1"]["std_error"] = 9.2
    path.write_text(json.dumps(doc))
    assert read_fit_json(path, setting="config `tune.fit`").std_error["K1"] == 9.2
    assert fit.effects.active == frozenset()  # no model_form: no terms


def test_the_fit_json_model_form_is_read_as_effects(tmp_path):
    """`model_form` (the sensor lags, the breakaway torques fitted with the parameters) comes back as
    the `Effects` that `tune` and `sensitivity` simulate with, and a broken entry is named."""
    p, _ = hd2()
    form = {"sensor_bandwidth": {"note": "lags", "torque_lag": {"value": 2.5e-4, "unit": "s", "std_error": 3e-5},
                                 "velocity_lag": {"value": 5.9e-4, "unit": "s", "std_error": 8e-6}},
            "breakaway_friction": {"note": "torques", "breakaway_p": {"value": 0.102, "std_error": None, "grid": [0.0, 0.1]},
                                   "breakaway_n": {"value": 0.045, "std_error": None}}}
    path = tmp_path / "fit.json"
    path.write_text(json.dumps(_fit_doc(p, model_form=form)))
    eff = read_fit_json(path, setting="config `tune.fit`").effects
    assert eff.active == {"sensor_bandwidth", "breakaway_friction"}
    assert float(eff.breakaway_friction.breakaway_p) == 0.102 and float(eff.breakaway_friction.breakaway_n) == 0.045
    assert float(eff.sensor_bandwidth.velocity_lag) == 5.9e-4
    left = eff.without("sensor_bandwidth")
    assert left.active == {"breakaway_friction"} and float(left.sensor_bandwidth.torque_lag) == 0.0
    form["breakaway_friction"]["breakaway_n"] = {"std_error": None}  # no value
    path.write_text(json.dumps(_fit_doc(p, model_form=form)))
    with pytest.raises(ValueError, match=r"model_form\.breakaway_friction.*python -m hdjax.fit"):
        read_fit_json(path, setting="config `tune.fit`")


@pytest.mark.parametrize("break_it, field", [
    (lambda d: d["parameters"].pop("Jeff"), "Jeff"),
    (lambda d: d["parameters"]["K1"].update(value="stiff"), "value"),
    (lambda d: d["parameters"]["Tst"].update(value=float("nan")), "not finite"),
])
def test_a_broken_fit_json_names_the_file_the_field_and_the_fix(tmp_path, break_it, field):
    p, _ = hd2()
    doc = _fit_doc(p)
    break_it(doc)
    path = tmp_path / "fit.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError) as e:
        read_fit_json(path, setting="config `sensitivity.fit_json`")
    msg = str(e.value)
    assert str(path) in msg and field in msg and "python -m hdjax.fit" in msg and "sensitivity.fit_json" in msg
    assert fit_json_dataset(tmp_path / "missing.json") is None


def test_effects_round_trip_through_the_extended_model(tmp_path):
    eff = (Effects().with_periodic("kinematic_error", 2, 1.5e-4, 0.3).with_periodic("kinematic_error", 3, 4e-5, -1.0)
           .with_values("thermal_drift", beta=0.4, tau=450.0).with_values("presliding_friction", presliding=0.6,
                                                                           presliding_scale=-0.5))
    d = effects_to_dict(eff)
    assert set(d) == {"kinematic_error", "thermal_drift", "presliding_friction"} and d["thermal_drift"]["tau"] == 450.0
    assert d["presliding_friction"] == {"presliding": 0.6, "presliding_scale": -0.5}
    p, _ = hd2()
    path = tmp_path / "extended_model.json"
    path.write_text(json.dumps({"parameters": p.to_dict(), "effects": d}))
    p2, eff2 = read_extended_model(path)
    assert p2.to_dict() == p.to_dict() and eff2.active == eff.active
    d2 = effects_to_dict(eff2)  # through sin/cos coefficients: equal to round-off
    assert d2["thermal_drift"] == d["thermal_drift"] and d2["kinematic_error"]["orders"] == d["kinematic_error"]["orders"]
    assert d2["presliding_friction"] == d["presliding_friction"]
    for key in ("amplitudes", "phases"):
        np.testing.assert_allclose(d2["kinematic_error"][key], d["kinematic_error"][key], rtol=1e-12, atol=1e-15)
    with pytest.raises(ValueError, match="unknown effect 'backlash'"):
        effects_from_dict({"backlash": {}})
    path.write_text(json.dumps({"parameters": {k: 1.0 for k in PARAMETER_NAMES[:3]}}))
    with pytest.raises(ValueError, match="extended_model.json"):
        read_extended_model(path)


def test_an_output_is_replaced_whole_or_not_at_all(tmp_path):
    """`hdjax._workflows.io`: a write that fails midway (text that cannot be encoded, a figure whose save
    raises) leaves the previous file as it was and no temporary file beside it; a write that
    succeeds replaces it."""
    from hdjax._workflows.io import atomic_savefig, atomic_write_text

    out = tmp_path / "fit.json"
    atomic_write_text(out, "old\n")
    with pytest.raises(UnicodeEncodeError):
        atomic_write_text(out, "new \ud800\n")  # a lone surrogate: UTF-8 cannot encode it

    class BrokenFigure:
        def savefig(self, path, **_):
            pathlib.Path(path).write_bytes(b"partial")
            raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_savefig(BrokenFigure(), tmp_path / "fig.png")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fit.json"]
    assert out.read_text() == "old\n"
    atomic_write_text(out, "new\n")
    assert out.read_text() == "new\n" and sorted(p.name for p in tmp_path.iterdir()) == ["fit.json"]


def test_a_command_writes_its_json_and_report_together(tmp_path):
    """`write_results`, the one writer every command's workflow ends with: the JSON document (NaN
    as null, SPEC §3) and report.md, and one log line with the total time."""
    from hdjax._workflows.io import write_results

    lines = []
    write_results(tmp_path, "fit.json", {"value": float("nan"), "timing_s": {"total": 1.25}}, "# report\n",
                  log=lines.append)
    assert json.loads((tmp_path / "fit.json").read_text()) == {"value": None, "timing_s": {"total": 1.25}}
    assert (tmp_path / "report.md").read_text() == "# report\n"
    assert lines == [f"wrote {tmp_path / 'fit.json'} and {tmp_path / 'report.md'} in 1.2 s"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fit.json", "report.md"]
