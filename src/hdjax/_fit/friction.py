r"""Fitting eq. 9 (and its extensions) to friction experiments with optimistix Levenberg–Marquardt.

One compiled fit serves everything: the parameter vector always holds eq. 9 and every extension
slot (`hdjax._model.friction_only.FrictionStructure` switches them on as data), and a *row* is one fit — a weight
per sample saying which samples it may see. Rows are `vmap`ped:

- full rows: the pooled fit on all samples, then one fit per experiment (per-experiment
  estimates and the paper's consistency, std/|mean|);
- held-out rows: a chronological split (first `train_fraction` of every record to fit, the rest
  to test), then leave-one-experiment-out folds (fit on the others, test on the held one);
- record rows: the chronological split pooled, then each record fitted alone on its own first part.

Each row has `E + 1` entries, so all calls share one shape and one compilation.

The vector is normalised (viscous by RMS torque / RMS velocity, torques by RMS torque, `Tss2`,
`thermal_drift.tau` through their logarithm, the presliding distance by its term's own log scale
`presliding_friction.presliding_scale`), residuals are divided by the RMS
torque. Directions without data (fewer than `MIN_DIRECTION_SAMPLES` samples beyond
3 × `Smoothing.velocity_scale`, or under 2 % of the moving samples) cannot be identified: their three
parameters are tied to the other direction's (a symmetric-friction assumption the report states).
Likewise the Stribeck part is a low-speed feature: it is fitted only when at least as many
training samples (the same count) lie below `STRIBECK_LOW` = 1/10 of the training samples' own
speed range (98th percentile of |ω|). Without them (a fit on steady high-speed samples alone)
the Stribeck amplitudes are held at zero and `Tss2` is not fitted: otherwise the fit bends a
steep exponential tail through the high-speed samples, and what it predicts at low speed is
unbounded (seen: 6e13 N·m on the held-out start-up block of a real velocity sweep).

Standard errors come from the block sandwich covariance that the dynamic fit uses
(`hdjax._fit.covariance.block_covariance`, blocks of `se_block` = 0.1 s of one record): real friction
residuals are far from white, and white-noise errors would be optimistic. With fewer than two
blocks per fitted parameter they are the Gauss–Newton ones, $s^2 (J^\top J)^{-1}$, inflated by
$n / n_{eff}$ with $n_{eff} = \sum_e n_e (1-\rho_e)/(1+\rho_e)$ from each record's lag-1
residual autocorrelation $\rho_e$ (the rule before 2026-11-28, which on independent-bench data
left the truth up to 32 standard errors away, against 3.9 for the block ones).
"""

import dataclasses
from typing import cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import scipy.signal

from .._data.experiment import FrictionExperiment, stack_experiments
from .._model.effects import PRESLIDING_DISTANCE, THERMAL_TAU, PositionDependentFriction, PositionDependentTorque
from .._model.friction_only import (
    FRICTION_NAMES,
    HARMONIC_SLOTS,
    FrictionParameters,
    FrictionStructure,
    friction_model_torque,
)
from .._model.paper import Smoothing, friction_basis
from .covariance import inflated_covariance, robust_covariance, standard_errors, time_blocks
from .lm import MarquardtLM
from .parameterisation import Entry, Parameterisation, parameterisation, slots, vector_size

