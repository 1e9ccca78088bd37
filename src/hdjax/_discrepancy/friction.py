r"""Diagnosis of friction-only data: which extension of eq. 9 explains what it misses, by how much
on data the fit never saw.

Cross-validation folds (`friction_folds`): with one record, `N_BLOCKS` contiguous time blocks
(fit on the others, test on the held one); with several, leave-experiments-out, the experiments
dealt round-robin into at most `MAX_FOLDS` groups. Every sample is tested exactly once, so the
held-out predictions of all folds make one held-out record.

Greedy forward selection (`diagnose_friction`, through the dynamic diagnosis's own
`hdjax._discrepancy.significance.forward_selection`): starting from eq. 9, each applicable candidate of
`CANDIDATES` is added to the current model and refitted on every fold (all eq. 9 parameters free
too, started from the current fold fit). A candidate is *significant* under `hdjax._discrepancy.significance.FRICTION_RULES`
(the rules' type is shared with the dynamic diagnosis): the held-out RMS falls by at least
`min_gain` (relative) and the held-out error falls in every fold (all but one with 5 folds).
The best significant candidate is accepted and the loop repeats on the rest.

Start values are cheap linear least squares on the current fold residual: harmonic orders
(cycles per turn of `position`, greedy over 1 … `max_order`) for the two periodic candidates,
a grid of presliding distances (the model's own Dahl state, `presliding_state`, with eq. 9's
regressors refitted linearly with the state replacing sign), a grid of time constants for thermal drift.
"""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._fit.friction import (
    HARMONIC_FIELDS,
    SLOT,
    FrictionProblem,
    RowFit,
    Rows,
    rms_stats,
    vector_to_params,
)
from .._model.effects import PRESLIDING_DISTANCE
from .._model.friction_only import HARMONIC_SLOTS, FrictionParameters, FrictionStructure, presliding_state
from .._model.paper import Smoothing, friction_basis, friction_parts
from .._model.smooth import smooth_sign, smooth_step
from .significance import FRICTION_RULES, Significance, drift_untestable, forward_selection

MAX_FOLDS = 5
N_BLOCKS = 5
CANDIDATES = ("position_dependent_friction", "position_dependent_torque", "presliding_friction", "thermal_drift")
MIN_REVERSALS = 4  # velocity reversals a record set needs before presliding can be tested


def friction_folds(problem: FrictionProblem, *, n_blocks: int = N_BLOCKS, max_folds: int = MAX_FOLDS) -> Rows:
    """Cross-validation rows: contiguous time blocks of a single record, else experiments dealt
    round-robin into at most `max_folds` held-out groups."""
    mask, E = problem.mask, problem.E
    train, test, labels = [], [], []
    if E == 1:
        n = int(mask[0].sum())
        edges = np.linspace(0, n, n_blocks + 1).round().astype(int)
        t = np.asarray(problem.data.time[0])
        for k in range(n_blocks):
            block = np.zeros_like(mask)
            block[0, edges[k]:edges[k + 1]] = True
            block &= mask
            train.append(mask & ~block), test.append(block)
            labels.append(f"block {k + 1}/{n_blocks} ({t[edges[k]]:.3g}–{t[edges[k + 1] - 1]:.3g} s)")
    else:
        F = min(E, max_folds)
        group = np.arange(E) % F
        for f in range(F):
            sel = (group == f)[:, None]
            train.append(mask & ~sel), test.append(mask & sel)
            labels.append("hold out " + ", ".join(problem.files[e] for e in range(E) if group[e] == f))
    return Rows(np.stack(train).astype(float), np.stack(test).astype(float), labels, np.ones(len(labels), bool))


# ---------------------------------------------------------------------------------------------- start values


def _lstsq_gain(A, r):
    c, *_ = np.linalg.lstsq(A, r, rcond=None)
    return c, float(np.sum((r - A @ c) ** 2))


def choose_orders(problem: FrictionProblem, theta, r, g, on, *, max_order: int, min_drop: float = 0.1):
    """Greedy harmonic orders of `Σ g·(a sin kθ + b cos kθ)` explaining residual `r` on samples `on`:
    up to `HARMONIC_SLOTS` orders, each kept only if it cuts the residual sum of squares by `min_drop`."""
    th, rr, gg = theta[on], r[on], g[on]
    sse0 = float(np.sum(rr**2))
    cols, orders, coef = [], [], None
    for _ in range(HARMONIC_SLOTS):
        best = (sse0, None, None)
        for k in range(1, max_order + 1):
            if k in orders:
                continue
            A = np.stack(cols + [gg * np.sin(k * th), gg * np.cos(k * th)], 1)
            c, sse = _lstsq_gain(A, rr)
            if sse < best[0]:
                best = (sse, k, c)
        if best[1] is None or best[0] > (1 - min_drop) * sse0:
            break
        k = best[1]
        cols += [gg * np.sin(k * th), gg * np.cos(k * th)]
        orders.append(k)
        coef, sse0 = best[2], best[0]
    return orders, coef


