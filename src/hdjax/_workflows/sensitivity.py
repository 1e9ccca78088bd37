r"""The `sensitivity` command's workflow (`hdjax sensitivity`): options, where the parameter values
come from, which experiments are used, the sections of sensitivity.json and the markdown report.
The analysis itself (sensitivities, Fisher information, the section V ablations, design advice) is
in `hdjax._fit.sensitivity`.
"""

import math
import pathlib
import time

import jax
import numpy as np

from .._data.experiment import CHANNEL_UNITS, select_experiments, stack_experiments
from .._data.load import Dataset
from .._fit.least_squares import CHANNELS, noise_levels
from .._fit.sensitivity import (
    AGREE_FACTOR,
    ESTIMATED,
    ablation_study,
    compare_consistency,
    design_advice,
    fisher_per_experiment,
    fisher_summary,
    sensitivities,
    sub_fisher,
    typical_experiments,
    weighted_jacobians,
)
from .._model.effects import Effects
from .._model.paper import PARAMETER_NAMES, PARAMETER_UNITS
from .._plant.simulate import Simulator
from .._plant.stepper import VelocityImplicit
from .artifacts import fit_json_dataset, read_fit_json
from .config import section_options
from .fit import _tolerance, _whole_number
from .io import write_results

__all__ = ["DEFAULTS", "SCHEMA", "run_sensitivity", "workflow_simulator"]

SCHEMA = "hdjax.sensitivity/1"


DEFAULTS = {
    "fit_json": None,  # path of a fit.json whose parameter values to use
    "solver": "velocity_implicit",  # the fixed-step exact plant, or "rodas3" (see `workflow_simulator`)
    "substeps": 4,  # steps per sample interval of velocity_implicit
    "rtol": 1e-4,  # solver tolerance of the sensitivity and ablation simulations (rodas3)
    "max_steps": 20_000,  # step budget per experiment of rodas3 (a simulation that exhausts it is reported)
    "max_experiments": 50,  # sensitivities on at most this many experiments (evenly spread)
    "ablation_both_modes": True,  # also run each change on the other mode (not only the paper's)
    "significant_increase": 0.5,  # an RMS increase above this fraction counts as "matters"
}


def _channel_residual(r, blocks, ch):
    """The rows of the weighted residual `r` that belong to channel `ch` (same order as `blocks`)."""
    start = 0
    for name, A in blocks.items():
        if name == ch:
            return r[start : start + A.shape[0]]
        start += A.shape[0]
    raise KeyError(ch)


def _combination(components: dict, threshold: float = 0.2) -> str:
    terms = sorted(((v, k) for k, v in components.items() if abs(v) >= threshold), key=lambda x: -abs(x[0]))
    return " ".join(f"{'+' if v >= 0 else '−'} {abs(v):.2f}·ln|{k}|" for v, k in terms).lstrip("+ ")


def _options(config: dict) -> dict:
    return section_options(config, "sensitivity", DEFAULTS)


def workflow_simulator(opts: dict) -> Simulator:
    """The simulator of the sensitivity and ablation runs (options as `DEFAULTS`): `solver`
    "velocity_implicit" (the default: `hdjax.VelocityImplicit` at `substeps` steps per sample, the
    exact model the fit and the diagnosis use; derivatives by the implicit function theorem at each
    step) or "rodas3" (adaptive Rosenbrock on the smoothed model at `rtol`, with `max_steps`; the
    default until 2026-12-05). A bad value names its key.

    Measured on the shipped HD2 campaign (2026-12-04, fifty-second session, 2-core machine, empty
    compilation cache): "velocity_implicit" at 4 substeps 13.7 s inside against 20.7 s; its
    standard errors of K1 … Tsn within 1 % of Rodas3's, the Stribeck amplitudes' 4–13 % lower (the
    exact model against the smoothed one), within 0.3 % of its own at 16 substeps; the ablation
    figures within 2 %. What held it back was `initial_state`'s rest test, which used the smoothed
    plant's breakaway interval with the exact plant (see its comment; the tiny locked record of
    `tests/test_sensitivity.py` left the velocity at χ² 10.3 at the truth parameters, 0.74 now)."""
    name = opts["solver"]
    if name == "velocity_implicit":
        return Simulator(solver=VelocityImplicit(substeps=_whole_number(opts, "substeps", "sensitivity")))
    if name == "rodas3":
        rtol = _tolerance(opts, "rtol", "sensitivity")
        return Simulator(rtol=rtol, atol=rtol * 1e-2, max_steps=_whole_number(opts, "max_steps", "sensitivity"))
    raise ValueError(f"config `sensitivity.solver` must be one of ['velocity_implicit', 'rodas3'], got {name!r}.")


