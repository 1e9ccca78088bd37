r"""The harmonic-drive plant as a diffrax ODE driven by the measured motor current.

State (SI units): kinematic torsion $q = \theta_m/N - \theta_o$ (rad, output side; equal to the
flexspline torsion $\Delta\theta$ unless a kinematic error is modelled), wave-generator velocity $\omega_m$
(rad/s), output angle $\theta_o$ (rad) and output velocity $\omega_o$ (rad/s):

$$\dot q = \omega_m/N - \omega_o,\quad
J_{eff}\dot\omega_m = K_m i(t) - T/N - T_f(\omega_m),\quad
\dot\theta_o = \omega_o,\quad J_{load}\dot\omega_o = f\,T,$$

with $T$ from eq. 5 and $f = 1$ in free motion, $0$ with the output locked. Torsion is a state
(rather than the motor angle) so that it is never a small difference of large angles. The motor
angle is recovered as $\theta_m = \theta_{m0} + N((q - q_0) + (\theta_o - \theta_{o0}))$.

Numerics (measured, see `benchmarks/solver_choice.py` and the README): the structural damping
$|\dot{\Delta\theta}|^{1/2}$ and the smoothed Coulomb step give the ODE a very large Jacobian near
zero torsion rate and zero velocity; the default is an L-stable Rosenbrock method (`Rodas3`, see
`hdjax._plant.rosenbrock`) with a PID step controller, stepping onto every sample instant
(`StepToSamples`: the steps of `ClipStepSizeController(step_ts=time)` at O(1) per step) so that the kinks of the piecewise-linear current never
fall inside a step.
"""

import functools

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .._data.experiment import Experiment
from .._model.effects import PERIODIC, Effects, stiffness_torque
from .._model.paper import Drive, Parameters, Smoothing, compliance_torque, friction_parts
from .._model.smooth import smooth_sign, smooth_signed_power, smooth_step
from .rosenbrock import FirstStep, Rodas3, Ros34PW2, StepToSamples
from .sharding import (
    experiment_batching,
    experiment_mesh,
    for_each_experiment,
    is_concrete,
    map_experiments,
    shard_experiments,
)
from .stepper import VelocityImplicit, implicit_trajectory


class Trajectory(eqx.Module):
    """A simulated experiment at its sample times (SI units).

    **Attributes:**

    - `torque`: transmitted torque (N·m), eq. 5.
    - `motor_velocity`: wave-generator velocity (rad/s).
    - `motor_position`: wave-generator angle (rad).
    - `output_position`: output angle (rad).
    - `output_velocity`: output velocity (rad/s).
    - `torsion`: flexspline torsion (rad), including kinematic error when modelled.
    - `success`: True when the solve finished (False: step budget exhausted or solver failure).
    - `num_steps`: accepted solver steps.
    """

    torque: Float[Array, " time"]
    motor_velocity: Float[Array, " time"]
    motor_position: Float[Array, " time"]
    output_position: Float[Array, " time"]
    output_velocity: Float[Array, " time"]
    torsion: Float[Array, " time"]
    success: Bool[Array, ""]
    num_steps: Int[Array, ""]


class Simulator(eqx.Module):
    """Numerical options of the plant simulation (the physics lives in `Parameters`/`Drive`).

    **Arguments:**

    - `solver`: diffrax solver, or `VelocityImplicit()` (`hdjax._plant.stepper`); default `Rodas3()` (linearly
      implicit, see `hdjax._plant.rosenbrock`).
    - `rtol`, `atol`: PID step-size controller tolerances (atol on states in SI units).
    - `step_to_samples`: clip steps to the sample instants (kinks of the interpolated current).
    - `adjoint`: `ForwardMode()` by default, for LM Jacobians and `jacfwd` sensitivities; use
      `RecursiveCheckpointAdjoint()` for reverse-mode scalar gradients.
    - `max_steps`: step budget per experiment.
    - `fixed_step`: if given (s), use `ConstantStepSize` with this step instead of the PID
      controller. The discrete solution is then a smooth function of the parameters, which is what
      the AD-vs-finite-difference checks need; it must divide the sample period.
    - `smoothing`: scales of the smooth sign/step/power stand-ins (`Smoothing`).
    - `initial_window`: samples used to estimate the initial state by a local linear fit.
    - `measured_angle`: the wave-generator angle θm at which the periodic terms of SPEC §4 act
      (kinematic error, strain-gauge ripple, cogging, position-dependent friction) is taken from
      the record where it was measured (`MeasuredAngle`): the motor encoder where the record has
      `motor_position`; else, in free motion, N·(torsion + measured output angle). Off (False),
      θm is the simulated one, which in free motion drifts from the drive's: the simulation is
      driven by the recorded current, whose noise and the model's friction misfit integrate into
      the angle (independent-bench seed 5002, HD1: up to 5.6 rad at the paper's estimates, 1.1 rad
      at the true parameters, over 2.5 s; the output encoder and torque give it within 0.1 rad),
      so that a term of order k comes out of phase by k times that. `Trajectory.motor_position`
      is then that angle too (the diagnosis's order spectra are taken against it). Nothing else
      changes: the paper's model has no term of θm. The plant-based rig, which drives the plant
      with records that hold no measured angle, leaves it off.
    """

    solver: dfx.AbstractSolver | VelocityImplicit = Rodas3()
    rtol: float = 1e-7
    atol: float = 1e-9
    step_to_samples: bool = True
    adjoint: dfx.AbstractAdjoint = dfx.ForwardMode()
    max_steps: int = 200_000
    fixed_step: float | None = None
    smoothing: Smoothing = Smoothing()
    initial_window: int = 11
    measured_angle: bool = False


