r"""The `sensitivity` workflow: which parameters matter where, and how well each is determined.

1. **Normalised sensitivities** $S_k(t) = \partial y(t)/\partial\ln|p_k| = p_k\,\partial y/\partial p_k$
   of every output channel (torque, wave-generator velocity, output angle), every parameter and
   every experiment: `jax.jacfwd` through the diffrax solve (`Simulator.adjoint = ForwardMode()`),
   `vmap`ped over the stacked experiments, one `eqx.filter_jit` with the data as arguments.
   A unit of $\ln p$ is a relative change, so the eleven columns are directly comparable.
2. **Identifiability.** The noise-weighted residual Jacobian in $\ln p$ (the residual of
   `hdjax._fit.experiment_residuals`: each channel divided by its noise level, the output angle
   projected off its rigid-body components) gives the Fisher information $F = J^\top J$, the
   noise-only covariance $F^{-1}$ of $\ln p$ (so its square-root diagonal is the *relative* standard
   error), correlations, and the eigen-directions of $F$ (the right singular vectors of $J$): the
   parameter combinations the data barely constrain.
3. **The paper's section V study**: the complete model against Coulomb = 0, viscous = 0, K1 / 10 and
   Tst = 0, each simulated against the measured records, with the RMS increase per change.
4. **Experiment-design advice** from the per-experiment Fisher information.

Numerics (measured on the HD2 campaign, `benchmarks/sensitivity_hd2.py`): the Jacobian is computed
with the Rosenbrock solver at `rtol = 1e-4` (atol = rtol·1e-2): against `rtol = 1e-7` the standard
errors agree to 0.4 % and the ablation RMS figures to 3 digits, at a fifth of the cost (a tighter
tolerance takes 5–10× more steps through the stiff velocity reversals).
"""

import math
import pathlib
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._artifacts import fit_json_dataset, read_fit_json
from ._config import section_options
from ._data import Dataset
from ._experiment import Experiment, select_experiments, stack_experiments, take_experiments
from ._fit import CHANNELS, DEFAULT_FREE, noise_levels
from ._io import atomic_write_json, atomic_write_text
from ._model import PARAMETER_NAMES, PARAMETER_UNITS, Drive, Parameters
from ._parameterisation import Entry, Parameterisation
from ._plant import Simulator, Trajectory, is_fixed_cost, simulate
from ._sharding import for_each_experiment

__all__ = [
    "ABLATIONS",
    "SCHEMA",
    "Sensitivities",
    "fisher_summary",
    "run_sensitivity",
    "scaled_parameters",
    "sensitivities",
    "simulate_lanes",
    "weighted_jacobians",
    "workflow_simulator",
]

SCHEMA = "hdjax.sensitivity/1"
CHANNEL_UNITS = {"torque": "N·m", "motor_velocity": "rad/s", "output_position": "rad"}
CHANNEL_SYMBOL = {"torque": "T", "motor_velocity": "ω_m", "output_position": "θ_o"}
#: the parameters the fit (and the paper) estimate; alpha and Tss2 are fixed there
ESTIMATED = tuple(DEFAULT_FREE)
#: the paper's per-experiment regressions estimate these groups together (the rest held fixed)
GROUPS = {
    "K1": ("K1", "Tst"),
    "Tst": ("K1", "Tst"),
    "Jeff": ("Jeff", "Tvp", "Tvn", "Tsp", "Tsn"),
    "Tvp": ("Jeff", "Tvp", "Tvn", "Tsp", "Tsn"),
    "Tvn": ("Jeff", "Tvp", "Tvn", "Tsp", "Tsn"),
    "Tsp": ("Jeff", "Tvp", "Tvn", "Tsp", "Tsn"),
    "Tsn": ("Jeff", "Tvp", "Tvn", "Tsp", "Tsn"),
    "Tssp1": ("Tssp1", "Tssn1"),
    "Tssn1": ("Tssp1", "Tssn1"),
}
#: the paper's section V changes: (key, label, the mode the paper studied it in, parameter change)
ABLATIONS = (
    ("coulomb_zero", "Coulomb = 0 (Tsp = Tsn = 0)", "free", lambda p: p.replace(Tsp=0.0, Tsn=0.0)),
    ("viscous_zero", "viscous = 0 (Tvp = Tvn = 0)", "free", lambda p: p.replace(Tvp=0.0, Tvn=0.0)),
    ("K1_div10", "K1 / 10", "constrained", lambda p: p.replace(K1=p.K1 / 10.0)),
    ("Tst_zero", "Tst = 0", "constrained", lambda p: p.replace(Tst=0.0)),
)
DEFAULTS = {
    "fit_json": None,  # path of a fit.json whose parameter values to use
    "rtol": 1e-4,  # solver tolerance of the sensitivity and ablation simulations
    "max_steps": 20_000,  # step budget per experiment (a simulation that exhausts it is reported)
    "max_experiments": 50,  # sensitivities on at most this many experiments (evenly spread)
    "ablation_both_modes": True,  # also run each change on the other mode (not only the paper's)
    "significant_increase": 0.5,  # an RMS increase above this fraction counts as "matters"
}
_AGREE_FACTOR = 3.0


