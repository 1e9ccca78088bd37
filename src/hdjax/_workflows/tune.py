"""The `tune` workflow: identified plant -> feasible references -> baselines (relay/Ziegler–Nichols
PI, model-based PI) -> robust gradient tuning -> validation -> tune.json, report.md and figures.
The command `hdjax tune` (`python -m hdjax.tune`) is a thin wrapper around `run_tune`.

Steps (all SI units):

1. Identified plant: `fit.json` (from `tune.fit` in the config, else `DIR/fit.json`, else
   `results/<dataset folder name>/fit.json`); with an `extended_model.json` beside it (from
   `diagnose`) its base parameters and effects are used. Without a fit.json the paper's
   identification (`hdjax._fit.paper.identify_paper`, seconds) is run and the report says so.
2. Hardware: sensor sample period = the records' time step; current limit = `tune.current_limit`
   or the largest |current| in the records; sensor noise = the fit's noise levels.
3. References (0.5 s each, at the sensor rate): locked step and sine, free step (a doublet that
   brings the load back to rest) and free sine, requested as a fraction of the largest torque seen
   in the locked / free records. With `tune.scale_references` (default) each amplitude is scaled
   down until the identified model's feed-forward current stays within `tune.headroom` of the
   current limit (`hdjax._control.loopshape.feasible_scale`), and sine frequencies are capped at a
   twentieth of the sample rate; the scaling is reported. Without it, the requested references
   are used and the validation splits the tracking cost into the samples at the current limit
   (saturation) and the others (tracking).
4. Baselines: (a) Åström–Hägglund relay test on the identified locked model and the
   Ziegler–Nichols PI (no feed-forward); (b) a model-based PI: MIGO (largest integral gain with
   sensitivity peak Ms ≤ `tune.model_pi_ms`) on the linearised sampled locked and free plants
   (`hdjax._control.loopshape`), with the model's reference, inertia and friction feed-forward.
5. Robust tuning of kp, ki, kd, the feed-forward weights and a free-output gain schedule (kpf,
   kif multiply kp, ki when the output is free), and of where the friction feed-forward is
   evaluated: at the measured motor velocity (kf, as the model-based PI baseline) or at the
   velocity the reference asks for (kfr; `hdjax._control.closed_loop.reference_motor_velocity`). Plant
   parameter sets drawn from the per-experiment estimates, with their friction scaled by
   1 ± `tune.friction_uncertainty` (the feed-forward keeps the identified friction); cost = tracking
   cost averaged over plants, references and `tune.noise_realisations` noise draws (`vmap`) + `tune.margin_weight`·Σ max(0, Ms − `tune.ms_max`)²
   over the linearised locked and free loops of every plant set. A start search over the baselines
   and scaled model-based PIs (with either friction feed-forward), then BFGS from the best
   `tune.starts` candidates (multi-start).
6. Validation, never on the model that was tuned. When the dataset's `truth.yaml` was written by
   the independent bench `hdjax._testbench.independent`, the bench is rebuilt from it and the three controllers
   run on its own physics (stick–slip, current loop, sensor dynamics, hidden effects, its own
   noise). Otherwise (a user's data) they run on the identified model with the estimated noise,
   and the report and figures say "identified model". Every cost is the mean over
   `tune.validation_runs` runs with independent noise: on the bench one run's cost of the same
   controller varied by up to 2x (stick–slip at the start of a free reference).
"""

import math
import pathlib
import time
from types import SimpleNamespace
from typing import Any, Literal, overload

import jax
import jax.numpy as jnp
import numpy as np

from .._control import loopshape as ls
from .._control.closed_loop import (
    GAIN_NAMES,
    GAIN_UNITS,
    GainScaling,
    Plant,
    TorqueController,
    TorqueGains,
    batch_cost,
    closed_loop,
    doublet_reference,
    numpy_torque_law,
    relay_test,
    sine_reference,
    step_metrics,
    step_reference,
    tune_gains,
    ziegler_nichols_pi,
)
from .._data.load import Dataset
from .._model.effects import Effects
from .._model.paper import EQ9_COEFFICIENTS, PARAMETER_NAMES, Parameters, Smoothing
from .artifacts import read_extended_model, read_fit_json
from .config import is_number, section_options, unit_share
from .io import write_results
from .progress import task

DEFAULTS = {
    "fit": None,  # path to a fit.json (relative to the config file's folder is not resolved: give it absolute or cwd-relative)
    "current_limit": None,  # A; default: largest |current| in the records
    "duration": 0.5,  # s per reference
    "locked_fraction": 0.5,  # locked reference amplitude / largest locked |torque| recorded (requested)
    "free_fraction": 0.5,  # free reference amplitude / largest free |torque| recorded (requested)
    "locked_sine_hz": 3.0,
    "free_sine_hz": 2.0,
    "scale_references": True,  # scale the requested references to what the model can follow under the limit
    "headroom": 0.7,  # feed-forward current of a scaled reference / current limit
    "plants": 6,  # plant parameter sets drawn for the robust cost
    "noise_realisations": 2,  # measurement-noise realisations per reference in the tuning cost (1: the start search and BFGS chased one noise draw)
    "friction_uncertainty": 0.2,  # friction of plant sets 2.. scaled by 1 ± this (the feed-forward keeps the fit's)
    "seed": 0,
    "max_steps": 8,  # BFGS steps per start
    "max_first_step": 0.05,  # cap of the (start-cost-normalised) gradient norm: BFGS's first trial step in log-gains
    "starts": 2,  # BFGS runs from the best candidates of the start search
    "start_factors": [0.5, 1.0, 2.0],  # kp, ki multiples of the model-based PI tried (grid) before BFGS
    "ms_max": 1.7,  # sensitivity peak above which the margin term acts
    "margin_weight": 0.2,  # weight of the squared Ms excess in the tuning cost
    "model_pi_ms": 1.4,  # Ms bound of the model-based (MIGO) PI baseline
    "solver": "velocity_implicit",  # plant of the tuning model and of a validation on it: the fixed-step exact plant, or "rodas3" (smoothed)
    "substeps": 2,  # plant steps per sample in the tuning model
    # keep the fit's breakaway torques in the tuning model (velocity_implicit only); on the independent bench's ten
    # drives (2026-12-06) with them: the worst drive's bench cost -27 %, the median +3 % (HD1-like better, HD2-like worse)
    "breakaway_friction": True,
    "velocity_scale": 0.03,  # rad/s, friction sign() smoothing of the tuning model (rodas3 only)
    "torsion_rate_scale": 1e-3,  # rad/s, |rate|^alpha smoothing of the tuning model (rodas3 only)
    "effort_weight": 0.01,
    "relay_amplitude": 0.25,  # relay amplitude / current limit
    "rig_substeps": 16,  # plant steps per sample when validating on the identified model (user data)
    "validation_runs": 5,  # validation runs with independent noise, averaged (one run's cost varies by up to ~2x)
}
REFERENCE_NAMES = ("locked_step", "locked_sine", "free_step", "free_sine")
CONTROLLERS = ("relay_zn", "model_pi", "tuned")
LABELS = {"relay_zn": "relay + Ziegler–Nichols PI", "model_pi": "model-based PI (MIGO) + feed-forward", "tuned": "tuned"}