M = HARMONIC_SLOTS
#: The fit's vector: eq. 9 (torques scaled, Tss2 on a log scale), the harmonic slots of the two
#: position terms (scaled), the presliding term's log distance scale, thermal β (scaled) and τ (log).
FRICTION_ENTRIES = (
    Entry("law.Tvp"), Entry("law.Tvn"), Entry("law.Tsp"), Entry("law.Tsn"), Entry("law.Tssp1"), Entry("law.Tssn1"),
    Entry("law.Tss2", transform="log"),
    Entry("position_dependent_friction.sin", M), Entry("position_dependent_friction.cos", M),
    Entry("position_dependent_torque.sin", M), Entry("position_dependent_torque.cos", M),
    Entry("presliding_friction.presliding_scale"), Entry("thermal_drift.beta"), Entry("thermal_drift.tau", transform="log"),
)  # fmt: skip
_PATH_SLOT = slots(FRICTION_ENTRIES)  # by field path ("law.Tvp", "position_dependent_friction.sin", ...)
#: Vector index / slice of each field, keyed by its name (the eq. 9 fields without their `law.` path).
SLOT = {k.removeprefix("law."): v for k, v in _PATH_SLOT.items()}
IDX = {k: v for k, v in SLOT.items() if isinstance(v, int)}  # the scalar fields' indices
N_PARAMS = vector_size(FRICTION_ENTRIES)
LOG_INDICES = [_PATH_SLOT[e.field] for e in FRICTION_ENTRIES if e.transform == "log"]
#: The (sin, cos) coefficient paths of each periodic extension.
HARMONIC_FIELDS = {name: (f"{name}.sin", f"{name}.cos") for name in ("position_dependent_friction", "position_dependent_torque")}
EQ9_SLOTS = [IDX[k] for k in FRICTION_NAMES]  # the eq. 9 part of the vector, in `FRICTION_NAMES` order
MIN_DIRECTION_SAMPLES = 50
DENSE_BELOW = 10.0  # velocity scales below which every sample enters the fit (`FrictionProblem.index`)
MIN_DIRECTION_FRACTION = 0.02
STRIBECK_LOW = 0.1  # low speed, as a fraction of the training samples' 98th-percentile |ω| (Stribeck support)
TIE_NONE, TIE_NEG_TO_POS, TIE_POS_TO_NEG = 0, 1, 2
RTOL, ATOL, XTOL = 1e-10, 1e-14, 1e-9  # LM stopping: relative / absolute cost change, relative step


def _tied(p: FrictionParameters, tie) -> FrictionParameters:
    """`p` with one direction's eq. 9 parameters copied from the other (`TIE_NEG_TO_POS`: the
    negative direction takes the positive one's; `TIE_POS_TO_NEG`: the reverse)."""
    neg, pos = tie == TIE_NEG_TO_POS, tie == TIE_POS_TO_NEG
    q = p.law
    return eqx.tree_at(
        lambda m: (m.law.Tvp, m.law.Tvn, m.law.Tsp, m.law.Tsn, m.law.Tssp1, m.law.Tssn1), p,
        (jnp.where(pos, q.Tvn, q.Tvp), jnp.where(neg, q.Tvp, q.Tvn), jnp.where(pos, q.Tsn, q.Tsp),
         jnp.where(neg, q.Tsp, q.Tsn), jnp.where(pos, q.Tssn1, q.Tssp1), jnp.where(neg, q.Tssp1, q.Tssn1)))  # fmt: skip


def vector_to_params(x, pmap: Parameterisation, tie) -> FrictionParameters:
    """Normalised vector (`N_PARAMS`,) to `FrictionParameters` through the problem's
    parameterisation, applying a direction tie."""
    base = FrictionParameters(**dict.fromkeys(FRICTION_NAMES, 0.0))  # every fitted field is replaced
    return _tied(pmap.to_model(x, base), tie)


def predict(p: FrictionParameters, structure: FrictionStructure, data: FrictionExperiment, smoothing: Smoothing,
            at=None):
    """Model torque (N·m) on every record of a stacked batch, shape (experiment, time), or
    (experiment, sample) at the sample indices `at`."""

    def one(v, t, th, hp, st):
        return friction_model_torque(p, structure, v, time=t, position=th, has_position=hp, start_time=st,
                                     smoothing=smoothing, at=at)

    return jax.vmap(one)(data.velocity, data.time, data.position, data.has_position, data.start_time)


def _residual(x, x0, free, w, tie, data, structure, pmap, sigma, smoothing, index):
    p = vector_to_params(jnp.where(free, x, x0), pmap, tie)
    pred = predict(p, structure, data, smoothing, at=index)
    return (jnp.sqrt(w[:, index]) * (pred - data.friction_torque[:, index]) / sigma).ravel()


