r"""The paper's own identification (Taghirad & Bélanger, section III), per experiment.

The paper identifies each experiment separately by least squares and judges a parameter by its
*consistency*, the standard deviation over the absolute mean of its per-experiment estimates. This
module reproduces that procedure, vectorised with `jax.vmap` over a padded, masked batch of
experiments (`hdjax.stack_experiments`):

1. **Preprocessing** (numpy/scipy, outside `jit`). Motor velocity and torque are low-pass filtered
   with a zero-phase Butterworth filter (`scipy.signal.butter` + `filtfilt`, order 5 like the
   paper's Fig. 5 filter, cutoff `cutoff_hz`, default 50 Hz; short records use a shorter
   `padlen`). The motor acceleration is the derivative of the filtered velocity (`np.gradient`).
   The current is *not* filtered: it only enters the left-hand side of a regression, where noise
   does not bias least squares, while filtering it would smear the Coulomb step at every velocity
   reversal into the high-velocity samples. The motor angle $\theta_m$ is `motor_position` where
   measured, otherwise the cumulative trapezoid integral of the unfiltered tachometer velocity (so
   its origin is unknown). With the output locked, torsion $\Delta\theta = \theta_m/N$ and
   torsion rate $\dot{\Delta\theta} = \omega_{m,filt}/N$.
2. **Compliance**, eq. 5, constrained experiments only, with an unknown torsion offset $c$:
   $T = K_1(\Delta\theta + c) + T_{st}|\dot{\Delta\theta}|^\alpha\mathrm{sign}(\dot{\Delta\theta})$.
   (a) Nonlinear regression for $\alpha, K_1, T_{st}, c$ (optimistix `LevenbergMarquardt`,
   rtol = atol = 1e-8, started from the linear fit at $\alpha = 1/2$, $\alpha$ kept in
   `alpha_bounds` by a sigmoid). (b) With $\alpha$ fixed (default 1/2, the paper's choice), a
   linear least-squares fit for $K_1, T_{st}, c$; these are the reported $K_1, T_{st}$.
   $|x|^\alpha\mathrm{sign}(x)$ is `smooth_signed_power` with scale `1e-9` rad/s: exact to
   rounding for any measurable torsion rate, but with finite derivatives at 0.
3. **Friction**, eq. 8 rearranged, $K_m i - T/N = J_{eff}\dot\omega + T_f(\omega)$ with
   `friction_basis` at `Smoothing(velocity_scale=1e-4)` (1e-3 of the paper's $T_{ss2}$; at the
   samples used, $|\omega| \ge 2\cdot10^{-4}$ rad/s, sign() and u() are then within 4 % of exact
   and within 1e-15 of exact above 4e-3 rad/s). (a) High velocity: free experiments, samples with
   $|\omega| > k\,T_{ss2}$ (default $k = 3$: $e^{-9} \approx 10^{-4}$, Stribeck negligible),
   linear LS for $J_{eff}, T_{vp}, T_{vn}, T_{sp}, T_{sn}$. Free experiments classed low-velocity
   (see (b)) are left out here, as in the paper, which splits experiments into high- and
   low-velocity ones: their few fast samples span too narrow a velocity range to separate viscous
   from Coulomb friction (measured: up to 20 % error in Tvn on synthetic data). A direction with fewer than
   `min_samples` samples leaves its two terms undetermined (NaN, with a note). (b) Low velocity:
   experiments (constrained and free) whose median $|\omega|$ is below `low_velocity_factor`
   $\cdot T_{ss2}$; $J_{eff}$ and the viscous/Coulomb terms are fixed at the mean high-velocity
   estimates, their contribution subtracted, and the remainder regressed on the two Stribeck
   columns with $T_{ss2}$ fixed (default 0.1 rad/s). Samples with $|\omega|$ below
   `2 * velocity_scale` (where sign() is ambiguous) are skipped.
4. **Consistency**: std (ddof = 1) / |mean| of the per-experiment estimates, NaN ignored (NaN when
   fewer than two experiments informed the parameter). The fixed $\alpha$ and $T_{ss2}$ have
   consistency 0, as in the paper's Table I.

Float64 is expected (call `jax.config.update("jax_enable_x64", True)`); this module does not switch
it on.
"""

import dataclasses
import math
from typing import Any, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import scipy.integrate
import scipy.signal
from jaxtyping import Array, Bool, Float