def _options(config: dict) -> dict:
    out = section_options(config, "tune", DEFAULTS)
    for k in ("duration", "locked_fraction", "free_fraction", "locked_sine_hz", "free_sine_hz", "relay_amplitude",
              "headroom", "ms_max", "model_pi_ms", "max_first_step"):  # fmt: skip
        if not is_number(out[k]) or out[k] <= 0:
            raise ValueError(f"config `tune.{k}` must be a positive number, got {out[k]!r}.")
    out["friction_uncertainty"] = unit_share(out["friction_uncertainty"], "tune.friction_uncertainty")
    if not is_number(out["margin_weight"]) or out["margin_weight"] < 0:
        raise ValueError(f"config `tune.margin_weight` must be a number >= 0, got {out['margin_weight']!r}.")
    for k in ("scale_references", "breakaway_friction"):
        if not isinstance(out[k], bool):
            raise ValueError(f"config `tune.{k}` must be true or false, got {out[k]!r}.")
    for k in ("plants", "max_steps", "substeps", "rig_substeps", "starts", "validation_runs", "noise_realisations"):
        if not isinstance(out[k], int) or out[k] < 1:
            raise ValueError(f"config `tune.{k}` must be a positive integer, got {out[k]!r}.")
    if out["solver"] not in ("velocity_implicit", "rodas3"):
        raise ValueError(f"config `tune.solver` must be one of ['velocity_implicit', 'rodas3'], got {out['solver']!r}.")
    f = out["start_factors"]
    if not isinstance(f, (list, tuple)) or not f or not all(is_number(x) and x > 0 for x in f):
        raise ValueError(f"config `tune.start_factors` must be a non-empty list of positive numbers, got {f!r}.")
    if out["current_limit"] is not None and (not is_number(out["current_limit"]) or out["current_limit"] <= 0):
        raise ValueError(f"config `tune.current_limit` must be a positive number in A, got {out['current_limit']!r}.")
    return out


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
    from .._data.experiment import stack_experiments
    from .._fit.least_squares import noise_levels

    dyn = dataset.dynamic_indices()
    path = _find_fit(dataset, opts, out)
    if path is not None:
        fit = read_fit_json(path, setting="config `tune.fit` / `--fit`")
        params = fit.parameters.to_dict()
        per = {k: v or [] for k, v in fit.per_experiment.items()}
        nl = fit.noise_levels
        source = f"fit.json at {path}"
        effects = fit.effects  # the terms fitted with the parameters (`_tuning_effects` keeps what the loop models)
        ext = path.parent / "extended_model.json"
        if ext.is_file():
            p_ext, effects = read_extended_model(ext)
            params = p_ext.to_dict()
            source += f" with the extended model {ext} (effects: {sorted(effects.active) or 'none'})"
        log(f"      identified plant from {source}")
    else:
        from .._fit.paper import identify_paper
        from .fit import _options as fit_options

        fo = fit_options(config)  # the `fit:` section, validated, with the fit command's defaults
        log("      no fit.json found: running the paper's identification (hdjax._fit.paper) on the records")
        assert dataset.drive is not None  # run_tune checked it
        paper = identify_paper([dataset.experiments[i] for i in dyn], dataset.drive, alpha=fo["alpha"], Tss2=fo["Tss2"],
                               cutoff_hz=fo["cutoff_hz"])
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


@overload
def draw_parameter_sets(nominal: Parameters, per_experiment: dict, n: int, *, seed: int = ...,
                        friction_uncertainty: float = ...,
                        with_friction_factors: Literal[False] = ...) -> Parameters: ...
@overload
def draw_parameter_sets(nominal: Parameters, per_experiment: dict, n: int, *, seed: int = ...,
                        friction_uncertainty: float = ...,
                        with_friction_factors: Literal[True]) -> tuple[Parameters, np.ndarray]: ...
def draw_parameter_sets(nominal: Parameters, per_experiment: dict, n: int, *, seed: int = 0,
                        friction_uncertainty: float = 0.0,
                        with_friction_factors: bool = False) -> Parameters | tuple[Parameters, np.ndarray]:
    """`n` plant parameter sets (stacked leaves, leading axis `plant`), the first the nominal one.
    Each parameter is drawn independently from its per-experiment estimates (None/NaN skipped,
    and outliers: farther from their median than `OUTLIER_MADS` scaled median absolute
    deviations), recentred on the nominal value: multiplicatively ($v\\,e_j/\\tilde e$, $\\tilde e$
    their median) when the estimates share a sign, additively otherwise, so the spread is the
    fit's consistency and the centre the best estimate. Parameters with fewer than two estimates
    stay nominal. (One per-experiment fit that runs off along a flat direction must not set the
    plant sets: on the shipped HD2 campaign one record's Stribeck amplitude Tssp1 came out at
    −1.2e5 N·m, where the breakaway torque makes the cost flat; recentred on the mean it gave every
    drawn plant Tssp1 ≈ +8 000 N·m and a tracking cost 300× the nominal plant's.)

    `friction_uncertainty` $u$ (-): plant $j \\ge 1$ also has all its eq. 9 friction terms
    (`hdjax._model.paper.EQ9_COEFFICIENTS`) multiplied by a common factor $1 + u\\,z_j$, the $z_j$ spread evenly over
    $[-1, 1]$ (so the set holds the friction $u$ above and below the identified one). The
    controller's friction feed-forward keeps the identified values: a controller that leans on
    it is charged for friction that drifts with temperature and wear, or that the fit got wrong.

    Returns the stacked `Parameters`; with `with_friction_factors` also the factors, shape
    (plant,), 1 for the nominal plant (`_plant_effects` scales the breakaway torques by them)."""
    rng = np.random.default_rng(seed)
    out = {}
    for k in PARAMETER_NAMES:
        v = float(getattr(nominal, k))
        e = np.array([x for x in (per_experiment.get(k) or []) if x is not None], dtype=float)
        e = _without_outliers(e[np.isfinite(e)])
        col = np.full(n, v)
        if len(e) >= 2 and n > 1:
            pick = e[rng.integers(0, len(e), n - 1)]
            m = float(np.median(e))
            if np.all(e > 0) or np.all(e < 0):
                col[1:] = v * pick / m
            else:
                col[1:] = v + pick - m
        out[k] = col
    factors = np.ones(n)
    if friction_uncertainty > 0 and n > 1:
        z = np.linspace(-1.0, 1.0, n - 1) if n > 2 else np.ones(1)
        z = rng.permutation(z)
        factors[1:] = 1.0 + friction_uncertainty * z
        for k in EQ9_COEFFICIENTS:
            out[k][1:] *= factors[1:]
    params = Parameters(**{k: jnp.asarray(v) for k, v in out.items()})
    return (params, factors) if with_friction_factors else params


#: `draw_parameter_sets` leaves out per-experiment estimates farther than this many scaled median
#: absolute deviations (1.4826 MAD, σ for normal data) from their median.
OUTLIER_MADS = 5.0


def _without_outliers(e: np.ndarray) -> np.ndarray:
    """`e` less the values farther than `OUTLIER_MADS` scaled MADs from its median (all of `e`
    when the MAD is 0 or fewer than three values)."""
    if len(e) < 3:
        return e
    med = np.median(e)
    mad = 1.4826 * np.median(np.abs(e - med))
    return e if mad == 0 else e[np.abs(e - med) <= OUTLIER_MADS * mad]


def _plant_effects(effects: Effects, factors: np.ndarray) -> tuple[Effects, bool]:
    """The tuning model's effects per plant set: with `breakaway_friction` on, its torques scaled
    by each plant's friction factor (`draw_parameter_sets`), stacked along a leading `plant` axis
    (True); otherwise `effects`, shared by every plant (False). A breakaway torque is friction: a
    plant set whose friction drifts by a factor breaks away at that factor too."""
    if "breakaway_friction" not in effects.active:
        return effects, False
    b = effects.breakaway_friction
    each = [effects.with_values("breakaway_friction", breakaway_p=float(b.breakaway_p) * f,
                                breakaway_n=float(b.breakaway_n) * f) for f in factors]
    return jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v) for v in x]), *each), True


def _stack(trees):
    return jax.tree.map(lambda *x: jnp.stack(x), *trees)