@eqx.filter_jit
def _solve(x0, free, w, tie, data, structure, pmap, sigma, smoothing, index, max_steps):
    """One row's fit: `optx.least_squares` with `MarquardtLM` (`hdjax._fit.lm`: Marquardt-scaled
    normal equations, a materialised forward-mode Jacobian, one model evaluation per step), which
    on these small problems is far cheaper per step than `optimistix.LevenbergMarquardt` (a
    6 000-sample record: residual 0.06 ms, 22-column Jacobian 0.5 ms, an optimistix LM step
    15 ms); stops at a relative cost change below `RTOL` or a step below `XTOL`. Parameters that
    are not free are held at `x0` (their Jacobian columns are zero). Returns (x, converged, steps).

    The rows are fitted one after the other (a Python loop): a `vmap`ped while-loop would run
    every row for as long as the slowest."""

    def residuals(x, args):
        return _residual(x, x0, free, w, tie, data, structure, pmap, sigma, smoothing, index)

    sol = optx.least_squares(residuals, MarquardtLM(rtol=RTOL, atol=ATOL, xtol=XTOL), x0, None,
                             max_steps=max_steps, throw=False)
    return sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]


@eqx.filter_jit
def _predict_row(x, tie, data, structure, pmap, smoothing):
    return predict(vector_to_params(x, pmap, tie), structure, data, smoothing)


@eqx.filter_jit
def _jacobian(x, free, w, tie, data, structure, pmap, sigma, smoothing, index):
    return jax.jacfwd(lambda x: _residual(x, x, free, w, tie, data, structure, pmap, sigma, smoothing, index))(x)


@dataclasses.dataclass(frozen=True, eq=False)
class Rows:
    """A batch of fits: `train` / `test` weights (row, experiment, time), labels, `valid` rows."""

    train: np.ndarray
    test: np.ndarray
    labels: list[str]
    valid: np.ndarray


@dataclasses.dataclass(eq=False)
class RowFit:
    """Fitted rows: normalised vectors `x`, ties, free masks, convergence, predictions (N·m)."""

    x: np.ndarray
    tie: np.ndarray
    free: np.ndarray
    converged: np.ndarray
    steps: np.ndarray
    prediction: np.ndarray
    structure: FrictionStructure
    structures: list

    def params(self, b: int, problem: "FrictionProblem") -> FrictionParameters:
        return vector_to_params(jnp.asarray(self.x[b]), problem.pmap, self.tie[b])


