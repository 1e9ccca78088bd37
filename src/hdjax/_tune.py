"""The `tune` workflow: identified plant -> rule-tuned PI baseline -> robust gradient tuning ->
validation on the virtual bench -> tune.json, report.md and figures. The command
`python -m hdjax.tune` is a thin wrapper around `run_tune`.

Steps (all SI units):

1. Identified plant: `fit.json` (from `tune.fit` in the config, else `DIR/fit.json`, else
   `results/<dataset folder name>/fit.json`); with an `extended_model.json` beside it (from
   `diagnose`) its base parameters and effects are used. Without a fit.json the paper's
   identification (`hdjax._paper_id.identify_paper`, seconds) is run and the report says so.
2. Hardware: sensor sample period = the records' time step; current limit = `tune.current_limit`
   or the largest |current| in the records; sensor noise = the fit's noise levels.
3. References (0.5 s each, at the sensor rate): locked step and sine, free step (a doublet that
   brings the load back to rest) and free sine, amplitudes a fraction of the largest torque seen
   in the locked / free records.
4. Baseline: Åström–Hägglund relay test on the identified (locked) model, Ziegler–Nichols PI.
5. Robust tuning: plant parameter sets drawn from the per-experiment estimates, the tuning cost
   averaged over them (`vmap` over plants and references) and minimised by BFGS from the baseline.
6. Validation on the virtual bench: the rig's true parameters, its hidden effects and fresh
   sensor noise (from the dataset's `truth.yaml`), integrated with 16 substeps per sample and the
   rig's own smoothing. Without a `truth.yaml` (real data) this step uses the identified model
   with the estimated noise, and the report says so.
"""

import json
import pathlib
import time

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np


matplotlib.use("Agg")
import matplotlib.pyplot as plt

from ._control import (
    GAIN_NAMES,
    GAIN_UNITS,
    GainScaling,
    Plant,
    Reference,
    TorqueController,
    TorqueGains,
    batch_cost,
    closed_loop,
    doublet_reference,
    relay_test,
    sine_reference,
    step_metrics,
    step_reference,
    tune_gains,
    ziegler_nichols_pi,
)
from ._config import section_options
from ._progress import task
from ._data import Dataset
from ._effects import MODEL_FORM, PERIODIC, SCALAR, Effects
from ._io import atomic_savefig, atomic_write_json, atomic_write_text
from ._model import PARAMETER_NAMES, Parameters, Smoothing


DEFAULTS = {
    "fit": None,  # path to a fit.json (relative to the config file's folder is not resolved: give it absolute or cwd-relative)
    "current_limit": None,  # A; default: largest |current| in the records
    "duration": 0.5,  # s per reference
    "locked_fraction": 0.5,  # locked reference amplitude / largest locked |torque| recorded
    "free_fraction": 0.5,  # free reference amplitude / largest free |torque| recorded
    "locked_sine_hz": 3.0,
    "free_sine_hz": 2.0,
    "plants": 6,  # plant parameter sets drawn for the robust cost
    "seed": 0,
    "max_steps": 8,  # BFGS steps
    "start_factors": [1.0, 0.5, 0.25],  # kp, ki multiples of the baseline tried (grid) before BFGS
    "substeps": 2,  # Rodas3 steps per sample in the tuning model
    "velocity_scale": 0.03,  # rad/s, friction sign() smoothing of the tuning model
    "torsion_rate_scale": 1e-3,  # rad/s, |rate|^alpha smoothing of the tuning model
    "effort_weight": 0.01,
    "relay_amplitude": 0.25,  # relay amplitude / current limit
    "rig_substeps": 16,
}
REFERENCE_NAMES = ("locked_step", "locked_sine", "free_step", "free_sine")