def is_fixed_cost(simulator: "Simulator") -> bool:
    """True when every step of `simulator` costs the same in every experiment (a fixed-step solver
    such as `hdjax.VelocityImplicit`): then `vmap` over experiments has no slowest lane."""
    return isinstance(simulator.solver, VelocityImplicit)


def _line_at_start(t: Array, y: Array, mask: Array, n: int) -> tuple[Array, Array]:
    """Value and slope at t[0] of a least-squares line through the first `n` valid samples.

    Rest detection: a value or slope statistically indistinguishable from zero (|estimate| below
    three standard errors of the line fit) is set to exactly zero, so that a record that starts
    at rest starts the simulation at rest instead of from a noise-sized state error. (With the
    power-law damping, a 0.02 rad/s velocity error is a 0.6 N·m torque error at the start, and a
    torsion error creeps away only over seconds.)"""
    tt = t[:n] - t[0]
    yy = y[:n]
    w = mask[:n].astype(float)
    sw = jnp.maximum(jnp.sum(w), 1.0)  # an all-padding record (mask all False) starts at rest
    tm = jnp.sum(w * tt) / sw
    ym = jnp.sum(w * yy) / sw
    sxx = jnp.maximum(jnp.sum(w * (tt - tm) ** 2), 1e-300)
    slope = jnp.sum(w * (tt - tm) * (yy - ym)) / sxx
    value = ym - slope * tm
    resid = w * (yy - value - slope * tt)
    s2 = jnp.sum(resid**2) / jnp.maximum(sw - 2.0, 1.0)
    se_value = jnp.sqrt(s2 * (1.0 / sw + tm**2 / sxx))
    se_slope = jnp.sqrt(s2 / sxx)
    value = jnp.where(jnp.abs(value) < 3.0 * se_value, 0.0, value)
    slope = jnp.where(jnp.abs(slope) < 3.0 * se_slope, 0.0, slope)
    return value, slope


def initial_state(p: Parameters, drive: Drive, exp: Experiment, simulator: Simulator = Simulator(), *,
                  exact_sticking: bool | None = None):
    """Initial plant state estimated from the first samples of the measured record.

    Motor velocity, torque and output angle come from local linear fits (unbiased under a linear
    trend, averaging the sensor noise); torsion inverts eq. 5 at the initial torsion rate.
    `exact_sticking` (default: the simulator's solver is `VelocityImplicit`) says which law decides
    whether the motor can be at rest (see the comment in the body).
    Returns `(y0, theta_m0)`: the state tuple and the initial motor angle (rad)."""
    n = min(simulator.initial_window, exp.time.shape[0])
    N = drive.gear_ratio
    wm0, _ = _line_at_start(exp.time, exp.motor_velocity, exp.mask, n)
    T0, dT0 = _line_at_start(exp.time, exp.torque, exp.mask, n)
    i0, _ = _line_at_start(exp.time, exp.current, exp.mask, n)
    # Stuck at the start: the motor's net drive torque lies inside the breakaway interval
    # [−(Tsn + Tssn1), Tsp + Tssp1] with a margin that friction would stop the estimated velocity
    # with inside one sample period (Jeff·|ω| / margin < Δt). Such a motor is at rest at every
    # sample the record holds, so it starts at rest. (The power-law damping turns a velocity error
    # δω into a torque error Tst·|δω/N|^α: 0.05 rad/s, a noise excursion of the tachometer over the
    # first samples, is 1.3 N·m on HD1, and a motor that sticks at once keeps that torsion error
    # until it breaks away.)
    #
    # Which net torques hold the motor depends on the friction law at zero velocity. A breakaway
    # torque below zero (T_s + T_ss1 < 0, as the paper's HD2 in the negative direction: friction
    # that would push a resting motor) counts as zero for the smoothed plant (its tanh friction
    # creeps to a stable rest for any net torque between −(Tsn + Tssn1)₊ and (Tsp + Tssp1)₊) and
    # under `low_speed_friction`'s creep ramp (the stepper clamps the ramped magnitude at zero).
    # The exact stepper's set-valued law does not clamp it: it holds the motor only for net torques
    # in [−(Tsn + Tssn1), Tsp + Tssp1], and outside that the motor moves at once, so a start
    # estimated at rest there would be wrong from the first step (measured: a locked record of the
    # paper's HD2 started at rest slides back at −0.037 rad/s, the damping taking −0.91 N·m; taken as
    # stuck, the start put that torque into the spring, and the motor velocity's χ² at the true
    # parameters was 10.3 instead of about 1).
    exact = isinstance(simulator.solver, VelocityImplicit) if exact_sticking is None else exact_sticking
    lower, upper = p.Tsn + p.Tssn1, p.Tsp + p.Tssp1
    if not exact:
        lower, upper = jnp.maximum(lower, 0.0), jnp.maximum(upper, 0.0)
    net = drive.torque_constant * i0 - T0 / N
    margin = jnp.minimum(upper - net, net + lower)
    dt = exp.time[1] - exp.time[0]
    stuck = (margin > 0) & (p.Jeff * jnp.abs(wm0) < margin * dt)
    wm0 = jnp.where(stuck, 0.0, wm0)
    th_o0, _ = _line_at_start(exp.time, exp.output_position, exp.mask, n)
    th_o0 = th_o0 * exp.free + exp.output_position[0] * (1 - exp.free) * exp.has_output_position
    wo0 = exp.free * (wm0 / N - dT0 / p.K1)
    rate0 = wm0 / N - wo0
    damping = compliance_torque(p, 0.0, rate0, simulator.smoothing)
    torsion0 = (T0 - damping) / p.K1
    th_m0 = jnp.where(exp.has_motor_position > 0, exp.motor_position[0], N * (torsion0 + th_o0))
    return (torsion0, wm0, th_o0, wo0), th_m0