def _references(dataset: Dataset, drive, opts: dict, ts: float, nominal: Parameters, ilim: float):
    """Four references, their descriptions (name, amplitude, step window, scaling) and whether any was
    scaled. Requested amplitudes: fractions of the largest recorded torques; with
    `scale_references`, each is scaled to the identified model's feasibility (module doc, step 3)."""
    T_locked = max((float(np.max(np.abs(np.asarray(dataset.experiments[i].torque)))) for i in dataset.indices("constrained")), default=0.0)
    free_idx = dataset.indices("free")
    T_free = max((float(np.max(np.abs(np.asarray(dataset.experiments[i].torque)))) for i in free_idx), default=0.0)
    w_free = max((float(np.max(np.abs(np.asarray(dataset.experiments[i].motor_velocity)))) for i in free_idx), default=0.0)
    if T_locked <= 0:
        raise ValueError(f"{dataset.folder}: `tune` needs constrained (locked-output) experiments to size the torque references.")
    if T_free <= 0 or w_free <= 0:
        raise ValueError(f"{dataset.folder}: `tune` needs free-motion experiments to size the free-output references.")
    dur = float(opts["duration"])
    N = float(drive.gear_ratio)
    J = float(drive.load_inertia)
    scale_on = bool(opts["scale_references"])
    f_cap = 0.05 / ts  # a twentieth of the sample rate
    # step edges: half the period of the identified locked resonance (the motor inertia on the
    # flexspline spring), which the torque cannot outrun without a current spike
    f_res = math.sqrt(float(nominal.K1) / (N**2 * float(nominal.Jeff))) / (2 * math.pi)
    rise = 0.5 / f_res if scale_on else 0.0

    def build(name, amp, free, hz=None):
        if name == "locked_step":
            return step_reference(amp, duration=dur, sample_period=ts, start=0.02, rise=rise), {"rise_s": rise}
        if name == "free_step":
            # hold ±amp for `width` each way; width keeps the output within 80 % of the recorded speed
            width = float(min(0.4 * dur, 0.8 * (w_free / N) * J / amp))
            width = max(width, rise)
            ref = doublet_reference(amp, width, duration=dur, sample_period=ts, start=0.02, rise=rise)
            return ref, {"width_s": width, "rise_s": rise}
        return sine_reference(amp, hz, duration=dur, sample_period=ts, free=free), {}  # pyright: ignore[reportArgumentType]  sines have a frequency

    refs, info = [], []
    for name, amp0, free, hz0 in (
        ("locked_step", opts["locked_fraction"] * T_locked, False, None),
        ("locked_sine", opts["locked_fraction"] * T_locked, False, float(opts["locked_sine_hz"])),
        ("free_step", opts["free_fraction"] * T_free, True, None),
        ("free_sine", opts["free_fraction"] * T_free, True, float(opts["free_sine_hz"])),
    ):
        hz = hz0 if hz0 is None or not scale_on else min(hz0, f_cap)
        ref, extra = build(name, amp0, free, hz)
        s, need = ls.feasible_scale(np.asarray(ref.torque), free=free, p=nominal, drive=drive, ts=ts, current_limit=ilim,
                                    headroom=float(opts["headroom"]))  # fmt: skip
        amp = amp0 * s if scale_on else amp0
        if scale_on and s < 1.0:
            ref, extra = build(name, amp, free, hz)
        row = {"name": name, "amplitude": float(amp), "requested_amplitude": float(amp0), "scale": float(s) if scale_on else 1.0,
               "feasible_scale": float(s), "feedforward_peak_over_limit": float(need), **extra}  # fmt: skip
        if hz0 is not None:
            row.update(frequency_hz=float(hz), requested_frequency_hz=float(hz0))  # pyright: ignore[reportArgumentType]  hz is None only with hz0
        if name == "locked_step":
            row["step"] = (0.02 + rise, dur)
        if name == "free_step":
            if extra["width_s"] - rise >= 10 * ts:
                row["step"] = (0.02 + rise, 0.02 + extra["width_s"])
            else:  # the speed bound leaves no plateau between the edges: no overshoot or settling to measure
                row["note"] = ("no plateau between the doublet's edges (the recorded speed bounds the width to the "
                               "edge time): no step metrics")
        refs.append(ref)
        info.append(row)
    return refs, info


def _linear_loops(params_list, drive, ref_info, ts, derivative_filter, sensor_lag: float = 0.0):
    """Sampled linearised locked and free plants of every parameter set, measured through the
    torque sensor's lag `sensor_lag` (s; `ls.plant_response`): (z, P (loops, freq), state spaces,
    labels). Torsion-rate amplitude of the describing function: reference amplitude × locked
    resonance / K1."""
    z = None
    Ps, sss, labels = [], [], []
    A_locked = ref_info[0]["amplitude"]
    A_free = ref_info[2]["amplitude"]
    for j, p in enumerate(params_list):
        wr = math.sqrt(float(p.K1) / (float(drive.gear_ratio) ** 2 * float(p.Jeff)))
        for free, A in ((False, A_locked), (True, A_free)):
            R = max(A * wr / float(p.K1), 1e-6)
            z, P, ss = ls.plant_response(p, drive, free=free, ts=ts, rate_amplitude=R, sensor_lag=sensor_lag)
            Ps.append(P)
            sss.append(ss)
            labels.append(f"plant {j} {'free' if free else 'locked'}")
    return z, np.stack(Ps), sss, labels


def _margin_report(g: TorqueGains, z, P, sss, labels, ts, df) -> dict:
    rows = []
    for Pj, ss, lab in zip(P, sss, labels):
        free = lab.endswith("free")
        kp = float(g.kp) * (float(g.kpf) if free else 1.0)
        ki = float(g.ki) * (float(g.kif) if free else 1.0)
        m = ls.margins(kp, ki, float(g.kd), z, Pj, ts=ts, derivative_filter=df)
        m["stable"] = bool(ls.closed_loop_radius(kp, ki, float(g.kd), ss, ts=ts, derivative_filter=df) < 1.0)
        m["loop"] = lab
        rows.append(m)
    nominal = [r for r in rows if r["loop"].startswith("plant 0")]
    return {"Ms_max": max(r["Ms"] for r in rows), "all_stable": all(r["stable"] for r in rows), "nominal": nominal}


def _split_cost(err, current, ilim, amplitude):
    """(total, while saturated, unsaturated) tracking cost and saturated fraction of one run: the
    cost mean((r − T)²)/A² split additively over samples with |current| ≥ 99 % of the limit."""
    sat = np.abs(current) >= 0.99 * ilim
    e2 = err**2 / amplitude**2
    n = len(err)
    return float(e2.sum() / n), float(e2[sat].sum() / n), float(e2[~sat].sum() / n), float(sat.mean())


def _mean_or_none(values):
    """Mean over the validation runs; None when any run has None (a step metric of a run that never
    settles), so that one run's failure is not averaged away."""
    return None if any(x is None for x in values) else float(np.mean(values))


def _bench_from_truth(dataset: Dataset):
    truth = dataset.truth or {}
    if not str(truth.get("generator", "")).startswith("hdjax._bench"):
        return None
    from .._testbench.independent import Bench

    return Bench.from_truth(truth)


def _plant_solver(opts: dict, effects: Effects, notes: list, log) -> dict:
    """`opts` with the tuning model's plant that can carry `effects`: the exact plant does not model
    `presliding_friction` (a Dahl state; its exact sticking is that law's rigid limit), so an
    extended model with it is tuned on the smoothed `rodas3` plant, and a note says so."""
    if opts["solver"] == "velocity_implicit" and "presliding_friction" in effects.active:
        msg = ("the extended model holds presliding_friction, which the exact velocity_implicit plant does not model: "
               "tuned and validated on the smoothed rodas3 plant instead (`tune.solver`)")
        notes.append(msg)
        log(f"  note: {msg}")
        return {**opts, "solver": "rodas3"}
    return opts


