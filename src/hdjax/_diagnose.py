r"""The discrepancy loop: what the fitted paper model gets wrong, which SPEC §4 effect explains it,
and how much an extended model gains on experiments held out of its fit.

Method (one JIT-compiled Jacobian per round, real simulations for every held-out figure):

1. Base model: the paper's identification, refined by a few trajectory-error LM steps.
2. Evidence from residuals: order spectra against the simulated wave-generator angle θm (cycles
   per turn) for torque, velocity and output position, split locked/free, and correlations of the
   residuals with torsion, torsion³, |T|·sign(ω), di/dt and session time.
3. Candidates: every effect of `hdjax._effects` as a term inside the plant, all switched on at
   zero magnitude (which leaves the simulation equal to the base model). A forward-mode Jacobian
   of the noise-weighted residuals of all experiments w.r.t. the base parameters *and* every
   candidate's parameters gives, for each candidate, a Gauss–Newton step fitted on one half of
   the experiments (base parameters held at their fit on all experiments; on acceptance, base and
   effect parameters are re-fitted jointly, so an effect cannot hide in K1 or the friction); the
   extended model is then *simulated* on the other half, and vice versa (2-fold
   cross-validation by experiment).
4. A finding needs a held-out reduction of the weighted squared error in both folds, above 3 %
   overall and far beyond the chance level of its parameter count. Greedy: the best finding is
   added to the model and the loop repeats (up to `max_findings`).

Look-alikes (kinematic error, strain-gauge ripple, cogging, position-dependent friction are all
periodic in θm) are told apart by their held-out gains: each predicts a different pattern across
torque, velocity and output position and between locked and free tests, so the wrong one does not
transfer to held-out experiments as well as the right one.
"""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from ._effects import EFFECT_NAMES, MAX_ORDER, PERIODIC, Effects
from ._experiment import Experiment, stack_experiments
from ._fit import DEFAULT_FREE, ParameterMap, experiment_residuals, make_parameter_map, nrmse
from ._model import Drive, Parameters
from ._plant import Simulator, simulate_batch


@dataclasses.dataclass(frozen=True)
class _Column:
    effect: str
    field: str
    index: int | None
    scale: float
    start: float


def _effect_columns(name: str, orders, ctx: dict) -> list[_Column]:
    """Parameters of one candidate, each with a scale (unit of the fitted coefficient) and start."""
    if name in PERIODIC:
        scale = {
            "kinematic_error": ctx["torque_noise"] / ctx["K1"],
            "torque_sensor_ripple": ctx["torque_noise"],
            "cogging": ctx["coulomb"],
            "position_dependent_friction": 0.1,
        }[name]
        cols = []
        for k in orders:
            cols.append(_Column(name, f"{name}_sin", k - 1, scale, 0.0))
            cols.append(_Column(name, f"{name}_cos", k - 1, scale, 0.0))
        return cols
    tw = ctx["torsion"]
    return {
        "nonlinear_stiffness": [_Column(name, "K3", None, ctx["K1"] / tw**2, 0.0)],
        "lost_motion": [_Column(name, "backlash", None, 0.01 * tw, 1e-9)],
        "load_dependent_friction": [_Column(name, "mu", None, 0.1, 0.0)],
        "thermal_drift": [_Column(name, "beta", None, 1.0, 0.0)],
        "input_delay": [_Column(name, "delay", None, ctx["dt"], 0.0)],
        "rate_independent_hysteresis": [_Column(name, "Th", None, 0.03 * ctx["torque_max"], 0.0)],
    }[name]


def _apply(effects: Effects, cols: list[_Column], values) -> Effects:
    for c, v in zip(cols, values):
        if c.index is None:
            effects = eqx.tree_at(lambda e: getattr(e, c.field), effects, c.start + c.scale * v)
        else:
            arr = getattr(effects, c.field).at[c.index].set(c.start + c.scale * v)
            effects = eqx.tree_at(lambda e: getattr(e, c.field), effects, arr)
    return effects