from .._data.experiment import Experiment, stack_experiments, take_rows
from .._model.paper import PARAMETER_NAMES, Drive, Parameters, Smoothing, friction_basis
from .._model.smooth import smooth_signed_power

__all__ = ["PAPER_HD2_SI", "PaperIdentification", "identify_paper"]

#: Fallback values used by `PaperIdentification.parameters()` for undetermined parameters: the
#: paper's Table I, harmonic drive 2, in SI units with K1 and Tst read as per-degree values
#: (K1 = 104.2 N·m/deg = 5970 N·m/rad; Tst = 7.96·(180/π)^½ = 60.2 N·m/(rad/s)^½).
PAPER_HD2_SI: dict[str, float] = {
    "alpha": 0.5,
    "K1": 5970.0,
    "Tst": 60.2,
    "Jeff": 1.0e-4,
    "Tvp": 1.8e-3,
    "Tvn": 2.1e-3,
    "Tsp": 7.5e-2,
    "Tsn": 3.3e-2,
    "Tssp1": -0.0487,
    "Tssn1": -0.0450,
    "Tss2": 0.1,
}

COMPLIANCE_NAMES = ("K1", "Tst")
HIGH_VELOCITY_NAMES = ("Jeff", "Tvp", "Tvn", "Tsp", "Tsn")
STRIBECK_NAMES = ("Tssp1", "Tssn1")

_TORSION_RATE_SCALE = 1e-9  # rad/s, smooth |x|^α sign(x) in the compliance regression
_COND_FLOOR = 1e-12  # smallest eigenvalue of the column-normalised normal matrix (= rel. sv 1e-6)


@dataclasses.dataclass(frozen=True)
class PaperIdentification:
    """Result of `identify_paper` (SI units; parameter keys as `hdjax.PARAMETER_NAMES`).

    **Attributes:**

    - `estimates`: mean of the per-experiment estimates (NaN where no experiment informed the
      parameter). `alpha` and `Tss2` are the fixed values used.
    - `per_experiment`: one list per parameter, aligned with the input experiment list, NaN where
      an experiment did not inform the parameter.
    - `experiment_indices`: indices of the experiments that informed each parameter.
    - `consistency`: the paper's measure std/|mean| of the per-experiment estimates.
    - `alpha_nonlinear`: the nonlinear compliance regression: per-experiment optimal `alpha`,
      `K1`, `Tst`, `offset` (rad), `converged` (bools), `indices`, plus `mean` and `consistency`
      of alpha.
    - `notes`: why a parameter or an experiment could not be used, in plain words.
    - `details`: per-experiment diagnostics (torsion offsets of the linear fit, sample counts,
      median |ω|, which experiments were classed low-velocity, options used).
    """

    estimates: dict[str, float]
    per_experiment: dict[str, list[float]]
    experiment_indices: dict[str, list[int]]
    consistency: dict[str, float]
    alpha_nonlinear: dict
    notes: list[str]
    details: dict = dataclasses.field(default_factory=dict)

    def undetermined(self) -> list[str]:
        """Names of the parameters no experiment determined."""
        return [k for k in PARAMETER_NAMES if not math.isfinite(self.estimates[k])]

    def parameters(self, fallback: dict[str, float] | Parameters | None = None) -> Parameters:
        """The estimates as `hdjax.Parameters`. Undetermined (NaN) parameters are replaced by
        `fallback` (default `PAPER_HD2_SI`, the paper's Table I for harmonic drive 2 in SI);
        `notes` already says which ones."""
        if fallback is None:
            fallback = PAPER_HD2_SI
        elif isinstance(fallback, Parameters):
            fallback = fallback.to_dict()
        values = {k: (v if math.isfinite(v) else float(fallback[k])) for k, v in self.estimates.items()}
        return Parameters.from_dict(values)

    def to_dict(self) -> dict:
        """A JSON-ready copy (NaN written as None)."""

        def clean(x) -> Any:
            if isinstance(x, dict):
                return {k: clean(v) for k, v in x.items()}
            if isinstance(x, (list, tuple)):
                return [clean(v) for v in x]
            if isinstance(x, (float, np.floating)):
                return float(x) if math.isfinite(x) else None
            if isinstance(x, np.integer):
                return int(x)
            if isinstance(x, np.bool_):
                return bool(x)
            return x

        return clean(dataclasses.asdict(self))


# --------------------------------------------------------------------------------------------
# Preprocessing (numpy, outside jit)


