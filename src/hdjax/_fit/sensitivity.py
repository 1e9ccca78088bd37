r"""The sensitivity analysis: which parameters matter where, and how well each is determined.
(The command's workflow, options, JSON sections and report: `hdjax._workflows.sensitivity`.)

1. **Normalised sensitivities** $S_k(t) = \partial y(t)/\partial\ln|p_k| = p_k\,\partial y/\partial p_k$
   of every output channel (torque, wave-generator velocity, output angle), every parameter and
   every experiment: `jax.jacfwd` through the diffrax solve (`Simulator.adjoint = ForwardMode()`),
   `vmap`ped over the stacked experiments, one `eqx.filter_jit` with the data as arguments.
   A unit of $\ln p$ is a relative change, so the eleven columns are directly comparable.
2. **Identifiability.** The noise-weighted residual Jacobian in $\ln p$ (the residual of
   `hdjax._fit.least_squares.experiment_residuals`: each channel divided by its noise level, the output angle
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

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._data.experiment import Experiment, take_experiments
from .._model.effects import Effects
from .._model.paper import PARAMETER_NAMES, Drive, Parameters
from .._plant.sharding import for_each_experiment
from .._plant.simulate import Simulator, Trajectory, is_fixed_cost, simulate
from .least_squares import CHANNELS, DEFAULT_FREE
from .parameterisation import Entry, Parameterisation

__all__ = [
    "ABLATIONS",
    "Sensitivities",
    "ablation_study",
    "compare_consistency",
    "design_advice",
    "fisher_per_experiment",
    "fisher_summary",
    "scaled_parameters",
    "sensitivities",
    "simulate_lanes",
    "sub_fisher",
    "typical_experiments",
    "weighted_jacobians",
]

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
AGREE_FACTOR = 3.0


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


def _sensitivity_one(p: Parameters, drive: Drive, exp: Experiment, simulator: Simulator, effects: Effects):
    def f(s):
        tr = simulate(scaled_parameters(p, s), drive, exp, simulator=simulator, effects=effects)
        y = jnp.stack([tr.torque, tr.motor_velocity, tr.output_position])
        return y, (y, tr.success, tr.num_steps)

    S, (y, ok, steps) = jax.jacfwd(f, has_aux=True)(jnp.zeros(len(PARAMETER_NAMES)))
    return Sensitivities(outputs=y, S=S, success=ok, num_steps=steps)


@eqx.filter_jit
def _sensitivities_jit(p, drive, batch, simulator, effects):
    # data enter as arguments, never as closed-over constants (which XLA would try to fold)
    return for_each_experiment(lambda e: _sensitivity_one(p, drive, e, simulator, effects), batch,
                               fixed_cost=is_fixed_cost(simulator))


def sensitivities(p: Parameters, drive: Drive, batch: Experiment, *, simulator: Simulator = Simulator(),
                  effects: Effects = Effects()) -> Sensitivities:
    """Forward-mode sensitivities ∂y/∂ln|p| of all channels of a stacked batch
    (`hdjax.stack_experiments`), by `jax.jacfwd` through the diffrax solve, `vmap`ped over the
    experiments, the plant carrying `effects` (held). `simulator.adjoint` must support forward mode
    (the default `ForwardMode()`)."""
    return _sensitivities_jit(p, drive, batch, simulator, effects)


@eqx.filter_jit
def _simulate_lanes_jit(P, drive, lanes, simulator, E):
    return for_each_experiment(lambda q, f, e: simulate(q, drive, e, simulator=simulator, effects=f), P, E, lanes,
                               fixed_cost=is_fixed_cost(simulator))


def simulate_lanes(P: Parameters, drive: Drive, lanes: Experiment, *, simulator: Simulator = Simulator(),
                   effects: Effects = Effects()) -> Trajectory:
    """Simulate lane `i` of a stacked batch `lanes` with parameter set `i` of the stacked `P` (each
    `Parameters` leaf with a leading lane axis), the plant carrying `effects`: many parameter sets in
    one `vmap`."""
    n = int(np.shape(lanes.time)[0])
    arrays, static = eqx.partition(effects, eqx.is_array)
    E = eqx.combine(jax.tree.map(lambda x: jnp.broadcast_to(x, (n, *jnp.shape(x))), arrays), static)
    return _simulate_lanes_jit(P, drive, lanes, simulator, E)


def _rigid_body_projector(t: np.ndarray) -> np.ndarray:
    """Orthonormal basis (2, n) of {1, t}: the output angle's rigid-body components."""
    b = np.stack([np.ones_like(t), t - t.mean()])
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def weighted_jacobians(S, outputs, batch: Experiment, sigma) -> tuple[list[np.ndarray], list[np.ndarray], list[dict]]:
    """Per experiment, the noise-weighted residual Jacobian in ln p and the weighted residual.

    Rows: the masked samples of torque / σ_T, motor velocity / σ_ω and, in free motion with a
    measured output angle, the output angle / σ_θ projected off its rigid-body components {1, t}
    (as in `hdjax._fit.least_squares.experiment_residuals`). Returns `(J_list, r_list, channel_rows)` where
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


def sub_fisher(F, names, sub):
    idx = [names.index(k) for k in sub]
    return F[np.ix_(idx, idx)]


# ----------------------------------------------------------------------------------------------
# Consistency against the Fisher prediction; the paper's section V study
# ----------------------------------------------------------------------------------------------


def fisher_per_experiment(Js, ok, P):
    """Per experiment the Fisher information JᵀJ in ln p (zero where the simulation failed), and
    the information √F_kk laid out (parameter, experiment)."""
    F_e = np.stack([J.T @ J if ok[j] else np.zeros((P, P)) for j, J in enumerate(Js)])
    info = np.sqrt(np.clip(np.einsum("ekk->ek", F_e), 0, None)).T  # (parameter, experiment)
    return F_e, info


def compare_consistency(F_e, ok, names, est, fs_est, consistency, per_exp_est, paper, sel, exps, modes, batch, Tss2) -> list[dict]:
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
            Fg = sub_fisher(F_e[j], names, group)
            d = np.diag(Fg)
            if d[group.index(k)] <= 0:
                continue
            keep = [g for g, v in zip(group, d) if g == k or v > 1e-12 * d.max()]
            fsj = fisher_summary(sub_fisher(F_e[j], names, keep), keep, n_directions=0)
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
            agree = bool(1.0 / AGREE_FACTOR <= ratio <= AGREE_FACTOR)
            if agree:
                why = "the spread of per-experiment estimates is what the measurement noise predicts"
            elif ratio > AGREE_FACTOR:
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


def ablation_study(p, drive, batch, sens, ok, modes, files, opts, simulator, effects=Effects()):
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
    # "Coulomb = 0" takes the breakaway torques (static dry friction above eq. 9's) with it: 0 = none
    dry_off = effects.with_values("breakaway_friction", breakaway_p=0.0, breakaway_n=0.0) \
        if "breakaway_friction" in effects.active else effects
    per_lane = [dry_off if ABLATIONS[a][0] == "coulomb_zero" else effects for a, _ in lanes_idx]
    E = jax.tree.map(lambda *x: jnp.stack([jnp.asarray(v) for v in x]), *per_lane)
    tr = jax.block_until_ready(_simulate_lanes_jit(P, drive, lanes, simulator, E))
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


def design_advice(F, F_e, ok, names, est, fs_est, files, modes, batch, p) -> dict:
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
    Fe = sub_fisher(F, names, est)

    def se_with(extra, m=1):
        return fisher_summary(Fe + m * sub_fisher(extra, names, est), est, n_directions=0)["std_error"][worst]

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
# Figures
# ----------------------------------------------------------------------------------------------


def typical_experiments(info, ok, modes) -> dict:
    """Per mode, the experiment with the median total information (a typical record)."""
    tot = np.sqrt(np.sum(info**2, axis=0))
    out = {}
    for mode in ("constrained", "free"):
        js = [j for j, m in enumerate(modes) if m == mode and ok[j]]
        if js:
            js = sorted(js, key=lambda j: tot[j])
            out[mode] = js[len(js) // 2]
    return out


