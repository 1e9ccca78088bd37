"""The discrepancy loop on data the package did not make: datasets from the independent bench
(`hdjax._testbench.independent`), where the paper model is never exact.

What differs from hdjax's plant, in every dataset here (all `hdjax._testbench.independent.Deviations` on, their
defaults): the bench is a numpy/numba fixed-step (20 kHz) velocity-level integrator written apart from
hdjax; its low-speed friction is exact stick–slip with a breakaway torque 1.1–1.3× the friction
level (not tanh(ω/s)); the current comes from a simulated PI current loop on an R–L winding with
PWM ripple and is *sampled*; strain gauge and tachometer are low-pass filtered, the tachometer
has ripple, the encoder is quantised, every sensor has a DC offset, time stamps jitter; the drive
is drawn around HD1/HD2. Effects are hidden at 4× the sensor noise (the RMS change in torque or
motor velocity over the records where the effect acts).

Small datasets (4 locked + 4 free records of 1.5 s at 1 kHz) keep the suite fast; the three effects
that need more (`FULL_SIZE`) and the two-effect dataset (a thermal drift, whose trend test needs
more than four free records) use the benchmark's size, 8 + 8 records of 2.5 s. The full-size check
with fresh seeds is `benchmarks/diagnose_independent.py`.
"""

import math
import pathlib

import jax
import pytest
import yaml

from hdjax import diagnose_effects as diagnose, identify_paper, load_dataset
from hdjax.bench import Deviations, make_dataset

jax.config.update("jax_enable_x64", True)

N_LOCKED, N_FREE, DURATION, SNR = 4, 4, 1.5, 4.0
PERIODIC = {"kinematic_error": 2, "torque_sensor_ripple": 3, "cogging": 1, "position_dependent_friction": 2}
EFFECTS = list(PERIODIC) + [
    "nonlinear_stiffness", "lost_motion", "load_dependent_friction", "thermal_drift", "input_delay",
    "rate_independent_hysteresis",
]  # fmt: skip


# Three effects need the benchmark's dataset size (8 locked + 8 free records of 2.5 s): on the small
# datasets the cubic stiffness was not among the two best predicted (thermal_drift +53 % with one
# half -1.7 %, input_delay gaining in one half only) and the Dahl hysteresis was predicted at
# -0.4 % after sensor_bandwidth. At full size (seeds 900 + the effect's index, fixed before the
# first run, 2026-12-01) both are named alone. The input delay on the small dataset hides in the
# fitted torque lag (0.472 ms: the bench's 0.279 ms + the 0.213 ms delay; predicted -27 % after
# viscous_friction_law, sensor_offset and sensor_bandwidth, 2026-12-03); at full size (seed 908,
# missed on 2026-12-01 at +1.6 % predicted) it is named alone since the tachometer lag is measured
# (2026-12-04: lag 0.633 ms, input_delay +6.2 % held out, halves +6.3 / +6.1 %, no record
# worse by 1 % or more). Each full-size diagnosis takes about twice a small one.
FULL_SIZE = {"nonlinear_stiffness", "rate_independent_hysteresis", "input_delay"}

# Not yet named (issue 18 stays open; reasons measured with leave-one-experiment-out held-out fits).
# Strict: a case that starts to pass must be moved out of this list.
NOT_YET = {
    "thermal_drift": "thermal drift at 4x noise over a 1.5 s x 8 session: no candidate predicted above 1 %; with the "
                     "drift rule (between-record share, 2026-11-27) predicted -22.8 % held out, share 0.00: 4 free "
                     "records of 1.5 s do not pin a drift (the full-size benchmark's seed 5009 is named, share 0.80). "
                     "At full size too (seed 907, 2026-12-01): share 0.67, but +2.3 % held out with 4 of 8 free records "
                     "improved, +18 % of it in the one free record recorded early in the session (185 s; beta = 0.011, "
                     "tau = 510 s: under 0.5 % of the viscous friction in every other free record). The between-record "
                     "trend test (2026-12-05) cannot name it on 4 free records (smallest p 1/4! = 0.042); at full size "
                     "(seed 907) it gave p 0.011, amplitude 0.0104 against the hidden 0.011: just above its 0.01. Why (2026-12-05, "
                     "fifty-seventh session): three of the 8 free records have ~1e-3 of the median's information and the "
                     "drift shows in one early record (course 0.79, level 0.0053 against +-0.001 elsewhere); a permutation "
                     "test cannot make one record worth more than about 1/8",
}


def _size(name) -> tuple[int, int, float]:
    return (8, 8, 2.5) if name in FULL_SIZE else (N_LOCKED, N_FREE, DURATION)


def _spec(name):
    spec = {"snr": SNR, "channels": ["torque", "motor_velocity"]}
    if name in PERIODIC:
        spec["orders"] = [PERIODIC[name]]
    return spec


