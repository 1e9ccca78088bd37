"""`fit` and `diagnose` on friction-only datasets (every experiment `mode: friction`): fit.json /
diagnosis.json with the SPEC §3 keys, report.md and figures."""

import math
import pathlib
import time
import types

import numpy as np

from .._data.load import Dataset
from .._discrepancy.friction import _add, _Fold, diagnose_friction, fold_params
from .._discrepancy.significance import FRICTION_RULES
from .._fit.friction import (
    HARMONIC_FIELDS,
    TIE_NEG_TO_POS,
    TIE_POS_TO_NEG,
    FrictionProblem,
    Rows,
    fit_coulomb_viscous,
    physical_std_errors,
    rms_stats,
)
from .._fit.friction_low_speed import fit_low_speed, low_speed_reason
from .._model.effects import FIELD_UNITS
from .._model.friction_only import FRICTION_NAMES, FRICTION_UNITS, HARMONIC_SLOTS, amplitude_phase
from .diagnose import with_units
from .io import write_results

TRAIN_FRACTION = 0.7
_TIED = {TIE_NEG_TO_POS: ("Tvn", "Tsn", "Tssn1"), TIE_POS_TO_NEG: ("Tvp", "Tsp", "Tssp1")}


def is_friction_only(dataset: Dataset) -> bool:
    """True when every experiment of `dataset` is `mode: friction`."""
    return len(dataset.modes) > 0 and all(m == "friction" for m in dataset.modes)


def _problem(dataset: Dataset, config: dict) -> FrictionProblem:
    fit = dict((config or {}).get("fit", {}) or {})
    tss2 = fit.get("Tss2")
    return FrictionProblem(list(dataset.experiments), list(dataset.files), Tss2=None if tss2 is None else float(tss2))


def _tie_note(problem: FrictionProblem, tie: int) -> str | None:
    if tie == 0:
        return None
    npos, nneg = problem.directions(problem.mask.astype(float))
    side, other = ("negative", "positive") if tie == TIE_NEG_TO_POS else ("positive", "negative")
    return (f"Only {npos} positive and {nneg} negative velocity samples: the {side}-direction parameters "
            f"({', '.join(_TIED[tie])}) cannot be identified and are set equal to the {other}-direction ones "
            f"(a symmetric-friction assumption, not a measurement). Record runs in both directions.")


# ---------------------------------------------------------------------------------------------- fit