# ----------------------------------------------------------------------------------------------
# Sensitivities
# ----------------------------------------------------------------------------------------------


def scaled_parameters(p: Parameters, s: jax.Array) -> Parameters:
    """`p` with every parameter multiplied by `exp(s_k)` (order `PARAMETER_NAMES`), so that a
    derivative with respect to `s_k` at 0 is one with respect to `ln|p_k|`."""
    relative = Parameterisation(entries=tuple(Entry(k, transform="log") for k in PARAMETER_NAMES),
                                scale=jnp.stack([getattr(p, k) for k in PARAMETER_NAMES]),
                                offset=jnp.zeros(len(PARAMETER_NAMES)))
    return relative.to_model(s, p)


class Sensitivities(eqx.Module):
    """Output of `sensitivities` for a stacked batch of experiments.

    **Attributes:**

    - `outputs`: simulated (torque N·m, motor velocity rad/s, output angle rad), shape
      (experiment, 3, time).
    - `S`: ∂output/∂ln|p| in the channel's unit, shape (experiment, 3, time, parameter), parameters
      in the order of `PARAMETER_NAMES`.
    - `success`, `num_steps`: per experiment, from the solve.
    """

    outputs: jax.Array
    S: jax.Array
    success: jax.Array
    num_steps: jax.Array


def _sensitivity_one(p: Parameters, drive: Drive, exp: Experiment, simulator: Simulator):
    def f(s):
        tr = simulate(scaled_parameters(p, s), drive, exp, simulator=simulator)
        y = jnp.stack([tr.torque, tr.motor_velocity, tr.output_position])
        return y, (y, tr.success, tr.num_steps)

    S, (y, ok, steps) = jax.jacfwd(f, has_aux=True)(jnp.zeros(len(PARAMETER_NAMES)))
    return Sensitivities(outputs=y, S=S, success=ok, num_steps=steps)


@eqx.filter_jit
def _sensitivities_jit(p, drive, batch, simulator):
    # data enter as arguments, never as closed-over constants (which XLA would try to fold)
    return for_each_experiment(lambda e: _sensitivity_one(p, drive, e, simulator), batch,
                               fixed_cost=is_fixed_cost(simulator))


def sensitivities(p: Parameters, drive: Drive, batch: Experiment, *, simulator: Simulator = Simulator()) -> Sensitivities:
    """Forward-mode sensitivities ∂y/∂ln|p| of all channels of a stacked batch
    (`hdjax.stack_experiments`), by `jax.jacfwd` through the diffrax solve, `vmap`ped over the
    experiments. `simulator.adjoint` must support forward mode (the default `ForwardMode()`)."""
    return _sensitivities_jit(p, drive, batch, simulator)


@eqx.filter_jit
def _simulate_lanes_jit(P, drive, lanes, simulator):
    return for_each_experiment(lambda q, e: simulate(q, drive, e, simulator=simulator), P, lanes,
                               fixed_cost=is_fixed_cost(simulator))


def simulate_lanes(P: Parameters, drive: Drive, lanes: Experiment, *, simulator: Simulator = Simulator()) -> Trajectory:
    """Simulate lane `i` of a stacked batch `lanes` with parameter set `i` of the stacked `P` (each
    `Parameters` leaf with a leading lane axis): many parameter sets in one `vmap`."""
    return _simulate_lanes_jit(P, drive, lanes, simulator)