def _tuning_effects(effects: Effects, solver: str, notes: list, log, *, breakaway: bool = True) -> Effects:
    """The identified `effects` less what the closed-loop plant does not model, each left out with a
    note: `breakaway_friction` on the smoothed `rodas3` plant (breakaway needs the exact plant's
    set-valued sticking) or when `breakaway` is False (`tune.breakaway_friction: false`). The
    fit's sensor lags (`sensor_bandwidth`) stay: the loop's controller reads the torque and
    velocity through them (`hdjax._control.closed_loop`), and the linearised loops through the
    torque lag."""
    drop = {}
    if solver != "velocity_implicit":
        drop["breakaway_friction"] = (f"the fitted breakaway torques are left out: the {solver} plant has no exact "
                                      f"sticking (`tune.solver: velocity_implicit` keeps them)")
    elif not breakaway:
        drop["breakaway_friction"] = "the fitted breakaway torques are left out (`tune.breakaway_friction: false`)"
    for name, why in drop.items():
        if name in effects.active:
            effects = effects.without(name)
            notes.append(why)
            log(f"  note: {why}")
    return effects


def run_tune(dataset: Dataset, config: dict, out: pathlib.Path, *, log=print) -> dict:
    """Run the whole tuning workflow on `dataset` and write outputs into `out`. Returns tune.json."""
    t_start = time.time()
    out = pathlib.Path(out)
    opts = _options(config)
    drive, exps, _, _ = dataset.dynamic_part("tune")
    notes = []
    timing = {}

    log("[1/6] identified plant")
    nominal, effects, per, sigma, source = _identified(dataset, config, opts, out, log)
    opts = _plant_solver(opts, effects, notes, log)
    effects = _tuning_effects(effects, opts["solver"], notes, log, breakaway=opts["breakaway_friction"])
    ts, ilim, ctrl = _controller(exps, nominal, drive, opts, notes)
    df = ctrl.derivative_filter

    log("[2/6] references the actuator can follow")
    refs, ref_info = _feasible_references(dataset, drive, opts, ts, nominal, ilim, notes, log)
    R = _stack(refs)
    scales = jnp.asarray([r["amplitude"] for r in ref_info])
    n = refs[0].torque.shape[0]
    K = int(opts["noise_realisations"])
    noise_all, noise = _measurement_noise(opts, K, n, sigma)
    R_cost = _stack(refs * K)
    sm = Smoothing(velocity_scale=float(opts["velocity_scale"]), torsion_rate_scale=float(opts["torsion_rate_scale"]))
    nominal_plant = Plant(nominal, drive, effects)
    torque_lag = float(effects.sensor_bandwidth.torque_lag) if "sensor_bandwidth" in effects.active else 0.0
    plant_sets, factors, (z, Pall, sss, loop_labels) = _plant_sets(nominal, per, drive, ref_info, ts, df, opts,
                                                                   sensor_lag=torque_lag)

    def margins(g):  # the linearised loops' stability and Ms for gains `g`
        return _margin_report(g, z, Pall, sss, loop_labels, ts, df)

    log("[3/6] baselines: relay + Ziegler–Nichols PI; model-based PI (MIGO on the linearised plants) + feed-forward")
    t0 = time.time()
    zn, relay_info = _relay_zn(nominal_plant, ref_info, opts, ilim, ts, sm, notes, log)
    model_pi, kp_m, ki_m, migo = _model_pi(drive, z, Pall, sss, ts, df, opts, log)
    timing["baselines"] = time.time() - t0

    log(f"[4/6] robust tuning: {opts['plants']} plant sets x {len(refs)} references (vmap) + Ms terms on {len(loop_labels)} linearised loops")
    plant_effects, per_plant = _plant_effects(effects, factors)
    plants = Plant(plant_sets, drive, plant_effects)
    kw: dict[str, Any] = dict(controller=ctrl, scales=jnp.tile(scales, K), noise=noise_all, substeps=int(opts["substeps"]), smoothing=sm,
                          solver=opts["solver"], effects_per_plant=per_plant)
    parts_jit, cost_fn, total = _objective(plants, R_cost, kw, K, len(refs), z, Pall, loop_labels, ts, df, opts)
    t0 = time.time()
    search = _start_search(_start_candidates(zn, model_pi, kp_m, ki_m, opts), total, margins, log)
    timing["start_search"] = time.time() - t0
    scaling = GainScaling(kp0=float(model_pi.kp), ki0=float(model_pi.ki), derivative_time=4.0 * df)
    res, picked, t_bfgs = _bfgs(search, cost_fn, scaling, opts, notes, log)
    timing["bfgs"] = t_bfgs
    tuned = res.gains
    start_best = search[picked[res.best_run]]
    gains = {"relay_zn": zn, "model_pi": model_pi, "tuned": tuned}
    model = {name: _model_costs(parts_jit(g), margins(g)) for name, g in gains.items()}

    bench = _bench_from_truth(dataset)
    where = "the independent bench" if bench is not None else "the identified model"
    log(f"[5/6] validation on {where}")
    t0 = time.time()
    trajs, val_desc = _validation_runs(bench, nominal_plant, gains, refs, R, ctrl, sigma, n, opts)
    timing["validation"] = time.time() - t0
    sim = _simulate_tuned(tuned, nominal_plant, R, noise, ctrl, sm, opts)
    val = {name: _validation_costs([tr_all[name] for tr_all, _ in trajs], ref_info, ilim) for name in CONTROLLERS}
    improvement = _improvement(val, where, log)

    log("[6/6] report and figures")
    kind = "bench" if bench is not None else "identified model"
    from .plots import tune_figures  # matplotlib loads only when figures are drawn
    figs = tune_figures(out, trajs[0][0], sim, ref_info, search, res, ilim, kind)
    total_t = time.time() - t_start
    result = {
        "schema": "hdjax.tune/2",
        "dataset": dataset.name,
        "identification": {"source": source, "parameters": nominal.to_dict(), "effects": sorted(effects.active)},
        "controller": _controller_section(ctrl, ts, ilim),
        "gains": tuned.to_dict(),
        "gain_units": GAIN_UNITS,
        "baselines": _baselines_section(zn, relay_info, model_pi, migo),
        "references": ref_info,
        "references_scaled": bool(opts["scale_references"]),
        "tuning": _tuning_section(opts, K, sigma, sm, search, start_best, res, picked),
        "model": model,
        "validation": {"on": kind, "description": val_desc, **val, "improvement_over": improvement},
        "notes": notes,
        "figures": figs,
        "timing_s": {"total": total_t, **timing},
    }
    write_results(out, "tune.json", result, _report(result), log=log)
    return result


def _controller(exps, nominal: Parameters, drive, opts: dict, notes: list[str]):
    """The sample period (s) of the records, the current limit (A; the largest |current| recorded
    unless `tune.current_limit` sets it) and the torque controller on the identified friction."""
    ts = float(exps[0].time[1] - exps[0].time[0])
    ilim = float(opts["current_limit"] or max(float(np.max(np.abs(np.asarray(e.current)))) for e in exps))
    if opts["current_limit"] is None:
        notes.append(f"Current limit {ilim:.3g} A = largest |current| in the records (set `tune.current_limit` for your amplifier).")
    ctrl = TorqueController(friction=nominal, drive=drive, sample_period=ts, current_limit=ilim)
    return ts, ilim, ctrl


def _feasible_references(dataset: Dataset, drive, opts: dict, ts: float, nominal: Parameters, ilim: float, notes, log):
    """`_references`, with one log line per reference (amplitudes in N·m) and a note when some ask
    for more current than `ilim` (A) and `tune.scale_references` is off."""
    refs, ref_info = _references(dataset, drive, opts, ts, nominal, ilim)
    for r in ref_info:
        fr = f", {r['frequency_hz']:.3g} Hz" if "frequency_hz" in r else ""
        log(f"      {r['name']}: requested {r['requested_amplitude']:.4g} N·m (feed-forward peak {r['feedforward_peak_over_limit']:.2f} x limit), "
            f"used {r['amplitude']:.4g} N·m (x{r['scale']:.3g}){fr}")  # fmt: skip
    if not opts["scale_references"] and any(r["feasible_scale"] < 1.0 for r in ref_info):
        notes.append("`tune.scale_references` is off and some references ask for more current than the limit allows (by the "
                     "identified model); the validation reports the saturated samples' share of the cost separately.")  # fmt: skip
    return refs, ref_info