class _Prepared(eqx.Module):
    """Preprocessed batch, padded by repeating the last sample; `mask` marks real samples."""

    torsion: Float[Array, "*exp time"]  # θm/N (rad), constrained reading θo = 0
    torsion_rate: Float[Array, "*exp time"]  # ωm_filt/N (rad/s)
    torque: Float[Array, "*exp time"]  # filtered T (N·m)
    velocity: Float[Array, "*exp time"]  # filtered ωm (rad/s)
    acceleration: Float[Array, "*exp time"]  # d(filtered ωm)/dt (rad/s²)
    drive_torque: Float[Array, "*exp time"]  # Km·i − T_filt/N (N·m)
    mask: Bool[Array, "*exp time"]


def _lowpass(x: Float[np.ndarray, " time"], fs: float, cutoff_hz: float, order: int) -> Float[np.ndarray, " time"]:
    b, a = cast(tuple[np.ndarray, np.ndarray], scipy.signal.butter(order, cutoff_hz / (0.5 * fs)))  # output="ba"
    padlen = min(3 * max(len(a), len(b)), len(x) - 1)
    return scipy.signal.filtfilt(b, a, x, padlen=padlen)


def _prepare(experiments, drive, cutoff_hz, filter_order, notes):
    batch = stack_experiments(experiments)
    n_pad = batch.time.shape[1]
    N = float(drive.gear_ratio)
    Km = float(drive.torque_constant)
    cols = {k: [] for k in _Prepared.__dataclass_fields__}
    medians = []
    # indexed per experiment on the host (eager JAX indexing compiles a small gather program per shape)
    host = {f: np.asarray(getattr(batch, f)) for f in ("mask", "time", "motor_velocity", "torque", "current", "motor_position", "has_motor_position")}
    for k in range(len(experiments)):
        m = host["mask"][k]
        n = int(m.sum())
        t = host["time"][k][:n]
        w_raw = host["motor_velocity"][k][:n]
        T_raw = host["torque"][k][:n]
        cur = host["current"][k][:n]
        dt = float(np.median(np.diff(t)))
        fs = 1.0 / dt
        if cutoff_hz is None or cutoff_hz >= 0.5 * fs:
            if cutoff_hz is not None:
                notes.append(
                    f"experiment {k}: filter cutoff {cutoff_hz} Hz is not below the Nyquist frequency "
                    f"{0.5 * fs:.4g} Hz; velocity and torque left unfiltered."
                )
            w, T = w_raw.copy(), T_raw.copy()
        else:
            w = _lowpass(w_raw, fs, cutoff_hz, filter_order)
            T = _lowpass(T_raw, fs, cutoff_hz, filter_order)
        acc = np.gradient(w, t)
        if float(host["has_motor_position"][k]) > 0.5:
            theta_m = host["motor_position"][k][:n]
        else:
            theta_m = scipy.integrate.cumulative_trapezoid(w_raw, t, initial=0.0)
        vals = {
            "torsion": theta_m / N,
            "torsion_rate": w / N,
            "torque": T,
            "velocity": w,
            "acceleration": acc,
            "drive_torque": Km * cur - T / N,
        }
        for name, v in vals.items():
            cols[name].append(np.pad(v, (0, n_pad - n), mode="edge"))
        cols["mask"].append(m)
        medians.append(float(np.median(np.abs(w))))
    prepared = _Prepared(**{k: jnp.asarray(np.stack(v)) for k, v in cols.items()})
    free = np.asarray(batch.free) > 0.5
    return prepared, free, np.asarray(medians)


# --------------------------------------------------------------------------------------------
# Masked least squares (normal equations on normalised columns)


def _masked_lstsq(
    A: Float[Array, "time column"], y: Float[Array, " time"], w: Float[Array, " time"], active: Bool[Array, " column"]
) -> tuple[Float[Array, " column"], Float[Array, ""]]:
    """Weighted LS `A θ ≈ y` on rows with weight `w` (0/1), using only `active` columns (others
    return 0). Columns are normalised; returns `(θ, λmin)` with λmin the smallest eigenvalue of
    the normalised normal matrix over the active columns (1 where none is active)."""
    Aw = A * w[:, None]
    norms = jnp.sqrt(jnp.sum(Aw * Aw, axis=0))
    ok = active & (norms > 0)
    safe = jnp.where(ok, norms, 1.0)
    An = Aw / safe
    G = An.T @ An
    okf = ok.astype(A.dtype)
    G = G * okf[:, None] * okf[None, :] + jnp.diag(1.0 - okf)
    rhs = (An.T @ (y * w)) * okf
    lam = jnp.linalg.eigvalsh(G)[0]
    theta = jnp.linalg.solve(G, rhs) * okf / safe
    return theta, lam