def friction_fit_summary(problem: FrictionProblem, *, train_fraction: float = TRAIN_FRACTION, log=print) -> dict:
    """Eq. 9 on friction experiments: pooled estimates with standard errors, per-experiment estimates
    and consistency, in-sample NRMSE, and the chronological held-out error (first `train_fraction`
    of each record to fit, the rest to test; pooled, and each record fitted alone)."""
    why_low = low_speed_reason(problem)
    if why_low is not None:
        return low_speed_summary(problem, why_low, train_fraction=train_fraction, log=log)
    log(f"[1/2] eq. 9 pooled and per experiment ({problem.E} experiments, LM)")
    full = problem.rows_full()
    fit = problem.fit_eq9(full)
    se_rows = [physical_std_errors(fit.x[b], problem.std_errors(fit, full, b), problem.scale)
               for b in range(len(full.labels))]
    params = {}
    notes = []
    note = _tie_note(problem, int(fit.tie[0]))
    if note:
        notes.append(note)
    if problem.Tss2 is not None:
        notes.append(f"Tss2 fixed at {problem.Tss2:g} rad/s by the config (`fit.Tss2`).")
    eq9_rows = [fit.params(b, problem).eq9() for b in range(len(full.labels))]  # pooled, then each experiment
    for i, k in enumerate(FRICTION_NAMES):
        value = eq9_rows[0][k]
        free0 = bool(fit.free[0][i])
        per, per_se = [], []
        for b in range(1, len(full.labels)):
            pb = eq9_rows[b][k]
            se = float(se_rows[b][i])
            determined = bool(fit.free[b][i]) and math.isfinite(se) and se < abs(pb)
            per.append(pb if determined else None)
            per_se.append(se if fit.free[b][i] else None)
        vals = [v for v in per if v is not None]
        cons = float(np.std(vals) / abs(np.mean(vals))) if len(vals) >= 2 and np.mean(vals) != 0 else None
        params[k] = {"value": value, "std_error": float(se_rows[0][i]) if free0 else None, "unit": FRICTION_UNITS[k],
                     "consistency": cons, "per_experiment": per, "per_experiment_std_error": per_se,
                     "fitted": free0}
    notes.append("A per-experiment estimate is null where that record alone does not determine it (its standard "
                 "error exceeds its magnitude, or its direction was not recorded); consistency (std/|mean|) uses "
                 f"the determined ones. Standard errors allow for correlated residuals (block sandwich over {problem.se_block:g} s "
                 "of each record).")
    log(f"[2/2] held-out: first {train_fraction:.0%} of each record to fit, the rest to test; "
        "Coulomb + viscous (eq. 9's special case) the same ways")
    rec = problem.rows_records(train_fraction)
    hfit = problem.fit_eq9(rec)
    cmp = compare_with_coulomb_viscous(problem, fit.prediction[0], hfit, rec)
    pred_sel = fit.prediction[0]
    if cmp["selected"] == "coulomb_viscous":
        pred_sel = cmp["_pred"]
        cv = cmp["baseline_coulomb_viscous"]["parameters"]
        for k in FRICTION_NAMES:
            v = {"Tvp": "Tv", "Tvn": "Tv", "Tsp": "Tc", "Tsn": "Tc"}.get(k)
            params[k] |= {"value": cv[v]["value"] if v else (0.0 if k != "Tss2" else params[k]["value"]),
                          "std_error": cv[v]["std_error"] if v else None, "fitted": bool(v),
                          "eq9_value": params[k]["value"]}
        notes.append(cmp["note"])
    elif cmp.get("note"):
        notes.append(cmp["note"])
    pooled = rms_stats(pred_sel, problem.T, problem.mask.astype(float), fs=problem.fs)
    per_exp = []
    for e in range(problem.E):
        w = np.zeros_like(problem.mask, dtype=float)
        w[e] = problem.mask[e]
        st = rms_stats(pred_sel, problem.T, w, fs=problem.fs)
        per_exp.append({"file": problem.files[e], "nrmse": {"friction_torque": st["nrmse"]}, "rms": st["rms"],
                        "rms_lowpass_1hz": st["rms_lowpass_1hz"], "n_samples": st["n"]})
    notes.append(LOWPASS_NOTE)
    return {
        "parameters": params,
        "fit": {"model": cmp["selected"],
                "nrmse": {"friction_torque": pooled["nrmse"]}, "rms": {"friction_torque": pooled["rms"]},
                "rms_lowpass_1hz": {"friction_torque": pooled["rms_lowpass_1hz"]},
                "per_experiment": per_exp,
                "heldout": cmp["heldout"],
                "converged": bool(np.all(fit.converged)), "lm_steps": fit.steps.tolist()},
        "model_selection": {k: v for k, v in cmp.items() if not k.startswith("_") and k != "heldout"},
        "notes": notes,
        "_fit": fit, "_rows": full, "_heldout_fit": hfit, "_heldout_rows": rec, "_pred": pred_sel,
    }


LOWPASS_NOTE = ("RMS figures are given raw and low-passed (`rms_lowpass_1hz`: the residual through a zero-phase "
                "4th-order Butterworth filter at 1 Hz, MATLAB-style filtfilt edge padding, each contiguous span "
                "filtered on its own, RMS over the span), the convention of published joint-friction comparisons; "
                "the low-passed figure ignores noise and dynamics above 1 Hz.")