def presliding_states(v, t, delta, smoothing: Smoothing) -> np.ndarray:
    """`hdjax.presliding_state` for every record `v`, `t` (experiment, time) and every presliding
    distance of `delta` (grid,): shape (grid, experiment, time)."""
    return np.asarray(_presliding_states(jnp.asarray(v), jnp.asarray(t), jnp.asarray(delta, dtype=float), smoothing))


@eqx.filter_jit
def _presliding_states(v, t, delta, smoothing):
    per_record = jax.vmap(presliding_state, in_axes=(0, 0, None, None))
    return jax.vmap(per_record, in_axes=(None, None, 0, None))(v, t, delta, smoothing)


@dataclasses.dataclass(eq=False)
class _Fold:
    x: np.ndarray
    tie: int
    free: np.ndarray
    structure: FrictionStructure


def _max_order(problem: FrictionProblem) -> int:
    """Highest order resolvable: at least 8 samples per period at the fastest position step."""
    th = np.asarray(problem.data.position)
    steps = np.abs(np.diff(th, axis=1))[problem.mask[:, 1:]]
    dmax = float(np.quantile(steps, 0.99)) if steps.size else 0.0
    return int(max(1, min(40, math.floor(2 * np.pi / 8 / max(dmax, 1e-12)))))


def _reversals(problem: FrictionProblem) -> int:
    thr = 3.0 * problem.smoothing.velocity_scale
    n = 0
    for e in range(problem.E):
        v = problem.v[e][problem.mask[e]]
        d = np.sign(v[np.abs(v) > thr])
        n += int(np.sum(d[1:] != d[:-1]))
    return n


def applicable(problem: FrictionProblem) -> dict[str, str | None]:
    """`None` for candidates the data can test, else why not."""
    has_pos = bool(np.all(np.asarray(problem.data.has_position) > 0))
    span = [float(np.ptp(np.asarray(problem.data.position)[e][problem.mask[e]])) for e in range(problem.E)]
    why_pos = None if has_pos else "no `position` column in every record"
    if has_pos and max(span) <= 0:
        why_pos = "position never changes"
    rev = _reversals(problem)
    return {
        "position_dependent_friction": why_pos,
        "position_dependent_torque": why_pos,
        "presliding_friction": None if rev >= MIN_REVERSALS else
        f"only {rev} velocity reversals (need {MIN_REVERSALS}): presliding memory shows only where velocity changes sign",
        "thermal_drift": drift_untestable(np.asarray(problem.data.start_time)),
    }


def _add(problem: FrictionProblem, fold: _Fold, name: str, w: np.ndarray, pred: np.ndarray, max_order: int) -> _Fold:
    """`fold` with candidate `name` switched on and its start values from the training residual."""
    x, free, st = fold.x.copy(), fold.free.copy(), fold.structure
    idx = np.asarray(problem.index)
    on = (w[:, idx] > 0) & problem.mask[:, idx]
    r = (problem.T - pred)[:, idx]
    theta = np.asarray(problem.data.position)[:, idx]
    v = problem.v[:, idx]
    scale = np.asarray(problem.scale)
    if name in ("position_dependent_friction", "position_dependent_torque"):
        p = fold_params(problem, fold)
        if name == "position_dependent_friction":
            g = np.asarray(friction_parts(p.law, v, problem.smoothing)[1])  # the Coulomb part it modulates
        else:
            g = np.ones_like(v)
        orders, coef = choose_orders(problem, theta, r, g, on, max_order=max_order)
        if coef is None:  # no order kept (`coef` is None exactly when `orders` is empty)
            orders, coef = [1], _lstsq_gain(np.stack([g[on] * np.sin(theta[on]), g[on] * np.cos(theta[on])], 1), r[on])[0]
        o = np.zeros(HARMONIC_SLOTS)
        o[: len(orders)] = orders
        sl_s, sl_c = (SLOT[k] for k in HARMONIC_FIELDS[name])
        cs, cc = np.zeros(HARMONIC_SLOTS), np.zeros(HARMONIC_SLOTS)
        cs[: len(orders)], cc[: len(orders)] = coef[0::2], coef[1::2]
        x[sl_s], x[sl_c] = cs / scale[sl_s], cc / scale[sl_c]
        free[sl_s] = free[sl_c] = o > 0
        if name == "position_dependent_friction":
            st = FrictionStructure(ripple_orders=o, torque_orders=st.torque_orders, presliding=st.presliding, thermal=st.thermal)
        else:
            st = FrictionStructure(ripple_orders=st.ripple_orders, torque_orders=o, presliding=st.presliding,
                                   thermal=st.thermal)
    elif name == "presliding_friction":
        x[SLOT["presliding_friction.presliding_scale"]] = np.log(_start_delta(problem, fold, w) / PRESLIDING_DISTANCE)
        free[SLOT["presliding_friction.presliding_scale"]] = True
        st = FrictionStructure(ripple_orders=st.ripple_orders, torque_orders=st.torque_orders, presliding=1.0,
                               thermal=st.thermal)
    elif name == "thermal_drift":
        beta, tau = _start_thermal(problem, fold, r, on, idx)
        x[SLOT["thermal_drift.beta"]], x[SLOT["thermal_drift.tau"]] = beta / scale[SLOT["thermal_drift.beta"]], np.log(tau)
        free[SLOT["thermal_drift.beta"]] = free[SLOT["thermal_drift.tau"]] = True
        st = FrictionStructure(ripple_orders=st.ripple_orders, torque_orders=st.torque_orders,
                               presliding=st.presliding, thermal=1.0)
    return _Fold(x, fold.tie, free, st)