# --------------------------------------------------------------------------------------------
# Compliance


def _compliance_design(p: _Prepared, alpha: float | Float[Array, ""]) -> Float[Array, "time 3"]:
    ones = jnp.ones_like(p.torsion)
    damping = smooth_signed_power(p.torsion_rate, alpha, _TORSION_RATE_SCALE)
    return jnp.stack([p.torsion, damping, ones], axis=-1)


@eqx.filter_jit
def _compliance_linear(p: _Prepared, alpha):
    def one(q):
        A = _compliance_design(q, alpha)
        w = q.mask.astype(A.dtype)
        theta, lam = _masked_lstsq(A, q.torque, w, jnp.ones(3, dtype=bool))
        K1, Tst, b = theta
        return K1, Tst, b / K1, lam

    return jax.vmap(one)(p)


def _compliance_nonlinear_one(q: _Prepared, lo, hi):
    w = q.mask.astype(q.torque.dtype)
    nw = jnp.maximum(jnp.sum(w), 1.0)
    y_scale = jnp.sqrt(jnp.sum(w * q.torque**2) / nw)
    y_scale = jnp.where(y_scale > 0, y_scale, 1.0)
    A0 = _compliance_design(q, 0.5)
    theta0, _ = _masked_lstsq(A0, q.torque, w, jnp.ones(3, dtype=bool))
    # column scales: coefficient · rms(column) ~ rms(T)
    col_rms = jnp.sqrt(jnp.sum(w[:, None] * A0**2, axis=0) / nw)
    scale = y_scale / jnp.where(col_rms > 0, col_rms, 1.0)
    s0 = jnp.log((0.5 - lo) / (hi - 0.5))  # sigmoid⁻¹ of α = 0.5

    def alpha_of(s):
        return lo + (hi - lo) * jax.nn.sigmoid(s)

    def residual(z, _):
        alpha = alpha_of(z[0])
        K1, Tst, b = z[1] * scale[0], z[2] * scale[1], z[3] * scale[2]
        damping = smooth_signed_power(q.torsion_rate, alpha, _TORSION_RATE_SCALE)
        model = K1 * q.torsion + Tst * damping + b
        return w * (model - q.torque) / y_scale

    z0 = jnp.concatenate([jnp.array([s0]), theta0 / scale])
    solver = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-8)
    sol = optx.least_squares(residual, solver, z0, max_steps=512, throw=False)
    z = sol.value
    K1 = z[1] * scale[0]
    converged = sol.result == optx.RESULTS.successful
    return alpha_of(z[0]), K1, z[2] * scale[1], z[3] * scale[2] / K1, converged


@eqx.filter_jit
def _compliance_nonlinear(p: _Prepared, lo, hi):
    return jax.vmap(_compliance_nonlinear_one, in_axes=(0, None, None))(p, lo, hi)


# --------------------------------------------------------------------------------------------
# Friction


@eqx.filter_jit
def _friction_high(p: _Prepared, Tss2, threshold, min_samples, smoothing):
    def one(q):
        B = friction_basis(q.velocity, Tss2, smoothing)
        A = jnp.concatenate([q.acceleration[:, None], B[:, :4]], axis=-1)
        sel = q.mask & (jnp.abs(q.velocity) > threshold)
        npos = jnp.sum(sel & (q.velocity > 0))
        nneg = jnp.sum(sel & (q.velocity < 0))
        pos_ok = npos >= min_samples
        neg_ok = nneg >= min_samples
        use = sel & (((q.velocity > 0) & pos_ok) | ((q.velocity < 0) & neg_ok))
        active = jnp.stack([pos_ok | neg_ok, pos_ok, neg_ok, pos_ok, neg_ok])
        theta, lam = _masked_lstsq(A, q.drive_torque, use.astype(A.dtype), active)
        return theta, active, lam, npos, nneg

    return jax.vmap(one)(p)