def _sample_interval(t, t0, dt, n: int):
    """Index i of the sample interval [t_i, t_i+1] holding `t` on the uniform grid t0 + k·dt of `n`
    samples (clipped to the first and last interval), and the fraction w ∈ [0, 1] of it."""
    s = (t - t0) / dt
    i = jnp.clip(jnp.floor(s), 0, n - 2).astype(int)
    return i, s - i.astype(s.dtype)


class UniformLinearInput(eqx.Module):
    """Piecewise-linear interpolation of samples on a uniform grid, O(1) per evaluation.

    (diffrax's `LinearInterpolation` searches the whole grid, which under `vmap` costs O(samples)
    per evaluation; here the grid is uniform, so the index is computed directly.)"""

    t0: Float[Array, ""]
    dt: Float[Array, ""]
    values: Float[Array, " time"]

    def evaluate(self, t):
        i, w = _sample_interval(t, self.t0, self.dt, self.values.shape[0])
        return (1.0 - w) * self.values[i] + w * self.values[i + 1]


class MeasuredAngle(eqx.Module):
    """The record's measured angles for `Simulator.measured_angle`, interpolated like the current:
    the output encoder (used in free motion) and the motor encoder (used wherever measured)."""

    output: UniformLinearInput
    motor: UniformLinearInput
    use_output: Float[Array, ""]
    use_motor: Float[Array, ""]

    def output_angle(self, t, th_o_simulated, reading=None):
        """The output angle (rad) at time `t` (s) that θm is built from: the encoder's in free
        motion, else the simulated `th_o_simulated`. `reading`: the encoder's angle at `t` where
        already read (`readings`), else it is read here."""
        return jnp.where(self.use_output > 0, self.output.evaluate(t) if reading is None else reading, th_o_simulated)

    def motor_angle(self, t, th_m, reading=None):
        """θm (rad) at time `t` (s): the motor encoder's where measured, else `th_m`. `reading` as in
        `output_angle`."""
        return jnp.where(self.use_motor > 0, self.motor.evaluate(t) if reading is None else reading, th_m)

    def readings(self, t):
        """(output, motor) encoder angles (rad) at times `t` (s, any shape), stacked on a last axis:
        the `reading`s of `output_angle` and `motor_angle`."""
        return jnp.stack([self.output.evaluate(t), self.motor.evaluate(t)], axis=-1)


class UniformCubicBlendInput(eqx.Module):
    """SPEC §4b `input_between_samples`: the samples on a uniform grid joined by the straight line
    plus `reconstruction` (λ, -) times the difference between the Catmull–Rom cubic through the
    same samples and that line. λ = 0 is `UniformLinearInput`; λ = 1 the cubic (slopes
    (v[k+1] − v[k−1]) / 2Δt, one-sided at the ends). Every λ passes through the samples, so the
    record is not altered; only the path between samples is. A current from a fast current loop
    sampled at a few hundred Hz rounds its edges between samples the way the cubic does (measured on
    the independent bench, 500 Hz square wave, true parameters: peak edge misfit of the motor
    velocity 4.6 σ with straight lines, 0.6 σ with the cubic; `benchmarks/RESULTS.md`)."""

    t0: Float[Array, ""]
    dt: Float[Array, ""]
    values: Float[Array, " time"]
    reconstruction: Float[Array, ""]

    def evaluate(self, t):
        v = self.values
        n = v.shape[0]
        i, w = _sample_interval(t, self.t0, self.dt, n)
        v0, v1 = v[i], v[i + 1]
        # per-sample slopes: the difference over the samples on either side (one-sided at the ends)
        lo, hi = jnp.maximum(i - 1, 0), jnp.minimum(i + 2, n - 1)
        m0 = (v1 - v[lo]) / (i + 1 - lo).astype(v.dtype)
        m1 = (v[hi] - v0) / (hi - i).astype(v.dtype)
        # cubic Hermite − line: w(w−1)(2w−1)(v0 − v1) + h10 m0 + h11 m1
        bend = w * (w - 1.0) * (2.0 * w - 1.0) * (v0 - v1) + w * (w - 1.0) ** 2 * m0 + w * w * (w - 1.0) * m1
        return (1.0 - w) * v0 + w * v1 + self.reconstruction * bend


def state_size(effects: Effects) -> int:
    """Length of the plant state with `effects`: torsion, wave-generator velocity, output angle and
    velocity, then the Dahl hysteresis state and the presliding friction state where those are on."""
    return 4 + ("rate_independent_hysteresis" in effects.active) + ("presliding_friction" in effects.active)


def _presliding_index(effects: Effects) -> int | None:
    """Index of `presliding_friction`'s Dahl friction state in the plant state (the last one), or None."""
    return state_size(effects) - 1 if "presliding_friction" in effects.active else None