def _stats_pair(pred, problem, w) -> dict:
    st = rms_stats(pred, problem.T, w, fs=problem.fs)
    return {"rms": st["rms"], "rms_lowpass_1hz": st["rms_lowpass_1hz"], "nrmse": st["nrmse"]}


def compare_with_coulomb_viscous(problem: FrictionProblem, pred_full: np.ndarray, hfit, rec: Rows) -> dict:
    """Eq. 9 against its special case, symmetric Coulomb + viscous (`fit_coulomb_viscous`), fitted the
    same ways: on all samples (in-sample RMS) and on the first part of every record (held-out RMS on
    the rest, pooled and each record alone). Raw and 1 Hz low-passed RMS for both. `selected` is
    the model with the lower pooled held-out RMS: eq. 9 never loses to its own special case."""
    allw = problem.mask.astype(float)
    cv, cv_se, cv_pred = fit_coulomb_viscous(problem, allw)
    cvh, _, cvh_pred = fit_coulomb_viscous(problem, rec.train[0])
    eq9_in, cv_in = _stats_pair(pred_full, problem, allw), _stats_pair(cv_pred, problem, allw)
    eq9_held, cv_held = _stats_pair(hfit.prediction[0], problem, rec.test[0]), _stats_pair(cvh_pred, problem, rec.test[0])
    per = []
    for e in range(problem.E):
        tr, te = rec.train[1 + e], rec.test[1 + e]
        cve, _, cve_pred = fit_coulomb_viscous(problem, tr)
        per.append({"file": problem.files[e],
                    "heldout_rms": rms_stats(hfit.prediction[1 + e], problem.T, te)["rms"],
                    "heldout_rms_lowpass_1hz": _stats_pair(hfit.prediction[1 + e], problem, te)["rms_lowpass_1hz"],
                    "heldout_nrmse": rms_stats(hfit.prediction[1 + e], problem.T, te)["nrmse"],
                    "train_rms": rms_stats(hfit.prediction[1 + e], problem.T, tr)["rms"],
                    "parameters": fit_params_dict(hfit, 1 + e, problem),
                    "coulomb_viscous": {"heldout": _stats_pair(cve_pred, problem, te), "parameters": cve}})
    selected = "eq9" if eq9_held["rms"] <= cv_held["rms"] else "coulomb_viscous"
    if selected == "coulomb_viscous":
        note = (f"Eq. 9 predicted the held-out data worse than its special case, symmetric Coulomb + viscous "
                f"(held-out RMS {eq9_held['rms']:.4g} against {cv_held['rms']:.4g} N·m): its direction-dependent and "
                "Stribeck terms overfit these data. The reported parameters and fit are Coulomb + viscous "
                "(Tvp = Tvn = Tv, Tsp = Tsn = Tc, Tssp1 = Tssn1 = 0; Tss2 then has no effect); eq. 9's own values are "
                "kept as `eq9_value`.")
    else:
        note = None
    return {
        "selected": selected,
        "rule": "the model with the lower pooled held-out RMS (raw) is reported; both are listed",
        "eq9": {"in_sample": eq9_in, "heldout": eq9_held},
        "baseline_coulomb_viscous": {
            "model": "Tv·ω + Tc·sign(ω), symmetric, linear least squares (sign smoothed as in eq. 9)",
            "parameters": {"Tv": {"value": cv["Tv"], "std_error": float(cv_se[0]), "unit": "N·m·s/rad"},
                           "Tc": {"value": cv["Tc"], "std_error": float(cv_se[1]), "unit": "N·m"}},
            "in_sample": cv_in, "heldout": cv_held},
        "note": note,
        "heldout": {"split": f"first {rec_fraction(problem, rec):.0%} of each record → the rest",
                    "pooled": {"rms": eq9_held["rms"], "rms_lowpass_1hz": eq9_held["rms_lowpass_1hz"],
                               "nrmse": eq9_held["nrmse"]} if selected == "eq9" else
                              {"rms": cv_held["rms"], "rms_lowpass_1hz": cv_held["rms_lowpass_1hz"],
                               "nrmse": cv_held["nrmse"]},
                    "each_record_alone": per},
        "_pred": cv_pred,
    }