def _run(tmp_path: pathlib.Path, effects: dict, *, seed: int, drive: str, size=(N_LOCKED, N_FREE, DURATION)):
    folder = tmp_path / "bench"
    n_locked, n_free, duration = size
    make_dataset(folder, drive=drive, seed=seed, n_locked=n_locked, n_free=n_free, duration=duration,
                 effects=effects or None)  # fmt: skip
    ds = load_dataset(folder)
    exps = [ds.experiments[i] for i in ds.dynamic_indices()]
    d = diagnose(identify_paper(exps, ds.drive).parameters(), ds.drive, exps, max_findings=2)
    return d


def _named(d):
    return {f["effect"]: sorted(f.get("orders") or []) for f in d.findings}


def _summary(d) -> str:
    out = []
    for i, rnd in enumerate(d.rounds):
        out.append(f"stage {i + 1}: " + "; ".join(
            f"{c} {100 * s['gain']:+.1f}%" + (f" folds {[round(100 * g, 1) for g in s['fold_gains']]} "
                                              f"improved {s['improved_fraction']:.2f}" if s["simulated"] else " (pred.)")
            for c, s in sorted(rnd.items(), key=lambda x: -x[1]["gain"])[:4]))  # fmt: skip
    out.append("model_form: " + ", ".join(f["assumption"] for f in d.model_form))
    return "\n".join(out)


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.xfail(reason=NOT_YET[n], strict=True)) if n in NOT_YET else n for n in EFFECTS]
)
def test_hidden_effect_on_the_independent_bench_is_named_alone(name, tmp_path):
    i = EFFECTS.index(name)
    d = _run(tmp_path, {name: _spec(name)}, seed=(900 if name in FULL_SIZE else 700) + i, drive=("hd1", "hd2")[i % 2],
             size=_size(name))
    found = _named(d)
    assert list(found) == [name], f"{name} hidden, named {found}:\n{_summary(d)}"
    if name in PERIODIC:
        assert found[name] == [PERIODIC[name]], f"{name}: orders {found[name]}, hidden {PERIODIC[name]}"
    f = d.findings[0]
    assert f["gain"]["relative_reduction"] > 0 and all(g > 0 for g in f["gain"]["fold_reductions"])
    for item in d.model_form:  # every model_form item carries its held-out gain, or says it was measured
        g = item["gain"]["relative_reduction"]
        assert "measured, not fitted" in item["evidence"] if g is None else g > 0, item


def test_a_cubic_stiffness_the_held_out_rules_refuse_is_named_by_its_between_record_trend(tmp_path):
    """An HD2-like drive with a cubic stiffness at 4× the noise (8 + 8 records × 2.5 s, seed 961,
    found 2026-12-07 as the first of the searched seeds where the held-out rules refuse it). The base
    fit's one K1 takes up most of it record by record, so its held-out gain is small (refused:
    effect size without the best record), but each locked record's own K1 rises with how far it is
    twisted: trend p 0.0020 over all 8! assignments (`Significance.stiffness_trend_p`, 0.01). It is
    named alone, with K3 from that trend near the hidden one. With the route off nothing is named
    (the loop before 2026-12-07; the default bench's HD2 seeds 5019 and 5077 were missed so)."""
    d = _run(tmp_path, {"nonlinear_stiffness": _spec("nonlinear_stiffness")}, seed=961, drive="hd2", size=(8, 8, 2.5))
    assert _named(d) == {"nonlinear_stiffness": []}, _summary(d)
    g = d.findings[0]["gain"]
    assert g["held_out_rules_refused"] and g["between_record_trend_p"] <= 0.01, g
    truth = yaml.safe_load((tmp_path / "bench" / "truth.yaml").read_text())["effects"]["nonlinear_stiffness"]["magnitude"]
    assert abs(g["between_record_trend_amplitude"] / truth - 1) < 0.4, (g["between_record_trend_amplitude"], truth)
    assert "locked tests' own K1" in d.findings[0]["evidence"]