def _friction_direction(wm, y, effects: Effects, smoothing: Smoothing):
    """(sign, step) that the Coulomb and Stribeck terms of eq. 9 switch on: the smoothed sign(ω)
    and u(ω), blended with `presliding_friction`'s state s (fraction `presliding`; its
    step u(s) at `STATE_SCALE`, as in the friction-only fits); None without that item."""
    k = _presliding_index(effects)
    if k is None:
        return None
    sg, up = smooth_sign(wm, smoothing.velocity_scale), smooth_step(wm, smoothing.velocity_scale)
    return effects.presliding_friction.direction(sg, up, y[k])


def _friction(p: Parameters, drive: Drive, wm, theta_m, T, t_session, effects: Effects, smoothing: Smoothing,
              direction=None):
    """Eq. 9 with the friction extensions of `effects` (N·m); `direction` as in `friction_basis`."""
    viscous, coulomb, stribeck = friction_parts(p, wm, smoothing, direction=direction)
    if "thermal_drift" in effects.active:
        viscous = viscous * effects.thermal_drift.factor(t_session)
    if "viscous_friction_law" in effects.active:
        viscous = viscous * effects.viscous_friction_law.factor(wm)
    if "position_dependent_friction" in effects.active:
        coulomb = coulomb * (1.0 + effects.periodic("position_dependent_friction", theta_m))
    if "load_dependent_friction" in effects.active:
        sg = smooth_sign(wm, smoothing.velocity_scale)
        coulomb = coulomb + effects.load_dependent_friction.mu * jnp.sqrt(T * T + 1e-6) / drive.gear_ratio * sg
    return viscous + coulomb + stribeck


def _outputs(p, drive, y, geometry, effects: Effects, smoothing: Smoothing, t=None):
    """Motor angle, true torsion, torsion rate and transmitted torque from the state at time `t`
    (s; needed when `geometry` holds a `MeasuredAngle`)."""
    q, wm, th_o, wo = y[:4]
    q0, th_o0, th_m0, measured = geometry
    N = drive.gear_ratio
    th_o_angle = th_o if measured is None else measured.output_angle(t, th_o)
    th_m = th_m0 + N * ((q - q0) + (th_o_angle - th_o0))
    if measured is not None:
        th_m = measured.motor_angle(t, th_m)
    torsion = q + effects.periodic("kinematic_error", th_m)
    rate = wm / N - wo + effects.periodic_rate("kinematic_error", th_m, wm)
    T = stiffness_torque(p.K1, torsion, effects) + p.Tst * smooth_signed_power(
        rate, p.alpha, smoothing.torsion_rate_scale
    )
    if "rate_independent_hysteresis" in effects.active:
        T = T + effects.rate_independent_hysteresis.Th * y[4]
    return th_m, torsion, rate, T


def _low_speed_friction(p: Parameters, effects: Effects, smoothing: Smoothing):
    """`low_speed_friction` (SPEC §4b): the friction regularisation scale and the Stribeck velocity
    Tss2 multiplied by exp(`friction_scale`) and exp(`stribeck_scale`)."""
    if "low_speed_friction" not in effects.active:
        return p, smoothing
    smoothing = Smoothing(
        velocity_scale=smoothing.velocity_scale * jnp.exp(effects.low_speed_friction.friction_scale),  # pyright: ignore[reportArgumentType]  a traced scale is a valid leaf
        torsion_rate_scale=smoothing.torsion_rate_scale,
    )
    return eqx.tree_at(lambda q: q.Tss2, p, p.Tss2 * jnp.exp(effects.low_speed_friction.stribeck_scale)), smoothing


def stepper_friction(p: Parameters, effects: Effects, smoothing: Smoothing):
    """The parameters and creep-ramp width `vc` (rad/s) of the fixed-step stepper's friction:
    exact set-valued Coulomb friction (vc = 0), unless `low_speed_friction` fits a ramp width and
    a Stribeck velocity (`_low_speed_friction`). Shared by `simulate` and the sampled loop."""
    p_dyn, smoothing_dyn = _low_speed_friction(p, effects, smoothing)
    return p_dyn, (smoothing_dyn.velocity_scale if "low_speed_friction" in effects.active else 0.0)


#: Most lead (a negative sensor lag) the sensor model allows, in sample periods: down to −0.45 Δt
#: the low-pass factor stays smooth and |a| < 1 (stable).
MAX_SENSOR_LEAD = 0.45


def sensor_lag_factor(tau, dt):
    """The factor a = τ/(τ+Δt) of the sensors' sample-level low-pass (`_first_order_lag`) for a
    lag `tau` (s) at the sample period `dt` (s), a lead clipped at −`MAX_SENSOR_LEAD`·Δt. Shared by
    `simulate` and the sampled loop (`hdjax._control.closed_loop`)."""
    tau = jnp.maximum(tau, -MAX_SENSOR_LEAD * dt)
    return tau / (tau + dt)


def _first_order_lag(x: Float[Array, " time"], tau, dt) -> Float[Array, " time"]:
    """First-order low-pass (time constant `tau` s, backward-Euler discretisation
    y[n] = a·y[n−1] + (1−a)·x[n], a = τ/(τ+Δt), `sensor_lag_factor`), started at y[0] = x[0].
    Identity at τ = 0, with a finite derivative there (∂a/∂τ = 1/Δt), so a sensor lag can be
    fitted from zero."""
    a = sensor_lag_factor(tau, dt)

    def step(y, xn):
        y = a * y + (1.0 - a) * xn
        return y, y

    _, ys = jax.lax.scan(step, x[0], x[1:])
    return jnp.concatenate([x[:1], ys])