def rec_fraction(problem: FrictionProblem, rec: Rows) -> float:
    return float(rec.train[0][problem.mask].sum() / max(problem.mask.sum(), 1))


def low_speed_summary(problem: FrictionProblem, why: str, *, train_fraction: float = TRAIN_FRACTION,
                      log=print) -> dict:
    """`friction_fit_summary` for friction recorded wholly at low speed (`hdjax._fit.friction_low_speed`)."""
    log(f"low-speed friction: {why}")
    r = fit_low_speed(problem, train_fraction=train_fraction)
    sel = r["laws"][r["selected"]]
    law = sel["_law"]
    params = {}
    for k, p in sel["parameters"].items():
        params[k] = {"value": p["value"], "std_error": p["std_error"], "unit": p["unit"], "consistency": None,
                     "per_experiment": [None] * problem.E, "per_experiment_std_error": [None] * problem.E,
                     "fitted": p["std_error"] is not None}
    per_exp = []
    for e in range(problem.E):
        w = np.zeros_like(problem.mask, dtype=float)
        w[e] = problem.mask[e]
        st = rms_stats(law.prediction, problem.T, w, fs=problem.fs)
        per_exp.append({"file": problem.files[e], "nrmse": {"friction_torque": st["nrmse"]}, "rms": st["rms"],
                        "rms_lowpass_1hz": st["rms_lowpass_1hz"], "n_samples": st["n"]})
    other = [m for m in r["laws"] if m != r["selected"]][0]
    notes = [f"Low-speed law instead of eq. 9: {why}. Both laws were fitted on the first {train_fraction:.0%} of each "
             f"record and compared on the rest: `{r['selected']}` held-out RMS {sel['heldout']['rms']:.4g} N·m against "
             f"`{other}` {r['laws'][other]['heldout']['rms']:.4g} N·m; the parameters are the selected law refitted "
             "on all samples. Per-experiment estimates are not computed for the low-speed law.", LOWPASS_NOTE]
    first, last = problem._split(train_fraction)
    held = sel["heldout"]
    return {
        "parameters": params,
        "fit": {"model": r["selected"], "nrmse": {"friction_torque": sel["in_sample"]["nrmse"]},
                "rms": {"friction_torque": sel["in_sample"]["rms"]},
                "rms_lowpass_1hz": {"friction_torque": sel["in_sample"]["rms_lowpass_1hz"]},
                "per_experiment": per_exp,
                "heldout": {"split": r["split"], "pooled": held, "each_record_alone": []},
                "converged": True, "lm_steps": []},
        "low_speed": {"reason": why, "selected": r["selected"],
                      "laws": {m: {k: v for k, v in d.items() if not k.startswith("_")} for m, d in r["laws"].items()}},
        "notes": notes,
        "_pred": law.prediction, "_heldout_pred": sel["_heldout_law"].prediction,
        "_heldout_rows": Rows(np.stack([first] * (problem.E + 1)).astype(float),
                              np.stack([last] * (problem.E + 1)).astype(float),
                              ["pooled"] + list(problem.files), np.ones(problem.E + 1, bool)),
    }


def fit_params_dict(fit, b, problem) -> dict:
    return fit.params(b, problem).eq9()


