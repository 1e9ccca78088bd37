r"""Joint trajectory-error identification with optimistix Levenberg–Marquardt.

The residual is the difference between simulated and measured trajectories of *all* experiments
at once (torque, wave-generator velocity, and output position in free motion), each channel
divided by its noise level, so that the cost is a log-likelihood under white Gaussian noise:

$$r = \big[(T_{sim}-T)/\sigma_T,\ (\omega_{sim}-\omega)/\sigma_\omega,\ (\theta_{o,sim}-\theta_o)/\sigma_\theta\big].$$

Parameters are fitted in an unconstrained space: positive ones (`K1, Tst, Jeff, Tvp, Tvn, Tsp,
Tsn, Tss2`) through their logarithm, `alpha` through a logistic map onto (0.05, 1.5), the signed
Stribeck amplitudes scaled by their start value. Standard errors come from the Gauss–Newton
covariance $s^2 (J^\top J)^{-1}$ with $s^2$ the reduced chi-square, mapped to physical units by the
delta method.

Free motion has a rigid-body mode: the output *position* integrates any velocity error. The fit
stays well posed because (1) each simulation starts from the measured state (local line fits of
the first samples, `hdjax.initial_state`), (2) the wave-generator velocity — not an integrated
position — carries the rigid-body information, and (3) the output-position residual is projected off the rigid-body
components {offset, constant velocity} of each experiment before weighting, so an initial-state
error cannot dominate it; what remains (torsion and acceleration history) carries the information.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._effects import Effects
from ._experiment import Experiment
from ._model import PARAMETER_NAMES, Drive, Parameters
from ._plant import Simulator, simulate
from ._sharding import experiment_mesh, map_experiments, replicated, shard_experiments


CHANNELS = ("torque", "motor_velocity", "output_position")
POSITIVE = ("K1", "Tst", "Jeff", "Tvp", "Tvn", "Tsp", "Tsn", "Tss2")
ALPHA_BOUNDS = (0.05, 1.5)
DEFAULT_FREE = ("K1", "Tst", "Jeff", "Tvp", "Tvn", "Tsp", "Tsn", "Tssp1", "Tssn1")


class ParameterMap(eqx.Module):
    """Map between physical `Parameters` and the unconstrained vector that LM works on."""

    free: tuple[str, ...] = eqx.field(static=True)
    scale: jax.Array

    def to_theta(self, p: Parameters) -> jax.Array:
        out = []
        for k, s in zip(self.free, self.scale):
            v = getattr(p, k)
            if k in POSITIVE:
                out.append(jnp.log(v))
            elif k == "alpha":
                lo, hi = ALPHA_BOUNDS
                u = (v - lo) / (hi - lo)
                out.append(jnp.log(u) - jnp.log1p(-u))
            else:
                out.append(v / s)
        return jnp.stack(out)

    def to_params(self, theta: jax.Array, base: Parameters) -> Parameters:
        values = {}
        for j, (k, s) in enumerate(zip(self.free, self.scale)):
            t = theta[j]
            if k in POSITIVE:
                values[k] = jnp.exp(t)
            elif k == "alpha":
                lo, hi = ALPHA_BOUNDS
                values[k] = lo + (hi - lo) * jax.nn.sigmoid(t)
            else:
                values[k] = t * s
        return base.replace(**values)


def make_parameter_map(p0: Parameters, free) -> ParameterMap:
    free = tuple(free)
    unknown = [k for k in free if k not in PARAMETER_NAMES]
    if unknown:
        raise ValueError(f"`fit_parameters`: unknown parameter(s) {unknown} in `free`; choose from {list(PARAMETER_NAMES)}.")
    for k in free:
        v = float(getattr(p0, k))
        if k in POSITIVE and not v > 0:
            raise ValueError(f"`fit_parameters`: start value of {k} must be > 0 (it is fitted on a log scale), got {v}.")
        if k == "alpha" and not ALPHA_BOUNDS[0] < v < ALPHA_BOUNDS[1]:
            raise ValueError(f"`fit_parameters`: start value of alpha must lie in {ALPHA_BOUNDS}, got {v}.")
    scale = jnp.array([max(abs(float(getattr(p0, k))), 1e-3) for k in free])
    return ParameterMap(free=free, scale=scale)


def noise_levels(batch: Experiment) -> jax.Array:
    """Per-channel white-noise level (torque N·m, velocity rad/s, output position rad) estimated from
    the data itself: the second difference of a smooth signal plus white noise of std σ has std
    $\\sqrt6\\,\\sigma$. Median over experiments; position only over free-motion records."""
    out = []
    m = np.asarray(batch.mask)
    free = np.asarray(batch.free) > 0
    for name in CHANNELS:
        x = np.asarray(getattr(batch, name))
        vals = []
        for e in range(x.shape[0]):
            if name == "output_position" and not free[e]:
                continue
            xe = x[e][m[e]]
            if len(xe) > 10:
                v = np.std(np.diff(xe, 2)) / np.sqrt(6.0)
                if name == "output_position":
                    # a quantised encoder on a slow signal has mostly-zero second differences: floor
                    # at the quantisation noise q/sqrt(12), q = smallest non-zero step
                    steps = np.abs(np.diff(xe))
                    steps = steps[steps > 0]
                    if len(steps):
                        v = max(v, float(np.min(steps)) / np.sqrt(12.0))
                vals.append(v)
        v = float(np.median(vals)) if vals else 1.0
        out.append(max(v, 1e-12))
    return jnp.asarray(out)


def experiment_residuals(
    p: Parameters, drive: Drive, exp: Experiment, sigma, simulator: Simulator, effects: Effects = Effects()
):
    """Noise-weighted residuals of one experiment, shape (3, time); zero on padding and on channels
    that were not measured."""
    tr = simulate(p, drive, exp, effects=effects, simulator=simulator)
    m = exp.mask
    use_pos = exp.free * exp.has_output_position
    r = jnp.stack(
        [
            (tr.torque - exp.torque) / sigma[0],
            (tr.motor_velocity - exp.motor_velocity) / sigma[1],
            use_pos * (tr.output_position - exp.output_position) / sigma[2],
        ]
    )
    r = jnp.where(m[None, :], r, 0.0)
    # rigid-body mode: project the output-position residual off {1, t} (offset and constant
    # velocity), which an initial-state error adds and which carries no parameter information
    w = m.astype(float)
    tt = (exp.time - exp.time[0]) * w
    basis = jnp.stack([w, tt - jnp.sum(tt) / jnp.maximum(jnp.sum(w), 1.0) * w])
    coef = (basis @ r[2]) / jnp.maximum(jnp.sum(basis**2, axis=1), 1e-300)
    r = r.at[2].set(r[2] - coef @ basis)
    # a failed solve gives a large finite residual (never NaN), so LM backs off
    return jnp.where(tr.success & jnp.all(jnp.isfinite(r)), r, 1e3)


def nrmse(sim: np.ndarray, meas: np.ndarray) -> float:
    """RMS(sim − meas) / RMS(meas − mean(meas)) (SPEC §3)."""
    d = np.sqrt(np.mean((sim - meas) ** 2))
    s = np.sqrt(np.mean((meas - np.mean(meas)) ** 2))
    return float(d / s) if s > 0 else float("nan")


@dataclasses.dataclass
class TrajectoryFit:
    """Result of `fit_parameters`.

    **Attributes:**

    - `params`: fitted `Parameters` (SI).
    - `free`: names of the fitted parameters.
    - `std_error`: Gauss–Newton standard error per fitted parameter (SI).
    - `correlation`: correlation matrix of the fitted parameters (order of `free`).
    - `chi2_reduced`: residual sum of squares / (n − p); ≈1 when the model explains the data
      to the noise level.
    - `converged`: LM reached its tolerance within `max_steps`.
    - `steps`: LM iterations.
    - `sigma`: channel noise levels used as weights.
    - `jacobian_singular_values`: of the weighted Jacobian in the unconstrained space.
    """

    params: Parameters
    free: tuple[str, ...]
    std_error: dict
    correlation: np.ndarray
    chi2_reduced: float
    converged: bool
    steps: int
    sigma: np.ndarray
    jacobian_singular_values: np.ndarray


def _covariance(J: np.ndarray, chi2: float):
    JtJ = J.T @ J
    try:
        cov = np.linalg.pinv(JtJ, rcond=1e-13) * chi2
    except np.linalg.LinAlgError:
        cov = np.full_like(JtJ, np.nan)
    return cov


def fit_parameters(
    p0: Parameters,
    drive: Drive,
    batch: Experiment,
    *,
    free=DEFAULT_FREE,
    simulator: Simulator = Simulator(rtol=1e-6, atol=1e-8),
    solver=optx.LevenbergMarquardt(rtol=1e-6, atol=1e-6),
    max_steps: int = 40,
    sigma=None,
) -> TrajectoryFit:
    """Fit `free` parameters on the trajectory error of all experiments of `batch` at once.

    **Main arguments:**

    - `p0`: start values (for example the paper's regressions, `identify_paper`).
    - `drive`: drive constants.
    - `batch`: stacked experiments (`stack_experiments`), constrained and free mixed.
    - `free`: names of the parameters to fit; the others stay at `p0`.

    **Other arguments:** `simulator` (ODE numerics), `solver` (optimistix LM), `max_steps`,
    `sigma` (channel noise levels; estimated from the data by `noise_levels` when None).

    **Returns:** a `TrajectoryFit`.
    """
    pmap = make_parameter_map(p0, free)
    sigma = noise_levels(batch) if sigma is None else jnp.asarray(sigma)
    theta0 = pmap.to_theta(p0)
    # several devices: split the experiment axis over all of them (masked dummies pad the batch)
    mesh = experiment_mesh() if jax.device_count() > 1 else None
    if mesh is not None:
        batch, _ = shard_experiments(batch, mesh)

    def residuals(theta, args):
        p0_, drive_, batch_, sigma_ = args
        p = pmap.to_params(theta, p0_)

        def per_experiment(shared, b):
            p_, d_, s_ = shared
            return jax.vmap(lambda e: experiment_residuals(p_, d_, e, s_, simulator))(b)

        r = map_experiments(per_experiment, mesh)((p, drive_, sigma_), batch_)
        return r.reshape(-1)

    # LM linearises the residuals at every iterate and applies the linearisation several times
    # (materialising J, predicted reduction); through the solver's while loops each application
    # re-runs the ODE solve. Materialising J once per iterate (forward mode) and answering every
    # JVP with J @ t is the same arithmetic up to round-off, with 39 % less time per LM step and
    # 25 % less compilation (measured, benchmarks/RESULTS.md).
    @jax.custom_jvp
    def residuals_lm(theta, args):
        return residuals(theta, args)

    @residuals_lm.defjvp
    def _residuals_lm_jvp(primals, tangents):
        (theta, args), (dtheta, _) = primals, tangents  # the data are never differentiated
        J, r = jax.jacfwd(lambda t: (lambda r: (r, r))(residuals(t, args)), has_aux=True)(theta)
        return r, J @ dtheta

    # one JIT for the whole fit; data enter as arguments (never as closed-over constants, which
    # XLA would try to constant-fold)
    @eqx.filter_jit
    def run(theta0, args):
        sol = optx.least_squares(residuals_lm, solver, theta0, args, max_steps=max_steps, throw=False)
        r = residuals(sol.value, args)
        J = jax.jacfwd(residuals)(sol.value, args)
        if mesh is not None:  # every process can read the result (multi-host)
            r, J = (jax.lax.with_sharding_constraint(x, replicated(mesh)) for x in (r, J))
        return sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"], r, J

    theta, ok, steps, r, J = run(theta0, (p0, drive, batch, sigma))
    theta, r, J = np.asarray(theta), np.asarray(r), np.asarray(J)
    n_obs = int(np.sum(r != 0.0))
    chi2 = float(np.sum(r**2) / max(n_obs - len(free), 1))
    cov_theta = _covariance(J, chi2)
    # delta method: d p / d theta
    dp = np.asarray(jax.jacfwd(lambda t: jnp.stack([getattr(pmap.to_params(t, p0), k) for k in free]))(jnp.asarray(theta)))
    cov = dp @ cov_theta @ dp.T
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se, se)
    params = pmap.to_params(jnp.asarray(theta), p0)
    return TrajectoryFit(
        params=params,
        free=tuple(free),
        std_error={k: float(v) for k, v in zip(free, se)},
        correlation=corr,
        chi2_reduced=chi2,
        converged=bool(ok),
        steps=int(steps),
        sigma=np.asarray(sigma),
        jacobian_singular_values=np.linalg.svd(J, compute_uv=False),
    )