def _vector_field(t, y, args, *, stiff_only: bool = False):
    """The plant's ODE: state (torsion, wave-generator velocity, output angle, output velocity[,
    Dahl hysteresis state][, presliding friction state]). `stiff_only`: only the terms of `plant_stiff_part` (no current, cogging or
    friction factors; the linear kinematic rows zero)."""
    p, drive, current, free, start_time, geometry, effects, smoothing = args
    q, wm, th_o, wo = y[:4]
    th_m, torsion, rate, T = _outputs(p, drive, y, geometry, effects, smoothing, t)
    direction = _friction_direction(wm, y, effects, smoothing)
    if stiff_only:
        drive_torque = jnp.zeros_like(wm)
        Tf = sum(friction_parts(p, wm, smoothing, direction=direction))
    else:
        i = current.evaluate(t - effects.input_delay.delay) if "input_delay" in effects.active else current.evaluate(t)
        drive_torque = drive.torque_constant * i + effects.periodic("cogging", th_m)
        Tf = _friction(p, drive, wm, th_m, T, start_time + t, effects, smoothing, direction)
    dwm = (drive_torque - T / drive.gear_ratio - Tf) / p.Jeff
    dwo = free * T / drive.load_inertia
    zero = jnp.zeros_like(wm)
    dy = (zero, dwm, zero, dwo) if stiff_only else (wm / drive.gear_ratio - wo, dwm, wo, dwo)
    if "rate_independent_hysteresis" in effects.active:
        dy = dy + (effects.rate_independent_hysteresis.rate(y[4], rate, smoothing.torsion_rate_scale),)
    k = _presliding_index(effects)
    if k is not None:
        dy = dy + (effects.presliding_friction.rate(y[k], wm, smoothing.velocity_scale),)
    return dy


def plant_stiff_part(t, y, args):
    """The part of `_vector_field` whose Jacobian changes fast or with the parameters: the transmitted
    torque (spring, power-law damping near zero torsion rate, Dahl term) and eq. 9 near zero
    speed (its smoothed sign and step, or the presliding state), with the Dahl and presliding states; the current, cogging, the smooth
    friction factors (thermal, position- and load-dependent) and the linear kinematic rows left out.
    For `Ros34PW2(stiff_part=plant_stiff_part)`: its frozen-J tangents keep the second derivatives
    of these terms only."""
    return _vector_field(t, y, args, stiff_only=True)


#: The Rosenbrock-W method with the plant's stiff part, `Ros34PW2(stiff_part=plant_stiff_part)`:
#: the solver of the diagnosis's Jacobians and of the fit command's trajectory fit (`ros34pw2`).
PLANT_W_METHOD = Ros34PW2(stiff_part=plant_stiff_part)


def _at_sample_times(step_ts, step_ys, time):
    """States at the sample instants, read off the saved solver steps (`SaveAt(t0=True, steps=True)`)
    of a solve whose steps were clipped to land on every sample instant.

    A clipped step ends on its sample up to a few ulps, so the nearest saved step is taken.
    Unused step slots hold `inf` times and sort last; a failed solve (which stops early) is
    reported by `Trajectory.success`."""
    last = step_ts.shape[0] - 1
    right = jnp.clip(jnp.searchsorted(step_ts, time), 0, last)
    left = jnp.clip(right - 1, 0, last)
    idx = jnp.where(jnp.abs(step_ts[left] - time) <= jnp.abs(step_ts[right] - time), left, right)
    return jax.tree.map(lambda y: y[idx], step_ys)


def _invert_stiffness(K1, elastic_torque, effects: Effects, *, iterations: int = 80):
    """The torsion Δθ (rad) at which `stiffness_torque` gives `elastic_torque` (N·m), for the
    cubic (`nonlinear_stiffness`) and dead-zone (`lost_motion`) springs.

    Bisection on a bracket that holds the root of a monotone spring (|Δθ| ≤ |Tk/K1| + backlash +
    |Tk/K1| of margin), with the bracket's ends held constant (`stop_gradient`), then one Newton
    step: at the converged root that step carries the implicit-function derivative
    −(∂Tk/∂p)/(∂Tk/∂Δθ) to every parameter, so forward-mode Jacobians stay exact. Where the
    bracket holds no sign change (a softening K3 < 0 past its turning point), the linear
    inverse Tk/K1 is kept."""
    target = jnp.asarray(elastic_torque)
    x_lin = target / K1
    d = jnp.abs(effects.lost_motion.backlash) if "lost_motion" in effects.active else jnp.zeros_like(x_lin)
    width = jax.lax.stop_gradient(jnp.abs(x_lin) + d + 1e-12)
    lo0 = jax.lax.stop_gradient(jnp.minimum(x_lin, 0.0)) - width
    hi0 = jax.lax.stop_gradient(jnp.maximum(x_lin, 0.0)) + width

    def residual(x):
        return stiffness_torque(K1, x, effects) - target

    f_const = lambda x: jax.lax.stop_gradient(residual(x))  # noqa: E731
    bracketed = f_const(lo0) * f_const(hi0) <= 0.0

    def bisect(_, lohi):
        lo, hi = lohi
        mid = 0.5 * (lo + hi)
        up = f_const(mid) > 0.0  # a monotone increasing spring: the root is below mid
        return jnp.where(up, lo, mid), jnp.where(up, mid, hi)

    lo, hi = jax.lax.fori_loop(0, iterations, bisect, (lo0, hi0))
    x0 = jax.lax.stop_gradient(0.5 * (lo + hi))
    f0, slope = jax.jvp(residual, (x0,), (jnp.ones_like(x0),))
    x1 = x0 - f0 / jnp.where(slope > 0, slope, 1.0)
    return jnp.where(bracketed & (slope > 0), x1, x_lin)