@eqx.filter_jit
def _friction_stribeck(p: _Prepared, fixed, fixed_ok, Tss2, floor, upper, min_samples, smoothing):
    """`fixed` = [Jeff, Tvp, Tvn, Tsp, Tsn] (finite; `fixed_ok` = [pos_ok, neg_ok])."""

    def one(q):
        B = friction_basis(q.velocity, Tss2, smoothing)
        known = fixed[0] * q.acceleration + B[:, :4] @ fixed[1:]
        remainder = q.drive_torque - known
        speed = jnp.abs(q.velocity)
        sel = q.mask & (speed >= floor)
        informative = sel & (speed < upper)
        npos = jnp.sum(informative & (q.velocity > 0))
        nneg = jnp.sum(informative & (q.velocity < 0))
        pos_ok = (npos >= min_samples) & fixed_ok[0]
        neg_ok = (nneg >= min_samples) & fixed_ok[1]
        use = sel & (((q.velocity > 0) & pos_ok) | ((q.velocity < 0) & neg_ok))
        active = jnp.stack([pos_ok, neg_ok])
        theta, lam = _masked_lstsq(B[:, 4:], remainder, use.astype(B.dtype), active)
        return theta, active, lam, npos, nneg

    return jax.vmap(one)(p)


# --------------------------------------------------------------------------------------------
# Statistics


def _mean(values) -> float:
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return float(np.mean(v)) if v.size else float("nan")