@dataclasses.dataclass(eq=False)
class FrictionProblem:
    """Friction experiments stacked for fitting, with the scales and options of the fit.

    **Arguments:** `experiments` (`FrictionExperiment` list), `files` (labels), `Tss2` (rad/s:
    fixed value, or `None` to fit it), `smoothing`, `max_steps` (LM steps per fit),
    `max_fit_samples`: the LM residual uses every `stride`-th sample so that at most this many
    enter a fit (the model, and the presliding state, still run through every sample; held-out
    errors use every sample). Neighbouring samples at 0.3–2 ms carry nearly the same information.
    Every sample slower than `DENSE_BELOW` velocity scales enters as well, weighted as itself
    while a strided sample stands for `stride` (`sample_weight`), so the fit's cost stays an
    estimate of the whole record's. With the stride alone, a Stribeck peak narrower than the
    velocity step between fitted samples could hide between them (Kinova joint 7, 2026-11-26:
    Tss2 fell to 6e-4 and 1e-131 rad/s, and eq. 9's whole-record RMS came out up to 1.8× that of
    its special case Coulomb + viscous, with 194 N·m errors at samples the fit did not see).
    A fit whose weighted squared error summed over all its training samples ends above its
    start's keeps its start (`solve`).

    The class stays long (about 240 lines) on purpose: its methods are short (the longest,
    `__post_init__`, about 35 lines) and all work on the same stacked arrays, scales and options,
    so splitting it would scatter one cohesive object.
    """

    experiments: list
    files: list[str]
    Tss2: float | None = None
    smoothing: Smoothing = Smoothing()
    max_steps: int = 100
    max_fit_samples: int = 6000
    se_block: float = 0.1

    def __post_init__(self):
        if not self.experiments:
            raise ValueError("`FrictionProblem`: no friction experiments given.")
        self.data = stack_experiments(self.experiments)
        self.mask = np.asarray(self.data.mask)
        self.v = np.asarray(self.data.velocity)
        self.T = np.asarray(self.data.friction_torque)
        vs = float(np.sqrt(np.mean(self.v[self.mask] ** 2)))
        ts = float(np.sqrt(np.mean(self.T[self.mask] ** 2)))
        if not vs > 0:
            raise ValueError(f"`FrictionProblem` ({', '.join(self.files)}): every velocity is zero; eq. 9 needs motion.")
        self.sigma = jnp.asarray(ts if ts > 0 else 1.0)  # an array: a Python float would be static under jit
        scale = np.ones(N_PARAMS)
        for k in ("Tvp", "Tvn"):
            scale[SLOT[k]] = self.sigma / vs
        for k in ("Tsp", "Tsn", "Tssp1", "Tssn1"):
            scale[SLOT[k]] = self.sigma
        # the periodic terms' coefficient units, from the terms themselves (friction-only context)
        ctx = {"torque_scale": float(self.sigma)}
        for term in (PositionDependentFriction, PositionDependentTorque):
            for k in HARMONIC_FIELDS[term.name]:
                scale[SLOT[k]] = term.amplitude_scale(ctx)
        self.pmap = parameterisation(FRICTION_ENTRIES, scale)  # log slots keep scale 1: value = exp(x)
        self.scale = self.pmap.scale
        self.E, self.N = self.mask.shape
        self.fs = sample_rates(self.data)
        self.stride = max(1, -(-self.E * self.N // int(self.max_fit_samples)))
        # every `stride`-th sample, and every sample where a record moves slower than
        # `DENSE_BELOW` velocity scales: a Stribeck peak no wider than that cannot hide between
        # the strided samples (see the class docstring)
        slow = (np.abs(self.v) < DENSE_BELOW * self.smoothing.velocity_scale) & self.mask
        strided = np.zeros(self.N, bool)
        strided[:: self.stride] = True
        self.index = jnp.asarray(np.flatnonzero(strided | slow.any(0)))
        # how many samples of the record each fitted sample stands for, so that the fit's cost
        # stays an estimate of the whole record's (a slow sample for itself, a strided one for
        # `stride`, one taken only for another record's sake for none); multiplies the row weights
        self.sample_weight = np.where(slow, 1.0, np.where(strided[None, :], float(self.stride), 0.0))

    def blocks(self) -> np.ndarray:
        """Block label of every sample (experiment, time) for the standard errors: `se_block`
        seconds of one record (`hdjax._fit.covariance.time_blocks`)."""
        return time_blocks(np.asarray(self.data.time), self.se_block)

    # ---------------------------------------------------------------- rows
    def _split(self, frac):
        first = np.zeros_like(self.mask)
        for e in range(self.E):
            n = int(self.mask[e].sum())
            first[e, : int(round(frac * n))] = True
        return first & self.mask, ~first & self.mask

    def rows_full(self) -> Rows:
        """Pooled fit on all samples, then one fit per experiment."""
        w = [self.mask] + [self.mask & (np.arange(self.E) == e)[:, None] for e in range(self.E)]
        w = np.stack(w).astype(float)
        return Rows(w, w.copy(), ["pooled"] + list(self.files), np.ones(self.E + 1, bool))

    def rows_heldout(self, train_fraction: float = 0.7) -> Rows:
        """Chronological split pooled over records, then leave-one-experiment-out folds."""
        first, last = self._split(train_fraction)
        train, test, labels = [first], [last], [f"first {train_fraction:.0%} → last {1 - train_fraction:.0%}"]
        for e in range(self.E):
            sel = (np.arange(self.E) == e)[:, None]
            train.append(self.mask & ~sel)
            test.append(self.mask & sel)
            labels.append(f"leave out {self.files[e]}")
        valid = np.ones(self.E + 1, bool)
        if self.E == 1:
            train[1], test[1], valid[1] = first, last, False
        return Rows(np.stack(train).astype(float), np.stack(test).astype(float), labels, valid)

    def rows_records(self, train_fraction: float = 0.7) -> Rows:
        """Chronological split pooled, then each record alone on its own first part."""
        first, last = self._split(train_fraction)
        train, test = [first], [last]
        for e in range(self.E):
            sel = (np.arange(self.E) == e)[:, None]
            train.append(first & sel)
            test.append(last & sel)
        return Rows(np.stack(train).astype(float), np.stack(test).astype(float),
                    ["pooled"] + list(self.files), np.ones(self.E + 1, bool))

    # ---------------------------------------------------------------- identifiability
    def directions(self, w: np.ndarray) -> tuple[int, int]:
        """(positive, negative) samples of weight > 0 beyond 3 velocity scales."""
        on = (w > 0) & self.mask
        thr = 3.0 * self.smoothing.velocity_scale
        return int(np.sum(on & (self.v > thr))), int(np.sum(on & (self.v < -thr)))

    def eq9_identifiable(self, w: np.ndarray) -> bool:
        """True when samples `w > 0` hold enough motion in at least one direction for eq. 9."""
        return max(self.directions(w)) >= self._needed(w)

    def tie_for(self, w: np.ndarray) -> int:
        npos, nneg = self.directions(w)
        need = self._needed(w)
        if npos < need and nneg < need:
            raise ValueError(
                f"friction fit ({', '.join(self.files)}): only {npos} positive and {nneg} negative velocity samples "
                f"beyond {3 * self.smoothing.velocity_scale:g} rad/s; eq. 9 needs at least {need:.0f} in one direction. "
                "Record motion, or lower `velocity_scale`; friction recorded wholly at low speed is fitted by the "
                "low-speed law instead (`hdjax._fit.friction_low_speed.fit_low_speed`, used by `fit` automatically).")
        return TIE_NONE if min(npos, nneg) >= need else (TIE_NEG_TO_POS if npos >= need else TIE_POS_TO_NEG)

    def _needed(self, w: np.ndarray) -> float:
        """Samples a direction (or the Stribeck part) needs among those of weight `w` > 0."""
        npos, nneg = self.directions(w)
        return float(max(MIN_DIRECTION_SAMPLES, MIN_DIRECTION_FRACTION * (npos + nneg)))

    def stribeck_supported(self, w: np.ndarray) -> bool:
        """True when the samples `w > 0` hold enough low-speed samples to fit the Stribeck part
        (module docstring: `STRIBECK_LOW`)."""
        speed = np.abs(self.v[(w > 0) & self.mask])
        if not speed.size:
            return False
        return bool(np.sum(speed <= STRIBECK_LOW * np.quantile(speed, 0.98)) >= self._needed(w))

    def base_free(self, tie: int | np.integer, w: np.ndarray | None = None) -> np.ndarray:
        """Eq. 9's free slots for a fit of direction tie `tie` on the samples `w > 0` (all
        samples when None); the Stribeck slots are held when `w` cannot see the term."""
        free = np.zeros(N_PARAMS, bool)
        free[EQ9_SLOTS] = True
        if tie == TIE_NEG_TO_POS:
            free[[IDX["Tvn"], IDX["Tsn"], IDX["Tssn1"]]] = False
        elif tie == TIE_POS_TO_NEG:
            free[[IDX["Tvp"], IDX["Tsp"], IDX["Tssp1"]]] = False
        if self.Tss2 is not None:
            free[SLOT["Tss2"]] = False
        if not self.stribeck_supported(self.mask.astype(float) if w is None else w):
            free[[IDX["Tssp1"], IDX["Tssn1"], SLOT["Tss2"]]] = False
        return free

    # ---------------------------------------------------------------- eq. 9 start values
    def basis(self, Tss2: float) -> np.ndarray:
        """Eq. 9 regressors (experiment, time, 6) at `Tss2` (`hdjax.friction_basis`, the model's smoothing)."""
        return np.asarray(friction_basis(jnp.asarray(self.v), Tss2, self.smoothing))

    def tss2_grid(self) -> np.ndarray:
        if self.Tss2 is not None:
            return np.array([float(self.Tss2)])
        vmax = float(np.quantile(np.abs(self.v[self.mask]), 0.98))
        lo = max(3.0 * self.smoothing.velocity_scale, 1e-3 * vmax)
        return np.geomspace(lo, max(vmax, 2 * lo), 10)

    def start_eq9(self, w: np.ndarray, tie: int | np.integer) -> np.ndarray:
        """Normalised start vector for one row: weighted linear least squares of eq. 9's six
        coefficients on a grid of `Tss2`, keeping the best."""
        best, x_best = np.inf, None
        sw = np.sqrt(w[self.mask])
        y = self.T[self.mask] * sw
        stribeck = self.stribeck_supported(w)
        n_cols = 6 if stribeck else 4  # without low-speed samples: no Stribeck columns (held at zero)
        pairs = [(0, 1), (2, 3), (4, 5)][: n_cols // 2]
        for tss2 in self.tss2_grid() if stribeck else self.tss2_grid()[-1:]:
            A = self.basis(tss2)[self.mask][:, :n_cols] * sw[:, None]
            if tie != TIE_NONE:
                A = np.stack([A[:, i] + A[:, j] for i, j in pairs], 1)
            c, *_ = np.linalg.lstsq(A, y, rcond=None)
            sse = float(np.sum((A @ c - y) ** 2))
            if sse < best:
                coef = np.repeat(c, 2) if tie != TIE_NONE else c
                coef = np.concatenate([coef, np.zeros(6 - n_cols)])
                best, x_best = sse, np.concatenate([coef, [np.log(tss2)]])
        x = np.zeros(N_PARAMS)
        eq9 = EQ9_SLOTS
        x[eq9] = x_best  # six torques, then ln Tss2 (`FRICTION_NAMES` order)
        x[eq9[:6]] /= np.asarray(self.scale)[eq9[:6]]
        x[SLOT["presliding_friction.presliding_scale"]] = np.log(1e-3 / PRESLIDING_DISTANCE)  # δ = 1 mrad
        x[SLOT["thermal_drift.tau"]] = np.log(THERMAL_TAU)
        return x

    # ---------------------------------------------------------------- fitting
    def solve(self, rows: Rows, structure, x0: np.ndarray, free: np.ndarray, tie: np.ndarray) -> RowFit:
        """LM on every row from `x0` with `free` masks and direction ties; `structure` is one
        `FrictionStructure` for all rows or a list with one per row."""
        structures = structure if isinstance(structure, (list, tuple)) else [structure] * len(rows.labels)
        xs, oks, steps, preds = [], [], [], []
        for b in range(len(rows.labels)):
            if not rows.valid[b]:  # placeholder row (one experiment: no leave-one-out fold)
                xs.append(xs[0]), oks.append(oks[0]), steps.append(0), preds.append(preds[0])
                continue
            x, ok, n = _solve(jnp.asarray(x0[b]), jnp.asarray(free[b]), jnp.asarray(rows.train[b] * self.sample_weight),
                              jnp.asarray(tie[b]), self.data, structures[b], self.pmap, self.sigma, self.smoothing,
                              self.index, self.max_steps)
            x, pred = np.asarray(x), self.predict_row(np.asarray(x), int(tie[b]), structures[b])
            # the fit sees a subsample: keep the start if the result's squared error, summed over all
            # the training samples, is larger than the start's
            pred0 = self.predict_row(np.asarray(x0[b]), int(tie[b]), structures[b])
            if self._sse(pred0, rows.train[b]) < self._sse(pred, rows.train[b]):
                x, pred = np.asarray(x0[b], dtype=float), pred0
            xs.append(x), oks.append(bool(ok)), steps.append(int(n)), preds.append(pred)
        return RowFit(np.stack(xs), np.asarray(tie), np.asarray(free), np.asarray(oks), np.asarray(steps),
                      np.stack(preds), structures[0], list(structures))

    def _sse(self, pred: np.ndarray, w: np.ndarray) -> float:
        """Weighted sum of squared errors (N·m²) of a prediction over every sample of weight `w`."""
        on = self.mask & (w > 0)
        return float(np.sum((w * (pred - self.T) ** 2)[on]))

    def predict_row(self, x: np.ndarray, tie: int | np.integer, structure: FrictionStructure) -> np.ndarray:
        """Model torque (N·m) of one normalised vector on every sample, shape (experiment, time)."""
        return np.asarray(_predict_row(jnp.asarray(x), jnp.asarray(tie), self.data, structure, self.pmap,
                                       self.smoothing))

    def fit_eq9(self, rows: Rows) -> RowFit:
        """Eq. 9 alone on every row (start values from `start_eq9`)."""
        tie = np.array([self.tie_for(w) for w in rows.train])
        x0 = np.stack([self.start_eq9(w, t) for w, t in zip(rows.train, tie)])
        free = np.stack([self.base_free(t, w) for w, t in zip(rows.train, tie)])
        return self.solve(rows, FrictionStructure(), x0, free, tie)

    def std_errors(self, fit: RowFit, rows: Rows, b: int = 0) -> np.ndarray:
        """Standard errors (normalised units) of row `b` that allow for correlated residuals (see
        the module docstring); NaN for parameters not fitted."""
        w = rows.train[b]
        J = np.asarray(_jacobian(jnp.asarray(fit.x[b]), jnp.asarray(fit.free[b]), jnp.asarray(w),
                                 jnp.asarray(fit.tie[b]), self.data, fit.structures[b], self.pmap, self.sigma,
                                 self.smoothing, self.index))
        free = fit.free[b]
        Jf = J[:, free]
        idx = np.asarray(self.index)
        w, mask = w[:, idx], self.mask[:, idx]
        on = (w > 0) & mask
        r = np.where(on, np.sqrt(w) * (fit.prediction[b][:, idx] - self.T[:, idx]) / self.sigma, 0.0).ravel()
        Jf = Jf * on.ravel()[:, None]
        records = [(fit.prediction[b][e, idx] - self.T[e, idx])[on[e]] for e in range(self.E)]
        cov, _ = robust_covariance(Jf, r, self.blocks()[:, idx].ravel(), lambda: inflated_covariance(Jf, r, records))
        se = np.full(N_PARAMS, np.nan)
        se[free] = standard_errors(cov, Jf)
        return se


def physical_std_errors(x: np.ndarray, se: np.ndarray, scale) -> np.ndarray:
    """Normalised standard errors to physical units (delta method through the logarithms)."""
    out = se * np.asarray(scale)
    for i in LOG_INDICES:
        out[i] = np.exp(x[i]) * se[i]
    return out


LOWPASS_HZ = 1.0  # cutoff of the low-passed RMS (the published joint-friction comparisons' convention)
LOWPASS_ORDER = 4


def matlab_filtfilt(b, a, x: np.ndarray) -> np.ndarray:
    """Zero-phase forward–backward filtering as MATLAB's `filtfilt(b, a, x)` does it.

    MATLAB extends the signal at both ends by an *odd* reflection about the end sample
    (`2·x(1) − x(nfact+1:-1:2)`), of length `nfact = 3·(nfilt − 1)` with
    `nfilt = max(length(a), length(b))`, and starts each pass from the filter's steady state for
    the first sample (`lfilter_zi` times that sample). scipy's `filtfilt` does the same with
    `padtype="odd"` except that its default `padlen` is `3·nfilt`, three samples longer; here it is
    set to MATLAB's (and to `len(x) − 1` for shorter signals, where MATLAB refuses)."""
    x = np.asarray(x, dtype=float)
    padlen = min(3 * (max(len(a), len(b)) - 1), x.size - 1)
    return scipy.signal.filtfilt(b, a, x, padtype="odd", padlen=padlen)


def filtered_rms(residual, fs: float, cutoff_hz: float = LOWPASS_HZ, order: int = LOWPASS_ORDER) -> float:
    """RMS (N·m) of a residual low-passed by a zero-phase Butterworth filter: `order`-th order
    `scipy.signal.butter(order, cutoff_hz / (fs / 2))` in transfer-function form (as MATLAB's
    `butter` returns it; at 1 Hz and 500 Hz the 4th-order `b, a` agree with second-order
    sections to 5e-8 relative), applied forward and backward by `matlab_filtfilt`, RMS over every
    sample of the contiguous record `residual` sampled at `fs` (Hz).

    This is how the published joint-friction comparisons (e.g. the NNFM study's RMS table) score a
    model: residual = measured − predicted friction torque, low-passed at 1 Hz, RMS over the whole
    file. It measures the slow, systematic part of the error and ignores sensor noise and fast
    dynamics above the cutoff; report it beside the raw RMS, never instead of it. NaN when the
    cutoff is not below the Nyquist frequency or the record has fewer than 3 samples."""
    r = np.asarray(residual, dtype=float)
    if r.size < 3 or not cutoff_hz < 0.5 * fs:
        return float("nan")
    b, a = cast(tuple[np.ndarray, np.ndarray], scipy.signal.butter(order, cutoff_hz / (0.5 * fs)))  # output="ba"
    return float(np.sqrt(np.mean(matlab_filtfilt(b, a, r) ** 2)))


def sample_rates(data: FrictionExperiment) -> np.ndarray:
    """Sample rate (Hz) of each record of a stacked batch: 1 / median time step of its samples."""
    t, m = np.asarray(data.time), np.asarray(data.mask)
    return np.array([1.0 / float(np.median(np.diff(t[e][m[e]]))) if m[e].sum() > 1 else np.nan
                     for e in range(t.shape[0])])


def _runs(on: np.ndarray) -> list[tuple[int, int]]:
    d = np.diff(np.concatenate([[0], on.astype(int), [0]]))
    return [(int(i), int(j)) for i, j in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1))]


def lowpass_sq_sum(err: np.ndarray, on: np.ndarray, fs, cutoff_hz: float = LOWPASS_HZ,
                   order: int = LOWPASS_ORDER) -> tuple[float, int]:
    """(sum of squares, samples) of `err` (experiment, time) low-passed as in `filtered_rms`, each
    contiguous run of selected samples `on` filtered on its own (a held-out part is filtered
    without the training samples around it); runs too short to filter are left out."""
    ss, n = 0.0, 0
    for e in range(err.shape[0]):
        for i, j in _runs(on[e]):
            f = filtered_rms(err[e, i:j], float(fs[e]), cutoff_hz, order)
            if np.isfinite(f):
                ss += f**2 * (j - i)
                n += j - i
    return ss, n


def rms_stats(pred: np.ndarray, meas: np.ndarray, w: np.ndarray, fs=None) -> dict:
    """RMS error (N·m) and NRMSE (RMS error / RMS of measured minus its mean) on samples w > 0.

    With `fs` (sample rate per record, Hz; `pred`, `meas`, `w` shaped (experiment, time)) also
    `rms_lowpass_1hz`: the RMS of the error low-passed at `LOWPASS_HZ` (`filtered_rms`, each
    contiguous run of selected samples filtered on its own), the published comparisons' metric."""
    on = w > 0
    if not on.any():
        out = {"rms": float("nan"), "nrmse": float("nan"), "n": 0}
        return out | ({"rms_lowpass_1hz": float("nan")} if fs is not None else {})
    err = (pred - meas)[on]
    m = meas[on]
    rms = float(np.sqrt(np.mean(err**2)))
    out = {"rms": rms, "nrmse": rms / max(float(np.std(m)), 1e-300), "n": int(on.sum())}
    if fs is not None:
        ss, n = lowpass_sq_sum(np.atleast_2d(pred - meas), np.atleast_2d(on), np.atleast_1d(fs))
        out["rms_lowpass_1hz"] = float(np.sqrt(ss / n)) if n else float("nan")
    return out


# ---------------------------------------------------------------------------------------------- special case


def coulomb_viscous_basis(v: np.ndarray, smoothing: Smoothing) -> np.ndarray:
    """Regressors (..., 2) of symmetric Coulomb + viscous friction, `Tv·ω + Tc·sign(ω)`: eq. 9's
    columns (`hdjax.friction_basis`) with `Tvp = Tvn`, `Tsp = Tsn` and no Stribeck term."""
    b = np.asarray(friction_basis(jnp.asarray(v), 1.0, smoothing))
    return np.stack([b[..., 0] + b[..., 1], b[..., 2] + b[..., 3]], -1)


def fit_coulomb_viscous(problem: "FrictionProblem", w: np.ndarray) -> tuple[dict, np.ndarray, np.ndarray]:
    """Weighted linear least squares of `Tv·ω + Tc·sign(ω)` on samples `w > 0` of `problem`:
    `({"Tv", "Tc"}, standard errors (2,), prediction (experiment, time))`. Standard errors allow
    for correlated residuals like `FrictionProblem.std_errors`."""
    A = coulomb_viscous_basis(problem.v, problem.smoothing)
    on = (w > 0) & problem.mask
    sw = np.sqrt(w[on])
    c, *_ = np.linalg.lstsq(A[on] * sw[:, None], problem.T[on] * sw, rcond=None)
    pred = A @ c
    Aw, rw = A[on] * sw[:, None], (pred - problem.T)[on] * sw
    records = [(pred - problem.T)[e][on[e]] for e in range(problem.E)]
    cov, _ = robust_covariance(Aw, rw, problem.blocks()[on], lambda: inflated_covariance(Aw, rw, records))
    return {"Tv": float(c[0]), "Tc": float(c[1])}, standard_errors(cov, Aw), pred
