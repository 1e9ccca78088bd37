"""The `diagnose` workflow: run `diagnose`, write diagnosis.json, the extended model, report.md and
figures (residual order spectra before/after, torque traces before/after)."""

import pathlib
import time

import jax
import matplotlib


matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from ._data import Dataset
from ._diagnose import diagnose
from ._effects import EFFECT_NAMES, MAX_ORDER, PERIODIC, SCALAR
from ._experiment import stack_experiments
from ._io import atomic_savefig, atomic_write_json, atomic_write_text
from ._paper_id import identify_paper
from ._plant import Simulator, simulate_batch


def effects_to_dict(effects) -> dict:
    """Plain-number description of active effects (periodic: orders, amplitudes, phases)."""
    out = {}
    for name in sorted(effects.active):
        if name in PERIODIC:
            k, a, ph = effects.amplitudes(name)
            out[name] = {"orders": [int(x) for x in k], "amplitudes": np.asarray(a).tolist(), "phases": np.asarray(ph).tolist()}
        else:
            fields = SCALAR[name]
            out[name] = {f: float(getattr(effects, f)) for f in fields}
    return out


def run_diagnose(dataset: Dataset, config: dict, out: pathlib.Path, *, log=print) -> dict:
    t_start = time.time()
    out = pathlib.Path(out)
    opts = dict(config.get("diagnose", {}) or {})
    dyn = dataset.dynamic_indices()
    if dataset.drive is None or len(dyn) < 2:
        raise ValueError(
            f"{dataset.folder}: `diagnose` needs at least two constrained or free experiments with a `drive` block "
            "(it holds experiments out for validation). Friction-only diagnosis is not implemented yet."
        )
    exps = [dataset.experiments[i] for i in dyn]
    files = [dataset.files[i] for i in dyn]
    fit_opts = dict(config.get("fit", {}) or {})
    log(f"[1/3] paper's identification on {len(exps)} experiments (start of the base model)")
    paper = identify_paper(exps, dataset.drive, alpha=fit_opts.get("alpha", 0.5), Tss2=fit_opts.get("Tss2", 0.1))
    log("[2/3] discrepancy loop (base fit, residual evidence, cross-validated candidates)")
    d = diagnose(
        paper.parameters(), dataset.drive, exps,
        candidates=opts.get("candidates", EFFECT_NAMES),
        base_steps=int(opts.get("base_steps", 5)),
        max_findings=int(opts.get("max_findings", 3)),
        min_relative_gain=float(opts.get("min_relative_gain", 0.03)),
        log=log,
    )
    log("[3/3] report and figures")
    figs = _figures(out, dataset, exps, files, d)
    unexplained = []
    if not d.findings:
        unexplained.append({
            "description": "no candidate effect improves held-out experiments significantly",
            "evidence": "the paper's model explains the data to within the noise, or the discrepancy is outside the "
                        "effect vocabulary (see the order spectra and correlations in `evidence`)",
        })
    result = {
        "schema": "hdjax.diagnosis/1",
        "dataset": dataset.name,
        "baseline": d.baseline,
        "findings": d.findings,
        "unexplained": unexplained,
        "evidence": d.evidence,
        "candidates_by_round": d.rounds,
        "extended_model": {"parameters": d.params.to_dict(), "effects": effects_to_dict(d.effects)},
        "figures": figs,
        "timing_s": {"total": time.time() - t_start},
    }
    atomic_write_json(out / "diagnosis.json", result)
    atomic_write_json(out / "extended_model.json", result["extended_model"])
    atomic_write_text(out / "report.md", _report(result))
    log(f"wrote {out / 'diagnosis.json'} in {result['timing_s']['total']:.1f} s")
    return result


def _report(r: dict) -> str:
    lines = [f"# Diagnosis of `{r['dataset']}`", ""]
    if r["findings"]:
        lines += ["## Findings (most important first)", ""]
        for f in r["findings"]:
            g = f["gain"]
            orders = f" at orders {f['orders']} per wave-generator turn" if "orders" in f else ""
            lines.append(f"- **{f['effect']}**{orders}: held-out error falls by {100 * g['relative_reduction']:.1f} % "
                         f"(torque NRMSE {g['heldout_nrmse_before']['torque']:.4f} → {g['heldout_nrmse_after']['torque']:.4f}); "
                         f"confidence {f['confidence']:.3f}. Parameters: "
                         + ", ".join(f"{k} = {v:.4g}" for k, v in f["parameters"].items()) + f". Evidence: {f['evidence']}.")
    else:
        lines += ["No finding: no effect of the vocabulary improves experiments held out of its fit significantly.", ""]
    lines += ["", "## Candidates (held-out relative reduction of the weighted squared error, per round)", ""]
    for i, rnd in enumerate(r["candidates_by_round"]):
        lines.append(f"Round {i + 1}: " + ", ".join(f"{c} {100 * s['gain']:+.1f} %" for c, s in sorted(rnd.items(), key=lambda x: -x[1]["gain"])))
        lines.append("")
    lines += ["## Figures", ""] + [f"![{f}]({f})" for f in r["figures"]] + [""]
    lines.append("The extended model (base parameters and effects) is saved in `extended_model.json`.")
    return "\n".join(lines) + "\n"


def _figures(out, dataset, exps, files, d) -> list[str]:
    names = []
    spectra = d.evidence["order_spectra"]
    if spectra:
        fig, ax = plt.subplots(figsize=(7, 4))
        k = np.arange(1, MAX_ORDER + 1)
        w = 0.8 / len(spectra)
        for j, (key, amp) in enumerate(spectra.items()):
            amp = np.asarray(amp)
            ax.bar(k + (j - len(spectra) / 2) * w, amp / max(amp.max(), 1e-300), width=w, label=key)
        ax.set_xlabel("order (cycles per wave-generator turn)")
        ax.set_ylabel("residual amplitude (normalised per channel)")
        ax.set_title("Residual order spectra of the fitted paper model")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
        atomic_savefig(fig, out / "residual_spectra.png", dpi=110, bbox_inches="tight")
        plt.close(fig)
        names.append("residual_spectra.png")
    if d.findings:
        batch = stack_experiments(exps)
        sim = jax.jit(lambda p, e, b: simulate_batch(p, dataset.drive, b, effects=e, simulator=Simulator(rtol=1e-6, atol=1e-8)))
        base = sim(d.params, type(d.effects)(), batch)
        ext = sim(d.params, d.effects, batch)
        m = np.asarray(batch.mask)
        pick = [0, len(exps) - 1] if len(exps) > 1 else [0]
        fig, axes = plt.subplots(len(pick), 1, figsize=(8, 2.6 * len(pick)), squeeze=False)
        for ax, j in zip(axes[:, 0], pick):
            t = np.asarray(batch.time[j])[m[j]]
            meas = np.asarray(batch.torque[j])[m[j]]
            ax.plot(t, meas - np.asarray(base.torque[j])[m[j]], color="0.6", lw=0.7, label="measured − paper model")
            ax.plot(t, np.asarray(ext.torque[j])[m[j]] - np.asarray(base.torque[j])[m[j]], color="C3", lw=1.0,
                    label="extended − paper model")
            ax.set_ylabel("torque (N·m)")
            ax.set_title(files[j], fontsize=9)
            ax.grid(alpha=0.3)
        axes[0, 0].legend(fontsize=8)
        axes[-1, 0].set_xlabel("time (s)")
        fig.tight_layout()
        atomic_savefig(fig, out / "residual_before_after.png", dpi=110)
        plt.close(fig)
        names.append("residual_before_after.png")
    return names