def _initial_state_with_effects(p, drive, exp, effects, simulator):
    """`initial_state` for a model with `effects`: the state at the first sample and θm0 (rad),
    from readings without the modelled sensor offsets and torque-sensor ripple, and with the
    kinematic torsion state corrected for a modelled kinematic error."""
    # the stepper's exact sticking, unless `low_speed_friction`'s creep ramp regularises it
    exact_sticking = isinstance(simulator.solver, VelocityImplicit) and "low_speed_friction" not in effects.active
    if "sensor_offset" in effects.active:  # the initial state from offset-free readings
        init_exp = eqx.tree_at(
            lambda e: (e.torque, e.motor_velocity),
            exp,
            (exp.torque - effects.sensor_offset.torque_offset, exp.motor_velocity - effects.sensor_offset.velocity_offset),
        )
    else:
        init_exp = exp
    y0, th_m0 = initial_state(p, drive, init_exp, simulator, exact_sticking=exact_sticking)
    if "torque_sensor_ripple" in effects.active:
        # the ripple is in the measured torque, not in the drive: the initial torsion comes from the
        # torque without it (else a locked test whose motor sticks keeps the ripple's value at the
        # start as a torque offset), with θm over the samples `initial_state` reads (the first
        # `initial_window`) from the first estimate
        n = min(simulator.initial_window, exp.time.shape[0])
        th_m = th_m0 + y0[1] * (exp.time[:n] - exp.time[0])
        init_exp = eqx.tree_at(lambda e: e.torque, init_exp,
                               init_exp.torque.at[:n].add(-effects.periodic("torque_sensor_ripple", th_m)))
        y0, th_m0 = initial_state(p, drive, init_exp, simulator, exact_sticking=exact_sticking)
    if "nonlinear_stiffness" in effects.active or "lost_motion" in effects.active:
        # `initial_state` inverted the linear spring (Δθ0 = Tk0/K1); with a cubic or dead-zone
        # spring the torsion that gives the same elastic torque Tk0 differs (by K3·Δθ³/K1 or up to
        # the backlash), and a stuck locked test would keep the difference as a torque offset
        torsion0 = _invert_stiffness(p.K1, p.K1 * y0[0], effects)
        th_m0 = jnp.where(exp.has_motor_position > 0, th_m0, drive.gear_ratio * (torsion0 + y0[2]))
        y0 = (torsion0,) + tuple(y0[1:])
    if "kinematic_error" in effects.active:
        # the measured torque fixes the true torsion Δθ0 = q0 + e(θm0), so the kinematic torsion
        # state starts at q0 = Δθ0 − e(θm0) (else the simulation starts K1·e(θm0) off the measured
        # torque, an offset a stuck motor in a locked test keeps); θm0 = N(q0 + θo0) where the motor
        # angle is not measured, with e evaluated once at the first estimate (error O(N e e'))
        torsion0, th_o0 = y0[0], y0[2]
        q0 = torsion0 - effects.periodic("kinematic_error", th_m0)
        th_m0 = jnp.where(exp.has_motor_position > 0, th_m0, drive.gear_ratio * (q0 + th_o0))
        q0 = torsion0 - effects.periodic("kinematic_error", th_m0)
        y0 = (q0,) + tuple(y0[1:])
    if "rate_independent_hysteresis" in effects.active:
        y0 = y0 + (jnp.zeros_like(y0[0]),)
    if _presliding_index(effects) is not None:
        y0 = y0 + (_presliding_start(p, drive, init_exp, y0[1], effects, simulator),)
    return y0, th_m0


def _presliding_start(p: Parameters, drive: Drive, exp: Experiment, wm0, effects: Effects, simulator: Simulator):
    """`presliding_friction`'s state at the first sample: its steady state sign(ω0) when moving;
    when `initial_state` put the motor at rest, the state whose share w·s of the breakaway torque
    carries the net drive torque at the start (clipped to ±1; exact for Tsp = Tsn), so that a stuck
    motor stays stuck as it does in the data."""
    n = min(simulator.initial_window, exp.time.shape[0])
    i0, _ = _line_at_start(exp.time, exp.current, exp.mask, n)
    T0, _ = _line_at_start(exp.time, exp.torque, exp.mask, n)
    p_dyn, smoothing = _low_speed_friction(p, effects, simulator.smoothing)
    net = drive.torque_constant * i0 - T0 / drive.gear_ratio
    breakaway = jnp.where(net >= 0, p_dyn.Tsp + p_dyn.Tssp1, p_dyn.Tsn + p_dyn.Tssn1)
    w = effects.presliding_friction.presliding
    # (1 − w)·sign(0) + w·s = s·w must carry net/breakaway at rest
    held = jnp.clip(net / jnp.where(jnp.abs(breakaway) > 0, breakaway, 1.0) / jnp.where(jnp.abs(w) > 1e-12, w, 1.0), -1.0, 1.0)
    moving = smooth_sign(wm0, smoothing.velocity_scale)
    return jnp.where(wm0 == 0.0, held, moving)