def fold_params(problem: FrictionProblem, fold: _Fold) -> FrictionParameters:
    """The fold's fitted parameters (its vector through the problem's parameterisation and tie)."""
    return vector_to_params(jnp.asarray(fold.x), problem.pmap, fold.tie)


def _start_delta(problem: FrictionProblem, fold: _Fold, w: np.ndarray) -> float:
    """Presliding distance (rad) from a grid: Dahl state replacing sign, eq. 9 refitted linearly."""
    p = fold_params(problem, fold)
    v, t = problem.v, np.asarray(problem.data.time)
    idx = np.asarray(problem.index)
    on = ((w > 0) & problem.mask)[:, idx]
    vabs = np.abs(v[problem.mask])
    h = float(np.median(np.diff(t[0])))
    dmin = max(float(np.quantile(vabs, 0.5)) * h, 1e-7)
    grid = dmin * np.geomspace(1.0, 1e3, 7)
    S = presliding_states(v, t, grid, problem.smoothing)[..., idx]  # (grid, E, n)
    vv = v[:, idx]
    y = problem.T[:, idx][on]
    vs = problem.smoothing.velocity_scale
    sign, step = smooth_sign(vv, vs), smooth_step(vv, vs)
    best, d_best = np.inf, grid[0]
    for g in range(len(grid)):
        direction = p.presliding_friction.direction(sign, step, S[g])  # the model's own blend (presliding = 1)
        A = np.asarray(friction_basis(vv, p.law.Tss2, problem.smoothing, direction=direction))[on]
        _, sse = _lstsq_gain(A, y)
        if sse < best:
            best, d_best = sse, grid[g]
    return float(d_best)


def _start_thermal(problem: FrictionProblem, fold: _Fold, r, on, idx) -> tuple[float, float]:
    """(beta, tau): viscous part × exp(−t_session/τ) regressed on the residual over a τ grid."""
    p = fold_params(problem, fold)
    v = problem.v[:, idx]
    ts = (np.asarray(problem.data.start_time)[:, None] + np.asarray(problem.data.time))[:, idx]
    visc = np.asarray(friction_parts(p.law, v, problem.smoothing)[0])
    span = max(float(np.ptp(ts[on])), 1e-6)
    t0 = float(np.min(ts[on]))
    best = (np.inf, 0.0, span)
    for tau in span * np.array([0.05, 0.15, 0.4, 1.0, 3.0]):
        a = (visc * np.exp(-(ts - t0) / tau))[on]
        c, sse = _lstsq_gain(a[:, None], r[on])
        if sse < best[0]:
            best = (sse, float(c[0]) * math.exp(t0 / tau) if t0 / tau < 700 else 0.0, float(tau))
    return best[1], best[2]


# ---------------------------------------------------------------------------------------------- CV fits


@dataclasses.dataclass(eq=False)
class CVResult:
    """Fold fits of one model: per-fold `_Fold`, pooled held-out prediction (experiment, time),
    held-out RMS / NRMSE over every sample, per-fold held-out mean squared error."""

    folds: list
    fit: RowFit
    heldout: np.ndarray
    rms: float
    nrmse: float
    fold_mse: np.ndarray
    converged: bool