def run_fit(dataset: Dataset, config: dict, out, *, log=print) -> dict:
    """`python -m hdjax.fit` on a friction-only dataset: writes fit.json, report.md, figures."""
    t0 = time.time()
    out = pathlib.Path(out)
    problem = _problem(dataset, config)
    s = friction_fit_summary(problem, log=log)
    doc = {"schema": "hdjax.fit/1", "dataset": dataset.name, "mode": "friction",
           **{k: v for k, v in s.items() if not k.startswith("_")},
           "timing_s": {"total": time.time() - t0}}
    model: str = doc["fit"]["model"]
    label = {"eq9": "eq. 9", "coulomb_viscous": "Coulomb + viscous"}.get(model, model)
    hfit = s.get("_heldout_fit")
    if hfit is None:  # low-speed law: one pooled held-out prediction serves every panel
        hfit = types.SimpleNamespace(prediction=np.stack([s["_heldout_pred"]] * (problem.E + 1)))
    from .plots import friction_heldout_time_figure, friction_velocity_figure  # matplotlib loads only when figures are drawn
    figs = [friction_velocity_figure(problem, s["_pred"], out / "friction_vs_velocity.png",
                          f"{label}, pooled fit on all samples", label=label),
            friction_heldout_time_figure(problem, hfit, s["_heldout_rows"], out / "heldout_time.png")]
    doc["figures"] = [f.name for f in figs]
    doc["timing_s"]["total"] = time.time() - t0
    write_results(out, "fit.json", doc, _fit_report(dataset, doc, figs), log=log)
    return doc


def _fit_report(dataset, doc, figs) -> str:
    lines = [f"# Friction fit: {dataset.name}", "",
             "Eq. 9 (direction-dependent viscous, Coulomb and Stribeck) fitted to friction torque against velocity "
             "(or, for friction recorded wholly at low speed, a low-speed law; see the notes).",
             "", "| parameter | value | std error | unit | consistency | per experiment |", "|---|---|---|---|---|---|"]
    for k, p in doc["parameters"].items():
        per = ", ".join("—" if v is None else f"{v:.4g}" for v in p["per_experiment"])
        se = "tied" if p["std_error"] is None and not p["fitted"] else (f"{p['std_error']:.3g}" if p["std_error"] is not None else "—")
        cons = "—" if p["consistency"] is None else f"{p['consistency']:.3g}"
        lines.append(f"| {k} | {p['value']:.5g} | {se} | {p['unit']} | {cons} | {per} |")
    f = doc["fit"]
    lines += ["", f"Reported model: **{f['model']}**.", "",
              f"In-sample NRMSE (all samples): {f['nrmse']['friction_torque']:.4f} "
              f"(RMS {f['rms']['friction_torque']:.4g} N·m raw, {f['rms_lowpass_1hz']['friction_torque']:.4g} N·m "
              "low-passed at 1 Hz).", "",
              f"Held-out ({f['heldout']['split']}): pooled RMS {f['heldout']['pooled']['rms']:.4g} N·m raw, "
              f"{f['heldout']['pooled']['rms_lowpass_1hz']:.4g} N·m low-passed at 1 Hz, "
              f"NRMSE {f['heldout']['pooled']['nrmse']:.4f}."]
    ms = doc.get("model_selection")
    if ms:
        b = ms["baseline_coulomb_viscous"]
        lines += ["", "## Eq. 9 against its special case, Coulomb + viscous", "",
                  f"Coulomb + viscous: {b['model']}; Tv = {b['parameters']['Tv']['value']:.4g} N·m·s/rad, "
                  f"Tc = {b['parameters']['Tc']['value']:.4g} N·m (all samples).", "",
                  "| model | in-sample RMS | in-sample RMS, 1 Hz | held-out RMS | held-out RMS, 1 Hz | (N·m) |",
                  "|---|---|---|---|---|---|"]
        for name, d in (("eq. 9", ms["eq9"]), ("Coulomb + viscous", b)):
            lines.append(f"| {name} | {d['in_sample']['rms']:.4g} | {d['in_sample']['rms_lowpass_1hz']:.4g} | "
                         f"{d['heldout']['rms']:.4g} | {d['heldout']['rms_lowpass_1hz']:.4g} | |")
        lines += ["", f"Selected: {ms['selected']} ({ms['rule']})."]
    ls = doc.get("low_speed")
    if ls:
        lines += ["", "## Low-speed laws", "", "| law | held-out RMS | held-out RMS, 1 Hz | in-sample RMS | parameters |",
                  "|---|---|---|---|---|"]
        for m, d in ls["laws"].items():
            ps = ", ".join(f"{k} = {p['value']:.4g} {p['unit']}" for k, p in d["parameters"].items())
            lines.append(f"| {m} | {d['heldout']['rms']:.4g} | {d['heldout']['rms_lowpass_1hz']:.4g} | "
                         f"{d['in_sample']['rms']:.4g} | {ps} |")
    if f["heldout"]["each_record_alone"]:
        lines += ["", "| record (fitted alone) | train RMS (N·m) | held-out RMS (N·m) | held-out RMS, 1 Hz | "
                  "held-out NRMSE | Coulomb + viscous held-out RMS / 1 Hz |", "|---|---|---|---|---|---|"]
    for r in f["heldout"]["each_record_alone"]:
        c = r["coulomb_viscous"]["heldout"]
        lines.append(f"| {r['file']} | {r['train_rms']:.4g} | {r['heldout_rms']:.4g} | "
                     f"{r['heldout_rms_lowpass_1hz']:.4g} | {r['heldout_nrmse']:.4f} | "
                     f"{c['rms']:.4g} / {c['rms_lowpass_1hz']:.4g} |")
    lines += ["", "## Notes", ""] + [f"- {n}" for n in doc["notes"]] + [""]
    lines += [f"![{p.stem}]({p.name})" for p in figs] + ["", f"Total time {doc['timing_s']['total']:.1f} s.", ""]
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------- diagnose