def _fixed_effect_settings(ctx: dict) -> Effects:
    """Effects with the shape parameters that are not fitted set from the data: thermal time
    constant = half the session span, Dahl σ = 2 % of the largest torsion."""
    e = Effects()
    e = eqx.tree_at(lambda x: x.tau, e, jnp.asarray(max(ctx["session_span"] / 2.0, 60.0)))
    e = eqx.tree_at(lambda x: x.sigma, e, jnp.asarray(0.02 * ctx["torsion"]))
    return e


def _order_spectrum(res: np.ndarray, theta: np.ndarray):
    """Amplitude per order k = 1..MAX_ORDER of a least-squares fit of sin/cos(k θ) to `res`."""
    k = np.arange(1, MAX_ORDER + 1)
    A = np.concatenate([np.sin(np.outer(theta, k)), np.cos(np.outer(theta, k)), np.ones((len(theta), 1))], axis=1)
    coef, *_ = np.linalg.lstsq(A, res, rcond=None)
    return np.hypot(coef[:MAX_ORDER], coef[MAX_ORDER : 2 * MAX_ORDER])


@dataclasses.dataclass
class Diagnosis:
    findings: list
    unexplained: list
    baseline: dict
    evidence: dict
    params: Parameters
    effects: Effects
    rounds: list