def _options(config: dict) -> dict:
    out = section_options(config, "tune", DEFAULTS)
    for k in ("duration", "locked_fraction", "free_fraction", "locked_sine_hz", "free_sine_hz", "relay_amplitude"):
        if not isinstance(out[k], (int, float)) or out[k] <= 0:
            raise ValueError(f"config `tune.{k}` must be a positive number, got {out[k]!r}.")
    for k in ("plants", "max_steps", "substeps", "rig_substeps"):
        if not isinstance(out[k], int) or out[k] < 1:
            raise ValueError(f"config `tune.{k}` must be a positive integer, got {out[k]!r}.")
    f = out["start_factors"]
    if not isinstance(f, (list, tuple)) or not f or not all(isinstance(x, (int, float)) and x > 0 for x in f):
        raise ValueError(f"config `tune.start_factors` must be a non-empty list of positive numbers, got {f!r}.")
    if out["current_limit"] is not None and (not isinstance(out["current_limit"], (int, float)) or out["current_limit"] <= 0):
        raise ValueError(f"config `tune.current_limit` must be a positive number in A, got {out['current_limit']!r}.")
    return out


def effects_from_dict(d: dict | None) -> Effects:
    """`Effects` from the plain-number description written in `truth.yaml` (`describe_effects`) or
    `extended_model.json` (`effects_to_dict`): periodic effects as orders/amplitudes/phases of
    `a_k·sin(k·θm + φ_k)`, scalar effects by their parameter names."""
    eff = Effects()
    for name, spec in (d or {}).items():
        if name in PERIODIC:
            for k, a, ph in zip(spec["orders"], spec["amplitudes"], spec["phases"]):
                if a:
                    eff = eff.with_periodic(name, int(k), float(a), float(ph))
        elif name in SCALAR or name in MODEL_FORM:
            fields = SCALAR[name] if name in SCALAR else MODEL_FORM[name]
            eff = eff.with_values(name, **{f: float(spec[f]) for f in fields if f in spec})
        else:
            raise ValueError(f"unknown effect {name!r} in an effects description; known: "
                             f"{list(PERIODIC) + list(SCALAR) + list(MODEL_FORM)}.")
    return eff


def _find_fit(dataset: Dataset, opts: dict, out: pathlib.Path) -> pathlib.Path | None:
    if opts["fit"] is not None:
        p = pathlib.Path(opts["fit"]).expanduser()
        if not p.is_file():
            raise ValueError(f"config `tune.fit`: {p} does not exist; give the path of a fit.json written by `hdjax.fit`.")
        return p
    for p in (out / "fit.json", pathlib.Path("results") / dataset.folder.name / "fit.json"):
        if p.is_file():
            return p
    return None


def _identified(dataset: Dataset, config: dict, opts: dict, out: pathlib.Path, log):
    """(nominal Parameters, effects, per-experiment lists, noise (σ_T, σ_ω), provenance text)."""
    from ._experiment import stack_experiments
    from ._fit import noise_levels

    dyn = dataset.dynamic_indices()
    path = _find_fit(dataset, opts, out)
    if path is not None:
        try:
            fit = json.loads(path.read_text())
            params = {k: float(fit["parameters"][k]["value"]) for k in PARAMETER_NAMES}
            per = {k: fit["parameters"][k].get("per_experiment") or [] for k in PARAMETER_NAMES}
        except (KeyError, TypeError, ValueError, json.JSONDecodeError) as e:
            raise ValueError(
                f"{path}: not a usable fit.json ({type(e).__name__}: {e}); it needs `parameters.<name>.value` for "
                f"{list(PARAMETER_NAMES)}. Re-run `python -m hdjax.fit` to rewrite it."
            ) from None
        nl = (fit.get("fit") or {}).get("noise_levels") or {}
        source = f"fit.json at {path}"
        effects = Effects()
        ext = path.parent / "extended_model.json"
        if ext.is_file():
            em = json.loads(ext.read_text())
            params = {k: float(em["parameters"][k]) for k in PARAMETER_NAMES}
            effects = effects_from_dict(em.get("effects"))
            source += f" with the extended model {ext} (effects: {sorted(effects.active) or 'none'})"
        log(f"      identified plant from {source}")
    else:
        from ._paper_id import identify_paper

        fo = dict(config.get("fit", {}) or {})
        log("      no fit.json found: running the paper's identification (hdjax._paper_id) on the records")
        paper = identify_paper([dataset.experiments[i] for i in dyn], dataset.drive, alpha=fo.get("alpha", 0.5), Tss2=fo.get("Tss2", 0.1))
        params = paper.parameters().to_dict()
        per = {k: list(paper.per_experiment.get(k) or []) for k in PARAMETER_NAMES}
        nl = {}
        effects = Effects()
        source = (
            "the paper's identification run by `tune` itself (no fit.json found; run `python -m hdjax.fit` first for the "
            "trajectory-error fit)"
        )
    if "torque" not in nl or "motor_velocity" not in nl:
        s = np.asarray(noise_levels(stack_experiments([dataset.experiments[i] for i in dyn])))
        nl = {"torque": float(s[0]), "motor_velocity": float(s[1])}
    bad = [k for k in ("K1", "Jeff") if not params[k] > 0]
    if bad:
        raise ValueError(f"identified {bad} not positive ({[params[k] for k in bad]}); the plant cannot be simulated. Check the fit.")
    return Parameters.from_dict(params), effects, per, (float(nl["torque"]), float(nl["motor_velocity"])), source