def _parameter_source(dataset: Dataset, config: dict, out: pathlib.Path, opts: dict, exps, log):
    """(Parameters, source dict, consistency, per-experiment estimates, paper identification or None,
    the fit's standard errors by name (empty without a fit.json), the terms fitted with the
    parameters (fit.json's `model_form`; `Effects()` without a fit.json))."""
    candidates = []
    if opts.get("fit_json"):
        p = pathlib.Path(opts["fit_json"]).expanduser()
        if not p.is_file():
            raise ValueError(f"config `sensitivity.fit_json`: {p} does not exist; give the path of a fit.json.")
        candidates.append((p, True))
    else:
        stem = out.name[: -len("-sensitivity")] if out.name.endswith("-sensitivity") else None
        if stem:
            candidates.append((out.parent / stem / "fit.json", False))
    for path, explicit in candidates:
        if not path.is_file():
            continue
        name = fit_json_dataset(path)
        if not explicit and name != dataset.name:
            log(f"      ignoring {path}: it belongs to dataset {name!r}, not {dataset.name!r}")
            continue
        fit = read_fit_json(path, setting="config `sensitivity.fit_json` / `--fit`")
        source: dict = {"kind": "fit.json", "path": str(path)}
        return (fit.parameters, source, fit.consistency, fit.per_experiment, None,
                fit.std_error, fit.effects)
    from .._fit.paper import identify_paper
    from .fit import _options as fit_options

    fo = fit_options(config)
    assert dataset.drive is not None  # run_sensitivity checked it
    paper = identify_paper(exps, dataset.drive, alpha=fo["alpha"], Tss2=fo["Tss2"], cutoff_hz=fo["cutoff_hz"])
    src = {
        "kind": "paper_identification",
        "note": "no fit.json found (config `sensitivity.fit_json`, or results/<name>/fit.json beside the output "
        "folder); the paper's regressions (section III) were run instead of the slow trajectory fit",
        "undetermined": paper.undetermined(),
    }
    return paper.parameters(), src, dict(paper.consistency), dict(paper.per_experiment), paper, {}, Effects()