def _measurement_noise(opts: dict, K: int, n: int, sigma):
    """K measurement-noise realisations per reference, torque (N·m) and motor velocity (rad/s),
    common to every plant set and every gain tried; and the first realisation alone."""
    rng = np.random.default_rng(int(opts["seed"]))
    noise_all = (jnp.asarray(rng.normal(size=(4 * K, n)) * sigma[0]), jnp.asarray(rng.normal(size=(4 * K, n)) * sigma[1]))
    noise = (noise_all[0][:4], noise_all[1][:4])
    return noise_all, noise


def _plant_sets(nominal: Parameters, per: dict, drive, ref_info, ts: float, df: float, opts: dict, *,
                sensor_lag: float = 0.0):
    """`tune.plants` parameter sets drawn around the identified ones (batched), their friction
    factors, and the linearised sampled loops of each set measured through the torque sensor's lag
    `sensor_lag` (s; `_linear_loops`)."""
    plant_sets, factors = draw_parameter_sets(nominal, per, int(opts["plants"]), seed=int(opts["seed"]),
                                              friction_uncertainty=float(opts["friction_uncertainty"]),
                                              with_friction_factors=True)
    params_list = [jax.tree.map(lambda x: x[j], plant_sets) for j in range(int(opts["plants"]))]
    return plant_sets, factors, _linear_loops(params_list, drive, ref_info, ts, df, sensor_lag)


def _relay_zn(nominal_plant: Plant, ref_info, opts: dict, ilim: float, ts: float, sm: Smoothing, notes, log):
    """Baseline 1: a relay test on the nominal locked plant (level N·m, relay amplitude A) and the
    Ziegler–Nichols PI from its limit cycle, with a note when that cycle is the sampled loop's own."""
    level = 0.5 * ref_info[0]["amplitude"]
    d = float(opts["relay_amplitude"]) * ilim
    relay = jax.jit(lambda pl: relay_test(pl, level=level, amplitude=d, sample_period=ts, duration=1.0, smoothing=sm,
                                          solver=opts["solver"]))(nominal_plant)
    zn, relay_info = ziegler_nichols_pi(relay, level=level, amplitude=d)
    relay_info.update({"level_Nm": level, "relay_amplitude_A": d})
    if relay_info["ultimate_period_s"] < 4.5 * ts:
        notes.append(f"The relay's limit cycle has a period of {relay_info['ultimate_period_s'] * 1e3:.3g} ms, "
                     f"{relay_info['ultimate_period_s'] / ts:.2g} samples: it is the sampled loop's own cycle, not the drive's, "
                     "so the Ziegler–Nichols PI derived from it is not model-based; it is reported as the rule an engineer would "
                     "apply to a relay test.")  # fmt: skip
    log(f"      relay: Ku = {relay_info['ultimate_gain']:.4g} A/(N·m), Tu = {relay_info['ultimate_period_s'] * 1e3:.3g} ms -> "
        f"kp = {float(zn.kp):.4g}, ki = {float(zn.ki):.4g}")  # fmt: skip
    return zn, relay_info


def _model_pi(drive, z, Pall, sss, ts: float, df: float, opts: dict, log):
    """Baseline 2: the MIGO PI on the first two linearised loops (static gain N·Km, N·m/A), with
    the model's reference, inertia and friction feed-forward (kr = kf = kj = 1), and its design."""
    G0 = float(drive.gear_ratio * drive.torque_constant)
    kp_m, ki_m, migo = ls.model_pi([(z, Pall[0]), (z, Pall[1])], sss[:2], static_gain=G0, ts=ts, derivative_filter=df,
                                   ms_max=float(opts["model_pi_ms"]))  # fmt: skip
    model_pi = TorqueGains(kp=kp_m, ki=ki_m, kr=1.0, kf=1.0, kj=1.0)
    log(f"      model-based PI: kp = {kp_m:.4g}, ki = {ki_m:.4g} ({migo['rule']}; Ms {migo['Ms']:.3g}), kr = kf = kj = 1")
    return model_pi, kp_m, ki_m, migo


def _objective(plants: Plant, R_cost, kw: dict, K: int, n_refs: int, z, Pall, loop_labels, ts: float, df: float, opts: dict):
    """The robust tuning cost over plant sets × K noise realisations × references, plus the Ms
    penalty on the linearised loops: `parts_jit(g)` (per plant and reference tracking and tuning
    costs, margin term, Ms), `cost_fn(g)` (traced, for BFGS) and `total(g)` (a float)."""

    def per_reference(x):  # (plant, K·reference) -> (plant, reference): mean over the noise realisations
        return x.reshape(x.shape[0], K, n_refs).mean(axis=1)
    ew = float(opts["effort_weight"])
    Pj = jnp.asarray(Pall)
    zj = jnp.asarray(z)
    ms_max, mw = float(opts["ms_max"]), float(opts["margin_weight"])

    free_loop = jnp.asarray([lab.endswith("free") for lab in loop_labels])

    def margin_term(g):
        per_loop = SimpleNamespace(kp=(g.kp * jnp.where(free_loop, g.kpf, 1.0))[:, None],
                                   ki=(g.ki * jnp.where(free_loop, g.kif, 1.0))[:, None], kd=g.kd)  # fmt: skip
        ms = ls.sensitivity_peak(per_loop, zj, Pj, ts=ts, derivative_filter=df)
        return mw * jnp.sum(jnp.maximum(ms - ms_max, 0.0) ** 2), ms

    def parts(g):
        track, tune_c = batch_cost(g, plants, R_cost, effort_weight=ew, **kw)
        mt, ms = margin_term(g)
        return per_reference(track), per_reference(tune_c), mt, ms

    parts_jit = jax.jit(parts)

    def cost_fn(g):
        _, tune_c = batch_cost(g, plants, R_cost, effort_weight=ew, **kw)
        return jnp.mean(tune_c) + margin_term(g)[0]

    def total(g):
        _, tc, mt, ms = parts_jit(g)
        return float(jnp.mean(tc) + mt)

    return parts_jit, cost_fn, total


def _start_candidates(zn: TorqueGains, model_pi: TorqueGains, kp_m: float, ki_m: float, opts: dict) -> list[tuple[str, TorqueGains]]:
    """The start search's candidates: both baselines, the model-based PI scaled on the
    `tune.start_factors` grid (its gains `kp_m`, `ki_m`), gentler free-motion PIs and the friction
    feed-forward variants."""
    cands = [("relay_zn", zn), ("model_pi", model_pi)]
    for fp in opts["start_factors"]:
        for fi in opts["start_factors"]:
            if fp == 1.0 and fi == 1.0:
                continue
            cands.append((f"model_pi kp x{fp:g}, ki x{fi:g}", TorqueGains(kp=fp * kp_m, ki=fi * ki_m, kr=1.0, kf=1.0, kj=1.0)))
    for ff in (0.5, 0.25):  # the same locked PI, a gentler free one (the torque sensor's noise acts on a small torque)
        cands.append((f"model_pi, free kp, ki x{ff:g}", TorqueGains(kp=kp_m, ki=ki_m, kr=1.0, kf=1.0, kj=1.0, kpf=ff, kif=ff)))
    # friction fed forward at the reference's velocity instead of the measured one (`TorqueGains.kfr`)
    for ff in (1.0, 0.5, 0.25):
        cands.append((f"model_pi, reference-velocity friction ff, free kp, ki x{ff:g}",
                      TorqueGains(kp=kp_m, ki=ki_m, kr=1.0, kf=0.0, kj=1.0, kpf=ff, kif=ff, kfr=1.0)))
    cands.append(("model_pi, half measured / half reference-velocity friction ff",
                  TorqueGains(kp=kp_m, ki=ki_m, kr=1.0, kf=0.5, kj=1.0, kfr=0.5)))
    return cands