def _consistency(values) -> float:
    """The paper's measure: std (ddof = 1) / |mean| over finite values; NaN if fewer than 2."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size < 2:
        return float("nan")
    m = float(np.mean(v))
    return float(np.std(v, ddof=1) / abs(m)) if m != 0 else float("inf")


def _fmt(idx) -> str:
    return ", ".join(str(int(i)) for i in idx)


# --------------------------------------------------------------------------------------------
# Stages of `identify_paper`


def _check_options(alpha, Tss2, alpha_bounds, nonlinear) -> tuple[float, float]:
    """The alpha bounds as floats `(lo, hi)`, after refusing an alpha outside them or a Tss2
    (rad/s) that is not positive."""
    lo, hi = float(alpha_bounds[0]), float(alpha_bounds[1])
    if not lo < alpha < hi and nonlinear:
        raise ValueError(f"`identify_paper`: alpha={alpha} must lie inside alpha_bounds={alpha_bounds}.")
    if Tss2 <= 0:
        raise ValueError(f"`identify_paper`: Tss2 must be positive (rad/s), got {Tss2}.")
    return lo, hi


def _prepare_or_nothing(experiments, drive, cutoff_hz, filter_order, notes):
    """Stage 1: `_prepare`, or `(None, no free flags, no medians)` with a note when there are no
    experiments. The medians are of |ω| (rad/s)."""
    if len(experiments) == 0:
        notes.append("no experiments given: every fitted parameter is undetermined.")
        return None, np.zeros(0, dtype=bool), np.zeros(0)
    return _prepare(experiments, drive, cutoff_hz, filter_order, notes)


def _compliance_stage(prepared, constrained_idx, alpha, alpha_bounds, nonlinear, per, details, alpha_nl, notes):
    """Stage 2, eq. 5 on the constrained experiments: K1 (N·m/rad) and Tst (N·m/(rad/s)^α) at the
    fixed alpha into `per`, the torsion offsets (rad) into `details["torsion_offset"]`, and, with
    `nonlinear`, the optimal alpha into `alpha_nl`."""
    if constrained_idx.size == 0:
        notes.append(
            "no constrained (output-locked) experiments: K1, Tst and the optimal alpha undetermined — "
            "record locked-output runs with a torque excursion of a good fraction of the rated torque."
        )
        return
    assert prepared is not None  # None only without experiments, when every index list is empty
    sub = take_rows(prepared, constrained_idx)
    K1, Tst, c, lam = (np.asarray(x) for x in _compliance_linear(sub, alpha))
    for j, k in enumerate(constrained_idx):
        if not (lam[j] > _COND_FLOOR and np.isfinite(K1[j]) and np.isfinite(Tst[j])):
            notes.append(
                f"experiment {k} (constrained): torsion, torsion rate and offset are collinear "
                "(no torque/velocity excursion?): K1, Tst not determined from it."
            )
            continue
        per["K1"][k], per["Tst"][k] = float(K1[j]), float(Tst[j])
        per["alpha"][k] = float(alpha)
        details["torsion_offset"][k] = float(c[j])
    if nonlinear:
        _optimal_alpha_stage(sub, constrained_idx, alpha_bounds, alpha_nl, notes)


def _optimal_alpha_stage(sub, constrained_idx, alpha_bounds, alpha_nl, notes) -> None:
    """Stage 2a, the nonlinear eq. 5 regression: per-experiment alpha, K1 (N·m/rad), Tst
    (N·m/(rad/s)^α) and offset (rad) into `alpha_nl`, with the mean and consistency of the
    converged alphas."""
    lo, hi = float(alpha_bounds[0]), float(alpha_bounds[1])
    a, K1n, Tstn, cn, conv = (np.asarray(x) for x in _compliance_nonlinear(sub, lo, hi))
    alpha_nl.update(
        alpha=[float(x) for x in a], K1=[float(x) for x in K1n], Tst=[float(x) for x in Tstn],
        offset=[float(x) for x in cn], converged=[bool(x) for x in conv],
        indices=[int(k) for k in constrained_idx],
    )
    good = conv & np.isfinite(a)
    alpha_nl["mean"] = _mean(a[good])
    alpha_nl["consistency"] = _consistency(a[good])
    if not np.all(conv):
        notes.append(
            "nonlinear compliance regression did not converge for experiment(s) "
            f"{_fmt(constrained_idx[~conv])}; excluded from the optimal-alpha mean."
        )
    at_bound = good & ((a < lo + 1e-3) | (a > hi - 1e-3))
    if np.any(at_bound):
        notes.append(
            f"optimal alpha reached its bound {alpha_bounds} for experiment(s) "
            f"{_fmt(constrained_idx[at_bound])}: the damping term is poorly excited there."
        )


def _sample_shortage_note(k, kind, min_samples, missing, notes) -> None:
    """Note that experiment `k` has too few samples in the velocity ranges listed in `missing`."""
    if missing:
        notes.append(
            f"experiment {k} ({kind}): fewer than {min_samples} samples at "
            + "; ".join(missing)
            + " not determined from it."
        )


def _high_velocity_stage(
    prepared, free, low_speed, Tss2, threshold, low_velocity_factor, min_samples, smoothing, per, details, notes
):
    """Stage 3a, eq. 8 on the fast free experiments (|ω| > `threshold` rad/s): Jeff (kg·m²), Tvp,
    Tvn (N·m/(rad/s)), Tsp, Tsn (N·m) into `per`, sample counts per direction into `details`."""
    n_exp = len(per["Jeff"])
    free_idx = np.flatnonzero(free & ~low_speed)
    details["high_velocity_samples"] = {"positive": [0] * n_exp, "negative": [0] * n_exp}
    if free_idx.size == 0:
        slow_free = np.flatnonzero(free & low_speed)
        what = (
            f"free-motion experiments ({_fmt(slow_free)}) are all low-velocity (median |ω| < "
            f"{low_velocity_factor * Tss2:.3g} rad/s)"
            if slow_free.size
            else "no free-motion experiments"
        )
        notes.append(
            f"{what}: Jeff, Tvp, Tvn, Tsp, Tsn undetermined — record free-motion "
            f"runs at |ω| > {threshold:.3g} rad/s in both directions."
        )
        return
    assert prepared is not None  # None only without experiments, when every index list is empty
    sub = take_rows(prepared, free_idx)
    theta, active, lam, npos, nneg = (
        np.asarray(x) for x in _friction_high(sub, Tss2, threshold, min_samples, smoothing)
    )
    for j, k in enumerate(free_idx):
        details["high_velocity_samples"]["positive"][k] = int(npos[j])
        details["high_velocity_samples"]["negative"][k] = int(nneg[j])
        missing = []
        if not active[j, 1]:
            missing.append(f"ω > {threshold:.3g} rad/s ({int(npos[j])} samples): Tvp, Tsp")
        if not active[j, 2]:
            missing.append(f"ω < −{threshold:.3g} rad/s ({int(nneg[j])} samples): Tvn, Tsn")
        _sample_shortage_note(k, "free", min_samples, missing, notes)
        if not active[j, 0]:
            continue
        if not (lam[j] > _COND_FLOOR and np.all(np.isfinite(theta[j]))):
            notes.append(
                f"experiment {k} (free): acceleration and friction regressors are collinear "
                "(constant velocity?): Jeff, Tvp, Tvn, Tsp, Tsn not determined from it."
            )
            continue
        for col, name in enumerate(HIGH_VELOCITY_NAMES):
            if active[j, col]:
                per[name][k] = float(theta[j, col])


def _stribeck_stage(
    prepared, low_idx, Tss2, threshold, low_velocity_factor, min_samples, velocity_scale, smoothing, per, details, notes
):
    """Stage 3b, eq. 8 on the slow experiments with the high-velocity terms fixed at their means:
    Tssp1, Tssn1 (N·m) into `per` (and the fixed Tss2, rad/s), sample counts into `details`."""
    n_exp = len(per["Tss2"])
    details["low_velocity_experiments"] = [int(k) for k in low_idx]
    fixed = {name: _mean(per[name]) for name in HIGH_VELOCITY_NAMES}
    details["stribeck_fixed"] = dict(fixed)
    floor = 2.0 * velocity_scale
    details["stribeck_samples"] = {"positive": [0] * n_exp, "negative": [0] * n_exp}
    if low_idx.size == 0:
        notes.append(
            "no low-velocity experiments (median |ω| below "
            f"{low_velocity_factor * Tss2:.3g} rad/s): Tssp1, Tssn1 undetermined — record slow runs "
            f"(constrained or free) that spend most time below {low_velocity_factor * Tss2:.3g} rad/s "
            "in both directions."
        )
        return
    if not math.isfinite(fixed["Jeff"]):
        notes.append(
            "Tssp1, Tssn1 undetermined: the Stribeck regression needs Jeff and the viscous/Coulomb "
            "terms from high-velocity free-motion experiments first."
        )
        return
    pos_ok = math.isfinite(fixed["Tvp"]) and math.isfinite(fixed["Tsp"])
    neg_ok = math.isfinite(fixed["Tvn"]) and math.isfinite(fixed["Tsn"])
    if not pos_ok:
        notes.append("Tssp1 undetermined: Tvp/Tsp (positive direction) were not identified.")
    if not neg_ok:
        notes.append("Tssn1 undetermined: Tvn/Tsn (negative direction) were not identified.")
    fixed_arr = jnp.asarray([fixed[n] if math.isfinite(fixed[n]) else 0.0 for n in HIGH_VELOCITY_NAMES])
    assert prepared is not None  # None only without experiments, when every index list is empty
    sub = take_rows(prepared, low_idx)
    theta, active, lam, npos, nneg = (
        np.asarray(x)
        for x in _friction_stribeck(
            sub, fixed_arr, jnp.asarray([pos_ok, neg_ok]), Tss2, floor, threshold, min_samples, smoothing
        )
    )
    for j, k in enumerate(low_idx):
        details["stribeck_samples"]["positive"][k] = int(npos[j])
        details["stribeck_samples"]["negative"][k] = int(nneg[j])
        missing = []
        if pos_ok and not active[j, 0]:
            missing.append(f"{floor:.3g} < ω < {threshold:.3g} rad/s ({int(npos[j])} samples): Tssp1")
        if neg_ok and not active[j, 1]:
            missing.append(f"−{threshold:.3g} < ω < −{floor:.3g} rad/s ({int(nneg[j])} samples): Tssn1")
        _sample_shortage_note(k, "low velocity", min_samples, missing, notes)
        if not np.any(active[j]):
            continue
        if not (lam[j] > _COND_FLOOR and np.all(np.isfinite(theta[j]))):
            notes.append(f"experiment {k} (low velocity): Stribeck regressors degenerate; skipped.")
            continue
        for col, name in enumerate(STRIBECK_NAMES):
            if active[j, col]:
                per[name][k] = float(theta[j, col])
        per["Tss2"][k] = float(Tss2)


def _summarise(per, alpha, Tss2, notes):
    """Stage 4: the mean estimates (SI), the paper's consistency and the informing experiments of
    each parameter, with a note for each undetermined or single-experiment parameter."""
    estimates = {k: _mean(per[k]) for k in PARAMETER_NAMES}
    estimates["alpha"] = float(alpha)
    estimates["Tss2"] = float(Tss2)
    consistency = {k: _consistency(per[k]) for k in PARAMETER_NAMES}
    consistency["alpha"] = 0.0
    consistency["Tss2"] = 0.0
    indices = {k: [int(i) for i in np.flatnonzero(np.isfinite(per[k]))] for k in PARAMETER_NAMES}
    for k in PARAMETER_NAMES:
        if not math.isfinite(estimates[k]):
            notes.append(
                f"{k} undetermined; `parameters()` falls back to {PAPER_HD2_SI[k]:g} "
                "(paper Table I, harmonic drive 2, SI)."
            )
        elif len(indices[k]) == 1 and k not in ("alpha", "Tss2"):
            notes.append(f"{k} was determined by a single experiment: its consistency is undefined (NaN).")
    return estimates, consistency, indices


# --------------------------------------------------------------------------------------------
# Entry point


def identify_paper(
    experiments: list[Experiment],
    drive: Drive,
    *,
    alpha: float = 0.5,
    Tss2: float = 0.1,
    cutoff_hz: float | None = 50.0,
    high_velocity_factor: float = 3.0,
    low_velocity_factor: float = 5.0,
    filter_order: int = 5,
    min_samples: int = 50,
    velocity_scale: float = 1e-4,
    alpha_bounds: tuple[float, float] = (0.05, 1.5),
    nonlinear: bool = True,
) -> PaperIdentification:
    """The paper's identification (section III), each experiment separately, see the module doc.

    **Arguments:**

    - `experiments`: constrained (`free == 0`) and free-motion (`free == 1`) records.
    - `drive`: gear ratio `N` and torque constant `Km` (load inertia unused).
    - `alpha`: structural-damping exponent fixed for the linear compliance regression (paper 1/2).
    - `Tss2`: Stribeck velocity (rad/s), fixed (paper 0.1).
    - `cutoff_hz`: low-pass cutoff of velocity and torque (None: no filtering).
    - `high_velocity_factor`: viscous/Coulomb regression uses |ω| > factor·Tss2.
    - `low_velocity_factor`: experiments with median |ω| < factor·Tss2 feed the Stribeck regression.
    - `filter_order`: Butterworth order (paper's Fig. 5 filter: 5).
    - `min_samples`: fewest samples per velocity direction to determine that direction's terms.
    - `velocity_scale`: smoothing scale (rad/s) of sign() and u() in `friction_basis`; samples with
      |ω| < 2·velocity_scale are skipped in the Stribeck regression.
    - `alpha_bounds`: open interval for alpha in the nonlinear regression.
    - `nonlinear`: run the nonlinear (optimal-alpha) compliance regression.

    Never raises on missing experiment types: undetermined parameters are NaN with a note.
    """
    n_exp = len(experiments)
    nan = float("nan")
    per = {k: [nan] * n_exp for k in PARAMETER_NAMES}
    smoothing = Smoothing(velocity_scale=velocity_scale)
    lo, hi = _check_options(alpha, Tss2, alpha_bounds, nonlinear)
    notes: list[str] = []
    if not jax.config.jax_enable_x64:  # pyright: ignore[reportAttributeAccessIssue]  jax.config options are dynamic attributes
        notes.append(
            "float64 is off (jax_enable_x64): the regressions ran in float32 and may be inaccurate; "
            'call jax.config.update("jax_enable_x64", True) first.'
        )
    alpha_nl = {"alpha": [], "K1": [], "Tst": [], "offset": [], "converged": [], "indices": [],
                "mean": nan, "consistency": nan}
    details: dict = {
        "options": {"alpha": alpha, "Tss2": Tss2, "cutoff_hz": cutoff_hz, "filter_order": filter_order,
                    "high_velocity_factor": high_velocity_factor, "low_velocity_factor": low_velocity_factor,
                    "min_samples": min_samples, "velocity_scale": velocity_scale,
                    "alpha_bounds": [lo, hi]},
        "torsion_offset": [nan] * n_exp,
    }

    prepared, free, medians = _prepare_or_nothing(experiments, drive, cutoff_hz, filter_order, notes)
    details["free"] = [bool(f) for f in free]
    details["median_abs_velocity"] = [float(m) for m in medians]
    low_speed = medians < low_velocity_factor * Tss2
    threshold = high_velocity_factor * Tss2

    _compliance_stage(prepared, np.flatnonzero(~free), alpha, alpha_bounds, nonlinear, per, details, alpha_nl, notes)
    _high_velocity_stage(
        prepared, free, low_speed, Tss2, threshold, low_velocity_factor, min_samples, smoothing, per, details, notes
    )
    _stribeck_stage(
        prepared, np.flatnonzero(low_speed), Tss2, threshold, low_velocity_factor, min_samples, velocity_scale,
        smoothing, per, details, notes,
    )
    estimates, consistency, indices = _summarise(per, alpha, Tss2, notes)
    return PaperIdentification(
        estimates=estimates,
        per_experiment=per,
        experiment_indices=indices,
        consistency=consistency,
        alpha_nonlinear=alpha_nl,
        notes=notes,
        details=details,
    )