def run_sensitivity(dataset: Dataset, config: dict, out, *, log=print) -> dict:
    """Run the sensitivity and identifiability study on `dataset` and write sensitivity.json,
    report.md and the figures into `out`. Returns the JSON dict."""
    log = log or (lambda *_: None)
    t_start = time.time()
    timing = {}
    opts = _options(config)
    out = pathlib.Path(out)
    drive, exps, files_all, modes_all = dataset.dynamic_part("sensitivity")
    notes: list[str] = []

    log("[1/5] parameters")
    t0 = time.time()
    p, source, consistency, per_exp_est, paper, fit_se, effects = _parameter_source(dataset, config, out, opts, exps, log)
    timing["parameters"] = time.time() - t0
    log(f"      from {source['kind']}" + (f" ({source['path']})" if "path" in source else ""))
    if opts["solver"] != "velocity_implicit" and "breakaway_friction" in effects.active:
        effects = effects.without("breakaway_friction")
        note = (f"the fit's breakaway torques are left out: the {opts['solver']} plant has no exact sticking "
                f"(`sensitivity.solver: velocity_implicit` keeps them)")
        notes.append(note)
        log(f"      note: {note}")
    if effects.active:
        source["effects"] = effects.to_dict()
        log(f"      with the terms fitted with them, held: {', '.join(sorted(effects.active))}")

    sel, files, modes, batch = _selection(exps, files_all, modes_all, opts, notes)
    sigma = np.asarray(noise_levels(stack_experiments(exps)))
    simulator = workflow_simulator(opts)

    log(f"[2/5] sensitivities ∂y/∂ln p: jacfwd through the solve, vmap over {len(sel)} experiments × {len(PARAMETER_NAMES)} parameters")
    t0 = time.time()
    sens = jax.block_until_ready(sensitivities(p, drive, batch, simulator=simulator, effects=effects))
    timing["sensitivities"] = time.time() - t0
    ok = _simulations_ok(sens, files, opts, notes)
    Js, rs, blocks = weighted_jacobians(sens.S, sens.outputs, batch, sigma)
    names = list(PARAMETER_NAMES)
    P = len(names)
    F_e, info = fisher_per_experiment(Js, ok, P)
    summary = _sensitivity_summary(names, info, ok, blocks, sigma)

    log("[3/5] Fisher information, standard errors, correlations, weakest directions")
    F = F_e.sum(0)
    n_obs, chi2, chi2_channel = _chi_square(rs, blocks, ok, P)
    fs_all = fisher_summary(F, names)
    est = [k for k in ESTIMATED if k in names]
    fs_est = fisher_summary(sub_fisher(F, names, est), est)
    comparison = compare_consistency(F_e, ok, names, est, fs_est, consistency, per_exp_est, paper, sel, exps, modes, batch,
                          float(p.Tss2))

    log("[4/5] the paper's section V study (complete vs Coulomb = 0, viscous = 0, K1/10, Tst = 0)")
    t0 = time.time()
    ablation, abl_traj = ablation_study(p, drive, batch, sens, ok, modes, files, opts, simulator, effects)
    timing["ablations"] = time.time() - t0

    log("[5/5] experiment-design advice, report and figures")
    advice = design_advice(F, F_e, ok, names, est, fs_est, files, modes, batch, p)
    t0 = time.time()
    typical = typical_experiments(info, ok, modes)
    from .plots import sensitivity_figures  # matplotlib loads only when figures are drawn
    figs = sensitivity_figures(out, names, info, ok, files, modes, batch, sens, typical, fs_all, abl_traj)
    timing["figures"] = time.time() - t0
    timing["total"] = time.time() - t_start

    result = {
        "schema": SCHEMA,
        "dataset": dataset.name,
        "parameter_source": source,
        "parameters": {k: float(getattr(p, k)) for k in names},
        "experiments": [
            {"file": f, "mode": m, "simulation_ok": bool(ok[j]), "solver_steps": int(np.asarray(sens.num_steps)[j])}
            for j, (f, m) in enumerate(zip(files, modes))
        ],
        "noise_levels": dict(zip(CHANNELS, sigma.tolist())),
        "sensitivity": _sensitivity_section(files, modes, summary),
        "standard_errors": _standard_errors(names, est, fs_est, fs_all, p, fit_se),
        "correlation": {"parameters": fs_all["parameters"], "matrix": fs_all["correlation"]},
        "svd": _svd_section(names, fs_all),
        "identifiability": _identifiability_section(chi2, chi2_channel, n_obs, fs_est, fs_all, comparison),
        "ablation": ablation,
        "advice": advice,
        "notes": notes,
        "figures": figs,
        "timing_s": timing,
    }
    write_results(out, "sensitivity.json", result, _report(result), log=log)
    return result


def _selection(exps, files_all, modes_all, opts, notes):
    """At most `sensitivity.max_experiments` experiments, evenly spread over constrained and free:
    their positions, files, modes and stacked batch."""
    sel = select_experiments(modes_all, int(opts["max_experiments"]))
    if len(sel) < len(exps):
        notes.append(
            f"Sensitivities, Fisher information and ablations use {len(sel)} of {len(exps)} experiments, evenly spread "
            "over constrained and free (`sensitivity.max_experiments`), to bound the run time."
        )
    files = [files_all[j] for j in sel]
    modes = [modes_all[j] for j in sel]
    return sel, files, modes, stack_experiments([exps[j] for j in sel])


