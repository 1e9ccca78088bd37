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
import functools
from collections.abc import Callable, Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float
from numpy.typing import ArrayLike

from .._data.experiment import Experiment, take_rows
from .._model.effects import TERMS, Effects
from .._model.paper import PARAMETER_NAMES, Drive, Parameters
from .._plant.sharding import (
    experiment_batching,
    experiment_mesh,
    for_each_experiment,
    map_experiments,
    pad_experiments,
    replicated,
    shard_experiments,
)
from .._plant.simulate import Simulator, Trajectory, is_fixed_cost, simulate
from .._workflows.progress import count_progress, lm_progress
from .covariance import UNDETERMINED_SE_RTOL, null_directions, poorly_determined, robust_covariance, time_blocks, white_covariance
from .lm import MarquardtLM, _MarquardtState, _reduced_chi2
from .paper import _consistency
from .parameterisation import Entry, Parameterisation, parameterisation

CHANNELS = ("torque", "motor_velocity", "output_position")
POSITIVE = ("K1", "Tst", "Jeff", "Tvp", "Tvn", "Tsp", "Tsn", "Tss2")
ALPHA_BOUNDS = (0.05, 1.5)
DEFAULT_FREE = ("K1", "Tst", "Jeff", "Tvp", "Tvn", "Tsp", "Tsn", "Tssp1", "Tssn1")


def make_parameter_map(p0: Parameters, free) -> Parameterisation:
    """The paper parameters' `Parameterisation` for LM: positive parameters (`POSITIVE`) on a log
    scale, α by a logit inside `ALPHA_BOUNDS`, the Stribeck amplitudes (signed) scaled by
    max(|start|, 1e-3)."""
    free = tuple(free)
    unknown = [k for k in free if k not in PARAMETER_NAMES]
    if unknown:
        raise ValueError(f"`fit_parameters`: unknown parameter(s) {unknown} in `free`; choose from {list(PARAMETER_NAMES)}.")
    entries, scale = [], []
    for k in free:
        v = float(getattr(p0, k))
        if k in POSITIVE:
            if not v > 0:
                raise ValueError(f"`fit_parameters`: start value of {k} must be > 0 (it is fitted on a log scale), got {v}.")
            entries.append(Entry(k, transform="log"))
            scale.append(1.0)
        elif k == "alpha":
            if not ALPHA_BOUNDS[0] < v < ALPHA_BOUNDS[1]:
                raise ValueError(f"`fit_parameters`: start value of alpha must lie in {ALPHA_BOUNDS}, got {v}.")
            entries.append(Entry(k, transform="logit", bounds=ALPHA_BOUNDS))
            scale.append(1.0)
        else:
            entries.append(Entry(k))
            scale.append(max(abs(v), 1e-3))
    return parameterisation(entries, np.asarray(scale))


def make_effect_map(effects: Effects, free_effects: Mapping[str, float] | None) -> Parameterisation | None:
    """The `Parameterisation` of the effect parameters a trajectory-error fit frees: each dotted path
    of `free_effects` into `effects` (e.g. "sensor_bandwidth.torque_lag") on a linear scale, from
    its value in `effects` (vector 0) with the given scale (one unit of the vector, e.g. the sample
    period for a time constant). None when nothing is freed."""
    if not free_effects:
        return None
    paths, scales, starts = [], [], []
    for path, scale in free_effects.items():
        name, _, field = path.partition(".")
        if name not in TERMS or field not in TERMS[name].parameter_names():
            raise ValueError(f"`fit_parameters`: unknown effect parameter {path!r} in `free_effects`; give "
                             "'<term>.<field>', e.g. 'sensor_bandwidth.torque_lag'.")
        if name not in effects.active:
            raise ValueError(f"`fit_parameters`: effect parameter {path!r} is freed, but `effects` does not switch "
                             f"{name!r} on; pass `effects=Effects().with_term(...)` with it active.")
        value = np.asarray(getattr(effects.term(name), field), dtype=float)
        if value.shape != () or not np.isfinite(value) or not float(scale) > 0:
            raise ValueError(f"`fit_parameters`: effect parameter {path!r} must be a finite scalar with a scale > 0, "
                             f"got value {value} and scale {scale!r}.")
        paths.append(Entry(path))
        scales.append(float(scale))
        starts.append(float(value))
    return parameterisation(paths, np.asarray(scales), np.asarray(starts))


def _models(theta, pmap: Parameterisation, p0: Parameters, emap: Parameterisation | None, e0: Effects):
    """(Parameters, Effects) of a fit vector θ: the paper parameters of `pmap` first, then the effect
    parameters of `emap` (none: `e0` as given)."""
    if emap is None:
        return pmap.to_model(theta, p0), e0
    n = pmap.size
    return pmap.to_model(theta[:n], p0), emap.to_model(theta[n:], e0)


def white_noise_level(x: ArrayLike) -> float:
    """White-noise std of a sampled signal: the second difference of a smooth signal plus white
    noise of std σ has std $\\sqrt6\\,\\sigma$."""
    return float(np.std(np.diff(np.asarray(x), 2)) / np.sqrt(6.0))


def noise_levels(batch: Experiment) -> Float[Array, " 3"]:
    """Per-channel white-noise level (torque N·m, velocity rad/s, output position rad) estimated from
    the data itself (`white_noise_level`). Median over experiments; position only over free-motion
    records."""
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
                v = white_noise_level(xe)
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


def process_noise(
    simulate, batch: Experiment, r_ref: Float[np.ndarray, "exp 3 time"], *, realisations: int = 2, seed: int = 0
) -> Float[np.ndarray, "realisation exp 3 time"]:
    """Change of the (weighted) residuals when white noise of the recorded current's own noise
    level is added to the current, shape (realisations, exp, channel, time): samples of the process
    noise that the current's sensor noise puts into every simulation (the simulation is driven by
    the recorded current). `simulate(batch)` returns the residuals; `r_ref` is its value on `batch`."""
    m = np.asarray(batch.mask)
    cur = np.asarray(batch.current)
    # records too short for a noise estimate (under 11 samples) do not vote
    level = float(np.median([white_noise_level(cur[e][m[e]]) for e in range(cur.shape[0]) if m[e].sum() > 10] or [0.0]))
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(realisations):
        noisy = eqx.tree_at(lambda b: b.current, batch, jnp.asarray(cur + level * rng.standard_normal(cur.shape) * m))
        out.append(np.asarray(simulate(noisy)) - r_ref)
    return np.stack(out)


def process_noise_levels(
    p: Parameters, drive: Drive, batch: Experiment, *, simulator: Simulator, realisations: int = 2, seed: int = 0
) -> Float[np.ndarray, " 3"]:
    """Per-channel RMS of the *process noise* (same units as `noise_levels`, `process_noise` at the
    parameters `p`): how far the simulation of each channel moves when white noise of the recorded
    current's own noise level is added to the current. In free motion the output position does a
    random walk (after the rigid-body projection of `experiment_residuals`) that can be 10³× the
    encoder's noise. Position over free records only."""
    simulate = lambda b: _unit_residuals(p, drive, b, simulator)
    d = process_noise(simulate, batch, np.asarray(simulate(batch)), realisations=realisations, seed=seed)
    m = np.asarray(batch.mask)
    free = m & (np.asarray(batch.free)[:, None] > 0)
    ms = [np.mean(d[:, :, 0][:, m] ** 2), np.mean(d[:, :, 1][:, m] ** 2),
          np.mean(d[:, :, 2][:, free] ** 2) if free.any() else 0.0]
    return np.sqrt(np.asarray(ms))


@eqx.filter_jit
def _unit_residuals(p, drive, batch, simulator):
    return for_each_experiment(lambda e: experiment_residuals(p, drive, e, jnp.ones(3), simulator), batch,
                               fixed_cost=is_fixed_cost(simulator))