def _cv_fit(problem: FrictionProblem, rows: Rows, folds: list) -> CVResult:
    fit = problem.solve(rows, [f.structure for f in folds], np.stack([f.x for f in folds]),
                        np.stack([f.free for f in folds]), np.array([f.tie for f in folds]))
    held = np.zeros_like(problem.T)
    mse = np.zeros(len(folds))
    for b in range(len(folds)):
        on = rows.test[b] > 0
        held[on] = fit.prediction[b][on]
        mse[b] = float(np.mean((fit.prediction[b] - problem.T)[on] ** 2))
    st = rms_stats(held, problem.T, problem.mask.astype(float))
    new = [_Fold(fit.x[b], f.tie, f.free, f.structure) for b, f in enumerate(folds)]
    return CVResult(new, fit, held, st["rms"], st["nrmse"], mse, bool(np.all(fit.converged)))


def cv_eq9(problem: FrictionProblem, rows: Rows) -> CVResult:
    """Eq. 9 alone on every fold."""
    folds = []
    for w in rows.train:
        tie = problem.tie_for(w)
        folds.append(_Fold(problem.start_eq9(w, tie), tie, problem.base_free(tie, w), FrictionStructure()))
    return _cv_fit(problem, rows, folds)


def _significant(before: CVResult, after: CVResult, rule: Significance) -> tuple[bool, float, float]:
    """(named?, held-out gain, share of folds improved) of `after` against `before` under `rule`."""
    gain = 1.0 - after.rms / before.rms
    improved = float((after.fold_mse < before.fold_mse).mean())
    return bool(gain >= rule.min_relative_gain and rule.consistent(improved)), float(gain), improved


@dataclasses.dataclass(eq=False)
class FrictionDiagnosis:
    """Result of `diagnose_friction`: fold rows, baseline and final CV fits, accepted findings
    (dicts), candidate scores per round, candidates not testable (name → why)."""

    rows: Rows
    baseline: CVResult
    final: CVResult
    findings: list
    rounds: list
    skipped: dict
    max_order: int


def diagnose_friction(problem: FrictionProblem, *, min_gain: float = FRICTION_RULES.min_relative_gain,
                      candidates=CANDIDATES, rows: Rows | None = None, physical_sign: bool = FRICTION_RULES.physical_sign,
                      log=print) -> FrictionDiagnosis:
    """Greedy cross-validated selection of friction extensions (module docstring), named under
    `FRICTION_RULES` with its effect size set to `min_gain`; with `physical_sign` a thermal drift
    only where every fold fits β > 0 (friction falls as the lubricant warms, SPEC §4)."""
    rule = dataclasses.replace(FRICTION_RULES, min_relative_gain=min_gain, physical_sign=physical_sign)
    rows = friction_folds(problem) if rows is None else rows
    why = applicable(problem)
    skipped = {c: why[c] for c in candidates if why[c] is not None}
    remaining = [c for c in candidates if why[c] is None]
    max_order = _max_order(problem)
    log(f"  eq. 9 on {len(rows.labels)} cross-validation folds")
    base = cv_eq9(problem, rows)
    current, findings = base, []

    def screen(pool: list[str]) -> dict[str, dict]:
        scores = {}
        for name in pool:
            folds = [_add(problem, f, name, rows.train[b], current.fit.prediction[b], max_order)
                     for b, f in enumerate(current.folds)]
            res = _cv_fit(problem, rows, folds)
            ok, gain, frac = _significant(current, res, rule)
            # friction falls as the lubricant warms (SPEC §4): a drift fitted the other way is no thermal drift
            physical = name != "thermal_drift" or all(float(fold_params(problem, f).thermal_drift.beta) > 0 for f in res.folds)
            ok = ok and (physical or not rule.physical_sign)
            scores[name] = {"significant": ok, "gain": gain, "folds_improved": frac, "result": res}
            log(f"  + {name}: held-out RMS {current.rms:.4g} → {res.rms:.4g} N·m ({gain:+.1%}, better in {frac:.0%} of folds)"
                + ("" if physical else ", fitted with friction rising over the session (β < 0)"))
        return scores

    def accept(best: str, scores: dict[str, dict]) -> None:
        nonlocal current
        s = scores[best]
        findings.append({"effect": best, "before": current, "after": s["result"], "relative_reduction": s["gain"],
                         "folds_improved": s["folds_improved"]})
        current = s["result"]

    # later rounds retest only candidates that lowered the held-out error in the round before
    scored = forward_selection(remaining, screen, accept, retest=lambda s: s["gain"] > 0)
    rounds = [{k: {"significant": v["significant"], "relative_reduction": v["gain"], "folds_improved": v["folds_improved"],
                   "heldout_rms": v["result"].rms} for k, v in scores.items()} for scores in scored]
    return FrictionDiagnosis(rows, base, current, findings, rounds, skipped, max_order)