def _simulations_ok(sens, files, opts, notes) -> np.ndarray:
    """Which experiments simulated with finite sensitivities (bools); a note names the others."""
    ok = np.asarray(sens.success) & np.all(np.isfinite(np.asarray(sens.S)), axis=(1, 2, 3))
    failed = [files[j] for j in range(len(files)) if not ok[j]]
    if failed:
        notes.append(
            f"The simulation failed (step budget `sensitivity.max_steps` = {opts['max_steps']} or solver failure) for "
            f"{len(failed)} experiment(s), left out of the Fisher information: {', '.join(failed)}."
        )
    return ok


def _sensitivity_summary(names, info, ok, blocks, sigma) -> dict:
    """Per parameter and experiment: the information √F_kk, and per channel the RMS over time of
    S_k/σ (–) and of S_k (N·m, rad/s, rad); None where the simulation failed or the channel is absent."""
    n_sel = len(blocks)
    summary = {}
    for k, name in enumerate(names):
        rms_sig, rms_si = {}, {}
        for c, ch in enumerate(CHANNELS):
            v_sig, v_si = [], []
            for j in range(n_sel):
                blk = blocks[j].get(ch)
                if blk is None or not ok[j]:
                    v_sig.append(None)
                    v_si.append(None)
                else:
                    rms = float(np.sqrt(np.mean(blk[:, k] ** 2)))
                    v_sig.append(rms)
                    v_si.append(rms * float(sigma[c]))
            rms_sig[ch], rms_si[ch] = v_sig, v_si
        summary[name] = {
            "information": [float(info[k, j]) if ok[j] else None for j in range(n_sel)],
            "rms_over_noise": rms_sig,
            "rms": rms_si,
        }
    return summary


def _chi_square(rs, blocks, ok, P) -> tuple[int, float, dict[str, float]]:
    """The number of observations, the reduced chi-square of the noise-weighted residual over the
    simulated experiments, and the mean squared weighted residual per channel (–)."""
    n_obs = int(sum(len(r) for j, r in enumerate(rs) if ok[j]))
    chi2 = float(sum(float(r @ r) for j, r in enumerate(rs) if ok[j]) / max(n_obs - P, 1))
    chi2_channel = {}
    for ch in CHANNELS:
        rr = [_channel_residual(rs[j], blocks[j], ch) for j in range(len(rs)) if ok[j] and ch in blocks[j]]
        if rr:
            chi2_channel[ch] = float(np.mean(np.concatenate(rr) ** 2))
    return n_obs, chi2, chi2_channel


def _standard_errors(names, est, fs_est, fs_all, p, fit_se: dict) -> dict:
    """sensitivity.json's `standard_errors`: relative (estimated set, and all free) and absolute
    (in each parameter's unit) noise-only standard errors, and beside them the fit's own relative
    standard error (`fit_relative`: from fit.json, allowing for a misfit correlated in time; None
    without a fit.json or where the fit did not estimate the parameter)."""
    std_errors = {}
    for k in names:
        rel = fs_est["std_error"].get(k, fs_all["std_error"][k])
        v, se = abs(float(getattr(p, k))), fit_se.get(k)
        std_errors[k] = {
            "relative": rel,
            "absolute": rel * v,
            "relative_all_free": fs_all["std_error"][k],
            "fit_relative": float(se) / v if se is not None and v > 0 and math.isfinite(float(se)) else None,
            "estimated": k in est,
            "unit": PARAMETER_UNITS[k],
        }
    return std_errors


def _sensitivity_section(files, modes, summary) -> dict:
    """sensitivity.json's `sensitivity`: the definition, the experiments and the per-parameter summary."""
    return {
        "definition": (
            "S_k(t) = ∂y(t)/∂ln|p_k| (forward-mode AD through the solve). Per parameter and experiment: "
            "`information` = √(Σ_t Σ_channels (S_k/σ_channel)²) = 1 / (relative standard error of p_k if it "
            "were the only unknown, from this experiment alone); `rms_over_noise` = RMS over time of S_k/σ "
            "per channel (–); `rms` = RMS over time of S_k per channel (N·m, rad/s, rad). The output angle "
            "is projected off its rigid-body components {1, t} first, as in the fit's residual."
        ),
        "experiments": files,
        "modes": modes,
        "parameters": summary,
    }


