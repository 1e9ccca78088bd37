"""The `diagnose` workflow: run `diagnose`, write diagnosis.json, the extended model, report.md and
figures (residual order spectra before/after, torque traces before/after)."""

import pathlib
import re
import time

from .._data.load import Dataset
from .._discrepancy.evidence import covariate_drifts
from .._discrepancy.loop import NOT_SCREENED, SCREENED_EFFECTS, diagnose
from .._discrepancy.significance import OUTPUT_ERROR_RULES
from .._fit.paper import identify_paper
from .._model.effects import DIAGNOSED_MODEL_FORM
from .._plant.simulate import Simulator
from .._plant.stepper import VelocityImplicit
from .artifacts import effects_to_dict
from .config import section_options, unit_share
from .fit import _options as fit_options, _tolerance, _whole_number
from .io import atomic_write_json, write_results
from .progress import task

DEFAULTS = {
    "candidates": list(SCREENED_EFFECTS),  # SPEC §4 effects screened, one finding per round
    "model_form": list(DIAGNOSED_MODEL_FORM),  # SPEC §4b base-model assumptions screened first
    "base_steps": 5,  # LM steps refining the base model
    "max_findings": 3,
    "min_relative_gain": OUTPUT_ERROR_RULES.min_relative_gain,  # held-out (misfit-scaled, whitened) SSE reduction where a finding acts
    "solver": "velocity_implicit",  # the plant's numerics: fixed-step `VelocityImplicit`, or "rodas3" (adaptive, `rtol`)
    "substeps": 4,  # steps per sample interval of velocity_implicit
    "rtol": 1e-6,  # ODE tolerance of every simulation with "rodas3"
    "measured_angle": True,  # periodic terms at the measured wave-generator angle (`Simulator.measured_angle`)
    "per_record_noise": True,  # weigh every experiment by its own sensor-noise level
    "misfit_scaling": True,  # scale each (experiment, channel) by its misfit where over the noise
    "min_improved_fraction": OUTPUT_ERROR_RULES.min_improved_fraction,  # of the held-out experiments where a candidate acts
    "negligible_record_loss": OUTPUT_ERROR_RULES.negligible_record_loss,  # a held-out record made worse by at most this share does not count against
    "untouched_record_change": OUTPUT_ERROR_RULES.untouched_record_change,  # records moved by at most this share do not raise the consistency floor
    "drift_trend_p": OUTPUT_ERROR_RULES.drift_trend_p,  # a drift over the session named also at this between-record trend p-value (0: off)
    "stiffness_trend_p": OUTPUT_ERROR_RULES.stiffness_trend_p,  # cubic stiffness named also at this p of the locked K1-torsion trend (0: off)
    "physical_sign": OUTPUT_ERROR_RULES.physical_sign,  # a signed effect (beta, mu, K3, Th, delay > 0, SPEC §4) only with that sign
    "measure_tachometer_lag": True,  # hold the tachometer's lag measured against the output encoder (not fitted)
}


def _run_diagnose(paper, dataset, exps, files, opts, simulator, log):
    return diagnose(
        paper.parameters(), dataset.drive, exps,
        candidates=opts["candidates"],
        model_form=opts["model_form"],
        per_record_noise=bool(opts["per_record_noise"]),
        misfit_scaling=bool(opts["misfit_scaling"]),
        min_improved_fraction=float(opts["min_improved_fraction"]),
        negligible_record_loss=float(opts["negligible_record_loss"]),
        untouched_record_change=float(opts["untouched_record_change"]),
        drift_trend_p=float(opts["drift_trend_p"]),
        stiffness_trend_p=float(opts["stiffness_trend_p"]),
        physical_sign=bool(opts["physical_sign"]),
        measure_tachometer_lag=bool(opts["measure_tachometer_lag"]),
        base_steps=int(opts["base_steps"]),
        max_findings=int(opts["max_findings"]),
        min_relative_gain=float(opts["min_relative_gain"]),
        simulator=simulator,
        labels=files,
        log=log,
    )


def diagnosis_simulator(opts: dict) -> Simulator:
    """The simulator of every diagnosis simulation from the `diagnose` options: `solver`
    "velocity_implicit" (the default: `hdjax.VelocityImplicit` at `substeps` steps per sample) or
    "rodas3" (adaptive, at `rtol`, the default before 2026-12-04); the periodic terms act at the
    measured wave-generator angle where `measured_angle`.

    Why the fixed-step plant (independent bench, `benchmarks/diagnose_independent.py --substeps 4`,
    2026-12-04, 2-core machine): 33 of 40 datasets named right against 34–35 with Rodas3 (the
    differences knife edges), in about half its time per dataset; the shipped HD2 diagnosis 129 s
    against 307 s with the same findings (see benchmarks/RESULTS.md)."""
    name = opts["solver"]
    measured = bool(opts["measured_angle"])
    if name == "velocity_implicit":
        return Simulator(solver=VelocityImplicit(substeps=_whole_number(opts, "substeps", "diagnose")), measured_angle=measured)
    if name == "rodas3":
        return Simulator(rtol=_tolerance(opts, "rtol", "diagnose"), atol=1e-8, measured_angle=measured)
    raise ValueError(f"config `diagnose.solver` must be one of ['velocity_implicit', 'rodas3'], got {name!r}.")