def _start_search(cands, total, margins, log) -> list[dict]:
    """Each candidate's cost and whether its linearised loops are stable, with a progress bar."""
    search = []
    with task(log, "start search (baselines and scaled model-based PIs)", len(cands), unit="candidates") as bar:
        for name, g in cands:
            c = total(g)
            stable = margins(g)["all_stable"]
            search.append({"name": name, "gains": g.to_dict(), "cost": c, "linear_stable": bool(stable)})
            bar.advance(1, info=f"{name}: {c:.5g}")
    return search


def _bfgs(search: list[dict], cost_fn, scaling: GainScaling, opts: dict, notes, log):
    """BFGS from the `tune.starts` cheapest finite candidates: the result, the positions in
    `search` of the starts, and the time it took (s)."""
    ok = [j for j, c in enumerate(search) if np.isfinite(c["cost"])]
    order = sorted(ok, key=lambda j: search[j]["cost"])
    picked = order[: int(opts["starts"])]
    starts = [TorqueGains(**search[j]["gains"]) for j in picked]
    log("      start search: " + ", ".join(f"{search[j]['name']} {search[j]['cost']:.5g}" for j in picked) + " (best first)")
    t0 = time.time()
    n_bfgs = int(opts["max_steps"]) * len(starts)
    with task(log, f"BFGS from {len(starts)} start(s)", n_bfgs, unit="iterations") as bar:
        res = tune_gains(starts, cost_fn, scaling=scaling, max_steps=int(opts["max_steps"]), log=log,
                         cost_scale=float(search[picked[0]]["cost"]), max_gradient=float(opts["max_first_step"]),
                         progress=lambda k, f: bar.advance(1, info=f"cost {f:.5g}"))  # fmt: skip
    t_bfgs = time.time() - t0
    start_best = search[picked[res.best_run]]
    log(f"      BFGS: cost {start_best['cost']:.5g} -> {res.history[-1]:.5g} (start: {start_best['name']}; runs: "
        + ", ".join(f"{search[j]['name']} -> {r['final_cost']:.5g}" for j, r in zip(picked, res.runs)) + ")")  # fmt: skip
    if not any(r["converged"] for r in res.runs):
        notes.append(f"BFGS stopped at its step budget ({opts['max_steps']} steps per start, `tune.max_steps`) before its tolerance.")
    return res, picked, t_bfgs


def _model_costs(parts, margins: dict) -> dict:
    """tune.json's `model` entry of one controller from its `parts_jit` output: costs on the
    identified plant sets (mean, worst plant, per plant, per reference) and its margins."""
    track, tune_c, mt, ms = (np.asarray(x) for x in parts)
    per_plant = track.mean(axis=1)
    return {
        "cost": float(tune_c.mean() + mt),
        "tuning_cost": float(tune_c.mean()),
        "margin_term": float(mt),
        "tracking_cost_mean": float(track.mean()),
        "tracking_cost_worst_plant": float(per_plant.max()),
        "tracking_cost_per_plant": per_plant.tolist(),
        "tracking_cost_per_reference": dict(zip(REFERENCE_NAMES, track.mean(axis=0).tolist())),
        "margins": margins,
    }


def bench_tracking_cost(dataset: Dataset, gains: TorqueGains, *, sample_period: float, current_limit: float,
                        out: pathlib.Path, config: dict | None = None) -> float:
    """Tracking cost, on the bench that made `dataset` (its `truth.yaml` from `hdjax.bench`), of a
    controller with `gains` and the identified model's friction: `run_tune`'s validation cost (the
    mean over its `tune.validation_runs` runs and the four references of the squared torque error
    over the reference amplitude squared). `sample_period` (s) and `current_limit` (A) as in tune.json's
    `controller`; `out` is where the identification's fit.json is looked up, as by `run_tune`."""
    bench = _bench_from_truth(dataset)
    if bench is None or dataset.drive is None:
        raise ValueError(f"`bench_tracking_cost`: dataset {dataset.name!r} has no truth.yaml from hdjax.bench; "
                         "give a dataset made by `hdjax.bench.make_dataset`.")
    drive = dataset.drive
    opts = _options({"tune": {}} if config is None else config)
    nominal, *_ = _identified(dataset, config or {}, opts, pathlib.Path(out), lambda *a: None)
    ctrl = TorqueController(friction=nominal, drive=drive, sample_period=sample_period, current_limit=current_limit)
    refs, info = _references(dataset, drive, opts, ctrl.sample_period, nominal, ctrl.current_limit)
    runs = [_validate_bench(bench, {"x": gains}, refs, ctrl, seed=seed)[0]["x"] for seed in _validation_seeds(opts)]
    return _validation_costs(runs, info, ctrl.current_limit)["tracking_cost"]


def _validation_seeds(opts: dict) -> list[int]:
    """Noise seeds of the `tune.validation_runs` validation runs."""
    return [int(opts["seed"]) + 1000 + k for k in range(int(opts["validation_runs"]))]


def _validation_runs(bench, nominal_plant: Plant, gains: dict, refs, R, ctrl: TorqueController, sigma, n: int, opts: dict):
    """`tune.validation_runs` runs of every controller, on the bench when the dataset came from one,
    else on the identified model: [(traj, description)], and the description of the whole."""
    seeds = _validation_seeds(opts)
    runs = len(seeds)
    if bench is not None:
        trajs = [_validate_bench(bench, gains, refs, ctrl, seed=sd) for sd in seeds]
    else:
        trajs = _validate_model(nominal_plant, gains, R, ctrl, sigma, n, opts, seeds=seeds)
    val_desc = trajs[0][1]
    val_desc += (f"; every figure is the mean over {runs} runs with independent noise (seeds {seeds[0]}-{seeds[-1]}), "
                 "the figures show the first") if runs > 1 else ""
    return trajs, val_desc


def _simulate_tuned(tuned: TorqueGains, nominal_plant: Plant, R, noise, ctrl: TorqueController, sm: Smoothing, opts: dict):
    """The tuned loop on the nominal identified plant, every reference with the first noise
    realisation (for the figures)."""
    return jax.jit(
        lambda g: jax.vmap(lambda r, a, b: closed_loop(g, nominal_plant, r, controller=ctrl, noise=(a, b),
                                                       substeps=int(opts["substeps"]), smoothing=sm, solver=opts["solver"]))(
            R, noise[0], noise[1]
        )
    )(tuned)


def _validation_row(tr: dict, j: int, info: dict, ilim: float) -> dict[str, Any]:
    """One controller on reference `j` of one run: tracking costs (saturated and unsaturated
    parts), tracking RMS (N·m), current RMS and peak (A), and step metrics for a step."""
    err = np.asarray(tr["reference"][j]) - np.asarray(tr["torque"][j])
    cur = np.asarray(tr["current"][j])
    tot, sat, unsat, fsat = _split_cost(err, np.asarray(tr["command_limited"][j]), ilim, info["amplitude"])
    row: dict[str, Any] = {
        "tracking_cost": tot,
        "tracking_cost_saturated": sat,
        "tracking_cost_unsaturated": unsat,
        "saturated_fraction": fsat,
        "tracking_rms_Nm": float(np.sqrt(np.mean(err**2))),
        "measured_tracking_rms_Nm": float(np.sqrt(np.mean((np.asarray(tr["reference"][j]) - np.asarray(tr["measured_torque"][j])) ** 2))),
        "current_rms_A": float(np.sqrt(np.mean(cur**2))),
        "current_peak_A": float(np.max(np.abs(cur))),
    }
    if "step" in info:
        row.update(step_metrics(tr["time"][j], tr["torque"][j], amplitude=info["amplitude"], start=info["step"][0], end=info["step"][1]))
    return row