def draw_parameter_sets(nominal: Parameters, per_experiment: dict, n: int, *, seed: int = 0) -> Parameters:
    """`n` plant parameter sets (stacked leaves, leading axis `plant`), the first the nominal one.
    Each parameter is drawn independently from its per-experiment estimates (None/NaN skipped),
    recentred on the nominal value: multiplicatively ($v\\,e_j/\\bar e$) when the estimates share a
    sign, additively otherwise, so the spread is the fit's consistency and the centre the best
    estimate. Parameters with fewer than two estimates stay nominal."""
    rng = np.random.default_rng(seed)
    out = {}
    for k in PARAMETER_NAMES:
        v = float(getattr(nominal, k))
        e = np.array([x for x in (per_experiment.get(k) or []) if x is not None], dtype=float)
        e = e[np.isfinite(e)]
        col = np.full(n, v)
        if len(e) >= 2 and n > 1:
            pick = e[rng.integers(0, len(e), n - 1)]
            m = e.mean()
            if np.all(e > 0) or np.all(e < 0):
                col[1:] = v * pick / m
            else:
                col[1:] = v + pick - m
        out[k] = jnp.asarray(col)
    return Parameters(**out)


def _stack(trees):
    return jax.tree.map(lambda *x: jnp.stack(x), *trees)


def _references(dataset: Dataset, drive, opts: dict, ts: float):
    """Four references and their descriptions (name, amplitude, step window)."""
    T_locked = max((float(np.max(np.abs(np.asarray(dataset.experiments[i].torque)))) for i in dataset.indices("constrained")), default=0.0)
    free_idx = dataset.indices("free")
    T_free = max((float(np.max(np.abs(np.asarray(dataset.experiments[i].torque)))) for i in free_idx), default=0.0)
    w_free = max((float(np.max(np.abs(np.asarray(dataset.experiments[i].motor_velocity)))) for i in free_idx), default=0.0)
    if T_locked <= 0:
        raise ValueError(f"{dataset.folder}: `tune` needs constrained (locked-output) experiments to size the torque references.")
    if T_free <= 0 or w_free <= 0:
        raise ValueError(f"{dataset.folder}: `tune` needs free-motion experiments to size the free-output references.")
    dur = float(opts["duration"])
    A = opts["locked_fraction"] * T_locked
    B = opts["free_fraction"] * T_free
    N = float(drive.gear_ratio)
    J = float(drive.load_inertia)
    # free step: hold ±B for `width` each way; width keeps the output within 80 % of the recorded speed
    width = float(min(0.4 * dur, 0.8 * (w_free / N) * J / B))
    refs = [
        step_reference(A, duration=dur, sample_period=ts, start=0.02),
        sine_reference(A, float(opts["locked_sine_hz"]), duration=dur, sample_period=ts),
        doublet_reference(B, width, duration=dur, sample_period=ts, start=0.02),
        sine_reference(B, float(opts["free_sine_hz"]), duration=dur, sample_period=ts, free=True),
    ]
    info = [
        {"name": "locked_step", "amplitude": A, "step": (0.02, dur)},
        {"name": "locked_sine", "amplitude": A, "frequency_hz": float(opts["locked_sine_hz"])},
        {"name": "free_step", "amplitude": B, "step": (0.02, 0.02 + width), "width_s": width},
        {"name": "free_sine", "amplitude": B, "frequency_hz": float(opts["free_sine_hz"])},
    ]
    return refs, info