def _finding_params(problem: FrictionProblem, fold: _Fold, effect: str) -> dict:
    st = fold.structure
    p = fold_params(problem, fold)
    if effect in HARMONIC_FIELDS:
        orders = np.asarray(st.ripple_orders if effect == "position_dependent_friction" else st.torque_orders)
        term = getattr(p, effect)
        sin_coef, cos_coef = np.asarray(term.sin), np.asarray(term.cos)
        key = "epsilon" if effect == "position_dependent_friction" else "b"
        out = {}
        for j in range(HARMONIC_SLOTS):
            if orders[j] > 0:
                a, ph = amplitude_phase(sin_coef[j], cos_coef[j])
                k = int(orders[j])
                out[f"{key}{k}"], out[f"phi{k}"] = a, ph
        return out
    if effect == "presliding_friction":
        return {"presliding_distance": float(p.presliding_friction.distance())}
    if effect == "thermal_drift":
        return p.thermal_drift.to_dict()
    return {}


#: Units of a friction-only finding's parameters (`_finding_params`), by name without its order;
#: thermal drift's β and τ as the dynamic model's (`FIELD_UNITS`).
_FINDING_UNITS = {"epsilon": "-", "b": "N·m", "phi": "rad", "presliding_distance": "rad",
                  **{k: FIELD_UNITS[k] for k in ("beta", "tau")}}


def _finding_units(params: dict) -> dict[str, str]:
    """The unit of each parameter `_finding_params` reports (`epsilon3` → "-", `phi3` → rad, ...)."""
    return {k: _FINDING_UNITS[k.rstrip("0123456789")] for k in params}


_PHYSICS = {
    "position_dependent_friction": "Coulomb friction modulated with joint angle (orders in cycles per turn of `position`)",
    "position_dependent_torque": "a direction-independent torque periodic in angle: on joint data a rigid-body "
                                 "(gravity) model error left upstream or torque-sensor ripple, not friction",
    "presliding_friction": "friction with memory at velocity reversals (Dahl state)",
    "thermal_drift": "viscous friction decaying with session time (lubricant warming)",
}