def diagnose(
    p0: Parameters,
    drive: Drive,
    experiments: list[Experiment],
    *,
    start_times=None,
    candidates=EFFECT_NAMES,
    base_free=DEFAULT_FREE,
    base_steps: int = 5,
    max_findings: int = 3,
    min_relative_gain: float = 0.03,
    simulator: Simulator = Simulator(rtol=1e-6, atol=1e-8),
    log=lambda *_: None,
) -> Diagnosis:
    """Find the SPEC §4 effects that the data show beyond the paper's model (see module docstring).

    **Arguments:** `p0` start parameters (paper identification), `drive`, `experiments`
    (constrained/free), `candidates` effect names to consider, `base_free` base parameters re-fitted
    with every candidate, `base_steps` LM steps refining the base model, `max_findings`,
    `min_relative_gain` held-out threshold.

    **Returns:** a `Diagnosis` with findings (most important first), evidence and the extended model.
    """
    from ._fit import fit_parameters, noise_levels

    candidates = [c for c in candidates if c != "presliding_friction"]
    batch = stack_experiments(experiments)
    n_exp = len(experiments)
    sigma = noise_levels(batch)
    log(f"diagnose: refining the base model ({base_steps} LM steps on {n_exp} experiments)")
    base = fit_parameters(p0, drive, batch, free=base_free, simulator=simulator, max_steps=base_steps, sigma=sigma)
    p_base = base.params
    traj = jax.jit(lambda p, b: simulate_batch(p, drive, b, simulator=simulator))(p_base, batch)
    m = np.asarray(batch.mask)
    modes = np.where(np.asarray(batch.free) > 0, "free", "constrained")
    ctx = {
        "K1": float(p_base.K1),
        "coulomb": 0.5 * (abs(float(p_base.Tsp)) + abs(float(p_base.Tsn))),
        "torque_noise": float(sigma[0]),
        "torsion": float(np.max(np.abs(np.asarray(traj.torsion)[m]))) or 1e-3,
        "torque_max": float(np.max(np.abs(np.asarray(batch.torque)[m]))),
        "dt": float(batch.time[0, 1] - batch.time[0, 0]),
        "session_span": float(np.max(np.asarray(batch.start_time)) + np.max(np.asarray(batch.time))),
    }

    # evidence: residual spectra and covariate correlations
    evidence, orders = _evidence(batch, traj, m, modes, sigma)
    folds = np.arange(n_exp) % 2
    # make each fold hold both modes when possible
    for md in ("constrained", "free"):
        idx = np.where(modes == md)[0]
        folds[idx] = np.arange(len(idx)) % 2

    pmap = make_parameter_map(p_base, base_free)
    chosen: list[tuple[str, list[_Column]]] = []
    chosen_values: list[np.ndarray] = []
    findings, rounds = [], []
    eff_fixed = _fixed_effect_settings(ctx)
    remaining = list(candidates)
    current_p = p_base
    sse_full_before = None
    for rnd in range(max_findings):
        if not remaining:
            break
        cand_cols = {c: _effect_columns(c, orders, ctx) for c in remaining}
        chosen_cols = [col for _, cols in chosen for col in cols]
        all_cols = chosen_cols + [col for c in remaining for col in cand_cols[c]]
        active = frozenset([c for c, _ in chosen] + remaining)
        eff0 = dataclasses.replace(eff_fixed, active=active)
        v0 = np.concatenate(chosen_values + [np.zeros(len(cand_cols[c])) for c in remaining]) if all_cols else np.zeros(0)
        theta0 = pmap.to_theta(current_p)
        n_base = theta0.shape[0]
        log(f"diagnose: round {rnd + 1}: Jacobian w.r.t. {n_base} base + {len(all_cols)} effect parameters")

        def residuals(z, args):
            p_b, b, sig = args
            p = pmap.to_params(z[:n_base], p_b)
            e = _apply(eff0, all_cols, z[n_base:])
            return jax.vmap(lambda ex: experiment_residuals(p, drive, ex, sig, simulator, e))(b)

        z0 = jnp.concatenate([theta0, jnp.asarray(v0)])
        r0, J = eqx.filter_jit(lambda z, a: (residuals(z, a), jax.jacfwd(residuals)(z, a)))(z0, (current_p, batch, sigma))
        r0 = np.asarray(r0)  # (exp, 3, time)
        J = np.asarray(J)  # (exp, 3, time, params)

        def gn_step(cols_idx, train):
            if not cols_idx:
                return np.zeros(0)
            rows_r = r0[train].reshape(-1)
            rows_J = J[train][..., cols_idx].reshape(-1, len(cols_idx))
            JtJ = rows_J.T @ rows_J
            JtJ += 1e-9 * np.trace(JtJ) / max(len(cols_idx), 1) * np.eye(len(cols_idx))
            return -np.linalg.solve(JtJ, rows_J.T @ rows_r)

        def heldout_sse(name, cols_idx, eff_names, eff_cols):
            """Fit on one fold, simulate the other; returns (sse per fold, residual arrays)."""
            sse, res_all = [], np.zeros_like(r0)
            for f in (0, 1):
                train, test = folds != f, folds == f
                delta = gn_step(cols_idx, train)
                z = np.asarray(z0).copy()
                z[cols_idx] += delta
                p = pmap.to_params(jnp.asarray(z[:n_base]), current_p)
                e = _apply(dataclasses.replace(eff_fixed, active=frozenset(eff_names)), eff_cols, [z[n_base + all_cols.index(c)] for c in eff_cols])
                tb = stack_experiments([experiments[i] for i in np.where(test)[0]])
                r = np.asarray(_sim_residuals(p, drive, tb, sigma, simulator, e))
                res_all[test] = r[:, :, : r0.shape[2]] if r.shape[2] >= r0.shape[2] else np.pad(r, ((0, 0), (0, 0), (0, r0.shape[2] - r.shape[2])))
                sse.append(float(np.sum(r**2)))
            return np.array(sse), res_all

        # Fold fits move only the effect parameters (the base parameters stay at the fit on all
        # experiments): with few experiments per fold, re-fitting nine base parameters on half the
        # data is itself under-determined and its held-out error would swamp the effect's.
        base_idx = [n_base + all_cols.index(c) for c in chosen_cols]
        chosen_names = [c for c, _ in chosen]
        sse_before, res_before = heldout_sse(None, base_idx, chosen_names, chosen_cols)
        if sse_full_before is None:
            sse_full_before = (sse_before.copy(), res_before)
        scores = {}
        for c in remaining:
            idx = base_idx + [n_base + all_cols.index(col) for col in cand_cols[c]]
            sse_after, res_after = heldout_sse(c, idx, chosen_names + [c], chosen_cols + cand_cols[c])
            gain = 1.0 - sse_after.sum() / sse_before.sum()
            k = len(cand_cols[c])
            dchi = sse_before.sum() - sse_after.sum()
            significant = bool(np.all(sse_after < sse_before) and gain > min_relative_gain and dchi > 10.0 * k + 50.0)
            scores[c] = {"gain": float(gain), "fold_gains": (1 - sse_after / sse_before).tolist(), "significant": significant,
                         "delta_chi2": float(dchi), "k": k, "res_after": res_after}
            log(f"  {c:30s} held-out gain {gain:+.3f} (folds {np.round(1 - sse_after / sse_before, 3).tolist()})")
        rounds.append({c: {k_: v for k_, v in s.items() if k_ != "res_after"} for c, s in scores.items()})
        best = max(scores, key=lambda c: scores[c]["gain"])
        if not scores[best]["significant"]:
            break
        # accept: refit base and effect parameters on all experiments (one GN step) for the reported values
        idx = list(range(n_base)) + base_idx + [n_base + all_cols.index(col) for col in cand_cols[best]]
        delta = gn_step(idx, np.ones(n_exp, bool))
        z = np.asarray(z0).copy()
        z[idx] += delta
        current_p = pmap.to_params(jnp.asarray(z[:n_base]), current_p)
        chosen.append((best, cand_cols[best]))
        chosen_values = [np.array([z[n_base + all_cols.index(col)] for col in cols]) for _, cols in chosen]
        s = scores[best]
        before_n = _channel_nrmse(res_before, sigma, batch, m)
        after_n = _channel_nrmse(s["res_after"], sigma, batch, m)
        conf = float(1.0 - stats.chi2.sf(max(s["delta_chi2"], 0.0), s["k"])) if s["delta_chi2"] > 0 else 0.0
        findings.append({
            "effect": best,
            "confidence": round(conf, 4),
            "gain": {"heldout_nrmse_before": before_n, "heldout_nrmse_after": after_n,
                     "relative_reduction": s["gain"], "fold_reductions": s["fold_gains"],
                     "heldout_weighted_sse_reduction": s["delta_chi2"]},
            "_cols": cand_cols[best],
            "_round": len(rounds) - 1,
            "_values": chosen_values[-1],
        })
        remaining.remove(best)

    final_effects = dataclasses.replace(eff_fixed, active=frozenset(c for c, _ in chosen))
    for (name, cols), vals in zip(chosen, chosen_values):
        final_effects = _apply(final_effects, cols, vals)
    for f in findings:
        f["parameters"], f["orders"] = _describe(final_effects, f["effect"], f.pop("_cols"))
        f.pop("_values")
        f["evidence"] = _evidence_text(f["effect"], evidence, rounds[f.pop("_round")], f)
        if f["orders"] is None:
            f.pop("orders")
    base_n = _channel_nrmse(sse_full_before[1], sigma, batch, m) if sse_full_before else {}
    unexplained = []
    return Diagnosis(findings=findings, unexplained=unexplained, baseline={"heldout_nrmse": base_n},
                     evidence=evidence, params=current_p, effects=final_effects, rounds=rounds)