def simulate(
    p: Parameters,
    drive: Drive,
    exp: Experiment,
    *,
    effects: Effects = Effects(),
    simulator: Simulator = Simulator(),
) -> Trajectory:
    """Simulate one experiment driven by its measured current; outputs at its sample times.

    `effects` switches on model extensions (`hdjax.Effects`, SPEC §4); the default is the
    paper's model. Padded samples (mask False) are simulated too (with the last current held) and
    should be ignored by the caller. Under `vmap`, failures are reported in `Trajectory.success`
    rather than raised.

    Called on concrete values (outside `jit`, `vmap`, `jvp`), it runs as one compiled program
    (`eqx.filter_jit`) that a later call with the same structure (numerics, effects switched on,
    array shapes) reuses, whatever the parameter and data values; before, such a call ran its
    set-up op by op and traced the solve again every time (a 12-call finite-difference check
    took 89 s, now 15 s). Under a caller's trace it is traced inline as before, so the compiled
    fits and diagnoses are unchanged to the bit (a nested `jit` there moved their figures by
    round-off).
    """
    if isinstance(simulator.solver, VelocityImplicit) and "presliding_friction" in effects.active:
        raise ValueError("`simulate`: `VelocityImplicit` does not model `presliding_friction` (its exact sticking is "
                         "that law's δ → 0 limit); use the default solver (`Rodas3`) or `PLANT_W_METHOD` for it.")
    if not isinstance(simulator.solver, VelocityImplicit) and "breakaway_friction" in effects.active:
        raise ValueError("`simulate`: `breakaway_friction` (static friction above eq. 9's) needs exact set-valued "
                         "sticking; use `Simulator(solver=VelocityImplicit(...))` for it.")
    return _simulate_one(p, drive, exp, effects, simulator)


def _compiled_when_concrete(fn):
    """`fn(*args)` as one compiled program (`eqx.filter_jit`, reused for calls of the same
    structure) when every argument is concrete, else traced inline into the caller's trace (a
    nested `jit` there would move compiled fits by round-off). `fn` takes positional arguments
    only and has no array defaults: a jitted function's signature is hashed, which is also why the
    public functions with an `Effects()` default call such a body instead of being it."""
    compiled = eqx.filter_jit(fn)

    @functools.wraps(fn)
    def call(*args):
        return compiled(*args) if is_concrete(args) else fn(*args)

    return call


@_compiled_when_concrete
def _simulate_one(p: Parameters, drive: Drive, exp: Experiment, effects: Effects, simulator: Simulator) -> Trajectory:
    """The body of `simulate`."""
    y0, th_m0 = _initial_state_with_effects(p, drive, exp, effects, simulator)
    # the mean sample step over the valid samples: time stamps may jitter (SPEC §2 allows up to 1 %
    # of the step), and one jittered first step would stretch the whole input's time axis
    n_valid = jnp.sum(exp.mask)
    t_last = exp.time[jnp.maximum(n_valid - 1, 1)]
    dt = (t_last - exp.time[0]) / jnp.maximum(n_valid - 1, 1).astype(t_last.dtype)
    # recorded current = true current + offset (SPEC §4b `sensor_offset`), removed once per solve
    true_current = exp.current - effects.sensor_offset.current_offset if "sensor_offset" in effects.active else exp.current
    if "input_between_samples" in effects.active:
        current = UniformCubicBlendInput(exp.time[0], dt, true_current, jnp.asarray(effects.input_between_samples.reconstruction))
    else:
        current = UniformLinearInput(exp.time[0], dt, true_current)
    measured = None
    if simulator.measured_angle:
        measured = MeasuredAngle(
            output=UniformLinearInput(exp.time[0], dt, exp.output_position),
            motor=UniformLinearInput(exp.time[0], dt, exp.motor_position),
            use_output=exp.free * exp.has_output_position, use_motor=exp.has_motor_position,
        )
    if isinstance(simulator.solver, VelocityImplicit):
        return _simulate_implicit(p, drive, exp, y0, th_m0, current, dt, effects, simulator, measured)
    # the reported angle is the measured one; the vector field reads it only where a term acts at it
    geometry = (y0[0], y0[2], th_m0, measured)
    geometry_ode = geometry if effects.active & set(PERIODIC) else geometry[:3] + (None,)
    if simulator.fixed_step is not None:
        controller = dfx.ConstantStepSize()
        dt0 = simulator.fixed_step
    else:
        pid = dfx.PIDController(rtol=simulator.rtol, atol=simulator.atol)
        clipped = StepToSamples(pid, exp.time) if simulator.step_to_samples else pid
        # the first step, a quarter of the sample step, set in the controller (`FirstStep`): the
        # same steps as `dt0=dt / 4`, with no host callback in the compiled program
        controller, dt0 = FirstStep(clipped, dt / 4), None
    # Steps clipped to the sample instants end on every sample: then the samples are read off the
    # saved steps (`SaveAt(steps=True)`, one array write per step) instead of diffrax's per-step
    # search-and-interpolate for `SaveAt(ts=...)`, which cost more than the Rosenbrock step itself
    # (benchmarks/RESULTS.md). The step buffer holds `max_steps` states (8 MB at the default, times
    # the number of forward-mode tangents), so only where experiments run one at a time
    # (`experiment_batching() == "map"`, the CPU default; under `vmap` every lane would hold one)
    # and in forward mode (reverse mode would carry the buffer through its checkpoints).
    save_steps = (
        simulator.fixed_step is None
        and simulator.step_to_samples
        and isinstance(simulator.adjoint, dfx.ForwardMode)
        and experiment_batching() == "map"
    )
    # `low_speed_friction` rescales Tss2 and the friction regularisation once per solve; it acts on
    # eq. 9 only (initial_state and the outputs use neither)
    p_dyn, smoothing_dyn = _low_speed_friction(p, effects, simulator.smoothing)
    sol = dfx.diffeqsolve(
        dfx.ODETerm(_vector_field),
        simulator.solver,
        t0=exp.time[0],
        t1=exp.time[-1],
        dt0=dt0,
        y0=y0,
        args=(p_dyn, drive, current, exp.free, exp.start_time, geometry_ode, effects, smoothing_dyn),
        saveat=dfx.SaveAt(t0=True, steps=True) if save_steps else dfx.SaveAt(ts=exp.time),
        stepsize_controller=controller,
        adjoint=simulator.adjoint,
        max_steps=simulator.max_steps,
        throw=False,
    )
    ys = _at_sample_times(sol.ts, sol.ys, exp.time) if save_steps else sol.ys
    assert ys is not None  # both SaveAt choices save states
    th_m, torsion, _, T = _outputs(p, drive, ys, geometry, effects, simulator.smoothing, exp.time)
    return _measured(
        T, ys[1], th_m, ys[2], ys[3], torsion, dt, effects,
        success=sol.result == dfx.RESULTS.successful, num_steps=sol.stats["num_accepted_steps"],
    )