def friction_diagnosis_doc(problem: FrictionProblem, dataset_name: str, *, min_gain: float = FRICTION_RULES.min_relative_gain,
                           log=print) -> dict:
    """Run `diagnose_friction` and build the SPEC §3 diagnosis.json (plus extras)."""
    d = diagnose_friction(problem, min_gain=min_gain, log=log)
    # the extended model on all samples, effects added in the order found
    full = Rows(problem.mask[None].astype(float), problem.mask[None].astype(float), ["all"], np.ones(1, bool))
    eq9 = problem.fit_eq9(full)
    fold = _Fold(eq9.x[0], int(eq9.tie[0]), eq9.free[0], eq9.structure)
    pred = eq9.prediction[0]
    ext_params = {}
    for f in d.findings:
        fold = _add(problem, fold, f["effect"], full.train[0], pred, d.max_order)
        r = problem.solve(full, fold.structure, fold.x[None], fold.free[None], np.array([fold.tie]))
        fold = _Fold(r.x[0], fold.tie, fold.free, fold.structure)
        pred = r.prediction[0]
    for f in d.findings:
        ext_params[f["effect"]] = _finding_params(problem, fold, f["effect"])
    span = max(float(np.ptp(np.asarray(problem.data.position)[e][problem.mask[e]])) for e in range(problem.E))
    findings = []
    for f in d.findings:
        b, a = f["before"], f["after"]
        findings.append({
            "effect": f["effect"],
            **({"orders": [int(o) for o in np.asarray(
                fold.structure.ripple_orders if f["effect"] == "position_dependent_friction" else fold.structure.torque_orders)
                if o > 0]} if f["effect"] in ("position_dependent_friction", "position_dependent_torque") else {}),
            "confidence": f["folds_improved"],
            "evidence": (f"{_PHYSICS[f['effect']]}: adding it cut the cross-validated held-out RMS from {b.rms:.4g} to "
                         f"{a.rms:.4g} N·m and lowered the held-out error in {f['folds_improved']:.0%} of "
                         f"{len(d.rows.labels)} folds ({'; '.join(d.rows.labels)})."
                         + _span_note(fold, f["effect"], span)),
            "parameters": ext_params[f["effect"]],
            "parameter_units": _finding_units(ext_params[f["effect"]]),
            "gain": {"heldout_nrmse_before": {"friction_torque": b.nrmse},
                     "heldout_nrmse_after": {"friction_torque": a.nrmse},
                     "heldout_rms_before": b.rms, "heldout_rms_after": a.rms,
                     "relative_reduction": f["relative_reduction"]},
        })
    unexplained = []
    res = (d.final.heldout - problem.T)
    rho = []
    for e in range(problem.E):
        r = res[e][problem.mask[e]]
        r = r - r.mean()
        rho.append(float(np.sum(r[1:] * r[:-1]) / max(np.sum(r * r), 1e-300)))
    if d.final.nrmse > 0.1 and np.mean(rho) > 0.5:
        unexplained.append({
            "description": "structured residual the named effects do not explain",
            "evidence": f"held-out NRMSE {d.final.nrmse:.3f} after the findings, residual lag-1 autocorrelation "
                        f"{np.mean(rho):.2f} (white noise: 0): the error is slow and systematic, not sensor noise. "
                        "On joint data this is typically dynamics or a rigid-body model error removed upstream, or "
                        "friction depending on more than velocity, angle and time."})
    for name, why in d.skipped.items():
        unexplained.append({"description": f"{name} not testable", "evidence": why})
    doc = {
        "schema": "hdjax.diagnosis/1", "dataset": dataset_name, "mode": "friction",
        "baseline": {"heldout_nrmse": {"friction_torque": d.baseline.nrmse}, "heldout_rms": d.baseline.rms,
                     "heldout_rms_lowpass_1hz": _lp(problem, d.baseline.heldout)},
        "findings": findings,
        "unexplained": unexplained,
        "cross_validation": {"folds": d.rows.labels, "min_gain": min_gain,
                             "rule": "significant when the pooled held-out RMS falls by at least min_gain and the "
                                     "held-out error falls in every fold (all but one with 5 or more folds)"},
        "rounds": d.rounds,
        "extended_model": {"eq9": fold_params(problem, fold).eq9(),
                           "effects": ext_params,
                           "heldout_nrmse": {"friction_torque": d.final.nrmse}, "heldout_rms": d.final.rms,
                           "heldout_rms_lowpass_1hz": _lp(problem, d.final.heldout)},
    }
    return doc | {"_d": d, "_pred_ext": pred, "_pred_eq9": eq9.prediction[0]}