def test_a_strain_gauge_ripple_is_named_with_the_torque_offset_it_explains(tmp_path):
    """The bench's variant (LuGre low-speed law, sensor noise scaled with each record's range), HD1,
    a strain-gauge ripple [3] at 4.5× the noise, 8 + 8 records × 2.5 s, seed 981 (found 2026-12-07
    as the first of the searched seeds where the ripple is named only with the offset). Over the part
    of a cycle that a locked or slow record turns the wave generator through, the ripple is an offset
    of that record's torque; the bench's torque sensor has an offset too, so each alone misfits the
    quiet slow records, sensor_offset is refused in round 1 and the ripple fitted alone was not
    named (measured with `SCREENED_WITH` emptied: nothing named). Screened with the torque offset
    (`SCREENED_WITH`), the ripple is named alone, beats the offset alone held out, and the offset
    joins the model as a model_form item. What differs from the fitted model: the bench's own
    integrator, LuGre friction, current loop, sensor filters, offsets and per-record noise."""
    folder = tmp_path / "bench"
    make_dataset(folder, drive="hd1", seed=981, n_locked=8, n_free=8, duration=2.5, low_speed="lugre", noise="per_record",
                 effects={"torque_sensor_ripple": {"snr": 4.5, "orders": [3], "channels": ["torque", "motor_velocity"]}})
    ds = load_dataset(folder)
    exps = [ds.experiments[i] for i in ds.dynamic_indices()]
    d = diagnose(identify_paper(exps, ds.drive).parameters(), ds.drive, exps, max_findings=2)
    assert _named(d) == {"torque_sensor_ripple": [3]}, _summary(d)
    f = d.findings[0]
    assert f["gain"]["over_companion"]["gain"] > 0.05 and "fitted together with sensor_offset.torque_offset" in f["evidence"]
    truth = yaml.safe_load((folder / "truth.yaml").read_text())
    b3 = truth["effects"]["torque_sensor_ripple"]["magnitude"]
    assert f["parameters"]["b3"] == pytest.approx(b3, rel=0.2)
    item = next(m for m in d.model_form if m["assumption"] == "sensor_offset")
    assert "fitted together with torque_sensor_ripple" in item["evidence"] and item["gain"]["relative_reduction"] > 0
    assert item["adjustment"]["velocity_offset"] == 0.0 and item["adjustment"]["current_offset"] == 0.0
    offset = truth["deviations"]["offset_factors"]["torque"] * truth["sensors"]["torque_noise"]
    assert item["adjustment"]["torque_offset"] == pytest.approx(offset, rel=0.3)


@pytest.mark.parametrize("drive,seed", [("hd1", 801), ("hd2", 802)])
def test_clean_independent_bench_gives_no_finding(drive, seed, tmp_path):
    d = _run(tmp_path, {}, seed=seed, drive=drive)
    assert not d.findings, f"clean data, named {_named(d)}:\n{_summary(d)}"


def test_two_effects_on_the_independent_bench_are_both_named(tmp_path):
    """A strain-gauge ripple [3] and a thermal drift, both at 4x the noise, on a full-size dataset
    (8 + 8 records of 2.5 s, seed 911, fixed on 2026-12-01). The drift is named by its
    between-record trend test (`Significance.drift_trend_p`): with the four free records of the small
    datasets no ordering of start times can reach p <= 0.01 (the smallest p is 1/4! = 0.042), and
    the held-out rules alone named the ripple only (drift +0.2-0.4 % held out after it; on the small
    dataset, seed 811, predicted -25 %). Measured 2026-12-05: ripple [3] +38.9 % held out, then the
    drift with trend p 0.0049, amplitude 0.0027 (+0.3 % held out)."""
    effects = {"torque_sensor_ripple": _spec("torque_sensor_ripple"), "thermal_drift": _spec("thermal_drift")}
    d = _run(tmp_path, effects, seed=911, drive="hd2", size=(8, 8, 2.5))
    found = _named(d)
    assert set(found) == set(effects), f"hidden {sorted(effects)}, named {found}:\n{_summary(d)}"
    assert found["torque_sensor_ripple"] == [PERIODIC["torque_sensor_ripple"]]
    drift = next(f for f in d.findings if f["effect"] == "thermal_drift")
    assert drift["gain"]["between_record_trend_p"] <= 0.01 and drift["gain"]["between_record_trend_amplitude"] > 0


def test_a_power_law_viscous_friction_is_adopted_as_model_form_with_its_exponent(tmp_path):
    """Clean bench data whose viscous friction grows as |ω|^0.7 (`Deviations.viscous_exponent`; the
    paper's law is linear): the loop adopts `viscous_friction_law` (hdjax's addition to SPEC §4b)
    with κ near the bench's, and names no effect. The bench's law is its own code (an exact power
    law, integrated by its fixed-step scheme); hdjax's is smoothed below 0.01 rad/s."""
    folder = tmp_path / "bench"
    make_dataset(folder, drive="hd1", seed=821, n_locked=N_LOCKED, n_free=N_FREE, duration=DURATION,
                 deviations=Deviations(viscous_exponent=0.7))
    ds = load_dataset(folder)
    exps = [ds.experiments[i] for i in ds.dynamic_indices()]
    d = diagnose(identify_paper(exps, ds.drive).parameters(), ds.drive, exps, max_findings=2)
    form = {f["assumption"]: f for f in d.model_form}
    assert "viscous_friction_law" in form, _summary(d)
    kappa = math.exp(form["viscous_friction_law"]["adjustment"]["viscous_exponent"])
    assert abs(kappa - 0.7) < 0.07, f"kappa {kappa:.3f} for 0.7 hidden:\n{_summary(d)}"
    assert form["viscous_friction_law"]["gain"]["relative_reduction"] > 0
    # 2026-11-29: an input_delay of 0.44 ms took up the bench's sensor lags here (+15.6 % held out)
    # while `sensor_bandwidth`, screened again after the viscous law, was predicted at −15 % and
    # never simulated; simulated (as every assumption now is on that re-screen) it gains +27 %
    assert not d.findings, f"clean data, named {_named(d)}:\n{_summary(d)}"