def _rigid_body_projector(t: np.ndarray) -> np.ndarray:
    """Orthonormal basis (2, n) of {1, t}: the output angle's rigid-body components."""
    b = np.stack([np.ones_like(t), t - t.mean()])
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def weighted_jacobians(S, outputs, batch: Experiment, sigma) -> tuple[list[np.ndarray], list[np.ndarray], list[dict]]:
    """Per experiment, the noise-weighted residual Jacobian in ln p and the weighted residual.

    Rows: the masked samples of torque / σ_T, motor velocity / σ_ω and, in free motion with a
    measured output angle, the output angle / σ_θ projected off its rigid-body components {1, t}
    (as in `hdjax._fit.experiment_residuals`). Returns `(J_list, r_list, channel_rows)` where
    `channel_rows[e]` maps channel name to that channel's weighted block of `J_list[e]`."""
    S = np.asarray(S)
    y = np.asarray(outputs)
    sigma = np.asarray(sigma)
    mask = np.asarray(batch.mask)
    time_ = np.asarray(batch.time)
    free = np.asarray(batch.free) * np.asarray(batch.has_output_position)
    meas = np.stack([np.asarray(batch.torque), np.asarray(batch.motor_velocity), np.asarray(batch.output_position)], 1)
    Js, rs, blocks = [], [], []
    for e in range(S.shape[0]):
        m = mask[e]
        blk, rr = {}, []
        for c, ch in enumerate(CHANNELS):
            if ch == "output_position" and free[e] <= 0:
                continue
            A = S[e, c][m] / sigma[c]
            r = (y[e, c][m] - meas[e, c][m]) / sigma[c]
            if ch == "output_position":
                B = _rigid_body_projector(time_[e][m])
                A = A - B.T @ (B @ A)
                r = r - B.T @ (B @ r)
            blk[ch] = A
            rr.append(r)
        Js.append(np.concatenate(list(blk.values()), axis=0))
        rs.append(np.concatenate(rr))
        blocks.append(blk)
    return Js, rs, blocks


# ----------------------------------------------------------------------------------------------
# Fisher information
# ----------------------------------------------------------------------------------------------