def _rig(dataset: Dataset, nominal: Parameters, effects: Effects, sigma):
    """(Plant, noise σ_T, σ_ω, description) of the validation bench."""
    truth = dataset.truth or {}
    if truth.get("parameters"):
        p = Parameters.from_dict({k: float(truth["parameters"][k]) for k in PARAMETER_NAMES})
        eff = effects_from_dict(truth.get("effects"))
        sens = truth.get("sensors", {})
        sT = float(sens.get("torque_noise", sigma[0]))
        sw = float(sens.get("tacho_noise", sigma[1]))
        desc = (
            f"virtual bench of {truth.get('drive_name', dataset.name)} (truth.yaml): true parameters, hidden effects "
            f"{sorted(eff.active) or 'none'}, strain-gauge noise {sT:g} N·m, tachometer noise {sw:g} rad/s"
        )
        return Plant(p, dataset.drive, eff), sT, sw, desc, True
    desc = (
        "no truth.yaml: validation on the identified model with the estimated sensor noise (not a real bench; run the "
        "tuned gains on the hardware)"
    )
    return Plant(nominal, dataset.drive, effects), sigma[0], sigma[1], desc, False


def run_tune(dataset: Dataset, config: dict, out: pathlib.Path, *, log=print) -> dict:
    """Run the whole tuning workflow on `dataset` and write outputs into `out`. Returns tune.json."""
    t_start = time.time()
    out = pathlib.Path(out)
    opts = _options(config)
    if dataset.drive is None or not dataset.dynamic_indices():
        raise ValueError(f"{dataset.folder}: `tune` needs constrained and free experiments with a `drive` block.")
    drive = dataset.drive
    notes = []

    log("[1/5] identified plant")
    nominal, effects, per, sigma, source = _identified(dataset, config, opts, out, log)
    exps = [dataset.experiments[i] for i in dataset.dynamic_indices()]
    ts = float(exps[0].time[1] - exps[0].time[0])
    ilim = float(opts["current_limit"] or max(float(np.max(np.abs(np.asarray(e.current)))) for e in exps))
    if opts["current_limit"] is None:
        notes.append(f"Current limit {ilim:.3g} A = largest |current| in the records (set `tune.current_limit` for your amplifier).")
    ctrl = TorqueController(friction=nominal, drive=drive, sample_period=ts, current_limit=ilim)
    refs, ref_info = _references(dataset, drive, opts, ts)
    R = _stack(refs)
    scales = jnp.asarray([r["amplitude"] for r in ref_info])
    n = refs[0].torque.shape[0]
    rng = np.random.default_rng(int(opts["seed"]))
    noise = (jnp.asarray(rng.normal(size=(4, n)) * sigma[0]), jnp.asarray(rng.normal(size=(4, n)) * sigma[1]))
    sm = Smoothing(velocity_scale=float(opts["velocity_scale"]), torsion_rate_scale=float(opts["torsion_rate_scale"]))
    nominal_plant = Plant(nominal, drive, effects)

    log("[2/5] baseline: relay test on the identified model, Ziegler–Nichols PI")
    level = 0.5 * ref_info[0]["amplitude"]
    d = float(opts["relay_amplitude"]) * ilim
    relay = jax.jit(lambda pl: relay_test(pl, level=level, amplitude=d, sample_period=ts, duration=1.0, smoothing=sm))(nominal_plant)
    baseline, relay_info = ziegler_nichols_pi(relay, level=level, amplitude=d)
    relay_info.update({"level_Nm": level, "relay_amplitude_A": d})
    log(f"      Ku = {relay_info['ultimate_gain']:.4g} A/(N·m), Tu = {relay_info['ultimate_period_s'] * 1e3:.3g} ms -> "
        f"kp = {float(baseline.kp):.4g}, ki = {float(baseline.ki):.4g}")  # fmt: skip

    log(f"[3/5] robust tuning: BFGS over {opts['plants']} plant sets x {len(refs)} references (vmap)")
    plants = Plant(draw_parameter_sets(nominal, per, int(opts["plants"]), seed=int(opts["seed"])), drive, effects)
    kw = dict(controller=ctrl, scales=scales, noise=noise, substeps=int(opts["substeps"]), smoothing=sm)
    costs = jax.jit(lambda g: batch_cost(g, plants, R, effort_weight=float(opts["effort_weight"]), **kw))
    cost_fn = lambda g: jnp.mean(batch_cost(g, plants, R, effort_weight=float(opts["effort_weight"]), **kw)[1])  # noqa: E731
    scaling = GainScaling(kp0=float(baseline.kp), ki0=float(baseline.ki), derivative_time=relay_info["ultimate_period_s"] / 8)
    t0 = time.time()
    # derivative-free first phase: the baseline PI with the model's feed-forward (kr = kf = kj = 1) and
    # its kp, ki scaled down on a grid. BFGS from the aggressive baseline alone stalls: there the
    # free-output loop is nearly chaotic and the gradient is huge and meaningless (see tune_gains).
    cost_jit = jax.jit(cost_fn)
    n_search = 1 + len(opts["start_factors"]) ** 2
    with task(log, "start search (baseline and kp, ki grid)", n_search, unit="candidates") as bar:
        search = [{"gains": baseline.to_dict(), "cost": float(cost_jit(baseline))}]
        bar.advance(1, info=f"baseline {search[0]['cost']:.5g}")
        for fp in opts["start_factors"]:
            for fi in opts["start_factors"]:
                g = TorqueGains(kp=fp * baseline.kp, ki=fi * baseline.ki, kr=1.0, kf=1.0, kj=1.0)
                search.append({"gains": g.to_dict(), "cost": float(cost_jit(g))})
                bar.advance(1, info=f"kp x{fp:g}, ki x{fi:g}: {search[-1]['cost']:.5g}")
    costs_found = [c["cost"] for c in search]
    best = int(np.nanargmin(np.where(np.isfinite(costs_found), costs_found, np.nan)))
    start = TorqueGains(**search[best]["gains"])
    log(f"      start search: baseline {search[0]['cost']:.5g}, best of {len(search)} candidates {search[best]['cost']:.5g} "
        f"(kp x{float(start.kp / baseline.kp):.3g}, ki x{float(start.ki / baseline.ki):.3g}, feed-forward {'on' if best else 'off'})")  # fmt: skip
    t_search = time.time() - t0
    with task(log, "BFGS on the robust tracking cost", int(opts["max_steps"]), unit="iterations") as bar:
        res = tune_gains(start, cost_fn, scaling=scaling, max_steps=int(opts["max_steps"]), log=log,
                         progress=lambda n, f: bar.advance(1, info=f"cost {f:.5g}"))
    t_opt = time.time() - t0
    tuned = res.gains
    if not res.converged:
        notes.append(f"BFGS stopped at its step budget ({res.steps} steps, `tune.max_steps`) before its tolerance.")
    model = {}
    for name, g in (("baseline", baseline), ("tuned", tuned)):
        track, tune_c = (np.asarray(x) for x in costs(g))
        per_plant = track.mean(axis=1)
        model[name] = {
            "tuning_cost": float(tune_c.mean()),
            "tracking_cost_mean": float(track.mean()),
            "tracking_cost_worst_plant": float(per_plant.max()),
            "tracking_cost_per_plant": per_plant.tolist(),
            "tracking_cost_per_reference": dict(zip(REFERENCE_NAMES, track.mean(axis=0).tolist())),
        }

    log("[4/5] validation on the bench")
    rig_plant, sT, sw, rig_desc, is_rig = _rig(dataset, nominal, effects, sigma)
    rng2 = np.random.default_rng(int(opts["seed"]) + 1000)
    rig_noise = (jnp.asarray(rng2.normal(size=(4, n)) * sT), jnp.asarray(rng2.normal(size=(4, n)) * sw))
    rig_sub = int(opts["rig_substeps"])

    def rig_runs(g):
        return jax.vmap(lambda r, a, b: closed_loop(g, rig_plant, r, controller=ctrl, noise=(a, b), substeps=rig_sub))(
            R, rig_noise[0], rig_noise[1]
        )

    rig_runs = jax.jit(rig_runs)
    model_runs = jax.jit(
        lambda g: jax.vmap(lambda r, a, b: closed_loop(g, nominal_plant, r, controller=ctrl, noise=(a, b), substeps=int(opts["substeps"]), smoothing=sm))(
            R, noise[0], noise[1]
        )
    )
    traj = {"baseline": rig_runs(baseline), "tuned": rig_runs(tuned)}
    sim = {"baseline": model_runs(baseline), "tuned": model_runs(tuned)}
    bench = {}
    for name in ("baseline", "tuned"):
        tr = traj[name]
        per_ref = {}
        for j, info in enumerate(ref_info):
            err = np.asarray(tr.reference[j] - tr.torque[j])
            row = {
                "tracking_cost": float(np.mean(err**2) / info["amplitude"] ** 2),
                "tracking_rms_Nm": float(np.sqrt(np.mean(err**2))),
                "measured_tracking_rms_Nm": float(np.sqrt(np.mean(np.asarray(tr.reference[j] - tr.measured_torque[j]) ** 2))),
                "current_rms_A": float(np.sqrt(np.mean(np.asarray(tr.current[j]) ** 2))),
                "current_peak_A": float(np.max(np.abs(np.asarray(tr.current[j])))),
            }
            if "step" in info:
                row.update(step_metrics(tr.time[j], tr.torque[j], amplitude=info["amplitude"], start=info["step"][0], end=info["step"][1]))
            per_ref[info["name"]] = row
        bench[name] = {
            "tracking_cost": float(np.mean([r["tracking_cost"] for r in per_ref.values()])),
            "references": per_ref,
            "refined_intervals": int(np.sum(np.asarray(tr.refined))),
        }
    b, t_ = bench["baseline"]["tracking_cost"], bench["tuned"]["tracking_cost"]
    reduction = 1.0 - t_ / b
    log(f"      bench tracking cost: baseline {b:.4g}, tuned {t_:.4g} ({100 * reduction:.1f} % lower)")

    log("[5/5] report and figures")
    figs = _figures(out, traj, sim, ref_info, search[0]["cost"], costs_found, res.history, ilim)
    total = time.time() - t_start
    result = {
        "schema": "hdjax.tune/1",
        "dataset": dataset.name,
        "identification": {"source": source, "parameters": nominal.to_dict(), "effects": sorted(effects.active)},
        "controller": {
            "law": "i = sat(kr*r/(N*Km) + kj*N*Jeff_hat*r/(J_L*Km) + kp*e + I - kd*dy_f + kf*Tf_hat(w)/Km) (J_L = load inertia, infinite when locked), e = r - y, back-calculation anti-windup",
            "sample_period_s": ts,
            "current_limit_A": ilim,
            "derivative_filter_s": ctrl.derivative_filter,
            "friction_feedforward_scale_rad_s": ctrl.friction_scale,
        },
        "gains": tuned.to_dict(),
        "gain_units": GAIN_UNITS,
        "baseline": {"rule": "relay test on the identified locked model + Ziegler-Nichols PI", "gains": baseline.to_dict(), "relay": relay_info},
        "references": [{k: v for k, v in r.items()} for r in ref_info],
        "tuning": {
            "optimiser": "grid over kp, ki (x start_factors) with the model feed-forward, then optimistix.BFGS (reverse-mode gradients through the closed loop)",
            "plants": int(opts["plants"]),
            "noise_sigma": {"torque": sigma[0], "motor_velocity": sigma[1]},
            "substeps": int(opts["substeps"]),
            "smoothing": {"velocity_scale": sm.velocity_scale, "torsion_rate_scale": sm.torsion_rate_scale},
            "effort_weight": float(opts["effort_weight"]),
            "steps": res.steps,
            "converged": res.converged,
            "start_search": search,
            "start_search_time_s": t_search,
            "cost_history": res.history,
            "time_s": t_opt,
        },
        "cost_before": model["baseline"]["tuning_cost"],
        "cost_after": model["tuned"]["tuning_cost"],
        "model": model,
        "bench": {"description": rig_desc, "is_virtual_rig": is_rig, "substeps": rig_sub, **bench, "relative_reduction": reduction},
        "notes": notes,
        "figures": figs,
        "timing_s": {"total": total, "optimisation": t_opt},
    }
    atomic_write_json(out / "tune.json", result)
    atomic_write_text(out / "report.md", _report(result))
    log(f"wrote {out / 'tune.json'} and {out / 'report.md'} in {total:.1f} s")
    return result