@eqx.filter_jit
def _sim_residuals(p, drive, batch, sigma, simulator, effects):
    return jax.vmap(lambda ex: experiment_residuals(p, drive, ex, sigma, simulator, effects))(batch)


def _channel_nrmse(res, sigma, batch, m) -> dict:
    """Pooled held-out NRMSE per channel from weighted residual arrays (exp, 3, time)."""
    out = {}
    for c, ch in enumerate(("torque", "motor_velocity")):
        meas = np.asarray(getattr(batch, ch))[m]
        err = (res[:, c, :] * float(sigma[c]))[m]
        out[ch] = float(np.sqrt(np.mean(err**2)) / np.std(meas))
    return out


def _evidence(batch, traj, m, modes, sigma):
    res_T = (np.asarray(traj.torque) - np.asarray(batch.torque))
    res_w = (np.asarray(traj.motor_velocity) - np.asarray(batch.motor_velocity))
    res_p = (np.asarray(traj.output_position) - np.asarray(batch.output_position))
    th = np.asarray(traj.motor_position)
    spectra = {}
    peaks = set()
    for md in ("constrained", "free"):
        sel = np.where(modes == md)[0]
        if not len(sel):
            continue
        for ch, res, sg in (("torque", res_T, sigma[0]), ("motor_velocity", res_w, sigma[1]), ("output_position", res_p, sigma[2])):
            if ch == "output_position" and md == "constrained":
                continue
            r = np.concatenate([res[i][m[i]] for i in sel])
            t = np.concatenate([th[i][m[i]] for i in sel])
            amp = _order_spectrum(r, t)
            spectra[f"{md}/{ch}"] = amp.tolist()
            n = len(r)
            noise_amp = 2.0 * float(sg) / math.sqrt(n)  # std of a fitted sin amplitude under white noise
            for k in np.where(amp > np.maximum(6.0 * noise_amp, 3.0 * np.median(amp)))[0]:
                peaks.add(int(k) + 1)
    orders = sorted(peaks)[:3] or [1, 2]
    cov = {}
    for md in ("constrained", "free"):
        sel = np.where(modes == md)[0]
        if not len(sel):
            continue
        tors = np.concatenate([np.asarray(traj.torsion[i])[m[i]] for i in sel])
        T = np.concatenate([np.asarray(traj.torque[i])[m[i]] for i in sel])
        w = np.concatenate([np.asarray(traj.motor_velocity[i])[m[i]] for i in sel])
        di = np.concatenate([np.gradient(np.asarray(batch.current[i])[m[i]]) for i in sel])
        ts = np.concatenate([np.full(int(m[i].sum()), float(batch.start_time[i])) + np.asarray(batch.time[i])[m[i]] for i in sel])
        rT = np.concatenate([res_T[i][m[i]] for i in sel])
        rw = np.concatenate([res_w[i][m[i]] for i in sel])
        covs = {"torsion": tors, "torsion^3": tors**3, "|T|sign(w)": np.abs(T) * np.sign(w), "di/dt": di, "session_time": ts}
        cov[md] = {}
        for name, x in covs.items():
            cov[md][name] = {ch: (float(np.corrcoef(x, r)[0, 1]) if np.std(x) > 0 and np.std(r) > 0 else 0.0)
                             for ch, r in (("torque", rT), ("motor_velocity", rw))}
    return {"order_spectra": spectra, "candidate_orders": orders, "correlations": cov}, orders