def fit_noise_levels(p: Parameters, drive: Drive, batch: Experiment, *, simulator: Simulator) -> Float[Array, " 3"]:
    """The weights of a trajectory-error fit: per channel √(sensor² + process²), the sensor noise
    from the data (`noise_levels`) and the process noise that the recorded current's noise puts into
    the simulation at `p` (`process_noise_levels`). Weighting the free-motion output position by the
    encoder noise alone let the current-noise random walk dominate the cost (χ²/n ≈ 380 at the true
    parameters on an independent-bench dataset) and trapped the fit in a local minimum of the
    Stribeck amplitudes; with this weighting it converged to them (benchmarks/RESULTS.md)."""
    sensor = np.asarray(noise_levels(batch))
    return jnp.asarray(np.sqrt(sensor**2 + process_noise_levels(p, drive, batch, simulator=simulator) ** 2))


def experiment_residuals(
    p: Parameters,
    drive: Drive,
    exp: Experiment,
    sigma: Float[Array, " 3"],
    simulator: Simulator,
    effects: Effects = Effects(),
) -> Float[Array, "3 time"]:
    """Noise-weighted residuals of one experiment, shape (3, time); zero on padding and on channels
    that were not measured."""
    return trajectory_residuals(simulate(p, drive, exp, effects=effects, simulator=simulator), exp, sigma)


def trajectory_residuals(tr: Trajectory, exp: Experiment, sigma: Float[Array, " 3"]) -> Float[Array, "3 time"]:
    """`experiment_residuals` of a simulated trajectory `tr` of `exp`."""
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


def nrmse(sim: Float[np.ndarray, " time"], meas: Float[np.ndarray, " time"]) -> float:
    """RMS(sim − meas) / RMS(meas − mean(meas)) (SPEC §3)."""
    d = np.sqrt(np.mean((sim - meas) ** 2))
    s = np.sqrt(np.mean((meas - np.mean(meas)) ** 2))
    return float(d / s) if s > 0 else float("nan")


class TrajectoryFit(eqx.Module):
    """Result of `fit_parameters`.

    **Attributes:**

    - `params`: fitted `Parameters` (SI).
    - `free`: names of the fitted parameters.
    - `effects`: the `Effects` every simulation of the fit applied, with the freed effect parameters
      at their fitted values (`Effects()` when the fit used none).
    - `free_effects`: the dotted paths of the fitted effect parameters (e.g.
      "sensor_bandwidth.torque_lag"), after `free` in the vector, the Jacobian and `correlation`.
    - `std_error`: standard error per fitted parameter (SI; effect parameters by path), robust to a
      misfit that is correlated in time (`std_error_method`, see `block_covariance`); infinite for
      a parameter that moves along a null direction of JᵀJ (`null_directions`: the records do not
      inform it, e.g. a negative-direction Stribeck amplitude fitted on records that only turn
      forward), whose correlations are then NaN.
    - `std_error_white`: the Gauss–Newton standard error, σ²(JᵀJ)⁻¹ with σ² the reduced χ²: right
      only when the residuals are white; on a bench where the model is not exact it is too small
      (`fit_parameters`'s `se_block`).
    - `std_error_method`: "block_sandwich" (`std_error` from `block_covariance`) or "white" (too
      few blocks for it; `std_error` is then `std_error_white`).
    - `se_block`: the block length of `block_covariance` (s).
    - `correlation`: correlation matrix of the fitted parameters (order of `free`, then
      `free_effects`), from the
      covariance that gives `std_error`.
    - `chi2_reduced`: residual sum of squares / (n − p); ≈1 when the model explains the data
      to the noise level.
    - `converged`: LM stopped by one of its rules (see `stop_reason`) within `max_steps`.
    - `steps`: LM iterations.
    - `sigma`: channel noise levels used as weights.
    - `jacobian_singular_values`: of the weighted Jacobian in the unconstrained space.
    - `stop_reason`: "tolerance" (optimistix's test), "gauss_newton_step_small" (the remaining
      Gauss–Newton step is under `step_se_tol` standard errors), "cost_stalled" (`STALL_WINDOW` LM
      steps lowered ½χ² by less than `cost_rtol`), "predicted_gain_small" (the full Gauss–Newton
      step predicts a decrease under `gain_rtol` of ½χ²), see `CostStop`; or "max_steps".
    - `result`: optimistix's result code (`optx.RESULTS.successful` when `converged`; otherwise
      the reason, e.g. `optx.RESULTS.nonlinear_max_steps_reached`).
    """

    params: Parameters
    free: tuple[str, ...] = eqx.field(static=True)
    effects: Effects
    free_effects: tuple[str, ...] = eqx.field(static=True)
    std_error: dict[str, float]
    std_error_white: dict[str, float]
    std_error_method: str
    se_block: float
    correlation: np.ndarray
    chi2_reduced: float
    converged: bool
    steps: int
    sigma: np.ndarray
    jacobian_singular_values: np.ndarray
    stop_reason: str
    result: optx.RESULTS


STALL_WINDOW = 3
"""LM steps between two checks of the cost-stall rule (`_stalled`)."""


def _stalled(cost_before, cost_after, cost_rtol):
    """The stopping rule used on top of optimistix's: `STALL_WINDOW` LM steps lowered ½χ² by less
    than `cost_rtol` of its value (or raised it). Works on floats and on JAX scalars.

    optimistix stops when the parameter change *and the change of every residual* fall below its
    tolerances (max norm). The residual of an adaptive ODE solve jitters under parameter changes at
    about its relative tolerance (½χ² moves by ~1 in 10⁵ at rtol 1e-5, measured on HD2), so that test
    is never met once the poorly determined Stribeck amplitudes wander inside their standard error;
    the fit then ran to its step cap with the cost flat to 5 digits after 6 steps."""
    return jnp.logical_not(cost_after < cost_before * (1.0 - cost_rtol))


def _gauss_newton_step_in_se(residual, jacobian):
    """Length of the full Gauss–Newton step from here, in standard errors (Mahalanobis):
    m² = δᵀJᵀJδ / s², δ = argmin ‖J δ + r‖ (minimum norm, so a rank-deficient J is fine),
    s² = ‖r‖²/(n − p) the reduced χ² over the non-zero residuals; and the decrease of ½χ² that step
    predicts, ½‖Jδ‖² = ½m²s². Built from the Jacobian, not from a difference of two residuals, so
    it does not see the ODE solver's jitter. Returns (m, predicted decrease)."""
    delta = jnp.linalg.lstsq(jacobian, -residual)[0]
    s2 = _reduced_chi2(residual, jacobian.shape[1])
    jd2 = jnp.sum((jacobian @ delta) ** 2)
    return jnp.sqrt(jd2 / jnp.maximum(s2, 1e-300)), 0.5 * jd2


class _StopState(eqx.Module):
    inner: object
    checkpoint: jax.Array  # ½χ² at the last stall check (inf before the first)
    reason: jax.Array  # index into STOP_REASONS (0: none of CostStop's rules)
    cost: jax.Array  # ½χ² at the accepted point after the last step (inf before the first)
    step_se: jax.Array  # the Gauss–Newton step left there, in standard errors (inf before the first)


STOP_REASONS = ("tolerance", "gauss_newton_step_small", "cost_stalled", "predicted_gain_small", "cost_jump")
"""How a fit ended (`TrajectoryFit.stop_reason`, `PerExperimentFit.stop_reason`), besides "max_steps":
the inner solver's tolerances, `CostStop`'s three rules, or (`MarquardtLM(reject_se_tol=...)`, the
per-experiment fits) a trial shorter than that many standard errors raised the cost: a jump of the
cost, such as a motor that sticks or not at a reversal, within that distance of the estimate."""