def _simulate_implicit(p, drive, exp, y0, th_m0, current, dt, effects, simulator, measured):
    """`simulate` with the fixed-step implicit velocity-level stepper (`hdjax._plant.stepper`);
    `measured` the record's angles (`Simulator.measured_angle`) or None."""
    # the stepper reads the measured angle only where a periodic term acts at it (as the adaptive
    # plant's vector field); the reported angle is the measured one either way
    geometry = (y0[0], y0[2], th_m0, measured)
    p_dyn, vc = stepper_friction(p, effects, simulator.smoothing)
    (q, wm, th_o, wo, T, torsion, th_m), ok, n_steps = implicit_trajectory(
        p_dyn, drive, exp, y0, geometry, current, effects, vc, dt, simulator.solver
    )
    return _measured(T, wm, th_m, th_o, wo, torsion, dt, effects, success=jnp.all(ok | ~exp.mask), num_steps=jnp.asarray(n_steps))


def _measured(T, wm, th_m, th_o, wo, torsion, dt, effects: Effects, *, success, num_steps) -> Trajectory:
    """The simulated sensor readings: torque ripple, sensor lags and offsets (SPEC §4, §4b)."""
    measured_T = T + effects.periodic("torque_sensor_ripple", th_m)
    measured_w = wm
    if "sensor_bandwidth" in effects.active:
        # smooth through τ = 0 (where the fit starts); a negative τ (a lead, |a| < 1) is allowed
        # down to −0.45 Δt so that the map stays smooth there and stable everywhere
        measured_T = _first_order_lag(measured_T, effects.sensor_bandwidth.torque_lag, dt)
        measured_w = _first_order_lag(measured_w, effects.sensor_bandwidth.velocity_lag, dt)
    if "sensor_offset" in effects.active:
        measured_T = measured_T + effects.sensor_offset.torque_offset
        measured_w = measured_w + effects.sensor_offset.velocity_offset
    return Trajectory(
        torque=measured_T,
        motor_velocity=measured_w,
        motor_position=th_m,
        output_position=th_o,
        output_velocity=wo,
        torsion=torsion,
        success=success,
        num_steps=num_steps,
    )


def simulate_batch(
    p: Parameters,
    drive: Drive,
    batch: Experiment,
    *,
    effects: Effects = Effects(),
    simulator: Simulator = Simulator(),
) -> Trajectory:
    """`simulate` over a stacked batch (`stack_experiments`), one shared parameter set.

    With several devices (`jax.device_count() > 1`) and a concrete batch, the experiment axis is
    spread over all of them (`hdjax._plant.sharding`); inside `jit` the caller's input shardings apply."""
    if jax.device_count() > 1 and is_concrete((p, drive, batch, effects)):
        sharded, n = shard_experiments(batch)
        out = _simulate_sharded(p, drive, sharded, effects, simulator, experiment_mesh())
        return jax.tree.map(lambda x: x[:n], out)
    return _simulate_each(p, drive, batch, effects, simulator)


@_compiled_when_concrete
def _simulate_each(p, drive, batch, effects, simulator):
    """`simulate` over the experiments of `batch` on one device."""
    return for_each_experiment(
        lambda e: simulate(p, drive, e, effects=effects, simulator=simulator),
        batch,
        fixed_cost=is_fixed_cost(simulator),
    )


@eqx.filter_jit
def _simulate_sharded(p, drive, batch, effects, simulator, mesh):
    def per_experiment(shared, b):
        p_, d_, eff = shared
        return for_each_experiment(lambda e: simulate(p_, d_, e, effects=eff, simulator=simulator), b)

    return map_experiments(per_experiment, mesh)((p, drive, effects), batch)