class DiagnosisProgress:
    """Progress bars for `diagnose`, driven by its log lines (it takes only `log=`): one bar per
    round over the candidates it scores (the round's Jacobian and refit run before the first
    candidate line; the bar shows them as elapsed time at 0/n). Every line is passed on to `log`.

    A line starting "diagnose: round N" opens round N; "  <name>  held-out gain" counts one
    candidate; "  accepted <names>" records findings (an effect round's pool shrinks by one)."""

    _CANDIDATE = re.compile(r"^  (\S+)\s+held-out gain")
    _ROUND = re.compile(r"^diagnose: round (\d+):")

    def __init__(self, log, opts: dict):
        self.log = log
        self.model_form = list(opts["model_form"])
        self.effects = [c for c in opts["candidates"] if c not in NOT_SCREENED]
        self.found = 0
        self.form_round = False
        self._task = None
        self.n_rounds = int(opts["max_findings"]) + 1 + (1 if self.model_form else 0)

    def __enter__(self):
        return self

    def __call__(self, line: str) -> None:
        if self.log is not None:
            self.log(line)
        line = str(line)
        m = self._ROUND.match(line)
        if m:
            self._close()
            rnd = int(m.group(1))
            self.form_round = rnd == 1 and bool(self.model_form)
            pool = len(self.model_form) if self.form_round else max(len(self.effects) - self.found, 1)
            what = "base-model assumptions" if self.form_round else "candidate effects"
            self._task = task(self.log, f"round {rnd}/{self.n_rounds}: Jacobian, refit, {what}", pool, unit="candidates")
            self._task.__enter__()
            self._task.update(info="Jacobian and refit")
            return
        m = self._CANDIDATE.match(line)
        if m and self._task is not None:
            self._task.advance(1, info=m.group(1))
            return
        if line.startswith("  accepted ") and not self.form_round:
            self.found += 1

    def _close(self):
        if self._task is not None:
            self._task.__exit__(None, None, None)
            self._task = None

    def __exit__(self, *exc):
        self._close()
        return False


def no_finding_entry(unexplained: list[dict]) -> dict:
    """The `unexplained` entry of a diagnosis that named nothing; it points to the entries that say
    which effects (or orders) these data cannot test, where there are any."""
    untested = [u["description"].replace(" not testable", "") for u in unexplained if " not testable" in u["description"]]
    return {
        "description": "no candidate effect improves held-out experiments significantly",
        "evidence": "the paper's model explains the data to within the noise, or the discrepancy is outside the "
                    "effect vocabulary (see the order spectra and correlations in `evidence`)"
                    + (f", or it is one these data cannot test ({'; '.join(untested)}: see the entries above)" if untested else ""),
    }


def run_diagnose(dataset: Dataset, config: dict, out: pathlib.Path, *, log=print) -> dict:
    t_start = time.time()
    out = pathlib.Path(out)
    opts = section_options(config, "diagnose", DEFAULTS)
    simulator = diagnosis_simulator(opts)  # a bad solver, substeps or tolerance is refused before any work
    for key in ("untouched_record_change", "drift_trend_p", "stiffness_trend_p"):  # and a bad share or level
        opts[key] = unit_share(opts[key], f"diagnose.{key}", " (0 turns its rule off)")
    drive, exps, files, _ = dataset.dynamic_part("diagnose", at_least=2)  # two: it holds experiments out
    fit_opts = fit_options(config)  # the `fit:` section, validated, with the fit command's defaults
    log(f"[1/3] paper's identification on {len(exps)} experiments (start of the base model)")
    paper = identify_paper(exps, drive, alpha=fit_opts["alpha"], Tss2=fit_opts["Tss2"], cutoff_hz=fit_opts["cutoff_hz"])
    log("[2/3] discrepancy loop (base fit, residual evidence, cross-validated candidates)")
    with DiagnosisProgress(log, opts) as watch:
        d = _run_diagnose(paper, dataset, exps, files, opts, simulator, watch)
    drifts = covariate_drifts(paper.per_experiment, exps)
    d.evidence["per_experiment_drifts"] = drifts
    log("[3/3] report and figures")
    from .plots import diagnosis_figures  # matplotlib loads only when figures are drawn
    figs = diagnosis_figures(out, dataset, exps, files, d)
    unexplained = list(d.unexplained)
    if not d.findings:
        unexplained.append(no_finding_entry(unexplained))
    result = {
        "schema": "hdjax.diagnosis/1",
        "dataset": dataset.name,
        "baseline": d.baseline,
        "findings": d.findings,
        "model_form": d.model_form,
        "unexplained": unexplained,
        "evidence": d.evidence,
        "candidates_by_round": d.rounds,
        "extended_model": {"parameters": d.params.to_dict(), "effects": effects_to_dict(d.effects)},
        "figures": figs,
        "timing_s": {"total": time.time() - t_start, **{k: round(v, 2) for k, v in d.timing.items() if k != "total"}},
    }
    atomic_write_json(out / "extended_model.json", result["extended_model"])
    write_results(out, "diagnosis.json", result, _report(result), log=log)
    return result