class CostStop(optx.AbstractLeastSquaresSolver):
    """A Gauss–Newton-type optimistix solver (e.g. `LevenbergMarquardt`) with two more stopping
    rules, checked at every accepted point:

    - *Gauss–Newton step small*: the full Gauss–Newton step from the accepted point is shorter
      than `step_se_tol` standard errors (`_gauss_newton_step_in_se`): what is left to gain is far
      inside the estimate's own uncertainty;
    - *cost stalled*: the last `window` steps lowered ½χ² by less than `cost_rtol` (`_stalled`),
      a safeguard when the Jacobian is poor;
    - *predicted gain small*: the full Gauss–Newton step from the accepted point predicts a decrease
      of ½χ² under `gain_rtol` of its value (MINPACK's predicted-reduction test; 0 switches it
      off): the stall rule's threshold, without waiting `window` steps to see it, and below what
      the adaptive solve resolves (½χ² jitters by ~1e-5 relative at rtol 1e-5). On the HD2 joint
      fit every step after that point was rejected (steps 5–9 of 9, ½χ² unchanged to 8 digits,
      2026-11-27).

    Everything else is the inner solver's, with one residual-and-Jacobian evaluation per LM step:
    in `optx.least_squares` it is one compiled optimistix loop, and `fit_parameters` takes the same
    steps from Python (`_stepped_least_squares`). `state.reason` says which rule stopped it
    (`STOP_REASONS`); `state.inner.f_info` holds the residual and Jacobian at the returned point."""

    inner: optx.AbstractLeastSquaresSolver
    step_se_tol: float = 0.1
    cost_rtol: float = 1e-5
    gain_rtol: float = 1e-5
    window: int = STALL_WINDOW
    callback: Callable | None = eqx.field(default=None, static=True)
    """Host function `(step, ½χ², Gauss–Newton step in standard errors)` called after every LM
    step through `jax.debug.callback`; None compiles nothing in. A program that holds a host
    callback is never written to JAX's persistent compilation cache: `fit_parameters` leaves it
    None and reports its steps from Python (`_stepped_least_squares`), reading the same figures
    from the state (`cost`, `step_se`)."""

    # equinox lets a property implement an `AbstractVar`; pyright takes them for dataclass fields
    @property
    def rtol(self):  # pyright: ignore[reportIncompatibleVariableOverride]
        return self.inner.rtol

    @property
    def atol(self):  # pyright: ignore[reportIncompatibleVariableOverride]
        return self.inner.atol

    @property
    def norm(self):  # pyright: ignore[reportIncompatibleMethodOverride]
        return self.inner.norm

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        inner = self.inner.init(fn, y, args, options, f_struct, aux_struct, tags)
        return _StopState(inner, jnp.array(jnp.inf), jnp.array(0), jnp.array(jnp.inf), jnp.array(jnp.inf))

    def step(self, fn, y, args, options, state, tags):
        y, inner, aux = self.inner.step(fn, y, args, options, state.inner, tags)
        r = inner.f_info.residual
        cost = 0.5 * jnp.sum(r**2)
        m, predicted = _gauss_newton_step_in_se(r, lx.materialise(inner.f_info.jac).as_matrix())
        check = (inner.num_steps % self.window) == 0
        stalled = check & _stalled(state.checkpoint, cost, self.cost_rtol)
        checkpoint = jnp.where(check, cost, state.checkpoint)
        small_gain = predicted < self.gain_rtol * cost
        reason = jnp.where(m < self.step_se_tol, 1, jnp.where(stalled, 2, jnp.where(small_gain, 3, 0)))
        if isinstance(inner, _MarquardtState):  # `MarquardtLM(reject_se_tol=...)`: a short trial raised the cost
            reason = jnp.where((reason == 0) & inner.blocked, STOP_REASONS.index("cost_jump"), reason)
        if self.callback is not None:
            jax.debug.callback(self.callback, inner.num_steps, cost, m)
        return y, _StopState(inner, checkpoint, reason, cost, m), aux

    def terminate(self, fn, y, args, options, state, tags):
        terminate, result = self.inner.terminate(fn, y, args, options, state.inner, tags)
        return terminate | (state.reason > 0), result

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.inner.postprocess(fn, y, aux, args, options, state.inner, tags, result)


def _stop_reason(result, reason) -> np.ndarray:
    """Per fit: one of `STOP_REASONS` or "max_steps"."""
    ok = np.asarray(result == optx.RESULTS.successful)
    return np.where(ok, np.asarray(STOP_REASONS)[np.asarray(reason)], "max_steps")


def _state_residual_and_jacobian(state):
    """Residual and (materialised) Jacobian at the accepted point of a `CostStop` state (already
    computed there)."""
    info = state.inner.f_info
    return info.residual, lx.materialise(info.jac).as_matrix()


def _final_residual_and_jacobian(sol):
    """Residual and (materialised) Jacobian at `sol.value`, from the LM state."""
    return _state_residual_and_jacobian(sol.state)


def _lm_objective(residuals):
    """`residuals(theta, args)` as LM's objective, with its linearisation materialised once per
    iterate.

    optimistix LM linearises the residuals at every iterate and applies the linearisation several
    times (materialising J, predicted reduction); through the solver's while loops each
    application re-runs the ODE solve. Materialising J once (forward mode) and answering every JVP
    with J @ t is the same arithmetic up to round-off, with 39 % less time per LM step and 25 %
    less compilation (measured, benchmarks/RESULTS.md)."""

    @eqx.filter_jit
    def jitted(theta, args):
        J, r = jax.jacfwd(lambda t: (lambda r: (r, r))(residuals(t, args)), has_aux=True)(theta)
        return r, J

    # The residual and its Jacobian, traced once per program however often LM asks: one jitted
    # function (JAX keeps its trace), so optimistix's start (an `eval_shape` of the linearisation)
    # and its step share one trace. Wrapped in a `custom_jvp` because `jax.linearize` partially
    # evaluates a jitted call again (every scan and loop inside it) even when all its inputs are
    # known, but binds a custom-JVP function with known inputs as it is. Shipped HD2 joint fit
    # (12 records, 4 substeps, one device): its LM programs traced in 2.75 s instead of 3.87 s
    # (8.8 s before the one jitted function), the same iterates (2026-12-04).
    @jax.custom_jvp
    def residual_and_jacobian(theta, args):
        return jitted(theta, args)

    @residual_and_jacobian.defjvp
    def _never_differentiated(primals, tangents):
        raise NotImplementedError("the LM objective's Jacobian is not differentiated (no second derivatives)")

    # The primal is the same jitted function's residual, not `residuals` itself: optimistix asks for
    # the objective's output shape (`jax.eval_shape` of the primal) before it linearises, and with
    # `residuals` as the primal that traced the whole plant once more only to learn a shape. Here
    # the shape comes from the trace the linearisation reuses. At run time the primal is never
    # evaluated on its own (every LM evaluation goes through the JVP rule). 12-record HD2 joint fit
    # as `benchmarks/fit_vs_scipy.py` runs it (2026-12-07): tracing 2.25 → 1.48 s, the fit 7.05 →
    # 6.08 s, the same iterates to the last bit.
    @jax.custom_jvp
    def objective(theta, args):
        return residual_and_jacobian(theta, args)[0]

    @objective.defjvp
    def _jvp(primals, tangents):
        (theta, args), (dtheta, _) = primals, tangents  # the data are never differentiated
        r, J = residual_and_jacobian(theta, args)
        return r, J @ dtheta

    return objective