def _figures(out, traj, sim, ref_info, baseline_cost, search_costs, history, ilim) -> list[str]:
    names = []
    colors = {"baseline": "tab:orange", "tuned": "tab:blue"}
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for j, (ax, info) in enumerate(zip(axes.flat, ref_info)):
        t = np.asarray(traj["tuned"].time[j])
        ax.plot(t, np.asarray(traj["tuned"].reference[j]), "k--", lw=1.2, label="reference")
        for name in ("baseline", "tuned"):
            ax.plot(t, np.asarray(traj[name].measured_torque[j]), color=colors[name], lw=0.6, alpha=0.45, label=f"{name}: bench, measured")
            ax.plot(t, np.asarray(traj[name].torque[j]), color=colors[name], lw=1.3, label=f"{name}: bench, true")
        ax.plot(t, np.asarray(sim["tuned"].torque[j]), ":", color="tab:green", lw=1.3, label="tuned: model, simulated")
        ax.set_title(info["name"].replace("_", " "))
        ax.set_ylabel("output torque (N·m)")
    for ax in axes[1]:
        ax.set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Torque tracking on the bench: baseline (Ziegler–Nichols PI) vs tuned")
    fig.tight_layout()
    atomic_savefig(fig, out / "tracking.png", dpi=110)
    plt.close(fig)
    names.append("tracking.png")

    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for j, (ax, info) in enumerate(zip(axes.flat, ref_info)):
        t = np.asarray(traj["tuned"].time[j])
        for name in ("baseline", "tuned"):
            ax.plot(t, np.asarray(traj[name].current[j]), color=colors[name], lw=1.0, label=f"{name}: bench")
        ax.plot(t, np.asarray(sim["tuned"].current[j]), ":", color="tab:green", lw=1.2, label="tuned: model, simulated")
        ax.axhline(ilim, color="0.5", lw=0.8, ls="--", label="current limit")
        ax.axhline(-ilim, color="0.5", lw=0.8, ls="--")
        ax.set_title(info["name"].replace("_", " "))
        ax.set_ylabel("motor current (A)")
    for ax in axes[1]:
        ax.set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Control effort")
    fig.tight_layout()
    atomic_savefig(fig, out / "control_effort.png", dpi=110)
    plt.close(fig)
    names.append("control_effort.png")

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.axhline(baseline_cost, color="tab:orange", ls="--", label="baseline (Ziegler–Nichols PI)")
    ns = len(search_costs)
    ax.semilogy(np.arange(-ns, 0), search_costs, "s", color="0.5", ms=4, label="start search (grid, model)")
    ax.semilogy(np.arange(len(history)), history, "o-", label="BFGS: robust tuning cost (mean over plant sets)")
    ax.set_xlabel("evaluation (<0: start search) / accepted BFGS iterate (-)")
    ax.set_ylabel("tuning cost (-)")
    ax.set_title("Cost over iterations (tuning model)")
    ax.legend()
    fig.tight_layout()
    atomic_savefig(fig, out / "cost_history.png", dpi=110)
    plt.close(fig)
    names.append("cost_history.png")
    return names