def fisher_summary(F, names, *, n_directions: int = 3, rcond: float = 1e-12) -> dict:
    """Standard errors, correlations and weakest directions from a Fisher information matrix.

    `F = JᵀJ` for a noise-weighted Jacobian `J` in the coordinates `names` (here ln p, so the
    standard errors are relative). Parameters with no information (F_kk = 0) get an infinite
    standard error and are left out of the inversion. The inverse is taken on the
    diagonal-scaled matrix (pseudo-inverse with `rcond`) so that very different information
    levels do not cost accuracy.

    Returns a dict: `parameters`, `std_error` (√diag F⁻¹), `correlation` (list of lists, NaN for
    uninformed parameters), `singular_values` (of J, ascending: √eig F), `directions`
    (the `n_directions` weakest eigen-directions, each with its singular value, the standard error
    along it, 1/s, and the unit-vector components)."""
    F = np.asarray(F, dtype=float)
    names = list(names)
    P = len(names)
    d = np.diag(F).copy()
    ok = d > 0
    se = np.full(P, np.inf)
    corr = np.full((P, P), np.nan)
    if ok.any():
        idx = np.flatnonzero(ok)
        Fs = F[np.ix_(idx, idx)]
        dsc = 1.0 / np.sqrt(np.diag(Fs))
        C = np.linalg.pinv(Fs * np.outer(dsc, dsc), rcond=rcond, hermitian=True) * np.outer(dsc, dsc)
        s = np.sqrt(np.clip(np.diag(C), 0.0, None))
        se[idx] = s
        with np.errstate(invalid="ignore", divide="ignore"):
            corr[np.ix_(idx, idx)] = C / np.outer(s, s)
    w, V = np.linalg.eigh(0.5 * (F + F.T))
    sv = np.sqrt(np.clip(w, 0.0, None))
    directions = []
    for i in range(min(n_directions, P)):
        v = V[:, i] * (1.0 if V[np.argmax(np.abs(V[:, i])), i] >= 0 else -1.0)
        directions.append(
            {
                "singular_value": float(sv[i]),
                "std_error_along": float(1.0 / sv[i]) if sv[i] > 0 else math.inf,
                "components": {k: float(v[j]) for j, k in enumerate(names)},
            }
        )
    return {
        "parameters": names,
        "std_error": {k: float(se[j]) for j, k in enumerate(names)},
        "correlation": corr.tolist(),
        "singular_values": sv.tolist(),
        "directions": directions,
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


def _sub_fisher(F, names, sub):
    idx = [names.index(k) for k in sub]
    return F[np.ix_(idx, idx)]


# ----------------------------------------------------------------------------------------------
# The workflow
# ----------------------------------------------------------------------------------------------


def _options(config: dict) -> dict:
    return section_options(config, "sensitivity", DEFAULTS)


def workflow_simulator(opts: dict) -> Simulator:
    """The simulator of the sensitivity and ablation runs (options as `DEFAULTS`)."""
    return Simulator(rtol=float(opts["rtol"]), atol=float(opts["rtol"]) * 1e-2, max_steps=int(opts["max_steps"]))


def _parameter_source(dataset: Dataset, config: dict, out: pathlib.Path, opts: dict, exps, log):
    """(Parameters, source dict, consistency, per-experiment estimates, paper identification or None,
    the fit's standard errors by name (empty without a fit.json))."""
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
        return fit.parameters, {"kind": "fit.json", "path": str(path)}, fit.consistency, fit.per_experiment, None, fit.std_error
    from ._identify import _options as fit_options
    from ._paper_id import identify_paper

    fo = fit_options(config)
    assert dataset.drive is not None  # run_sensitivity checked it
    paper = identify_paper(exps, dataset.drive, alpha=fo["alpha"], Tss2=fo["Tss2"], cutoff_hz=fo["cutoff_hz"])
    src = {
        "kind": "paper_identification",
        "note": "no fit.json found (config `sensitivity.fit_json`, or results/<name>/fit.json beside the output "
        "folder); the paper's regressions (section III) were run instead of the slow trajectory fit",
        "undetermined": paper.undetermined(),
    }
    return paper.parameters(), src, dict(paper.consistency), dict(paper.per_experiment), paper, {}


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
    p, source, consistency, per_exp_est, paper, fit_se = _parameter_source(dataset, config, out, opts, exps, log)
    timing["parameters"] = time.time() - t0
    log(f"      from {source['kind']}" + (f" ({source['path']})" if "path" in source else ""))

    sel, files, modes, batch = _selection(exps, files_all, modes_all, opts, notes)
    sigma = np.asarray(noise_levels(stack_experiments(exps)))
    simulator = workflow_simulator(opts)

    log(f"[2/5] sensitivities ∂y/∂ln p: jacfwd through the solve, vmap over {len(sel)} experiments × {len(PARAMETER_NAMES)} parameters")
    t0 = time.time()
    sens = jax.block_until_ready(sensitivities(p, drive, batch, simulator=simulator))
    timing["sensitivities"] = time.time() - t0
    ok = _simulations_ok(sens, files, opts, notes)
    Js, rs, blocks = weighted_jacobians(sens.S, sens.outputs, batch, sigma)
    names = list(PARAMETER_NAMES)
    P = len(names)
    F_e, info = _fisher_per_experiment(Js, ok, P)
    summary = _sensitivity_summary(names, info, ok, blocks, sigma)

    log("[3/5] Fisher information, standard errors, correlations, weakest directions")
    F = F_e.sum(0)
    n_obs, chi2, chi2_channel = _chi_square(rs, blocks, ok, P)
    fs_all = fisher_summary(F, names)
    est = [k for k in ESTIMATED if k in names]
    fs_est = fisher_summary(_sub_fisher(F, names, est), est)
    comparison = _compare(F_e, ok, names, est, fs_est, consistency, per_exp_est, paper, sel, exps, modes, batch,
                          float(p.Tss2))

    log("[4/5] the paper's section V study (complete vs Coulomb = 0, viscous = 0, K1/10, Tst = 0)")
    t0 = time.time()
    ablation, abl_traj = _ablations(p, drive, batch, sens, ok, modes, files, opts, simulator)
    timing["ablations"] = time.time() - t0

    log("[5/5] experiment-design advice, report and figures")
    advice = _advice(F, F_e, ok, names, est, fs_est, files, modes, batch, p)
    t0 = time.time()
    typical = _typical(info, ok, modes)
    from ._plots import sensitivity_figures  # matplotlib loads only when figures are drawn
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
    atomic_write_json(out / "sensitivity.json", result)
    atomic_write_text(out / "report.md", _report(result))
    log(f"wrote {out / 'sensitivity.json'} and {out / 'report.md'} in {timing['total']:.1f} s")
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


def _fisher_per_experiment(Js, ok, P):
    """Per experiment the Fisher information JᵀJ in ln p (zero where the simulation failed), and
    the information √F_kk laid out (parameter, experiment)."""
    F_e = np.stack([J.T @ J if ok[j] else np.zeros((P, P)) for j, J in enumerate(Js)])
    info = np.sqrt(np.clip(np.einsum("ekk->ek", F_e), 0, None)).T  # (parameter, experiment)
    return F_e, info


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


def _compare(F_e, ok, names, est, fs_est, consistency, per_exp_est, paper, sel, exps, modes, batch, Tss2) -> list[dict]:
    """Relative SE beside the paper's consistency, with the noise-predicted spread of
    per-experiment estimates (group of the paper's regression estimated, the rest fixed)."""
    rows = []
    w = np.asarray(batch.motor_velocity)
    m = np.asarray(batch.mask)
    med_w = [float(np.median(np.abs(w[j][m[j]]))) for j in range(len(sel))]
    pos_of = {orig: j for j, orig in enumerate(sel)}
    for k in est:
        group = [g for g in GROUPS.get(k, (k,)) if g in names]
        informing = None
        if paper is not None:
            informing = paper.experiment_indices.get(k)
        elif per_exp_est.get(k) is not None and len(per_exp_est[k]) == len(exps):
            informing = [i for i, v in enumerate(per_exp_est[k]) if v is not None and np.isfinite(v)]
        if informing is None:
            # the paper's classes: compliance from locked records; viscous/Coulomb/inertia from fast free
            # records; Stribeck from slow records (median |ω| < 5·Tss2) of either mode
            def cls(j):
                if k in ("K1", "Tst"):
                    return modes[j] == "constrained"
                slow = med_w[j] < 5.0 * Tss2
                return slow if k in ("Tssp1", "Tssn1") else (modes[j] == "free" and not slow)

            informing = [i for i in range(len(exps)) if i in pos_of and cls(pos_of[i])]
        js = [pos_of[i] for i in informing if i in pos_of and ok[pos_of[i]]]
        se_e = []
        for j in js:
            Fg = _sub_fisher(F_e[j], names, group)
            d = np.diag(Fg)
            if d[group.index(k)] <= 0:
                continue
            keep = [g for g, v in zip(group, d) if g == k or v > 1e-12 * d.max()]
            fsj = fisher_summary(_sub_fisher(F_e[j], names, keep), keep, n_directions=0)
            se_e.append(fsj["std_error"][k])
        se_e = [v for v in se_e if np.isfinite(v)]
        predicted = float(np.sqrt(np.mean(np.square(se_e)))) if se_e else None
        cons = consistency.get(k)
        cons = float(cons) if cons is not None and np.isfinite(cons) else None
        rel = fs_est["std_error"][k]
        if cons is None or predicted is None:
            agree, why = None, "no consistency figure (fewer than two experiments informed it)" if cons is None else "no experiment informs it"
        else:
            ratio = cons / predicted
            agree = bool(1.0 / _AGREE_FACTOR <= ratio <= _AGREE_FACTOR)
            if agree:
                why = "the spread of per-experiment estimates is what the measurement noise predicts"
            elif ratio > _AGREE_FACTOR:
                why = f"spread {ratio:.0f}× the noise prediction: not noise-limited (see the explanation)"
            else:
                why = (
                    f"spread {1 / ratio:.0f}× below the noise prediction: few experiments give a noisy std, or the "
                    "regression fixes parameters that the trajectory bound of its group leaves correlated"
                )
        rows.append(
            {
                "parameter": k,
                "relative_std_error": rel,
                "noise_predicted_spread": predicted,
                "consistency": cons,
                "experiments_informing": len(js),
                "agree": agree,
                "why": why,
            }
        )
    return rows


def _rms(a, b):
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


def _ablations(p, drive, batch, sens, ok, modes, files, opts, simulator):
    n = len(modes)
    lanes_idx = []
    for a, (key, _, mode, change) in enumerate(ABLATIONS):
        for j in range(n):
            if ok[j] and (opts["ablation_both_modes"] or modes[j] == mode):
                lanes_idx.append((a, j))
    if not lanes_idx:
        return {"changes": [], "note": "no experiment could be simulated"}, None
    sets = [change(p) for (_, _, _, change) in ABLATIONS]
    P = jax.tree.map(lambda *x: jnp.stack(x), *[sets[a] for a, _ in lanes_idx])
    idx = np.array([j for _, j in lanes_idx])
    lanes = take_experiments(batch, idx)
    tr = jax.block_until_ready(simulate_lanes(P, drive, lanes, simulator=simulator))
    succ = np.asarray(tr.success)
    mask = np.asarray(batch.mask)
    y_c = np.asarray(sens.outputs)
    meas = {"torque": np.asarray(batch.torque), "motor_velocity": np.asarray(batch.motor_velocity)}
    sim_lane = {"torque": np.asarray(tr.torque), "motor_velocity": np.asarray(tr.motor_velocity)}
    thr = float(opts["significant_increase"])
    changes = []
    for a, (key, label, paper_mode, _) in enumerate(ABLATIONS):
        per_mode = {}
        for mode in ("constrained", "free"):
            lane_ids = [li for li, (aa, j) in enumerate(lanes_idx) if aa == a and modes[j] == mode]
            if not lane_ids:
                continue
            good = [li for li in lane_ids if succ[li] and np.all(np.isfinite(sim_lane["torque"][li]))]
            bad = [files[lanes_idx[li][1]] for li in lane_ids if li not in good]
            entry = {"experiments": len(lane_ids), "failed": bad, "rms_complete": {}, "rms": {}, "rms_increase": {},
                     "nrmse_complete": {}, "nrmse": {}}
            for c, ch in enumerate(("torque", "motor_velocity")):
                if not good:
                    continue
                js = [lanes_idx[li][1] for li in good]
                m_all = np.concatenate([meas[ch][j][mask[j]] for j in js])
                c_all = np.concatenate([y_c[j, c][mask[j]] for j in js])
                s_all = np.concatenate([sim_lane[ch][li][mask[lanes_idx[li][1]]] for li in good])
                spread = float(np.sqrt(np.mean((m_all - m_all.mean()) ** 2)))
                rc, ra = _rms(c_all, m_all), _rms(s_all, m_all)
                entry["rms_complete"][ch] = rc
                entry["rms"][ch] = ra
                entry["rms_increase"][ch] = ra / rc - 1.0 if rc > 0 else None
                entry["nrmse_complete"][ch] = rc / spread if spread > 0 else None
                entry["nrmse"][ch] = ra / spread if spread > 0 else None
            incs = [v for v in entry["rms_increase"].values() if v is not None]
            entry["matters"] = bool(incs and max(incs) > thr) if good else None
            per_mode[mode] = entry
        changes.append({"change": key, "label": label, "paper_mode": paper_mode, "per_mode": per_mode})
    conclusions = _ablation_conclusions(changes, thr, p, drive, batch, modes)
    traj = {"lanes": lanes_idx, "torque": sim_lane["torque"], "motor_velocity": sim_lane["motor_velocity"], "success": succ}
    return {
        "definition": (
            "RMS(simulated − measured) pooled over the mode's experiments, per channel, for the complete model and "
            "each change; rms_increase = RMS_changed / RMS_complete − 1; nrmse divides by RMS(measured − mean). "
            f"A change `matters` in a mode when an RMS increase exceeds {thr:g}."
        ),
        "changes": changes,
        "conclusions": conclusions,
    }, traj


def _ablation_conclusions(changes, thr, p, drive, batch, modes) -> dict:
    by = {c["change"]: c for c in changes}

    def inc(key, mode):
        e = by.get(key, {}).get("per_mode", {}).get(mode)
        if not e or not e["rms_increase"]:
            return None
        return max(v for v in e["rms_increase"].values() if v is not None)

    def matters(key, mode):
        e = by.get(key, {}).get("per_mode", {}).get(mode)
        return None if not e else e.get("matters")

    friction_free = [matters(k, "free") for k in ("coulomb_zero", "viscous_zero")]
    compliance_cons = [matters(k, "constrained") for k in ("K1_div10", "Tst_zero")]
    lines = []
    for key, label, paper_mode in (("coulomb_zero", "Coulomb friction", "free"), ("viscous_zero", "viscous friction", "free"),
                                   ("K1_div10", "stiffness K1", "constrained"), ("Tst_zero", "structural damping Tst", "constrained")):
        other = "constrained" if paper_mode == "free" else "free"
        a, b = inc(key, paper_mode), inc(key, other)
        s = f"{label}: RMS +{100 * a:.0f} % in {paper_mode} motion" if a is not None else f"{label}: not simulated in {paper_mode} motion"
        if b is not None:
            s += f", +{100 * b:.0f} % in {other} motion"
        lines.append(s)
    reproduced_free = all(v is True for v in friction_free)
    reproduced_cons = all(v is True for v in compliance_cons)
    differences = []
    N = float(drive.gear_ratio)
    w = np.asarray(batch.motor_velocity)
    m = np.asarray(batch.mask)
    cons = [j for j, md in enumerate(modes) if md == "constrained"]
    w_rms = float(np.sqrt(np.mean(np.concatenate([w[j][m[j]] for j in cons]) ** 2))) if cons else 0.0
    reflected = {
        "coulomb_zero": N * 0.5 * (abs(float(p.Tsp)) + abs(float(p.Tsn))),
        "viscous_zero": N * 0.5 * (abs(float(p.Tvp)) + abs(float(p.Tvn))) * w_rms,
    }
    for key, label in (("coulomb_zero", "Coulomb"), ("viscous_zero", "viscous")):
        if matters(key, "constrained"):
            extra = (f" (RMS wave-generator velocity in the locked tests {w_rms:.3g} rad/s)" if key == "viscous_zero" else "")
            differences.append(
                f"{label} friction also matters with the output locked, which the paper did not test: with θo ≡ 0 the "
                f"motor torque balance gives T = N·(Km·i − Tf − Jeff·ω̇), so the friction appears in the transmitted "
                f"torque multiplied by the gear ratio N = {N:g}: ≈ {reflected[key]:.3g} N·m{extra}, large against the "
                "torque noise; the locked records therefore carry friction information too"
            )
    for key, label, why in (
        ("K1_div10", "K1", "it sets the load resonance"),
        ("Tst_zero", "Tst", "without structural damping the free load's torsional mode rings undamped at every "
         "current step"),
    ):
        if matters(key, "free"):
            differences.append(f"{label} also matters in free motion on these records ({why})")
    for key, label in (("K1_div10", "K1"), ("Tst_zero", "Tst")):
        if matters(key, "free") is False:
            # `matters` is False only where the increase was measured, so `inc` is not None
            differences.append(f"{label} barely matters in free motion (RMS +{100 * inc(key, 'free'):.2g} %), as in the paper")  # pyright: ignore[reportOperatorIssue]
    return {
        "paper": "Coulomb and viscous friction matter in free motion; K1 and Tst in constrained motion.",
        "free_motion_friction_reproduced": reproduced_free,
        "constrained_motion_compliance_reproduced": reproduced_cons,
        "summary": lines,
        "differences": differences,
    }


def _velocity_stats(batch, modes, Tss2):
    w = np.asarray(batch.motor_velocity)
    m = np.asarray(batch.mask)
    out = {}
    for mode in ("constrained", "free"):
        js = [j for j, md in enumerate(modes) if md == mode]
        if not js:
            continue
        v = np.concatenate([w[j][m[j]] for j in js])
        out[mode] = {
            "slow_positive": int(np.sum((v > 0) & (v < 3 * Tss2))),
            "slow_negative": int(np.sum((v < 0) & (v > -3 * Tss2))),
            "fast_positive": int(np.sum(v >= 3 * Tss2)),
            "fast_negative": int(np.sum(v <= -3 * Tss2)),
        }
    return out


def _record_features(w: np.ndarray, current: np.ndarray, Tss2: float) -> dict:
    """What an experiment does at the wave generator: velocity bands, reversals, current level."""
    n = max(len(w), 1)
    return {
        "median_abs_velocity": float(np.median(np.abs(w))),
        "share_slow_positive": float(np.sum((w > 0) & (w < 3 * Tss2)) / n),
        "share_slow_negative": float(np.sum((w < 0) & (w > -3 * Tss2)) / n),
        "velocity_reversals": int(np.sum(np.diff(np.sign(w[np.abs(w) > 1e-9])) != 0)),
        "rms_current": float(np.sqrt(np.mean(current**2))),
    }


def _advice(F, F_e, ok, names, est, fs_est, files, modes, batch, p) -> dict:
    """Rank the experiments by information on each parameter; for the worst-determined estimated
    parameter, which kind of record carries its information (per record, by class), which single
    record adds most when repeated, and how many such repeats would halve its standard error."""
    info = np.sqrt(np.clip(np.einsum("ekk->ek", F_e), 0, None))
    ranking = {}
    for k, name in enumerate(names):
        order = [j for j in np.argsort(-info[:, k]) if ok[j]]
        ranking[name] = [{"file": files[j], "mode": modes[j], "information": float(info[j, k])} for j in order]
    se = {k: v for k, v in fs_est["std_error"].items() if np.isfinite(v)}
    undetermined = [k for k, v in fs_est["std_error"].items() if not np.isfinite(v)]
    worst = max(se, key=se.__getitem__) if se else None
    result = {"ranking": ranking, "undetermined": undetermined}
    if worst is None:
        return result
    k = names.index(worst)
    cand = [j for j in range(len(files)) if ok[j]]
    after, best, repeats = _best_repeat(F, F_e, cand, names, est, worst, se[worst])
    Tss2 = float(p.Tss2)
    feats, per_class, best_class_of = _information_by_class(info, k, cand, modes, batch, Tss2)
    fb = feats[best]
    vs = _velocity_stats(batch, modes, Tss2)
    what = _what_helps(worst, info, cand, names, est, vs, per_class, best_class_of, best, fb, Tss2)
    result.update(
        {
            "worst_determined": {
                "parameter": worst,
                "relative_std_error": se[worst],
                "information_by_record_class": per_class,
            },
            "best_repeat": {
                "file": files[best],
                "mode": modes[best],
                "features": fb,
                "relative_std_error_after": after[best],
                "repeats_to_halve_std_error": repeats,
            },
            "velocity_samples": vs,
            "suggestion": (
                f"{worst} is the worst-determined estimated parameter (noise-only relative SE {100 * se[worst]:.3g} %). "
                f"Most informative records: {', '.join(r['file'] for r in ranking[worst][:3])}; per record, "
                + ", ".join(f"{c} {v['mean_information']:.3g} ({v['records']} records)" for c, v in per_class.items())
                + f". {what}. The best single record to repeat is {files[best]} ({modes[best]}, median |ω| "
                f"{fb['median_abs_velocity']:.3g} rad/s, {100 * fb['share_slow_positive']:.0f} % / "
                f"{100 * fb['share_slow_negative']:.0f} % of samples slow positive / negative, {fb['velocity_reversals']} "
                f"velocity reversals, RMS current {fb['rms_current']:.3g} A): one repeat brings the SE to "
                f"{100 * after[best]:.3g} %"
                + (f", {repeats} repeats would halve it" if repeats else ", and over 128 repeats would be needed to halve it")
                + " (from the Fisher information)."
            ),
        }
    )
    return result


def _best_repeat(F, F_e, cand, names, est, worst, se_worst):
    """The relative SE of `worst` after adding each candidate record once (position → SE), the
    record that lowers it most, and how many repeats of that record halve `se_worst` (None: over 128)."""
    Fe = _sub_fisher(F, names, est)

    def se_with(extra, m=1):
        return fisher_summary(Fe + m * _sub_fisher(extra, names, est), est, n_directions=0)["std_error"][worst]

    after = {j: se_with(F_e[j]) for j in cand}
    best = min(after, key=after.__getitem__)
    repeats = None
    for m in (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128):
        if se_with(F_e[best], m) <= 0.5 * se_worst:
            repeats = m
            break
    return after, best, repeats


def _information_by_class(info, k, cand, modes, batch, Tss2):
    """Each record's features (`_record_features`, Tss2 in rad/s), and the information on
    parameter `k` per record class as in the paper (locked; free low-velocity, median |ω| < 5·Tss2;
    free high-velocity), with each candidate's class."""
    w = np.asarray(batch.motor_velocity)
    cur = np.asarray(batch.current)
    mask = np.asarray(batch.mask)
    feats = [_record_features(w[j][mask[j]], cur[j][mask[j]], Tss2) for j in range(len(modes))]
    # record classes as in the paper: locked; free low-velocity (median |ω| < 5·Tss2); free high-velocity
    classes = {}
    for j in cand:
        c = modes[j] if modes[j] == "constrained" else (
            "free, slow (median |ω| < 5·Tss2)" if feats[j]["median_abs_velocity"] < 5 * Tss2 else "free, fast")
        classes.setdefault(c, []).append(j)
    per_class = {c: {"records": len(js), "mean_information": float(np.mean(info[js, k])),
                     "share_of_information": float(np.sum(info[js, k] ** 2) / max(np.sum(info[cand, k] ** 2), 1e-300))}
                 for c, js in classes.items()}
    best_class_of = {j: c for c, js in classes.items() for j in js}
    return feats, per_class, best_class_of


def _what_helps(worst, info, cand, names, est, vs, per_class, best_class_of, best, fb, Tss2) -> str:
    """The sentence on what to record for `worst`: for a Stribeck amplitude, whether its direction
    lacks slow samples (|ω| < 3·Tss2, rad/s) or the parameter just moves the outputs little; else
    the record class that informs it most per record."""
    k = names.index(worst)
    others = float(np.median([np.median(info[cand, names.index(q)]) for q in est if q != worst]))
    direction = {"Tssp1": "positive", "Tvp": "positive", "Tsp": "positive",
                 "Tssn1": "negative", "Tvn": "negative", "Tsn": "negative"}.get(worst)
    slow_pos = sum(v["slow_positive"] for v in vs.values())
    slow_neg = sum(v["slow_negative"] for v in vs.values())
    if worst in ("Tssp1", "Tssn1"):
        mine, other = (slow_pos, slow_neg) if direction == "positive" else (slow_neg, slow_pos)
        lacking = mine < other
        what = (
            f"Stribeck information comes from time spent at 0 < {'ω' if direction == 'positive' else '−ω'} < 3·Tss2 "
            f"= {3 * Tss2:.2g} rad/s: the campaign has {mine} such samples against {other} in the other direction"
            + (", so the direction lacks data: add slow runs in it (a current just above breakaway, "
               "|Km·i| ≈ Coulomb + |Stribeck| level, so the wave generator creeps for most of the record)"
               if lacking else
               "; the direction does not lack samples, the parameter simply moves the outputs little (its "
               f"median information per record is {others / max(float(np.median(info[cand, k])), 1e-300):.0f}× below "
               "the median of the other estimated parameters), so what "
               "helps is records that dwell at low speed with many velocity reversals under load, like the best one "
               f"below ({fb['velocity_reversals']} reversals, {100 * (fb['share_slow_positive'] + fb['share_slow_negative']):.0f} % "
               f"of its samples within ±3·Tss2; its information is {info[best, k] / per_class[best_class_of[best]]['mean_information']:.1f}× "
               "the mean of its class)")
        )
    else:
        top = max(per_class, key=lambda c: per_class[c]["mean_information"])
        what = f"Add records of the class that informs it most per record ({top})"
    return what


# ----------------------------------------------------------------------------------------------
# Figures and report
# ----------------------------------------------------------------------------------------------


def _typical(info, ok, modes) -> dict:
    """Per mode, the experiment with the median total information (a typical record)."""
    tot = np.sqrt(np.sum(info**2, axis=0))
    out = {}
    for mode in ("constrained", "free"):
        js = [j for j, m in enumerate(modes) if m == mode and ok[j]]
        if js:
            js = sorted(js, key=lambda j: tot[j])
            out[mode] = js[len(js) // 2]
    return out


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
          f"'agree' = consistency within a factor {_AGREE_FACTOR:g} of it.", ""]
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