def _svd_section(names, fs_all) -> dict:
    """sensitivity.json's `svd`: singular values and the weakest directions, each written out as a
    combination of ln p."""
    return {
        "parameters": names,
        "singular_values": fs_all["singular_values"],
        "weakest_directions": [
            dict(d, combination=_combination(d["components"])) for d in fs_all["directions"]
        ],
    }


def _identifiability_section(chi2, chi2_channel, n_obs, fs_est, fs_all, comparison) -> dict:
    """sensitivity.json's `identifiability`: chi-square, the Fisher summaries and the comparison
    with the consistency."""
    return {
        "chi2_reduced": chi2,
        "chi2_per_channel": chi2_channel,
        "observations": n_obs,
        "note": (
            "Standard errors are noise-only: √diag((JᵀJ)⁻¹) with J the noise-weighted residual Jacobian in ln p, "
            "so they are relative. `relative` holds the 9 parameters the fit estimates (alpha and Tss2 fixed, "
            "as in the paper); `relative_all_free` frees all 11. They are a design quantity (what noise alone "
            "leaves); the fit's own standard errors (`fit_relative`, from fit.json) allow for the model error "
            "that a bench leaves, correlated in time (a block sandwich), and are larger where the model is not exact."
        ),
        "estimated": fs_est,
        "all": fs_all,
        "comparison": comparison,
    }


def _short(f: str) -> str:
    return pathlib.Path(f).stem


def _pct(v):
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "—"
    return f"{100 * v:.3g} %"


def _g(v):
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "—"
    return f"{v:.4g}"


def _figure_md(r: dict, name: str, alt: str) -> list[str]:
    """Markdown lines embedding figure `name`, or none when it was not drawn."""
    return [f"![{alt}]({name})", ""] if name in set(r["figures"]) else []


def _report(r: dict) -> str:
    """report.md from sensitivity.json `r`: header, the four sections, notes and timing (s)."""
    L = _report_header(r)
    L += _report_sensitivities(r)
    L += _report_identifiability(r)
    L += _report_correlations(r)
    L += _report_ablation(r)
    L += _report_design(r)
    if r["notes"]:
        L += ["## Notes", ""] + [f"- {n}" for n in r["notes"]] + [""]
    L += ["## Timing", ""] + [f"- {k}: {v:.1f} s" for k, v in r["timing_s"].items()] + [""]
    return "\n".join(L)


def _report_header(r: dict) -> list[str]:
    """Title, parameter source, experiments and noise levels (in each channel's unit)."""
    L = [f"# Sensitivity and identifiability of `{r['dataset']}`", ""]
    src = r["parameter_source"]
    L.append(
        f"Parameters: **{src['kind'].replace('_', ' ')}**" + (f" (`{src['path']}`)" if "path" in src else "")
        + (f". {src['note']}." if "note" in src else ".")
    )
    n_exp = len(r["experiments"])
    n_ok = sum(e["simulation_ok"] for e in r["experiments"])
    L += ["", f"Experiments analysed: {n_exp} ({n_ok} simulated successfully). Noise levels (from the data): "
          + ", ".join(f"{k} {v:.3g} {CHANNEL_UNITS[k]}" for k, v in r["noise_levels"].items()) + "."]
    return L


def _report_sensitivities(r: dict) -> list[str]:
    """Section 1: the definition, figures and the most informative experiments per parameter."""
    L = ["", "## 1. Sensitivities", "", r["sensitivity"]["definition"], ""]
    L += _figure_md(r, "sensitivity_heatmap.png", "information heat map")
    L += _figure_md(r, "sensitivity_curves.png", "sensitivity curves")
    L += ["Most informative experiments per parameter (information √F_kk):", "",
          "| parameter | 1st | 2nd | 3rd | information from free motion |", "|---|---|---|---|---|"]
    sens = r["sensitivity"]["parameters"]
    modes = r["sensitivity"]["modes"]
    for k, rank in r["advice"]["ranking"].items():
        tot = sum((v or 0) ** 2 for v in sens[k]["information"])
        fr = sum((v or 0) ** 2 for v, m in zip(sens[k]["information"], modes) if m == "free")
        cells = [f"{_short(x['file'])} ({x['information']:.3g})" for x in rank[:3]] + ["—"] * (3 - min(3, len(rank)))
        L.append(f"| {k} | " + " | ".join(cells) + f" | {_pct(fr / tot) if tot > 0 else '—'} |")
    return L