def _validation_costs(runs: list[dict], ref_info, ilim: float) -> dict:
    """tune.json's `validation` entry of one controller from its runs: every figure per reference
    averaged over the runs, and the tracking cost per run and overall."""
    rows_runs = [{info["name"]: _validation_row(tr, j, info, ilim) for j, info in enumerate(ref_info)} for tr in runs]
    # mean over the runs of every figure (step metrics included)
    per_ref: dict[str, dict[str, Any]] = {
        ref: {k: _mean_or_none([rr[ref][k] for rr in rows_runs]) for k in rows_runs[0][ref]} for ref in rows_runs[0]
    }
    for ref in per_ref:
        per_ref[ref]["tracking_cost_per_run"] = [rr[ref]["tracking_cost"] for rr in rows_runs]
    run_costs = [float(np.mean([r["tracking_cost"] for r in rr.values()])) for rr in rows_runs]
    return {
        "tracking_cost": float(np.mean(run_costs)),
        "tracking_cost_per_run": run_costs,
        "tracking_cost_saturated": float(np.mean([r["tracking_cost_saturated"] for r in per_ref.values()])),
        "references": per_ref,
    }


def _improvement(val: dict, where: str, log) -> dict[str, float]:
    """How much lower the tuned loop's validation tracking cost is than each baseline's (fraction),
    logged."""
    improvement = {b: 1.0 - val["tuned"]["tracking_cost"] / val[b]["tracking_cost"] for b in ("relay_zn", "model_pi")}
    log(f"      tracking cost on {where}: relay/ZN {val['relay_zn']['tracking_cost']:.4g}, model-based PI "
        f"{val['model_pi']['tracking_cost']:.4g}, tuned {val['tuned']['tracking_cost']:.4g} "
        f"({100 * improvement['relay_zn']:.1f} % / {100 * improvement['model_pi']:.1f} % lower)")  # fmt: skip
    return improvement


def _controller_section(ctrl: TorqueController, ts: float, ilim: float) -> dict:
    """tune.json's `controller`: the control law, sample period (s), current limit (A), derivative
    filter (s) and friction feed-forward smoothing scale (rad/s)."""
    return {
        "law": ("i = sat(kr*r/(N*Km) + kj*N*Jeff_hat*r/(J_L*Km) + kp*e + I - kd*dy_f + kf*Tf_hat(w)/Km"
                " + kfr*Tf_hat(w_r)/Km) (J_L = load inertia, infinite when locked; w_r = N*(torsion rate of"
                " the identified compliance following r + integral of r/J_L), the motor velocity the reference"
                " asks for), e = r - y, back-calculation anti-windup"),
        "sample_period_s": ts,
        "current_limit_A": ilim,
        "derivative_filter_s": ctrl.derivative_filter,
        "friction_feedforward_scale_rad_s": ctrl.friction_scale,
    }


def _baselines_section(zn: TorqueGains, relay_info: dict, model_pi: TorqueGains, migo: dict) -> dict:
    """tune.json's `baselines`: each baseline's rule, gains and design data."""
    return {
        "relay_zn": {"rule": "relay test on the identified locked model + Ziegler-Nichols PI, no feed-forward",
                     "gains": zn.to_dict(), "relay": relay_info},
        "model_pi": {"rule": migo["rule"] + " (linearised sampled loops of the nominal identified plant), with the model's "
                     "reference, inertia and friction feed-forward (kr = kj = kf = 1)", "gains": model_pi.to_dict(), "design": migo},
    }  # fmt: skip


def _tuning_section(opts: dict, K: int, sigma, sm: Smoothing, search, start_best, res, picked) -> dict:
    """tune.json's `tuning`: the cost and optimiser, their settings (noise σ in N·m and rad/s,
    smoothing scales in rad/s), the start search and the BFGS runs."""
    return {
        "cost": "mean over plant sets and references of mean((r-T)^2)/A^2 + effort_weight*mean(di^2)/ilim^2, plus "
                "margin_weight * sum over linearised loops of max(0, Ms - ms_max)^2",
        "optimiser": "start search (baselines, model-based PI scaled on a kp x ki grid), then optimistix.BFGS from the "
                     "best `starts` candidates (reverse-mode gradients through the closed loop and the frequency response)",
        "plants": int(opts["plants"]),
        "noise_realisations": K,
        "noise_sigma": {"torque": sigma[0], "motor_velocity": sigma[1]},
        "solver": opts["solver"],
        "substeps": int(opts["substeps"]),
        "smoothing": {"velocity_scale": sm.velocity_scale, "torsion_rate_scale": sm.torsion_rate_scale},
        "effort_weight": float(opts["effort_weight"]),
        "ms_max": float(opts["ms_max"]),
        "margin_weight": float(opts["margin_weight"]),
        "start_search": search,
        "start_search_best": start_best["cost"],
        "cost_before_optimiser": start_best["cost"],
        "cost_after_optimiser": res.history[-1] if res.history else start_best["cost"],
        "bfgs_runs": [{"start": search[j]["name"], "start_cost": search[j]["cost"], **r} for j, r in zip(picked, res.runs)],
        "best_run": res.best_run,
        "cost_history": res.history,
    }


TARE_SAMPLES = 200


def _validate_bench(bench, gains: dict, refs, ctrl: TorqueController, *, seed: int):
    """Every controller on every reference, in one bench run (columns)."""
    names = list(gains)
    K = refs[0].torque.shape[0]
    cols = [(c, j) for c in names for j in range(len(refs))]
    rmat = np.stack([np.asarray(refs[j].torque) for _, j in cols], axis=1)
    free = np.array([bool(float(refs[j].free)) for _, j in cols])
    law = numpy_torque_law([gains[c] for c, _ in cols], ctrl, free)
    o = bench.closed_loop(law, rmat, free, current_limit=ctrl.current_limit, seed=seed, tare_samples=TARE_SAMPLES)
    traj = {}
    for c in names:
        idx = [k for k, (cc, _) in enumerate(cols) if cc == c]
        traj[c] = {
            "time": o["time"][:, idx].T, "reference": o["reference"][:, idx].T, "torque": o["torque"][:, idx].T,
            "measured_torque": o["measured_torque"][:, idx].T, "current": o["current"][:, idx].T,
            "command_limited": o["current_command"][:, idx].T,
        }  # fmt: skip
    st = bench.station
    desc = (f"the independent bench hdjax._testbench.independent rebuilt from truth.yaml ({st.name}, seed {bench.seed}): its own fixed-step "
            f"physics with stick-slip friction, a {bench.dev.current_bandwidth:g} Hz current loop, sensor low-passes, "
            f"offsets and ripple, hidden effects {sorted(bench.magnitudes) or 'none'}; the controller runs at "
            f"{bench.sample_rate:g} Hz on the sensed signals, its command held into the current loop; strain gauge and "
            f"tachometer zeroed at rest before each run (mean of {TARE_SAMPLES} samples, as an operator tares them); {K} "
            "samples per reference")  # fmt: skip
    return traj, desc


def _validate_model(nominal_plant: Plant, gains: dict, R, ctrl: TorqueController, sigma, n, opts, *, seeds) -> list:
    """Every controller on the identified model, one run per noise seed: [(traj, description)]."""
    sub = int(opts["rig_substeps"])
    run = jax.jit(lambda g, nT, nw: jax.vmap(lambda r, a, b: closed_loop(g, nominal_plant, r, controller=ctrl, noise=(a, b), substeps=sub,
                                                                           solver=opts["solver"]))(
        R, nT, nw))  # fmt: skip
    desc = ("this dataset has no truth.yaml written by hdjax._testbench.independent, so the controllers are "
            f"validated on the identified model ({sub} {opts['solver']} substeps per sample, estimated sensor noise); this is not a "
            "test on hardware: run the tuned gains on the real drive")  # fmt: skip
    out = []
    for seed in seeds:
        rng2 = np.random.default_rng(seed)
        nT, nw = jnp.asarray(rng2.normal(size=(4, n)) * sigma[0]), jnp.asarray(rng2.normal(size=(4, n)) * sigma[1])
        traj = {}
        for c, g in gains.items():
            tr = run(g, nT, nw)
            traj[c] = {"time": np.asarray(tr.time), "reference": np.asarray(tr.reference), "torque": np.asarray(tr.torque),
                       "measured_torque": np.asarray(tr.measured_torque), "current": np.asarray(tr.current),
                       "command_limited": np.asarray(tr.current)}  # fmt: skip
        out.append((traj, desc))
    return out




