r"""Friction recorded wholly at low speed (presliding and the Stribeck regime): a low-speed law.

Eq. 9 needs gross sliding: its Coulomb level is read where $|\omega|$ is many smoothing scales
(`Smoothing.velocity_scale`, 1e-3 rad/s) above zero, and `FrictionProblem.tie_for` refuses records
with too few such samples. Below about `LOW_SPEED_LIMIT` (0.01 rad/s) friction is instead set by
how it builds up from zero velocity, which eq. 9's fixed `tanh(ω/scale)` does not describe. Two
laws, each linear in its torques once one length or speed scale is fixed, are fitted here:

- `regularised_coulomb`: $T = T_c \tanh(\omega / s) + b$, the regularisation speed $s$ (rad/s)
  fitted instead of fixed (a friction that rises over a velocity band, Stribeck-regime creep).
- `dahl_presliding`: $T = T_c z + b$ with the Dahl state along the travelled angle
  $x = \int\omega\,dt$: $dz/dx = (\mathrm{sign}(\omega) - z)/\delta$, integrated exactly for a
  velocity held over each sample interval (as `hdjax._model.friction_only.presliding_state`, but with the exact
  sign: at 1e-4 rad/s a 1e-3 rad/s smoothing would cap the state at 0.1). Presliding distance
  $\delta$ (rad) fitted; presliding (Dahl) stiffness $\sigma_0 = T_c/\delta$ (N·m/rad), so that
  $T \approx \sigma_0 \cdot$ displacement after a reversal. The initial state $z_0$ is fitted when
  the data determine it (a record starting in motion), else 0 (starting at rest, unloaded).

$b$ is a direction-independent offset (N·m; a torque-sensor or rigid-body model offset): with
$|\omega|$ never far from zero it is not absorbed by direction-dependent Coulomb levels as in
eq. 9. There is no viscous term: below 0.01 rad/s a torque $T_v\omega$ is at most
$T_v \cdot 0.01$ and not separable from the slope of $\tanh(\omega/s)$ or from $\sigma_0$.

The nonlinear scale ($s$ or $\delta$) is profiled: the torques by linear least squares on a
logarithmic grid, then a bounded scalar search around the best grid point. The law with the lower
held-out RMS (first `train_fraction` of every record fitted, the rest predicted) is selected; both
are reported.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize

from .._model.friction_only import dahl_recurrence
from .covariance import inflated_covariance, robust_covariance, standard_errors
from .friction import FrictionProblem, rms_stats

LOW_SPEED_LIMIT = 0.01  # rad/s: records whose 98th percentile |ω| is below this use the low-speed law
LOW_SPEED_MODELS = ("regularised_coulomb", "dahl_presliding")
GRID = 33
COND_MAX = 1e8  # the initial-state column is dropped when it makes the design this ill-conditioned


def low_speed_reason(problem: FrictionProblem) -> str | None:
    """Why `problem` needs the low-speed law (`None` when eq. 9 applies)."""
    vabs = np.abs(problem.v[problem.mask])
    q98 = float(np.quantile(vabs, 0.98))
    if q98 < LOW_SPEED_LIMIT:
        return (f"98 % of the samples are below {q98:.3g} rad/s (< {LOW_SPEED_LIMIT:g} rad/s): presliding and "
                "Stribeck-regime friction, fitted by a low-speed law rather than eq. 9")
    if not problem.eq9_identifiable(problem.mask.astype(float)):
        npos, nneg = problem.directions(problem.mask.astype(float))
        return (f"only {npos} positive and {nneg} negative samples beyond "
                f"{3 * problem.smoothing.velocity_scale:g} rad/s, too few for eq. 9: fitted by a low-speed law")
    return None


def dahl_state_exact(v: np.ndarray, t: np.ndarray, delta) -> tuple[np.ndarray, np.ndarray]:
    """Dahl state from $z_0 = 0$ and the decay of the initial state, shapes (grid, experiment, time)
    for presliding distances `delta` (grid,): $z_n = a_n z_{n-1} + (1 - a_n)\\,\\mathrm{sign}(\\omega_n)$,
    $a_n = e^{-|\\omega_n| h_n/\\delta}$ (exact for velocity held over the interval ending at sample n;
    padding with a repeated time holds the state), with the exact sign (no smoothing scale). The
    recurrence is the friction model's (`hdjax._model.friction_only.dahl_recurrence`). The state with
    initial value $z_0$ is `z + z0 * decay`, decay $P_n = \\prod_{m \\le n} a_m$."""
    z, P = _dahl_exact(jnp.asarray(delta, dtype=float), jnp.asarray(v, dtype=float), jnp.asarray(t, dtype=float))
    return np.asarray(z), np.asarray(P)


@jax.jit
def _dahl_exact(d, v, t):
    """`dahl_state_exact` compiled once per shape: the profiled law evaluates it ~40 times per fit
    (1 s each when run op by op)."""

    def one(dist, ve, te):
        return dahl_recurrence(dist, ve, te, None, target=jnp.sign(ve), s0=0.0)[0]

    z = jax.vmap(jax.vmap(one, in_axes=(None, 0, 0)), in_axes=(0, None, None))(d, v, t)
    travel = jnp.cumsum(jnp.abs(v) * jnp.diff(t, axis=-1, prepend=t[..., :1]), axis=-1)
    return z, jnp.exp(-travel[None] / d[:, None, None])


@dataclasses.dataclass(eq=False)
class LowSpeedLaw:
    """One fitted low-speed law: `model`, its nonlinear `scale` (s in rad/s or δ in rad),
    linear `coef` (Tc, b, and Tc·z0 for Dahl), `prediction` (experiment, time) on every sample."""

    model: str
    scale: float
    coef: dict
    prediction: np.ndarray
    z0_fitted: bool = False


def _design(problem: FrictionProblem, model: str, scale: np.ndarray) -> np.ndarray:
    """Design matrices (grid, experiment, time, columns) of `model` at scales `scale` (grid,)."""
    v = problem.v
    one = np.ones_like(v)
    if model == "regularised_coulomb":
        cols = [np.tanh(v[None] / np.asarray(scale)[:, None, None]), np.broadcast_to(one, (len(scale),) + v.shape)]
    else:
        z, P = dahl_state_exact(v, np.asarray(problem.data.time), scale)
        cols = [z, np.broadcast_to(one, z.shape), P]
    return np.stack(cols, -1)


def _solve_linear(A: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float, bool]:
    """Least squares on columns of A; the Dahl initial-state column (the third) is dropped when
    it leaves the design ill-conditioned. Returns (coefficients with 0 for dropped, SSE, used z0)."""
    use_z0 = A.shape[1] == 3
    if use_z0:
        sv = np.linalg.svd(A / np.maximum(np.linalg.norm(A, axis=0), 1e-300), compute_uv=False)
        if sv[-1] <= 0 or sv[0] / sv[-1] > COND_MAX:
            use_z0 = False
    cols = A if use_z0 or A.shape[1] == 2 else A[:, :2]
    c, *_ = np.linalg.lstsq(cols, y, rcond=None)
    sse = float(np.sum((cols @ c - y) ** 2))
    if A.shape[1] == 3 and not use_z0:
        c = np.concatenate([c, [0.0]])
    return c, sse, use_z0


def _grid(problem: FrictionProblem, model: str, on: np.ndarray) -> np.ndarray:
    vabs = np.abs(problem.v[on])
    if model == "regularised_coulomb":
        top = max(float(np.quantile(vabs, 0.98)), 1e-12)
        return np.geomspace(1e-3 * top, 10 * top, GRID)
    t = np.asarray(problem.data.time)
    h = np.diff(t, axis=-1, prepend=t[..., :1])
    step = np.abs(problem.v) * h
    lo = max(float(np.median(step[on])), 1e-12)
    path = max(float(np.max(np.sum(np.where(on, step, 0.0), -1))), 10 * lo)
    return np.geomspace(lo, path, GRID)


def fit_law(problem: FrictionProblem, model: str, w: np.ndarray) -> LowSpeedLaw:
    """Fit `model` (one of `LOW_SPEED_MODELS`) to the samples `w > 0` of `problem` (profile over
    the nonlinear scale, module docstring); the prediction covers every sample."""
    on = (w > 0) & problem.mask
    y = problem.T[on]

    def sse(scale):
        A = _design(problem, model, np.atleast_1d(scale))
        return np.array([_solve_linear(A[g][on], y)[1] for g in range(A.shape[0])])

    grid = _grid(problem, model, on)
    costs = sse(grid)
    i = int(np.argmin(costs))
    lo, hi = np.log(grid[max(i - 1, 0)]), np.log(grid[min(i + 1, len(grid) - 1)])
    res = scipy.optimize.minimize_scalar(lambda u: float(sse(np.exp(u))[0]), bounds=(lo, hi), method="bounded",
                                         options={"xatol": 1e-4})
    scale = float(np.exp(res.x)) if res.fun <= costs[i] else float(grid[i])
    A = _design(problem, model, np.array([scale]))[0]
    c, _, used = _solve_linear(A[on], y)
    pred = A @ c
    if model == "regularised_coulomb":
        coef = {"Tc": float(c[0]), "offset": float(c[1])}
    else:
        coef = {"Tc": float(c[0]), "offset": float(c[1]), "z0": float(c[2] / c[0]) if used and c[0] != 0 else 0.0}
    return LowSpeedLaw(model, scale, coef, pred, used)


def law_parameters(law: LowSpeedLaw) -> dict[str, tuple[float, str]]:
    """Physical parameters of a fitted law: name → (value, unit)."""
    out = {"Tc": (law.coef["Tc"], "N·m")}
    if law.model == "regularised_coulomb":
        out["velocity_scale"] = (law.scale, "rad/s")
    else:
        out["presliding_distance"] = (law.scale, "rad")
        out["sigma0"] = (law.coef["Tc"] / law.scale, "N·m/rad")
        out["z0"] = (law.coef["z0"], "-")
    out["offset"] = (law.coef["offset"], "N·m")
    return out


def law_std_errors(problem: FrictionProblem, law: LowSpeedLaw, w: np.ndarray) -> dict[str, float]:
    """Gauss–Newton standard errors of Tc, offset and the scale (central difference in its
    logarithm), allowing for correlated residuals as `FrictionProblem.std_errors`."""
    on = (w > 0) & problem.mask
    lin = ["Tc", "offset"] + (["z0"] if law.z0_fitted else [])
    c = np.array([law.coef["Tc"], law.coef["offset"]] + ([law.coef["Tc"] * law.coef["z0"]] if law.z0_fitted else []))
    u = np.log(law.scale)
    eps = 1e-4
    A = _design(problem, law.model, np.exp(np.array([u - eps, u, u + eps])))[..., : len(c)]
    J = np.concatenate([A[1][on], ((A[2] - A[0]) @ c / (2 * eps))[on][:, None]], 1)
    r = (A[1] @ c - problem.T)[on]
    records = [(A[1] @ c - problem.T)[e][on[e]] for e in range(problem.E)]
    cov, _ = robust_covariance(J, r, problem.blocks()[on], lambda: inflated_covariance(J, r, records))
    se = standard_errors(cov, J)
    out = {k: float(se[i]) for i, k in enumerate(lin[:2])}
    out["velocity_scale" if law.model == "regularised_coulomb" else "presliding_distance"] = law.scale * float(se[-1])
    if law.model == "dahl_presliding":
        # σ0 = Tc/δ: relative errors add in quadrature (covariance neglected)
        out["sigma0"] = abs(law.coef["Tc"] / law.scale) * float(np.hypot(se[0] / max(abs(law.coef["Tc"]), 1e-300),
                                                                          se[-1]))
    return out


def check_low_speed_data(problem: FrictionProblem) -> None:
    """Refuse data no low-speed law can be fitted to (velocity never changes)."""
    v = problem.v[problem.mask]
    if float(np.ptp(v)) <= 0.0:
        raise ValueError(
            f"low-speed friction fit ({', '.join(problem.files)}): the velocity is constant ({v[0]:g} rad/s), so "
            "neither a regularisation speed nor a presliding stiffness can be told from the Coulomb level. "
            "Record motion with reversals or several speeds.")


def fit_low_speed(problem: FrictionProblem, *, train_fraction: float = 0.7) -> dict:
    """Both low-speed laws on `problem`: held-out comparison (first `train_fraction` of every
    record → the rest), then each refitted on all samples. Returns `{"selected", "laws": {model:
    {...}}, "split"}` with per law the held-out and in-sample RMS (raw and 1 Hz low-passed), the
    parameters with standard errors, and private `_law` / `_heldout_law` objects."""
    check_low_speed_data(problem)
    first, last = problem._split(train_fraction)
    allw = problem.mask.astype(float)
    laws = {}
    for model in LOW_SPEED_MODELS:
        held = fit_law(problem, model, first.astype(float))
        full = fit_law(problem, model, allw)
        se = law_std_errors(problem, full, allw)
        ht = rms_stats(held.prediction, problem.T, last.astype(float), fs=problem.fs)
        ins = rms_stats(full.prediction, problem.T, allw, fs=problem.fs)
        laws[model] = {
            "parameters": {k: {"value": v, "unit": u, "std_error": se.get(k)}
                           for k, (v, u) in law_parameters(full).items()},
            "heldout": {"rms": ht["rms"], "rms_lowpass_1hz": ht["rms_lowpass_1hz"], "nrmse": ht["nrmse"]},
            "in_sample": {"rms": ins["rms"], "rms_lowpass_1hz": ins["rms_lowpass_1hz"], "nrmse": ins["nrmse"]},
            "_law": full, "_heldout_law": held,
        }
    selected = min(LOW_SPEED_MODELS, key=lambda m: laws[m]["heldout"]["rms"])
    return {"selected": selected, "laws": laws,
            "split": f"first {train_fraction:.0%} of each record → last {1 - train_fraction:.0%}"}