def _report_identifiability(r: dict) -> list[str]:
    """Section 2, first part: chi-square, the standard-error table against the consistency, and
    why they differ."""
    idf = r["identifiability"]
    L = ["", "## 2. Identifiability", "", idf["note"], "",
         f"Reduced chi-square of the weighted residual at these parameters: {idf['chi2_reduced']:.3g} "
         f"({idf['observations']} observations): " + (
             "the model explains the data to the noise level." if idf["chi2_reduced"] < 1.5 else
             "above 1, so the residual holds more than noise (model error), which the noise-only SE leave out."), ""]
    L += ["| parameter | value | relative SE (9 estimated) | relative SE (all 11 free) "
          "| fit's relative SE (allows for model error) | noise-predicted per-experiment spread | consistency | agree? |",
          "|---|---|---|---|---|---|---|---|"]
    comp = {c["parameter"]: c for c in idf["comparison"]}
    for k, e in r["standard_errors"].items():
        c = comp.get(k, {})
        agree = {True: "yes", False: "no", None: "—"}[c.get("agree")]
        L.append(f"| {k} | {_g(r['parameters'][k])} {e['unit']} | {_pct(e['relative']) if e['estimated'] else 'fixed'} | "
                 f"{_pct(e['relative_all_free'])} | {_pct(e.get('fit_relative'))} | {_pct(c.get('noise_predicted_spread'))} | "
                 f"{_pct(c.get('consistency'))} | {agree} |")
    L += ["", "Why they differ: the consistency (std/|mean| of the paper's per-experiment estimates) contains the "
          "measurement noise of *one* experiment plus model error, the regression's own errors and any drift; the "
          "joint standard error contains noise only, pooled over all experiments (≈ 1/√n of a per-experiment spread). "
          "The fair comparison is the noise-predicted per-experiment spread: the SE of the parameter from one "
          "informing experiment with its regression group estimated (compliance K1, Tst; high-velocity Jeff, Tvp, Tvn, "
          "Tsp, Tsn; Stribeck Tssp1, Tssn1) and the rest fixed, RMS over the experiments the paper used. "
          f"'agree' = consistency within a factor {AGREE_FACTOR:g} of it.", ""]
    return L + _report_disagreement(idf)


def _report_disagreement(idf: dict) -> list[str]:
    """Section 2, second part: rank correlation of SE and consistency, and where the consistency
    exceeds the noise prediction, why."""
    L = []
    rows = [c for c in idf["comparison"] if c["consistency"] is not None and c["relative_std_error"] is not None
            and np.isfinite(c["relative_std_error"])]
    if len(rows) >= 3:
        se_rank = np.argsort(np.argsort([c["relative_std_error"] for c in rows]))
        co_rank = np.argsort(np.argsort([c["consistency"] for c in rows]))
        rho = float(np.corrcoef(se_rank, co_rank)[0, 1])
        worst_se = [rows[i]["parameter"] for i in np.argsort(se_rank)[::-1][:2]]
        worst_co = [rows[i]["parameter"] for i in np.argsort(co_rank)[::-1][:2]]
        L.append(f"Ranking: Spearman correlation between relative SE and consistency over {len(rows)} parameters "
                 f"ρ = {rho:.2f}; least determined by the Fisher analysis: {', '.join(worst_se)}; by the consistency: "
                 f"{', '.join(worst_co)}.")
        L.append("")
    bad = [c for c in idf["comparison"] if c["agree"] is False]
    if bad:
        chi = idf.get("chi2_per_channel", {})
        L.append(
            "Where the consistency exceeds the noise prediction, the spread is not measurement noise: (1) model error "
            "— the mean squared weighted residual per channel is "
            + ", ".join(f"{k} {v:.3g}" for k, v in chi.items())
            + " (1 = noise only), so the records hold effects or parameter errors the noise-only SE cannot see; "
            "(2) the paper's regressions are equation-error fits on low-pass-filtered signals with a numerically "
            "differentiated acceleration, which are neither efficient nor unbiased, and their bias changes with each "
            "experiment's spectrum and amplitude; (3) any drift between experiments. The standard errors say what "
            "the data could determine; the consistency says how reproducibly the paper's procedure determines it."
        )
        L.append("")
        for c in bad:
            L.append(f"- **{c['parameter']}**: {c['why']}.")
    return L