def with_units(values: dict, units: dict) -> str:
    """`k = v unit, ...` for a finding's parameters or a model_form adjustment (no unit for "-")."""
    return ", ".join(f"{k} = {v:.4g}" + (f" {units[k]}" if units.get(k, "-") != "-" else "") for k, v in values.items())


def _report(r: dict) -> str:
    lines = [f"# Diagnosis of `{r['dataset']}`", ""]
    if r["findings"]:
        lines += ["## Findings (most important first)", ""]
        for f in r["findings"]:
            g = f["gain"]
            orders = f" at orders {f['orders']} per wave-generator turn" if "orders" in f else ""
            change = (f"falls by {100 * g['relative_reduction']:.1f} %" if g["relative_reduction"] >= 0
                      else f"rises by {-100 * g['relative_reduction']:.1f} %")
            trend = (f"; named by its between-record trend (p = {g['between_record_trend_p']:.4f})"
                     if g.get("held_out_rules_refused") else "")
            lines.append(f"- **{f['effect']}**{orders}: held-out error {change}{trend} "
                         f"(torque NRMSE {g['heldout_nrmse_before']['torque']:.4f} → {g['heldout_nrmse_after']['torque']:.4f}); "
                         f"confidence {f['confidence']:.3f}. Parameters: "
                         + with_units(f["parameters"], f.get("parameter_units", {})) + f". Evidence: {f['evidence']}.")
    else:
        lines += ["No finding: no effect of the vocabulary improves experiments held out of its fit significantly.", ""]
    if r.get("model_form"):
        lines += ["", "## Base-model assumptions loosened for this bench (model_form)", "",
                  "Adopted before any effect was screened; each with its held-out gain (a sensor lag measured "
                  "from the sensors alone has none):", ""]
        for f in r["model_form"]:
            g = f["gain"]["relative_reduction"]
            lines.append(f"- **{f['assumption']}**: " + ("measured, not screened" if g is None else
                                                          f"held-out error falls by {100 * g:.1f} %")
                         + "; adjustment " + with_units(f["adjustment"], f.get("adjustment_units", {})) + ".")
    if r["unexplained"]:
        lines += ["", "## What the model still leaves unexplained", ""]
        lines += [f"- {u['description']}: {u['evidence']}" for u in r["unexplained"]]
    drifts = [x for x in r["evidence"].get("per_experiment_drifts", []) if x["p_value"] < 0.01]
    if drifts:
        lines += ["", "## The paper's consistency test as a detector", "",
                  "Per-experiment estimates of the paper's regressions that drift with an experiment covariate "
                  "(Spearman p < 0.01; evidence only, findings need a held-out gain):", ""]
        lines += [f"- {x['parameter']} vs {x['covariate']}: ρ = {x['spearman_rho']:+.2f} (p = {x['p_value']:.1e}, "
                  f"{x['n']} experiments)" + (f" — points at {x['points_at']}" if "points_at" in x else "") for x in drifts]
    ratio = r["evidence"].get("noise_over_sensor_noise", {})
    if ratio:
        lines += ["", "Noise model: the measured current drives the simulation, so its sensor noise makes the simulated "
                  "motion wander (process noise). It is sampled by simulating the paper model with white noise of the "
                  "current's own level added to the current; an autoregressive model of it plus the sensor noise, per "
                  "experiment and channel, whitens every residual before any fit or comparison. Noise RMS over sensor "
                  "noise: " + ", ".join(f"{k} ×{v:.2f}" for k, v in ratio.items()) + "."]
        rms = r["evidence"].get("base_residual_rms", {})
        white = r["evidence"].get("base_whitened_residual_rms", {})
        if rms:
            lines += ["", "Paper model's residual RMS over sensor noise, per mode and channel: "
                      + ", ".join(f"{k} ×{v:.2f}" for k, v in rms.items())
                      + ("; whitened by the noise model (1 = noise only): "
                         + ", ".join(f"{k} ×{v:.2f}" for k, v in white.items()) if white else "") + "."]
    lines += ["", "## Candidates (held-out relative reduction of the whitened squared error, per round)", ""]
    for i, rnd in enumerate(r["candidates_by_round"]):
        lines.append(f"Round {i + 1}: " + ", ".join(f"{c} {100 * s['gain']:+.1f} %" for c, s in sorted(rnd.items(), key=lambda x: -x[1]["gain"])))
        lines.append("")
    lines += ["## Figures", ""] + [f"![{f}]({f})" for f in r["figures"]] + [""]
    lines.append("The extended model (base parameters and effects) is saved in `extended_model.json`.")
    return "\n".join(lines) + "\n"