def fit_parameters(
    p0: Parameters,
    drive: Drive,
    batch: Experiment,
    *,
    free=DEFAULT_FREE,
    simulator: Simulator = Simulator(rtol=1e-6, atol=1e-8),
    solver=optx.LevenbergMarquardt(rtol=1e-6, atol=1e-6),
    max_steps: int = 40,
    step_se_tol: float = 0.1,
    cost_rtol: float = 1e-5,
    sigma=None,
    se_block: float = 0.1,
    throw: bool = True,
    effects: Effects = Effects(),
    free_effects: Mapping[str, float] | None = None,
) -> TrajectoryFit:
    """Fit `free` parameters on the trajectory error of all experiments of `batch` at once.

    **Main arguments:**

    - `p0`: start values (for example the paper's regressions, `identify_paper`).
    - `drive`: drive constants.
    - `batch`: stacked experiments (`stack_experiments`), constrained and free mixed.
    - `free`: names of the parameters to fit; the others stay at `p0`.

    **Other arguments:** `simulator` (ODE numerics), `solver` (optimistix LM), `max_steps` (LM
    steps in all), `step_se_tol` (also stop when the Gauss–Newton step left is shorter than this
    many standard errors), `cost_rtol` (also stop when `STALL_WINDOW` steps lower ½χ² by less than
    this fraction), see `CostStop`; `sigma` (channel noise levels; `fit_noise_levels` at `p0`, sensor plus process noise, when
    None); `se_block` (s: the standard errors allow a misfit correlated over this long, see
    `block_covariance`; 0.1 s, the scale of the records' motion: on clean independent-bench data
    0.05–0.25 s blocks gave standard errors within 2× of each other, single-sample blocks 4–6× smaller; with
    fewer than two blocks per fitted parameter the white-noise errors are reported); `throw` (as in
    optimistix: raise a `RuntimeError` when LM stops without converging;
    with `throw=False` the result is returned and `result` / `converged` say how it ended);
    `effects` (terms every simulation applies, e.g. the sensors' first-order lags of
    `sensor_bandwidth`), `free_effects` (dotted paths into `effects` fitted with the parameters,
    each with its scale, one unit of the LM vector: `{"sensor_bandwidth.torque_lag": dt}`; on a
    linear scale from their values in `effects`, see `make_effect_map`).

    **Returns:** a `TrajectoryFit`.
    """
    pmap = make_parameter_map(p0, free)
    emap = make_effect_map(effects, free_effects)
    sigma = fit_noise_levels(p0, drive, batch, simulator=simulator) if sigma is None else jnp.asarray(sigma)
    theta0 = pmap.to_vector(p0) if emap is None else jnp.concatenate([pmap.to_vector(p0), emap.to_vector(effects)])
    names = tuple(free) + (() if emap is None else emap.fields)
    # several devices: split the experiment axis over all of them (masked dummies pad the batch)
    mesh = experiment_mesh() if jax.device_count() > 1 else None
    n_exp = int(batch.time.shape[0])  # the real experiments (the progress line counts no dummies)
    if mesh is not None:
        batch, _ = shard_experiments(batch, mesh)
    with lm_progress(f"LM fit ({len(names)} parameters, {n_exp} experiments)", max_steps) as callback:
        run = _cached(_joint_fit_program, pmap.fields, simulator, solver, max_steps, step_se_tol, cost_rtol, mesh)
        theta, result, reason, steps, r, J = jax.block_until_ready(
            run(theta0, (pmap, p0, emap, effects, drive, batch, sigma), callback))
    stop = str(_stop_reason(result, reason))
    if throw and stop == "max_steps":
        raise RuntimeError(
            f"`fit_parameters`: Levenberg–Marquardt did not converge ({optx.RESULTS[result]}, max_steps={max_steps}, "
            f"{int(steps)} steps). Raise `max_steps`, or pass `throw=False` to get the last iterate with "
            "`converged=False`.")
    theta, r, J = np.asarray(theta), np.asarray(r), np.asarray(J)
    n_obs = int(np.sum(r != 0.0))
    chi2 = float(np.sum(r**2) / max(n_obs - len(names), 1))
    cov_white = white_covariance(J, chi2)
    blocks = np.broadcast_to(time_blocks(np.asarray(batch.time), se_block)[:, None, :], (batch.time.shape[0], 3, batch.time.shape[1]))
    cov_robust, how = robust_covariance(J, r, blocks, lambda: cov_white)  # residual rows: experiment, channel, sample
    method = "block_sandwich" if how == "block_sandwich" else "white"
    # delta method: d p / d theta (the effect parameters are linear in theta: their scales)
    n_p = pmap.size
    dp = np.zeros((len(names), len(names)))
    dp[:n_p, :n_p] = np.asarray(_model_jacobian(jnp.asarray(theta[:n_p]), pmap, p0, tuple(free)))
    if emap is not None:
        dp[n_p:, n_p:] = np.diag(np.asarray(emap.scale))
    cov = dp @ cov_robust @ dp.T
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    se_white = np.sqrt(np.clip(np.diag(dp @ cov_white @ dp.T), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se, se)
    # a parameter that moves along a null direction of JᵀJ is not informed by the records: the
    # pseudo-inverse gave it a variance of about 0, its standard error is infinite
    uninformed = np.any(dp[:, null_directions(J)] != 0, axis=1)
    se, se_white = np.where(uninformed, np.inf, se), np.where(uninformed, np.inf, se_white)
    corr[uninformed, :] = corr[:, uninformed] = np.nan
    params, fitted_effects = _models(jnp.asarray(theta), pmap, p0, emap, effects)
    return TrajectoryFit(
        params=params,
        free=tuple(free),
        effects=fitted_effects,
        free_effects=() if emap is None else emap.fields,
        std_error={k: float(v) for k, v in zip(names, se)},
        std_error_white={k: float(v) for k, v in zip(names, se_white)},
        std_error_method=method,
        se_block=float(se_block),
        correlation=corr,
        chi2_reduced=chi2,
        converged=stop != "max_steps",
        steps=int(steps),
        stop_reason=stop,
        sigma=np.asarray(sigma),
        jacobian_singular_values=np.linalg.svd(J, compute_uv=False),
        result=result,
    )


def profile_effect_parameters(
    fit: TrajectoryFit,
    drive: Drive,
    batch: Experiment,
    grids: Mapping[str, Sequence[float]],
    *,
    simulator: Simulator,
) -> tuple[Effects, dict]:
    """Set effect parameters that act on the trajectories through discrete events alone by a grid
    search of the noise-weighted squared error at `fit`'s estimate, one after the other.

    A breakaway torque (`breakaway_friction`) decides only *whether* a stuck motor slips in a step:
    the simulated trajectory is piecewise constant in it and its derivative is zero almost
    everywhere, so Levenberg–Marquardt cannot move it. Each dotted path of `grids` (into
    `fit.effects`, whose term must be active) is evaluated at every value of its grid with the
    other parameters at `fit`'s estimate (and the paths before it at their chosen values); the
    best value is refined by the parabola through it and its two neighbours where it lies inside the
    grid. One compiled program evaluates a path's whole grid at once (`vmap` over the grid values,
    which are arguments), each device taking its share of the experiments.

    `fit_breakaway_friction` alternates it with LM for the breakaway torques.

    **Returns:** the effects with the chosen values, and a report: `"paths"`, per path `{"value",
    "grid", "sse"}` (the whitened squared error at each grid value), and `"sse_start"`, `"sse_end"`
    (at `fit.effects` and at the chosen values).
    """
    effects = fit.effects
    sigma = jnp.asarray(fit.sigma)
    mesh = experiment_mesh() if jax.device_count() > 1 else None
    if mesh is not None:
        batch, _ = shard_experiments(batch, mesh)
    run = _cached(_sse_program, simulator, mesh)
    paths = tuple(grids)
    lanes = _cached(_sse_lanes_program, simulator, paths, mesh)
    make_effect_map(effects, dict.fromkeys(grids, 1.0))  # every path names an active term's scalar field
    report: dict = {"sse_start": float(run(fit.params, effects, drive, batch, sigma)), "paths": {}}
    for i, (path, grid) in enumerate(grids.items()):
        name, field = path.split(".", 1)

        def at(v, name=name, field=field):
            return effects.with_values(name, **{field: v})

        grid = np.asarray(list(grid), dtype=float)
        # one lane per grid value: every path at its current value, path i running over its grid
        now = np.array([float(getattr(effects.term(q.split(".", 1)[0]), q.split(".", 1)[1])) for q in paths])
        values = np.repeat(now[None, :], len(grid), axis=0)
        values[:, i] = grid
        sse = np.asarray(lanes(fit.params, effects, drive, batch, sigma, jnp.asarray(values)), dtype=float)
        k = int(np.argmin(sse))
        best = float(grid[k])
        if 0 < k < len(grid) - 1:  # the vertex of the parabola through the best and its neighbours
            x, y = grid[k - 1:k + 2], sse[k - 1:k + 2]
            den = (x[0] - x[1]) * (x[0] - x[2]) * (x[1] - x[2])
            a = (x[2] * (y[1] - y[0]) + x[1] * (y[0] - y[2]) + x[0] * (y[2] - y[1])) / den
            b = (x[2] ** 2 * (y[0] - y[1]) + x[1] ** 2 * (y[2] - y[0]) + x[0] ** 2 * (y[1] - y[2])) / den
            if a > 0:
                best = float(np.clip(-b / (2 * a), x[0], x[2]))
        effects = at(best)
        report["paths"][path] = {"value": best, "grid": grid.tolist(), "sse": sse.tolist()}
    report["sse_end"] = float(run(fit.params, effects, drive, batch, sigma))
    return effects, report


#: The breakaway torques `fit_breakaway_friction` sets, positive and negative direction.
BREAKAWAY_PATHS = ("breakaway_friction.breakaway_p", "breakaway_friction.breakaway_n")
#: `fit_breakaway_friction`'s grid, in units of the direction's Coulomb friction (Tsp for
#: `breakaway_p`, Tsn for `breakaway_n`, at the fit's estimate). 0 and every value at or below eq. 9's
#: friction at rest (Ts + Tss1) mean no breakaway above eq. 9. The independent bench breaks away at
#: 1.1–1.3× max(Ts, Ts + Tss1); the grid reaches 3× for drives that stick harder.
BREAKAWAY_GRID = (0.0, 0.8, 0.9, 1.0, 1.05, 1.1, 1.15, 1.2, 1.25, 1.3, 1.4, 1.5, 1.75, 2.0, 2.5, 3.0)


def fit_breakaway_friction(
    fit: TrajectoryFit,
    drive: Drive,
    batch: Experiment,
    *,
    simulator: Simulator,
    free_effects: Mapping[str, float] | None = None,
    grid: Sequence[float] = BREAKAWAY_GRID,
    max_steps: int = 40,
    step_se_tol: float = 0.1,
    cost_rtol: float = 1e-5,
) -> tuple[TrajectoryFit, dict]:
    """Fit `breakaway_friction` (`hdjax.BreakawayFriction`: static friction above eq. 9's at rest)
    with the parameters of a trajectory fit: a grid search of the breakaway torques at `fit`'s
    estimate (`profile_effect_parameters`; stick/slip events give LM no derivative), LM again from
    there with them held, and the search again at its estimate.

    The breakaway torques are torques of their own, so the LM fit in between moves the Stribeck
    amplitudes through the sliding friction alone, not through the stick events. Measured
    2026-12-06 on the shipped campaigns (the independent bench, breakaway 1.1–1.3× the friction
    level), against the same fit without it: breakaway torques within 2.5 % (HD1) and 5 % (HD2) of the
    bench's, reduced χ² 2.63 → 1.34 and 7.04 → 5.49, HD1's K1 consistency 11.9 → 1.8 %; about
    as close as with the bench's own torques held in LM from the start (χ² 1.28 and 5.56).

    **Arguments:** `fit` a `fit_parameters` result on `batch` whose `effects` has the
    `breakaway_friction` term switched on (at 0: the term changes nothing there); `simulator` the
    fixed-step stepper (`VelocityImplicit`) it used; `free_effects` the scales `fit` freed its effect
    parameters on (the same mapping; its paths must be `fit.free_effects`); `grid` in units of the
    direction's Coulomb friction; the LM options as `fit_parameters`'s.

    **Returns:** the fit with the breakaway torques in `effects` (its `steps` both LM runs', its
    `chi2_reduced` at the found torques; its standard errors are those of the LM fit with them
    held), and the second search's report (`profile_effect_parameters`), with `"lm_steps"` of the
    fit in between.
    """
    if "breakaway_friction" not in fit.effects.active:
        raise ValueError("`fit_breakaway_friction`: the fit's effects must have `breakaway_friction` switched on "
                         "(`Effects().with_term(hdjax.BreakawayFriction())`, at 0 it changes nothing).")
    scales = dict(free_effects or {})
    if tuple(scales) != tuple(fit.free_effects):
        raise ValueError(f"`fit_breakaway_friction`: `free_effects` must give the scales of the fit's freed effect "
                         f"parameters {list(fit.free_effects)}, got {list(scales)}.")

    def search(f):
        grids = {path: [abs(float(getattr(f.params, ts))) * x for x in grid]
                 for path, ts in zip(BREAKAWAY_PATHS, ("Tsp", "Tsn"))}
        return profile_effect_parameters(f, drive, batch, grids, simulator=simulator)

    found, _ = search(fit)
    refit = fit_parameters(
        fit.params, drive, batch, free=fit.free, simulator=simulator, max_steps=max_steps, step_se_tol=step_se_tol,
        cost_rtol=cost_rtol, sigma=fit.sigma, se_block=fit.se_block, throw=False, effects=found, free_effects=scales,
    )
    found, report = search(refit)
    report["lm_steps"] = refit.steps
    chi2 = refit.chi2_reduced * report["sse_end"] / report["sse_start"]
    out = eqx.tree_at(lambda r: (r.effects, r.chi2_reduced, r.steps), refit, (found, chi2, fit.steps + refit.steps))
    return out, report


# `experiment_residuals` as a jitted call inside the joint fit's residuals (`_batch_residuals`) and
# the two programs of `profile_effect_parameters` below: JAX keeps the jaxpr of its first trace (in
# the joint fit, differentiated there), and the breakaway stage's squared-error program reuses it as
# it is and its grid program, which `vmap`s it over the grid values, batches it, instead of tracing
# the plant again. HD2 fit command, reading the compilation cache, runs alternating with the code
# before (2026-12-07): the two profile programs alone sharing it, six runs each way, the grid
# program's first call 1.06 s instead of 1.86 s and the breakaway stage 4.8–5.1 s against 5.3–5.7 s;
# with the joint fit's too, two runs each way, JAX's trace events summed over the command 5.12–5.17 s
# against 5.51–5.68 s and the breakaway stage 4.6–4.7 s against 5.0–5.2 s; fit.json identical. The
# per-experiment fits' residuals call it plainly: there the JVP of the kept jaxpr cost about what
# tracing the plant does (no gain measured).
_experiment_residuals_jit = eqx.filter_jit(experiment_residuals)


@functools.lru_cache(maxsize=8)
def _sse_program(simulator, mesh):
    """The compiled whitened squared error of a batch: `run(p, effects, drive, batch, sigma)`."""

    @eqx.filter_jit
    def run(p, eff, drive_, batch_, sigma_):
        return jnp.sum(_batch_residuals(p, eff, drive_, batch_, sigma_, simulator, mesh) ** 2)

    return run


@functools.lru_cache(maxsize=8)
def _sse_lanes_program(simulator, paths, mesh):
    """The compiled whitened squared error of a batch at many values of the effect parameters
    `paths` (dotted): `run(p, effects, drive, batch, sigma, values)` with `values` (lane, path) →
    (lane,); each device of `mesh` (None: one) takes its share of the experiments and `vmap`s
    the lanes over them."""

    def at(eff, row):
        for j, path in enumerate(paths):
            name, field = path.split(".", 1)
            eff = eff.with_values(name, **{field: row[j]})
        return eff

    def per_device(shared, b):
        p_, eff_, d_, s_, values = shared

        def lane(row):
            r = for_each_experiment(lambda e: _experiment_residuals_jit(p_, d_, e, s_, simulator, at(eff_, row)), b,
                                    fixed_cost=is_fixed_cost(simulator))
            return jnp.sum(r.reshape(r.shape[0], -1) ** 2, axis=1)  # (experiment,)

        return jax.vmap(lane, out_axes=1)(values)  # (experiment, lane)

    @eqx.filter_jit
    def run(p, eff, drive_, batch_, sigma_, values):
        return jnp.sum(map_experiments(per_device, mesh)((p, eff, drive_, sigma_, values), batch_), axis=0)

    return run


PER_EXPERIMENT_REJECT_SE_TOL = 0.3
"""`fit_per_experiment`'s default `MarquardtLM(reject_se_tol=...)`: a fit ends once a trial shorter
than this many standard errors raises the cost (a jump of the stick–slip plant's cost lies within
that distance of the estimate). Measured 2026-12-07 on the shipped campaigns' per-experiment fits,
against 0.1: HD2 311 LM evaluations instead of 362 (the 19 fits that end at a jump 206 instead of
257), HD1 227 instead of 262; no estimate moved by more than 0.094 (HD2) and 0.115 (HD1) of its
standard error, no record's χ² rose by more than 0.07 %, every consistency figure the same to three
digits. At 0.5: 286 and 217 evaluations, estimates moved up to 0.25 standard errors (HD2); at 1.0: 253
evaluations (HD2). Halving the trial faster (to a quarter) cost more evaluations (378 at 0.1)."""


@dataclasses.dataclass
class PerExperimentFit:
    """Result of `fit_per_experiment`: one trajectory-error fit per experiment.

    **Attributes:**

    - `free`: names of the parameters (columns of `values` and `mask`).
    - `mask`: (experiments, parameters) bool; True where the parameter was fitted on that experiment.
    - `values`: (experiments, parameters) estimates (SI), NaN where not fitted or not converged.
    - `std_error`: (experiments, parameters) each estimate's standard error from its own record
      (block sandwich, `block_covariance`; SI), NaN where not fitted or not converged.
    - `undetermined`: (experiments, parameters) str: why the estimate does not count ("" where it
      does): a standard error that is infinite (the record does not inform it) or over `se_rtol` of it.
    - `converged`: per experiment, LM stopped by one of its rules (`CostStop`) within `max_steps`.
    - `steps`: LM iterations per experiment.
    - `chi2_reduced`: per experiment, residual sum of squares / (n − p).
    - `stop_reason`: per experiment, the rule that ended its LM fit (`STOP_REASONS` or "max_steps";
      "cost_jump": a trial under `PER_EXPERIMENT_REJECT_SE_TOL` standard errors raised the cost, see
      `MarquardtLM`).
    """

    free: tuple[str, ...]
    mask: np.ndarray
    values: np.ndarray
    std_error: np.ndarray
    undetermined: np.ndarray
    converged: np.ndarray
    steps: np.ndarray
    chi2_reduced: np.ndarray
    stop_reason: np.ndarray

    def per_experiment(self, name: str, *, determined_only: bool = False) -> list[float]:
        """Estimates of `name` per experiment (NaN where it was not fitted or LM did not converge,
        and with `determined_only` where it is undetermined)."""
        k = self.free.index(name)
        v = self.values[:, k]
        return [float(x) for x in (np.where(self.undetermined[:, k] == "", v, np.nan) if determined_only else v)]

    def consistency(self, name: str) -> float:
        """The paper's measure, std (ddof 1) / |mean| over the determined per-experiment estimates."""
        return _consistency(self.per_experiment(name, determined_only=True))

    def spread_over_std_error(self, name: str) -> float:
        """How far the determined estimates of `name` scatter beyond their own standard errors:
        √(Σ w (v − v̄_w)² / (n − 1)), w = 1/se², v̄_w their weighted mean; about 1 when the
        experiments agree within their errors, well above 1 when the model's form makes records
        disagree (or the errors are too small). NaN with fewer than 2."""
        k = self.free.index(name)
        v = np.asarray(self.per_experiment(name, determined_only=True))
        ok = np.isfinite(v) & np.isfinite(self.std_error[:, k]) & (self.std_error[:, k] > 0)
        if ok.sum() < 2:
            return float("nan")
        w = 1.0 / self.std_error[ok, k] ** 2
        mean = np.sum(w * v[ok]) / np.sum(w)
        return float(np.sqrt(np.sum(w * (v[ok] - mean) ** 2) / (ok.sum() - 1)))


def fit_per_experiment(
    p0: Parameters,
    drive: Drive,
    batch: Experiment,
    mask,
    *,
    free=DEFAULT_FREE,
    simulator: Simulator = Simulator(rtol=1e-5, atol=1e-7),
    solver: optx.AbstractLeastSquaresSolver = MarquardtLM(rtol=1e-6, atol=1e-6, shrink_on_reject=True,
                                                          reject_se_tol=PER_EXPERIMENT_REJECT_SE_TOL),
    max_steps: int = 12,
    step_se_tol: float = 0.1,
    cost_rtol: float = 1e-5,
    sigma=None,
    effects: Effects = Effects(),
    se_block: float = 0.1,
    se_rtol: float = UNDETERMINED_SE_RTOL,
) -> PerExperimentFit:
    """One trajectory-error LM fit per experiment, all by one compiled program (`for_each_experiment`:
    `lax.map` on the CPU, `vmap` on accelerators). On the CPU it is called on chunks of the batch
    (`_per_experiment_chunk`) so that progress is reported between them; the fits are the same to
    the last bit as in one call (a test).

    Experiment `e` fits the parameters `free[k]` with `mask[e, k]` True and keeps the others at
    `p0` (for example the joint fit's estimate), so each experiment estimates only what it can
    determine (locked: compliance; fast free motion: inertia, viscous and Coulomb; slow free
    motion: Stribeck). The spread of the estimates is the trajectory method's consistency measure.
    Each experiment carries only as many unknowns as the largest row of `mask` (forward-mode
    tangents cost in proportion), and stops on its own by `CostStop`'s rules.

    With several devices (`hdjax.use_host_devices`: one per CPU core) each device fits its share
    of the experiments (`jax.shard_map`). That needs a solver whose state holds no lineax operator
    built inside the device map: the default `hdjax._fit.lm.MarquardtLM` (Levenberg–Marquardt on the
    normal equations with Marquardt scaling) qualifies; `optimistix.LevenbergMarquardt` fails
    there in lineax's structure check and so runs on one device. Measured on the shipped HD2 data
    (50 experiments from the paper estimates, 2-core machine): `optimistix.LevenbergMarquardt` on
    one device 43.0 s, `MarquardtLM` on one 46.6 s, on two 25.7 s, the same 48/50 converged. In
    `hdjax fit configs/hd2.yaml` (from the joint estimate) the stage took 40.8 s before, 23.3 s
    now, 50/50 converged both ways; the well-determined estimates (K1 … Tsn) agree within 1e-3
    relative. One fit differs: on one slow free-motion record `MarquardtLM` rejects its first five
    steps, the cost-stall rule stops it at its start (χ²_red 86.4), where optimistix's LM had moved
    its Stribeck amplitude to +0.31 N·m (χ²_red 51.4, against −0.01 … −0.07 N·m on every other
    record).

    The default solver halves its trial after each rejected step and stops once a trial shorter
    than 0.3 standard errors is rejected (`MarquardtLM(shrink_on_reject=True,
    reject_se_tol=PER_EXPERIMENT_REJECT_SE_TOL)`): a stick–slip plant's cost jumps where a parameter
    decides whether the motor sticks. Before
    (2026-12-07), with Nielsen's damping alone, the first trials were often rejected three or four
    times unchanged and the cost-stall rule stopped the fit where it stood: on the shipped HD2
    campaign ten fits ended so after 6 evaluations, their Gauss–Newton step still 1.5–29 standard
    errors long (two never left their start), and were reported converged; 20 of the 50 ended on
    the cost-stall rule. Now none does: the stage's χ² is lower on eight records (by 0.3–18 %) and
    higher on one (0.2 %), for 362 LM steps instead of 361, and K1's consistency is 1.6 % instead
    of 2.6 % (HD1: 262 steps instead of 246, seven fits' χ² lower by 0.1–0.8 %, every consistency
    figure within 3 % of itself).

    **Arguments:** as `fit_parameters`, plus `mask`: (experiments, len(free)) bool; `effects` are
    applied in every simulation and held at their values (for example the joint fit's fitted sensor
    lags, `TrajectoryFit.effects`); `se_block` (s) as in `fit_parameters`: each estimate's standard
    error is the block sandwich of its own record; `se_rtol`: an estimate whose standard error is
    over this fraction of it (or infinite) is undetermined and left out of the consistency measure.

    (About 100 lines through this docstring; the body is one pass: slots per experiment, then the
    chunks that report progress, then the estimates read back.)

    **Returns:** a `PerExperimentFit`.
    """
    pmap = make_parameter_map(p0, free)
    sigma = fit_noise_levels(p0, drive, batch, simulator=simulator) if sigma is None else jnp.asarray(sigma)
    theta0 = pmap.to_vector(p0)
    mask = np.asarray(mask, dtype=bool)
    n_exp = int(batch.time.shape[0])
    if mask.shape != (n_exp, len(pmap.fields)):
        raise ValueError(f"`fit_per_experiment`: mask has shape {mask.shape}, expected ({n_exp}, {len(pmap.fields)}).")
    # slots: experiment e fits z[e, s] for parameter slot_index[e, s] where slot_on[e, s]
    n_slots = max(1, int(mask.sum(axis=1).max()))
    slot_index = np.zeros((n_exp, n_slots), dtype=int)
    slot_on = np.zeros((n_exp, n_slots))
    for e in range(n_exp):
        ks = np.flatnonzero(mask[e])
        slot_index[e, : len(ks)] = ks
        slot_on[e, : len(ks)] = 1.0

    active = mask.any(axis=1)
    # several devices: each fits its share of the experiments (masked dummies pad the batch; their
    # slots are off, so they hold still and are dropped below)
    mesh = experiment_mesh() if jax.device_count() > 1 and isinstance(solver, MarquardtLM) else None
    n_devices = 1 if mesh is None else mesh.size
    chunk = _per_experiment_chunk(n_exp, n_devices, experiment_batching(fixed_cost=is_fixed_cost(simulator)))
    run = _cached(_per_experiment_fit_program, pmap.fields, simulator, solver, max_steps, step_se_tol, cost_rtol, mesh)
    order = _interleaved(n_exp, n_devices, chunk)
    parts = []
    with count_progress("per-experiment LM fits", n_exp, unit="experiments") as done:
        for lo in range(0, n_exp, chunk):
            take = order[lo:lo + chunk]
            part, n_real = pad_experiments(take_rows(batch, take), chunk)
            if mesh is not None:
                part, _ = shard_experiments(part, mesh)
            pad = chunk - n_real  # dummies: slots off
            idx = jnp.asarray(np.concatenate([slot_index[take], np.zeros((pad, n_slots), dtype=int)]))
            on = jnp.asarray(np.concatenate([slot_on[take], np.zeros((pad, n_slots))]))
            z, result, reason, steps, r, J, D = jax.block_until_ready(
                run(jnp.zeros((chunk, n_slots)), (pmap, theta0, p0, effects, drive, part, sigma, idx, on)))
            parts.append([np.asarray(x)[:n_real] for x in (z, steps, r, J, D)] + [_stop_reason(result, reason)[:n_real]])
            if done is not None:
                for _ in range(n_real):
                    done()
    back = np.argsort(order)  # the fits in the batch's order
    z_final, steps, r, J, D, stop = (np.concatenate(xs)[back] for xs in zip(*parts))
    idx, on = np.asarray(slot_index), np.asarray(slot_on)
    ok = (stop != "max_steps") & active
    rss, n_obs = np.sum(r**2, axis=1), np.sum(r != 0.0, axis=1)
    dof = np.maximum(n_obs - mask.sum(axis=1), 1)
    values, std_error = np.full(mask.shape, np.nan), np.full(mask.shape, np.nan)
    undetermined = np.full(mask.shape, "", dtype=object)
    theta0_host, time_host = np.asarray(theta0), np.asarray(batch.time)
    n_time = time_host.shape[1]
    for e in np.flatnonzero(ok):
        theta_e = theta0_host.copy()  # `_full_theta` on the host (eagerly in JAX it compiled a scatter)
        np.add.at(theta_e, idx[e], on[e] * z_final[e])
        p = pmap.to_model(jnp.asarray(theta_e), p0)
        # standard errors: the block sandwich in z (residual rows: channel, sample), then the delta method
        blocks = np.broadcast_to(time_blocks(time_host[e:e + 1], se_block)[:, None, :], (1, r.shape[1] // n_time, n_time))
        cov_z, _ = robust_covariance(J[e], r[e], blocks, lambda e=e: white_covariance(J[e], float(rss[e] / dof[e])))
        se_slot = np.sqrt(np.clip(np.diag(D[e] @ cov_z @ D[e].T), 0, None))
        se_slot = np.where(null_directions(J[e]), np.inf, se_slot)  # the record does not inform these slots
        for s_, k in enumerate(idx[e]):
            if on[e, s_]:
                std_error[e, k] = se_slot[s_]
        for k, name in enumerate(pmap.fields):
            if mask[e, k]:
                values[e, k] = float(getattr(p, name))
                undetermined[e, k] = _per_experiment_undetermined(values[e, k], std_error[e, k], se_rtol)
    return PerExperimentFit(
        free=pmap.fields,
        mask=mask,
        values=values,
        std_error=std_error,
        undetermined=undetermined,
        converged=ok,
        steps=steps,
        chi2_reduced=rss / dof,
        stop_reason=np.asarray(stop, dtype=str),
    )


def _per_experiment_undetermined(value: float, se: float, se_rtol: float) -> str:
    """Why one experiment's estimate does not count ("" when it does): its standard error is not
    finite (the record does not inform it: on the shipped HD2 campaign one slow record's Stribeck
    amplitude had run along such a direction to -1.2e5 N·m) or over `se_rtol` of the estimate (the
    joint fit's rule for `undetermined`)."""
    if not np.isfinite(se):
        return f"the record does not inform it (a null direction of its Jacobian): the estimate {value:.3g} is arbitrary"
    if poorly_determined(value, se, se_rtol):
        return f"standard error {se:.3g} is over {se_rtol:.0%} of the estimate {value:.3g}: the record does not pin it down"
    return ""


# --- compiled fit programs, built once per problem structure -------------------------------------
#
# A fit program is one `eqx.filter_jit` function. Built inside `fit_parameters` it was a new Python
# function at every call, so every call traced and compiled it again (about 20 s on this 2-core CPU
# for the diagnosis's base fit, paid once per dataset). Built here, once per (free parameters,
# numerics, LM options), with every value (parameter map, start, data, noise levels) an argument,
# a second fit of the same shapes reuses the compiled program. The programs hold no host callback
# (progress is reported from Python between calls), so JAX's persistent compilation cache keeps
# them too (`hdjax.use_compilation_cache`).

PER_EXPERIMENT_REPORTS = 8
"""About how many progress reports `fit_per_experiment` makes (one per chunk of its batch)."""


def _interleaved(n_exp: int, n_devices: int, chunk: int) -> np.ndarray:
    """The order in which `fit_per_experiment` takes the experiments into its chunks of `chunk`:
    within each run of `chunk` neighbouring experiments, device d's share is every
    `n_devices`-th one from the d-th. A campaign lists its locked tests, then its free ones, whose
    fits cost several times more, so the devices' shares of a chunk cost about the same and
    neither waits long for the other at the chunk's end."""
    order = []
    for lo in range(0, n_exp, chunk):
        block = range(lo, min(lo + chunk, n_exp))
        order += [e for d in range(n_devices) for e in block[d::n_devices]]
    return np.asarray(order, dtype=int)


def _per_experiment_chunk(n_exp: int, n_devices: int, batching: str) -> int:
    """Experiments per call of the per-experiment fit program: the whole batch when a device runs
    its experiments in lock-step (`vmap`), else a multiple of the devices that splits the batch
    into about `PER_EXPERIMENT_REPORTS` calls. Each call is the same compiled program (the last
    chunk is padded with dummies); between calls the progress bar advances. On the CPU a device
    fits its experiments one after the other (`lax.map`), so a chunk costs the sum of its fits:
    what the chunks add is that both devices wait for the slower one at the end of each chunk."""
    per_device = max(1, -(-n_exp // n_devices))
    if batching == "vmap":
        return per_device * n_devices
    k = -(-per_device // PER_EXPERIMENT_REPORTS)
    return k * n_devices


def _cached(build, *key):
    """`build(*key)`, memoised on `key` (numerics and options); built afresh when a key is not
    hashable (an option holding an array)."""
    try:
        hash(key)
    except TypeError:
        return build.__wrapped__(*key)
    return build(*key)


def _strong(tree):
    """Every array leaf without JAX's weak type, so the state a step returns has the type of the
    state it was given (else the step program is traced and compiled a second time)."""
    return jax.tree.map(lambda x: jnp.asarray(x, dtype=x.dtype), tree)


def _stepped_least_squares(fn, solver: optx.AbstractLeastSquaresSolver, *, max_steps: int, finish, mesh=None):
    """`optx.least_squares(fn, solver, y0, args, max_steps=max_steps, throw=False)` as compiled
    programs stepped from Python, for a `CostStop` solver: `run(y0, args, on_step=None)` →
    `finish(y, state, result, num_steps, args)`.

    optimistix runs `solver.init`, then `solver.step` in a `while_loop` until `solver.terminate`
    says stop or `max_steps` steps are done. Here the start (init and the first termination test)
    is one compiled program and one step with its termination test is another, called in a Python
    loop, and `finish` (with optimistix's own `max_steps` result) a third. The arithmetic is
    optimistix's own, step for step: the iterates, the stop rule and the result code are the same
    to the last bit (`tests/test_fit.py`). What changes is where the progress report is made:
    `on_step(step, ½χ², Gauss–Newton step in standard errors)` is called from Python after each
    step, with the figures `CostStop` keeps in its state, where a `jax.debug.callback` inside the
    loop made it before. A compiled program that holds a host callback is never written to JAX's
    persistent compilation cache, so the LM programs (10–15 s of compilation each on the 2-core
    machine) were compiled on every run of a command; now they are read back.

    The state's non-array part (its structure, the linearisation's functions) is the start
    program's, passed to the step program as a static argument, as optimistix's loop combines
    its start state's static part with each step's arrays. The state the programs return has one
    type and, with a device `mesh`, one placement (replicated: the start's state would otherwise
    sit on one device and the steps' be spread over the mesh), so the step program is compiled
    once."""
    tags, options = frozenset(), {}

    def placed(tree):
        tree = _strong(tree)
        if mesh is None:
            return tree
        everywhere = replicated(mesh)
        return jax.tree.map(lambda x: jax.lax.with_sharding_constraint(x, everywhere), tree)

    def fn_aux(y, args):
        return fn(y, args), None

    def terminate(y, state, args):
        done, result = solver.terminate(fn_aux, y, args, options, state, tags)
        return done, optx.RESULTS.where(jnp.all(jnp.isfinite(y)), result, optx.RESULTS.nonfinite)

    @eqx.filter_jit
    def start(y0, args):
        f_struct = jax.eval_shape(fn, y0, args)
        state = solver.init(fn_aux, y0, args, options, f_struct, None, tags)
        dynamic, static = eqx.partition(state, eqx.is_array)
        return placed(dynamic), static, *placed(terminate(y0, state, args))

    @eqx.filter_jit
    def step(y, dynamic, static, args):
        y_new, state, _ = solver.step(fn_aux, y, args, options, eqx.combine(dynamic, static), tags)
        done, result = terminate(y, state, args)  # optimistix tests the new state at the old iterate
        return placed((y_new, eqx.partition(state, eqx.is_array)[0], done, result))

    @eqx.filter_jit
    def end(y, dynamic, static, done, result, num_steps, args):
        result = optx.RESULTS.where((result == optx.RESULTS.successful) & jnp.invert(done),
                                    optx.RESULTS.nonlinear_max_steps_reached, result)
        return finish(y, eqx.combine(dynamic, static), result, num_steps, args)

    def run(y0, args, on_step=None):
        y = _strong(jnp.asarray(y0, dtype=float))
        if mesh is not None:
            y = jax.device_put(y, replicated(mesh))
        dynamic, static, done, result = start(y, args)
        num_steps = 0
        while num_steps < max_steps and not bool(done) and result == optx.RESULTS.successful:
            y, dynamic, done, result = step(y, dynamic, static, args)
            num_steps += 1
            if on_step is not None:
                on_step(int(dynamic.inner.num_steps), float(dynamic.cost), float(dynamic.step_se))
        return end(y, dynamic, static, done, result, jnp.asarray(num_steps), args)

    run.start, run.step, run.end = start, step, end  # pyright: ignore[reportFunctionMemberAccess]  the programs, for tests
    return run


def _batch_residuals(p, effects, drive, batch, sigma, simulator, mesh):
    """Whitened residuals (experiment, channel, time) of every experiment of `batch` under (`p`,
    `effects`), each device of `mesh` (None: one) taking its share of the experiments."""

    def per_device(shared, b):
        p_, eff_, d_, s_ = shared
        return for_each_experiment(lambda e: _experiment_residuals_jit(p_, d_, e, s_, simulator, eff_), b,
                                   fixed_cost=is_fixed_cost(simulator))

    return map_experiments(per_device, mesh)((p, effects, drive, sigma), batch)


@functools.lru_cache(maxsize=32)
def _joint_fit_program(free, simulator, solver, max_steps, step_se_tol, cost_rtol, mesh):
    """The compiled joint fit: `run(theta0, (pmap, p0, emap, effects, drive, batch, sigma), on_step=None)` → (θ,
    result, stop rule, steps, residual, Jacobian at θ); LM stepped from Python
    (`_stepped_least_squares`), so its programs hold no host callback and JAX's persistent cache
    keeps them."""

    def residuals(theta, args):
        pmap, p0_, emap, e0, drive_, batch_, sigma_ = args
        p, eff = _models(theta, pmap, p0_, emap, e0)
        return _batch_residuals(p, eff, drive_, batch_, sigma_, simulator, mesh).reshape(-1)

    def finish(theta, state, result, num_steps, args):
        r, J = _state_residual_and_jacobian(state)
        if mesh is not None:  # every process can read the result (multi-host)
            r, J = (jax.lax.with_sharding_constraint(x, replicated(mesh)) for x in (r, J))
        return theta, result, state.reason, num_steps, r, J

    # data enter as arguments (never as closed-over constants, which XLA would try to constant-fold)
    lm = CostStop(solver, step_se_tol=step_se_tol, cost_rtol=cost_rtol)  # pyright: ignore[reportCallIssue]  rtol/atol/norm are properties
    return _stepped_least_squares(_lm_objective(residuals), lm, max_steps=max_steps, finish=finish, mesh=mesh)


@eqx.filter_jit
def _model_jacobian(theta, pmap, p0, free: tuple[str, ...]):
    """d(model fields `free`)/dθ at θ: one compiled program (run eagerly, `jacfwd` compiled a dozen
    small ones)."""
    return jax.jacfwd(lambda t: jnp.stack([getattr(pmap.to_model(t, p0), k) for k in free]))(theta)


def _full_theta(z, theta0, idx, on):
    """θ of one per-experiment fit: θ0 with its slots `idx` (where `on`) moved by z."""
    return theta0.at[idx].add(on * z)


@functools.lru_cache(maxsize=32)
def _per_experiment_fit_program(free, simulator, solver, max_steps, step_se_tol, cost_rtol, mesh):
    """The compiled per-experiment fits: `run(z0, (pmap, θ0, p0, effects, drive, batch, sigma, idx, on))` →
    per experiment (z, result, stop rule, steps, residual, its Jacobian in z, d(slot values)/dz). It holds no host callback, so JAX's
    persistent cache keeps it; `fit_per_experiment` calls it on chunks of the batch and reports
    its progress between them (`_per_experiment_chunk`)."""

    def residuals(z, args):
        pmap, theta0_, p0_, eff, drive_, exp, sigma_, idx, on = args
        p = pmap.to_model(_full_theta(z, theta0_, idx, on), p0_)
        return experiment_residuals(p, drive_, exp, sigma_, simulator, eff).reshape(-1)

    residuals_lm = _lm_objective(residuals)
    lm = CostStop(solver, step_se_tol=step_se_tol, cost_rtol=cost_rtol)  # pyright: ignore[reportCallIssue]  rtol/atol/norm are properties

    @eqx.filter_jit
    def run(z, args):
        pmap, theta0_, p0_, eff, drive_, batch_, sigma_, idx, on = args

        def per_device(shared, b):
            pmap_, theta0_d, p0_d, eff_d, drive_d, sigma_d = shared

            def one(z_e, exp, idx_e, on_e):
                sol = optx.least_squares(residuals_lm, lm, z_e, (pmap_, theta0_d, p0_d, eff_d, drive_d, exp, sigma_d, idx_e, on_e),
                                         max_steps=max_steps, throw=False)
                f_info = sol.state.inner.f_info  # residual and Jacobian at the returned point

                def slot_values(z):  # the physical value of each slot's parameter (SI)
                    p = pmap_.to_model(_full_theta(z, theta0_d, idx_e, on_e), p0_d)
                    return jnp.stack([getattr(p, k) for k in pmap_.fields])[idx_e]

                return (sol.value, sol.result, sol.state.reason, sol.stats["num_steps"], f_info.residual,
                        f_info.jac.as_matrix(), jax.jacfwd(slot_values)(sol.value))

            # each fit's LM solves its own small linear systems: mapped on a multi-device CPU (see
            # `for_each_experiment`); on one device and on accelerators as the batching says
            return for_each_experiment(one, *b, lapack_in_device_map=mesh is not None)

        return map_experiments(per_device, mesh)((pmap, theta0_, p0_, eff, drive_, sigma_), (z, batch_, idx, on))

    return run