def _lp(problem: FrictionProblem, pred: np.ndarray) -> float:
    """1 Hz low-passed RMS of `pred − measured` over every record (held-out predictions stitched
    from the folds; the filter runs over the whole record)."""
    return rms_stats(pred, problem.T, problem.mask.astype(float), fs=problem.fs)["rms_lowpass_1hz"]


def _span_note(fold, effect, span) -> str:
    if effect not in ("position_dependent_friction", "position_dependent_torque"):
        return ""
    orders = np.asarray(fold.structure.ripple_orders if effect == "position_dependent_friction"
                        else fold.structure.torque_orders)
    long = [int(k) for k in orders if k > 0 and 2 * np.pi / k > span]
    if not long:
        return ""
    return (f" Orders {long} have periods longer than the recorded angle range ({span:.3g} rad): there the term is "
            "a smooth function of angle, not a resolved harmonic, and its amplitude and phase are not physical.")


def run_diagnose(dataset: Dataset, config: dict, out, *, log=print) -> dict:
    """`python -m hdjax.diagnose` on a friction-only dataset: writes diagnosis.json, report.md, figures."""
    t0 = time.time()
    out = pathlib.Path(out)
    problem = _problem(dataset, config)
    log(f"friction diagnosis: {problem.E} experiments, cross-validated greedy selection")
    doc = friction_diagnosis_doc(problem, dataset.name, log=log)
    d = doc.pop("_d")
    doc.pop("_pred_ext"), doc.pop("_pred_eq9")
    from .plots import friction_cv_figure  # matplotlib loads only when figures are drawn
    figs = [friction_cv_figure(problem, d, out / "heldout_cv.png")]
    doc["figures"] = [f.name for f in figs]
    doc["timing_s"] = {"total": time.time() - t0}
    write_results(out, "diagnosis.json", doc, _diag_report(dataset, doc, figs), log=log)
    return doc


def _diag_report(dataset, doc, figs) -> str:
    lines = [f"# Friction diagnosis: {dataset.name}", "",
             f"Cross-validation folds: {'; '.join(doc['cross_validation']['folds'])}.", "",
             f"Eq. 9 held-out: RMS {doc['baseline']['heldout_rms']:.4g} N·m raw, "
             f"{doc['baseline']['heldout_rms_lowpass_1hz']:.4g} N·m low-passed at 1 Hz, NRMSE "
             f"{doc['baseline']['heldout_nrmse']['friction_torque']:.4f}.", "", "## Findings", ""]
    if not doc["findings"]:
        lines.append("None: no extension lowered the held-out error significantly (rule: "
                     f"{doc['cross_validation']['rule']}, min_gain {doc['cross_validation']['min_gain']}).")
    for f in doc["findings"]:
        lines.append(f"- **{f['effect']}** ({f['gain']['relative_reduction']:+.1%} held-out RMS): {f['evidence']} "
                     f"Parameters: {with_units(f['parameters'], f.get('parameter_units', {}))}.")
    lines += ["", "## Candidates per round", ""]
    for i, r in enumerate(doc["rounds"]):
        lines.append(f"Round {i + 1}: " + "; ".join(
            f"{k} {v['relative_reduction']:+.1%} (better in {v['folds_improved']:.0%} of folds)" for k, v in r.items()))
        lines.append("")
    if doc["unexplained"]:
        lines += ["## Unexplained / not testable", ""] + [f"- {u['description']}: {u['evidence']}" for u in doc["unexplained"]]
    lines += [""] + [f"![{p.stem}]({p.name})" for p in figs] + ["", f"Total time {doc['timing_s']['total']:.1f} s.", ""]
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------- figures