def _report_correlations(r: dict) -> list[str]:
    """Section 2, last part: the correlation figure, strongest correlations and weakest directions."""
    L = [""] + _figure_md(r, "correlation.png", "correlation matrix") + ["Strongest correlations (all 11 free):", ""]
    C = np.array(r["correlation"]["matrix"], dtype=float)
    names = r["correlation"]["parameters"]
    pairs = sorted(((abs(C[a, b]), a, b) for a in range(len(names)) for b in range(a + 1, len(names)) if np.isfinite(C[a, b])), reverse=True)
    for v, a, b in pairs[:4]:
        L.append(f"- {names[a]} – {names[b]}: {C[a, b]:+.3f}")
    L += ["", "Weakest directions (eigenvectors of F = JᵀJ with the smallest singular values of J, in ln p):", ""]
    for d in r["svd"]["weakest_directions"]:
        L.append(f"- s = {d['singular_value']:.3g} (relative SE along it {_pct(d['std_error_along'])}): {d['combination']}")
    return L


def _report_ablation(r: dict) -> list[str]:
    """Section 3: the paper's section V study, RMS torque (N·m) and velocity (rad/s) per change and
    mode, conclusions and figures."""
    ab = r["ablation"]
    L = ["", "## 3. The paper's section V study", "", ab.get("definition", ""), "",
         "| change | mode | experiments | RMS torque (N·m) complete → changed | increase "
         "| RMS velocity (rad/s) complete → changed | increase | failed |",
         "|---|---|---|---|---|---|---|---|"]
    for c in ab.get("changes", []):
        for mode, e in c["per_mode"].items():
            mark = " (paper)" if mode == c["paper_mode"] else ""
            cells = []
            for ch in ("torque", "motor_velocity"):
                if ch in e["rms"]:
                    cells += [f"{e['rms_complete'][ch]:.3g} → {e['rms'][ch]:.3g}", _pct(e["rms_increase"][ch])]
                else:
                    cells += ["—", "—"]
            L.append(f"| {c['label']} | {mode}{mark} | {e['experiments']} | " + " | ".join(cells) + f" | {len(e['failed'])} |")
    con = ab.get("conclusions", {})
    if con:
        L += ["", f"Paper: {con['paper']}", ""] + [f"- {s}" for s in con["summary"]]
        L += ["", f"Free-motion friction conclusion reproduced: **{'yes' if con['free_motion_friction_reproduced'] else 'no'}**; "
              f"constrained-motion compliance conclusion reproduced: **{'yes' if con['constrained_motion_compliance_reproduced'] else 'no'}**."]
        if con["differences"]:
            L += ["", "Where the data go beyond or differ from the paper:", ""] + [f"- {d}." for d in con["differences"]]
    L += [""] + _figure_md(r, "fig6_free_ablation.png", "Fig. 6: free motion")
    L += _figure_md(r, "fig7_constrained_ablation.png", "Fig. 7: constrained motion")
    return L


def _report_design(r: dict) -> list[str]:
    """Section 4: the experiment-design suggestion and the campaign ranking on the Stribeck terms."""
    adv = r["advice"]
    L = ["## 4. Experiment design", ""]
    if "suggestion" in adv:
        L += [adv["suggestion"], ""]
    if adv.get("undetermined"):
        L += [f"Not determined at all by these experiments: {', '.join(adv['undetermined'])}.", ""]
    for k in ("Tssp1", "Tssn1"):
        if k in adv["ranking"]:
            L.append(f"Ranking of the campaign by information on {k}: " + ", ".join(
                f"{_short(x['file'])} ({x['information']:.3g})" for x in adv["ranking"][k][:10]) + (" …" if len(adv["ranking"][k]) > 10 else ""))
            L.append("")
    return L