def _describe(effects: Effects, name: str, cols):
    if name in PERIODIC:
        orders = sorted({c.index + 1 for c in cols})
        k, amp, ph = effects.amplitudes(name)
        letter = {"kinematic_error": "a", "torque_sensor_ripple": "b", "cogging": "c", "position_dependent_friction": "eps"}[name]
        params = {}
        for o in orders:
            params[f"{letter}{o}"] = float(amp[o - 1])
            params[f"phi{o}"] = float(ph[o - 1])
        # report the orders that carry the effect (amplitude above 20 % of the largest)
        top = max(params[f"{letter}{o}"] for o in orders)
        orders = [o for o in orders if params[f"{letter}{o}"] >= 0.2 * top]
        return params, orders
    fields = {c.field for c in cols}
    params = {f: float(getattr(effects, f)) for f in fields}
    if name == "thermal_drift":
        params["tau"] = float(effects.tau)
    if name == "rate_independent_hysteresis":
        params["sigma"] = float(effects.sigma)
    return params, None


def _evidence_text(name, evidence, round_scores, finding) -> str:
    g = finding["gain"]
    txt = (f"adding {name} to the plant and re-fitting on half of the experiments reduces the weighted squared "
           f"error of the other half by {100 * g['relative_reduction']:.1f} % (folds: "
           f"{', '.join(f'{100 * x:.1f} %' for x in g['fold_reductions'])})")
    if name in PERIODIC:
        txt += f"; residual order spectra peak at orders {evidence['candidate_orders']} per wave-generator turn"
    others = sorted(((c, s["gain"]) for c, s in round_scores.items() if c != name), key=lambda x: -x[1])[:2]
    if others:
        txt += "; next best candidates: " + ", ".join(f"{c} ({100 * v:.1f} %)" for c, v in others)
    return txt