def _fmt(v):
    if v is None:
        return "—"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _report(r: dict) -> str:
    L = [f"# Torque-controller tuning: {r['dataset']}", ""]
    L.append(f"Identified plant: {r['identification']['source']}.")
    c = r["controller"]
    L.append(
        f"Controller: {c['law']}; sample period {c['sample_period_s'] * 1e3:g} ms (zero-order hold), current limit "
        f"{c['current_limit_A']:.3g} A."
    )
    L += ["", "## Gains", "", "| gain | unit | baseline (relay + Ziegler–Nichols PI) | tuned |", "|---|---|---|---|"]
    for k in GAIN_NAMES:
        L.append(f"| {k} | {r['gain_units'][k]} | {_fmt(r['baseline']['gains'][k])} | {_fmt(r['gains'][k])} |")
    rl = r["baseline"]["relay"]
    L += [
        "",
        f"Relay test: ultimate gain {rl['ultimate_gain']:.4g} A/(N·m), ultimate period {rl['ultimate_period_s'] * 1e3:.3g} ms.",
        "",
        "## Robust tuning (model)",
        "",
        f"Start search over {len(r['tuning']['start_search'])} candidate gain sets (baseline, and the baseline kp, ki scaled "
        f"with the model feed-forward kr = kf = kj = 1), then BFGS from the best, {r['tuning']['steps']} steps (converged: {r['tuning']['converged']}), {r['tuning']['time_s']:.1f} s; cost averaged "
        f"over {r['tuning']['plants']} plant parameter sets drawn from the per-experiment estimates and 4 references.",
        "",
        "| | baseline | tuned |",
        "|---|---|---|",
        f"| tuning cost (mean) | {_fmt(r['model']['baseline']['tuning_cost'])} | {_fmt(r['model']['tuned']['tuning_cost'])} |",
        f"| tracking cost, mean over plants | {_fmt(r['model']['baseline']['tracking_cost_mean'])} | {_fmt(r['model']['tuned']['tracking_cost_mean'])} |",
        f"| tracking cost, worst plant | {_fmt(r['model']['baseline']['tracking_cost_worst_plant'])} | {_fmt(r['model']['tuned']['tracking_cost_worst_plant'])} |",
        "",
        "## Validation on the bench",
        "",
        f"{r['bench']['description']}.",
        "",
        f"Tracking cost (mean over references of mean((r − T)²)/amplitude²): baseline {_fmt(r['bench']['baseline']['tracking_cost'])}, "
        f"tuned {_fmt(r['bench']['tuned']['tracking_cost'])}: **{100 * r['bench']['relative_reduction']:.1f} % lower**.",
        "",
        "| reference | controller | cost | RMS (N·m) | overshoot (%) | settling (s) | peak current (A) |",
        "|---|---|---|---|---|---|---|",
    ]
    for ref in REFERENCE_NAMES:
        for name in ("baseline", "tuned"):
            row = r["bench"][name]["references"][ref]
            L.append(
                f"| {ref} | {name} | {_fmt(row['tracking_cost'])} | {_fmt(row['tracking_rms_Nm'])} | {_fmt(row.get('overshoot_percent'))} | "
                f"{_fmt(row.get('settling_time_s'))} | {_fmt(row['current_peak_A'])} |"
            )
    L += ["", "Settling: into ±5 % of the step and staying until the step ends (— : never).", ""]
    if r["notes"]:
        L += ["## Notes", ""] + [f"- {n}" for n in r["notes"]] + [""]
    L += ["## Figures", ""] + [f"![{f}]({f})" for f in r["figures"]] + [""]
    L.append(f"Total time {r['timing_s']['total']:.1f} s.")
    return "\n".join(L) + "\n"