def _fmt(v):
    if v is None:
        return "—"
    if isinstance(v, float):
        if math.isinf(v):
            return "∞"
        return f"{v:.4g}"
    return str(v)


def _report(r: dict) -> str:
    kind = r["validation"]["on"]
    L = [f"# Torque-controller tuning: {r['dataset']}", ""]
    L.append(f"Identified plant: {r['identification']['source']}.")
    c = r["controller"]
    L.append(
        f"Controller: {c['law']}; sample period {c['sample_period_s'] * 1e3:g} ms (zero-order hold), current limit "
        f"{c['current_limit_A']:.3g} A."
    )
    L += ["", "## References", "",
          "Requested amplitudes are fractions of the largest recorded torques. "
          + ("Each is scaled down until the identified model's feed-forward current stays within the headroom of the current "
             "limit; sine frequencies are capped at a twentieth of the sample rate." if r["references_scaled"] else
             "Scaling is off (`tune.scale_references: false`): the requested references are used as they are, and the "
             "validation reports the cost of the samples at the current limit separately."),
          "", "| reference | requested (N·m) | model feed-forward peak / limit | scale | used (N·m) | frequency (Hz) |",
          "|---|---|---|---|---|---|"]  # fmt: skip
    for x in r["references"]:
        fr = "—" if "frequency_hz" not in x else f"{x['frequency_hz']:.3g}" + (
            f" (asked {x['requested_frequency_hz']:.3g})" if x["frequency_hz"] != x["requested_frequency_hz"] else "")
        L.append(f"| {x['name']} | {x['requested_amplitude']:.4g} | {x['feedforward_peak_over_limit']:.3g} | {x['scale']:.3g} | "
                 f"{x['amplitude']:.4g} | {fr} |")  # fmt: skip
    L += ["", "## Gains", "", "| gain | unit | relay + Ziegler–Nichols PI | model-based PI (MIGO) | tuned |", "|---|---|---|---|---|"]
    for k in GAIN_NAMES:
        L.append(f"| {k} | {r['gain_units'][k]} | {_fmt(r['baselines']['relay_zn']['gains'][k])} | "
                 f"{_fmt(r['baselines']['model_pi']['gains'][k])} | {_fmt(r['gains'][k])} |")  # fmt: skip
    rl = r["baselines"]["relay_zn"]["relay"]
    mp = r["baselines"]["model_pi"]
    L += [
        "",
        f"Relay test: ultimate gain {rl['ultimate_gain']:.4g} A/(N·m), ultimate period {rl['ultimate_period_s'] * 1e3:.3g} ms. "
        f"Model-based PI: {mp['rule']}; Ms {mp['design']['Ms']:.3g}.",
        "",
        "## Robust tuning (model)",
        "",
    ]
    t = r["tuning"]
    L.append(f"Cost: {t['cost']} (ms_max {t['ms_max']:g}, margin_weight {t['margin_weight']:g}), over {t['plants']} plant "
             f"parameter sets drawn from the per-experiment estimates and 4 references.")  # fmt: skip
    L += ["", f"Start search over {len(t['start_search'])} candidates: best {t['start_search_best']:.5g}. "
          f"**Gradient step (BFGS) alone: cost {t['cost_before_optimiser']:.5g} → {t['cost_after_optimiser']:.5g} "
          f"({100 * (1 - t['cost_after_optimiser'] / t['cost_before_optimiser']):.1f} % lower)**, kept run {t['best_run'] + 1}.", ""]
    L += ["| BFGS start | start cost | final cost | steps | converged |", "|---|---|---|---|---|"]
    for b in t["bfgs_runs"]:
        L.append(f"| {b['start']} | {b['start_cost']:.5g} | {b['final_cost']:.5g} | {b['steps']} | {b['converged']} |")
    L += ["", "| on the tuning model | relay + ZN | model-based PI | tuned |", "|---|---|---|---|"]
    m = r["model"]
    for key, lab in (("cost", "tuning cost incl. margin term"), ("margin_term", "margin term"),
                     ("tracking_cost_mean", "tracking cost, mean over plants"),
                     ("tracking_cost_worst_plant", "tracking cost, worst plant")):  # fmt: skip
        L.append(f"| {lab} | {_fmt(m['relay_zn'][key])} | {_fmt(m['model_pi'][key])} | {_fmt(m['tuned'][key])} |")
    L.append(f"| Ms, worst linearised loop | {_fmt(m['relay_zn']['margins']['Ms_max'])} | {_fmt(m['model_pi']['margins']['Ms_max'])} | "
             f"{_fmt(m['tuned']['margins']['Ms_max'])} |")  # fmt: skip
    L.append(f"| all linearised loops stable | {m['relay_zn']['margins']['all_stable']} | {m['model_pi']['margins']['all_stable']} | "
             f"{m['tuned']['margins']['all_stable']} |")  # fmt: skip
    for mode in (0, 1):
        row = []
        for name in CONTROLLERS:
            x = m[name]["margins"]["nominal"][mode]
            row.append(f"GM {_fmt(x['gain_margin'])}, PM {_fmt(x['phase_margin_deg'])}°")
        L.append(f"| margins, nominal {'free' if mode else 'locked'} | " + " | ".join(row) + " |")
    v = r["validation"]
    title = "Validation on the independent bench" if kind == "bench" else "Validation on the identified model (not a hardware test)"
    L += [
        "",
        f"## {title}",
        "",
        f"{v['description']}.",
        "",
        f"Tracking cost (mean over references of mean((r − T)²)/amplitude², T the true torque): relay + ZN "
        f"{_fmt(v['relay_zn']['tracking_cost'])}, model-based PI {_fmt(v['model_pi']['tracking_cost'])}, tuned "
        f"{_fmt(v['tuned']['tracking_cost'])}: **{100 * v['improvement_over']['relay_zn']:.1f} % lower than relay + ZN, "
        f"{100 * v['improvement_over']['model_pi']:.1f} % lower than the model-based PI** (on the {kind}).",
        "",
        "| reference | controller | cost | of which at the current limit | saturated samples (%) | RMS (N·m) "
        "| overshoot (%) | settling (s) | peak current (A) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for ref in REFERENCE_NAMES:
        for name in CONTROLLERS:
            row = v[name]["references"][ref]
            L.append(
                f"| {ref} | {LABELS[name]} | {_fmt(row['tracking_cost'])} | {_fmt(row['tracking_cost_saturated'])} | "
                f"{100 * row['saturated_fraction']:.1f} | {_fmt(row['tracking_rms_Nm'])} | {_fmt(row.get('overshoot_percent'))} | "
                f"{_fmt(row.get('settling_time_s'))} | {_fmt(row['current_peak_A'])} |"
            )
    L += ["", "Cost split: samples with the current command at the limit (saturation) vs the others (tracking); the two add up "
          "to the cost. Settling: into ±5 % of the step and staying until the step ends (— : never).", ""]  # fmt: skip
    if r["notes"]:
        L += ["## Notes", ""] + [f"- {n}" for n in r["notes"]] + [""]
    L += ["## Figures", ""] + [f"![{f}]({f})" for f in r["figures"]] + [""]
    tt = r["timing_s"]
    L.append(f"Total time {tt['total']:.1f} s (start search {tt['start_search']:.1f} s, BFGS {tt['bfgs']:.1f} s, "
             f"validation {tt['validation']:.1f} s).")  # fmt: skip
    return "\n".join(L) + "\n"
