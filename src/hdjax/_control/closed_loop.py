r"""A sampled torque controller in closed loop with the differentiable harmonic-drive plant.

The loop (SI units), at every sample instant $t_k = k\,T_s$ of the torque sensor:

1. measure: torque $y_k = T(t_k) + r_{ripple}(\theta_m) + n^T_k$ (strain gauges, with the plant's
   `torque_sensor_ripple` effect if any) and wave-generator velocity $w_k = \omega_m(t_k) + n^\omega_k$
   (tachometer); with the plant's `sensor_bandwidth` effect (the sensor lags the fit identifies)
   the noise-free readings first pass the same first-order low-pass as in `simulate`
   ($y^f_k = a\,y^f_{k-1} + (1-a)\,x_k$, $a = \tau/(\tau + T_s)$, started at $y^f_0 = x_0$);
2. control law, PI(D) on measured torque plus model-based feed-forward:
   $$u_k = k_r\frac{r_k}{N K_m} + k_j\frac{N \hat J_{eff}\,r_k}{J_L K_m} + k_p e_k + I_k
   - k_d\,\dot y^f_k + k_f\frac{\hat T_f(w_k)}{K_m}, \qquad e_k = r_k - y_k,$$
   with $J_L$ the load inertia ($\infty$, so no inertia term, with the output locked), $\hat J_{eff}$
   and $\hat T_f$ the identified motor inertia and friction (eq. 9, sign/step smoothed on the scale
   `friction_scale`, because the tachometer is noisy), $\dot y^f$ the measured-torque derivative
   through a first-order filter (time constant `derivative_filter`; derivative on measurement, so
   a reference step gives no kick);
3. current saturation, smooth so that gradients exist beyond the limit:
   $i_k = \mathrm{sat}(u_k)$ with
   $\mathrm{sat}(u) = u - s\,[\mathrm{softplus}((u - i_{max})/s) - \mathrm{softplus}((-u - i_{max})/s)]$,
   which equals $u$ to within $s\,e^{-(i_{max}-|u|)/s}$ inside the limit and $\pm i_{max}$ to within
   $s\ln 2$ beyond it (`saturation_scale` $s$ in A);
4. integrator with back-calculation anti-windup:
   $I_{k+1} = I_k + k_i T_s e_k + \beta\,(i_k - u_k)$;
5. zero-order hold: the plant (with any `hdjax.Effects`) runs from $t_k$ to $t_{k+1}$ with the
   current $i_k$.

The plant (`solver`): by default the fixed-step exact plant of `hdjax._plant.stepper` (TR-BDF2
steps on the velocity level, Coulomb sticking and power-law damping without smoothing scales,
derivatives by the implicit function theorem), `substeps` steps per sample interval. Where the
held current jumps at $t_k$, a stuck motor's holding friction is taken again for the new current
(`PlantSteps.with_friction`). Measured (2026-12-05, 2-core machine): the torque converges as the
steps shrink (HD1 locked step 0.06 / 0.02 / 0.006 % of the amplitude at 2 / 4 / 8 steps against
32; HD2 free sine 1.5 / 0.18 / 0.04 %; `tests/test_control.py`); the tuning cost and its gradient
over 6 plants × 8 references of 500 samples take 0.16 s after compilation against 1.5 s on the
smoothed Rodas3 plant with refinement, and compile in 15 s against 23 s; reverse-mode gradients
match central differences to 1e-4. `solver="rodas3"` keeps the smoothed plant described next.

Numerics of the smoothed plant (measured on HD2 at 1 kHz by `benchmarks/tune_numerics.py`, against 64 substeps): the plant
is stiff (power-law damping $|\dot{\Delta\theta}|^{1/2}$ and the smoothed Coulomb step give
Jacobian eigenvalues of $10^4$–$10^5\,\mathrm{s^{-1}}$), the input is constant on each sample
interval, and the controller state changes only at the samples. So the loop is a `lax.scan` over
sample intervals and each interval is integrated by `substeps` fixed steps of the L-stable
Rosenbrock method `Rodas3` (`hdjax._plant.rosenbrock`, called step by step rather than through
`diffeqsolve`, which costs a while loop per interval). One substep per sample is *not* enough
(relative RMS torque error 1–23 %, worst on a free-output step); 2 substeps give 0.15–1.2 % (the
tuning model), 4 give 0.02–0.5 %, 16 give 2e-5–2e-3 (the bench). The discrete closed loop is a
smooth function of the gains: reverse-mode gradients match central differences with h = 1e-6 to
1e-5 relative or better at the tuning smoothing; with h = 1e-4 they can differ by up to 30 % under an
aggressive PI on a free-output step, where the cost is rugged on that scale (nearly chaotic
stick-slip), which is why `hdjax._workflows.tune` starts BFGS from a grid search.

Refinement (rodas3; `refine` > 1, the default): an interval whose embedded error estimate fails the gross
check (error above 1 absolute scale + 10 % relative) is recomputed with `refine`x finer steps;
`LoopTrajectory.refined` flags it. Under `vmap` both branches are always computed, so it costs
`1 + refine` times the run time. Noise-free, it fired only at 1 substep in the benchmark, but with
HD2's measurement noise and sensor ripple in the loop the unrefined 2- and 16-substep loops blow
up (bench cost 1.6 instead of 0.03 for the same PI), so it stays on; `refine=1` switches it off.
"""

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._fit.parameterisation import Entry, Parameterisation, parameterisation
from .._model.effects import Effects
from .._model.paper import Drive, Parameters, Smoothing, _as_float, friction_torque
from .._plant.rosenbrock import Rodas3
from .._plant.simulate import (
    _low_speed_friction,
    _outputs,
    _vector_field,
    sensor_lag_factor,
    state_size,
    stepper_friction,
)
from .._plant.stepper import VelocityImplicit, plant_steps

_REFINE_RTOL = 0.1  # relative part of the gross step-failure check (see the module doc)


class TorqueGains(eqx.Module):
    """The tunable gains of `TorqueController` (array leaves, so `jax.grad` reaches them).

    - `kp`: proportional gain on the torque error (A/(N·m)).
    - `ki`: integral gain (A/(N·m·s)).
    - `kd`: derivative gain on the filtered measured torque (A·s/(N·m)).
    - `kr`: reference feed-forward, as a multiple of the static locked gain $1/(N K_m)$ (-).
    - `kf`: weight of the friction feed-forward $\\hat T_f(w)/K_m$ (-; 1 = the identified friction).
    - `kj`: weight of the motor-inertia feed-forward $N\\hat J_{eff}\\,r/(J_L K_m)$ (-; 1 = the
      identified inertia): the current that accelerates the motor along with a free load of
      inertia $J_L$; zero with the output locked ($J_L = \\infty$).
    - `kpf`, `kif`: multipliers of `kp` and `ki` with a free output (-; 1 = the same PI locked and
      free): a two-mode gain schedule, since the controller knows whether the output is clamped.
    - `kfr`: weight of the friction feed-forward $\\hat T_f(\\omega_r)/K_m$ evaluated at the motor
      velocity the *reference* asks for (-; 0 = off), $\\omega_r = N(\\dot{\\Delta\\theta}_r + v_r)$
      with $\\dot{\\Delta\\theta}_r$ the torsion rate of the identified compliance following $r$
      (`reference_motor_velocity`) and $v_r = \\int r\\,dt/J_L$ the output velocity of a free load
      that follows $r$ (0 locked).
      Unlike `kf`'s measured velocity it is noise-free and known before the motor moves, so it
      pushes through breakaway at once and does not act on a motor at rest under a held torque.
    """

    kp: Float[Array, ""] = eqx.field(converter=_as_float)
    ki: Float[Array, ""] = eqx.field(converter=_as_float)
    kd: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    kr: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    kf: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    kj: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    kpf: Float[Array, ""] = eqx.field(converter=_as_float, default=1.0)
    kif: Float[Array, ""] = eqx.field(converter=_as_float, default=1.0)
    kfr: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)

    def to_dict(self) -> dict[str, float]:
        return {k: float(getattr(self, k)) for k in GAIN_NAMES}


GAIN_NAMES = ("kp", "ki", "kd", "kr", "kf", "kj", "kpf", "kif", "kfr")
GAIN_UNITS = {"kp": "A/(N·m)", "ki": "A/(N·m·s)", "kd": "A·s/(N·m)", "kr": "-", "kf": "-", "kj": "-", "kpf": "-",
              "kif": "-", "kfr": "-"}  # fmt: skip


class TorqueController(eqx.Module):
    """The fixed part of the torque controller: its model for the feed-forward and its hardware.

    **Arguments:**

    - `friction`: identified `Parameters` whose eq. 9 friction is fed forward.
    - `drive`: the drive constants (N, Km) of the feed-forward.
    - `sample_period`: sensor sample period $T_s$ (s); the controller runs at this rate.
    - `current_limit`: amplifier current limit $i_{max}$ (A).
    - `saturation_scale`: smoothing scale $s$ of the saturation (A), see the module doc.
    - `derivative_filter`: time constant of the measured-torque derivative filter (s).
    - `friction_scale`: velocity scale of sign()/u() in the fed-forward friction (rad/s); keep it
      above the tachometer noise, or the feed-forward chatters at standstill.
    - `anti_windup`: back-calculation weight β (-), 0 switches it off.
    """

    friction: Parameters
    drive: Drive
    sample_period: float = eqx.field(static=True, default=1e-3)
    current_limit: float = eqx.field(static=True, default=5.0)
    saturation_scale: float = eqx.field(static=True, default=0.05)
    derivative_filter: float = eqx.field(static=True, default=2e-3)
    friction_scale: float = eqx.field(static=True, default=0.1)
    anti_windup: float = eqx.field(static=True, default=0.5)


class Plant(eqx.Module):
    """The plant in the loop: `Parameters`, `Drive` and optional model extensions (`Effects`)."""

    parameters: Parameters
    drive: Drive
    effects: Effects = Effects()


class Reference(eqx.Module):
    """A torque reference sampled at the controller's rate, with the output locked or free.

    - `torque`: reference output torque $r_k$ (N·m) at $t_k = k\\,T_s$, from $t_0 = 0$ at rest.
    - `free`: 1.0 with a free output (load inertia), 0.0 with the output locked.
    """

    torque: Float[Array, " time"] = eqx.field(converter=_as_float)
    free: Float[Array, ""] = eqx.field(converter=_as_float)


class LoopTrajectory(eqx.Module):
    """Closed-loop signals at the sample instants $t_k$ (SI units); `current[k]` is held on
    $[t_k, t_{k+1})$ and the plant signals are those at $t_k$ (before the new current acts)."""

    time: Float[Array, " time"]
    reference: Float[Array, " time"]
    torque: Float[Array, " time"]
    measured_torque: Float[Array, " time"]
    motor_velocity: Float[Array, " time"]
    output_velocity: Float[Array, " time"]
    current: Float[Array, " time"]
    command: Float[Array, " time"]
    refined: Bool[Array, " time"]


def smooth_saturation(u: ArrayLike, limit: ArrayLike, scale: ArrayLike) -> Float[Array, "..."]:
    """Smooth clip of `u` to ±`limit` with rounding scale `scale` (same unit), see the module doc."""
    u = jnp.asarray(u)
    return u - scale * (jnp.logaddexp(0.0, (u - limit) / scale) - jnp.logaddexp(0.0, (-u - limit) / scale))


def _edge(t, start, rise):
    """0 before `start`, 1 after `start + rise`, a smoothstep in between (a jump for rise = 0)."""
    if rise <= 0:
        return (t >= start).astype(float)
    x = jnp.clip((t - start) / rise, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def step_reference(
    amplitude: float, *, duration: float, sample_period: float = 1e-3, start: float = 0.02, free: bool = False,
    rise: float = 0.0,
) -> Reference:
    """A torque step of `amplitude` (N·m) at time `start` (s), `duration` s long; with `rise` > 0 (s)
    its edge is a smoothstep of that length (a step the drive can follow)."""
    n = int(round(duration / sample_period))
    t = jnp.arange(n, dtype=float) * sample_period
    return Reference(torque=amplitude * _edge(t + 0.5 * sample_period, start, rise), free=float(free))


def sine_reference(
    amplitude: float, frequency: float, *, duration: float, sample_period: float = 1e-3, free: bool = False
) -> Reference:
    """A torque sine `amplitude·sin(2π·frequency·t)` (N·m, Hz), `duration` s long."""
    n = int(round(duration / sample_period))
    t = jnp.arange(n, dtype=float) * sample_period
    return Reference(torque=amplitude * jnp.sin(2.0 * jnp.pi * frequency * t), free=float(free))


def doublet_reference(
    amplitude: float, width: float, *, duration: float, sample_period: float = 1e-3, start: float = 0.02,
    free: bool = True, rise: float = 0.0,
) -> Reference:
    """A torque step of `amplitude` (N·m) at `start` (s), reversed to −`amplitude` after `width`
    (s) and back to zero after another `width`: the free-motion step, which brings the load back to
    rest instead of accelerating it without bound. With `rise` > 0 (s) each edge is a smoothstep of
    that length starting at the switching instant (the areas, hence the final speed, stay zero)."""
    n = int(round(duration / sample_period))
    t = jnp.arange(n, dtype=float) * sample_period + 0.5 * sample_period
    e = lambda s: _edge(t, s, rise)  # noqa: E731
    return Reference(torque=amplitude * (e(start) - 2.0 * e(start + width) + e(start + 2 * width)), free=float(free))


class _Held(eqx.Module):
    """Zero-order-hold current as the plant's input: `value` from `t_k` on, `previous` before
    (seen only through an `input_delay` effect)."""

    t_k: Float[Array, ""]
    previous: Float[Array, ""]
    value: Float[Array, ""]

    def evaluate(self, t):
        return jnp.where(t < self.t_k, self.previous, self.value)


def _noise_samples(noise, n):
    """The measurement noise sequences (N·m, rad/s), zeros where `noise` is None."""
    if noise is None:
        return jnp.zeros(n), jnp.zeros(n)
    return tuple(jnp.broadcast_to(jnp.asarray(x, dtype=float), (n,)) for x in noise)


def _sensor_lags(effects: Effects, ts) -> tuple[Float[Array, ""], Float[Array, ""]] | None:
    """The low-pass factors (a_T, a_ω) of the plant's `sensor_bandwidth` lags at the sample period
    `ts` (s), as `simulate` filters (`sensor_lag_factor`); None without it."""
    if "sensor_bandwidth" not in effects.active:
        return None
    sb = effects.sensor_bandwidth
    return sensor_lag_factor(sb.torque_lag, ts), sensor_lag_factor(sb.velocity_lag, ts)


def _sensed(lags, previous, k, torque, velocity):
    """The noise-free torque and velocity readings at sample `k` through the sensors' low-passes
    `lags` (`_sensor_lags`; None: unfiltered), from the `previous` readings; returns the readings
    twice (the second as the filter state carried to the next sample)."""
    if lags is None:
        return (torque, velocity), previous
    first = k == 0
    out = tuple(jnp.where(first, x, a * x_prev + (1.0 - a) * x) for a, x_prev, x in zip(lags, previous, (torque, velocity)))
    return out, out


def _scan_loop(step, carry0, ts, r, nT, nw) -> LoopTrajectory:
    """`lax.scan` of the loop's sample step `step(carry, (k, r_k, nT_k, nw_k))` over the reference
    `r` (sample period `ts`, s) and the noise samples, into a `LoopTrajectory`."""
    ks = jnp.arange(r.shape[0], dtype=float)
    _, (T, y_meas, wm, wo, i, u, bad) = jax.lax.scan(step, carry0, (ks, r, nT, nw))
    return LoopTrajectory(
        time=ks * ts, reference=r, torque=T, measured_torque=y_meas, motor_velocity=wm, output_velocity=wo,
        current=i, command=u, refined=bad,
    )  # fmt: skip


def _run_loop_rodas3(law, law_state0, plant: Plant, reference: Reference, *, sample_period, noise, substeps, smoothing, refine=8):
    """The sampled loop shared by `closed_loop` and `relay_test`: measure at $t_k$, call
    `law(state, r_k, y_k, w_k) -> (state, current, command)`, hold the current over the interval
    and advance the plant by `substeps` fixed Rodas3 steps; an interval whose embedded error
    estimate fails the gross check of the module doc is redone with `refine`x finer steps."""
    p, drive, effects = plant.parameters, plant.drive, plant.effects
    ts = sample_period
    r = reference.torque
    n = r.shape[0]
    nT, nw = _noise_samples(noise, n)
    zero = jnp.zeros(())
    y0 = (zero,) * state_size(effects)  # at rest; the Dahl and presliding states relaxed
    geometry = (zero, zero, zero, None)
    solver = Rodas3()
    term = dfx.ODETerm(_vector_field)
    # eq. 9 with a fitted low-speed law (SPEC §4b), as in `simulate`; a recorded-current offset does
    # not apply here: the law commands the true current
    p_dyn, smoothing_dyn = _low_speed_friction(p, effects, smoothing)
    # absolute error scales of the state (torsion worth 1 N·m, 1 rad/s, 1 mrad, 10 mrad/s, Dahl z,
    # presliding s)
    scales = (1.0 / p.K1, 1.0, 1e-3, 1e-2, 1e-2, 1e-2)[: len(y0)]

    lags = _sensor_lags(effects, ts)

    def step(carry, inputs):
        y, law_state, i_prev, sensed = carry
        k, r_k, nT_k, nw_k = inputs
        t_k = k * ts
        th_m, _, _, T = _outputs(p, drive, y, geometry, effects, smoothing)
        (y_sensed, w_sensed), sensed = _sensed(lags, sensed, k, T + effects.periodic("torque_sensor_ripple", th_m), y[1])
        y_meas = y_sensed + nT_k
        w_meas = w_sensed + nw_k
        law_state, i, u = law(law_state, r_k, y_meas, w_meas)
        args = (p_dyn, drive, _Held(t_k, i_prev, i), reference.free, zero, geometry, effects, smoothing_dyn)

        def advance(m):
            hm = ts / (substeps * m)

            def sub(j, carry):
                yy, err = carry
                t0 = t_k + j * hm
                y1, y_err, _, _, _ = solver.step(term, t0, t0 + hm, yy, args, None, False)
                e = jnp.max(jnp.stack([
                    jnp.abs(a) / (s + _REFINE_RTOL * jnp.maximum(jnp.abs(b), jnp.abs(c)))
                    for a, b, c, s in zip(y_err, yy, y1, scales)
                ]))  # fmt: skip
                return y1, jnp.maximum(err, jnp.where(jnp.isfinite(e), e, jnp.inf))

            return jax.lax.fori_loop(0, substeps * m, sub, (y, jnp.zeros(())))

        y_a, err = advance(1)
        if refine <= 1:  # no refinement: one pass, failed steps only flagged
            y_next = y_a
            return (y_next, law_state, i, sensed), (T, y_meas, y[1], y[3], i, u, ~(err < 1.0))
        bad = ~(err < 1.0)
        # on a failed step, redo the interval with `refine`x finer steps, starting from a state that is
        # finite in both branches so that no NaN leaks into the gradient of the branch not taken
        y_b, _ = advance(refine)
        y_next = jax.tree.map(lambda a, b: jnp.where(bad, b, jnp.where(jnp.isfinite(a), a, 0.0)), y_a, y_b)
        return (y_next, law_state, i, sensed), (T, y_meas, y[1], y[3], i, u, bad)

    return _scan_loop(step, (y0, law_state0, zero, (zero, zero)), ts, r, nT, nw)


def _run_loop(law, law_state0, plant: Plant, reference: Reference, *, sample_period, noise, substeps, smoothing, refine=8,
              solver: str = "velocity_implicit"):
    """The sampled loop shared by `closed_loop` and `relay_test`: measure at $t_k$, call
    `law(state, r_k, y_k, w_k) -> (state, current, command)`, hold the current over the interval
    and advance the plant over it by `substeps` steps of `solver`: "velocity_implicit" (the
    fixed-step exact plant, `hdjax._plant.stepper`) or "rodas3" (`_run_loop_rodas3`)."""
    if solver == "rodas3" and "breakaway_friction" in plant.effects.active:
        raise ValueError("closed loop: `breakaway_friction` needs the velocity_implicit plant's exact sticking; "
                         "use solver='velocity_implicit' for such a plant.")
    if solver == "rodas3":
        return _run_loop_rodas3(law, law_state0, plant, reference, sample_period=sample_period, noise=noise,
                                substeps=substeps, smoothing=smoothing, refine=refine)
    if solver != "velocity_implicit":
        raise ValueError(f"closed loop: `solver` must be 'velocity_implicit' or 'rodas3', got {solver!r}.")
    p, drive, effects = plant.parameters, plant.drive, plant.effects
    if "presliding_friction" in effects.active:
        raise ValueError("closed loop: the velocity_implicit plant does not model `presliding_friction` (its exact "
                         "sticking is that law's rigid limit); use solver='rodas3' for such a plant.")
    ts = sample_period
    r = reference.torque
    n = r.shape[0]
    nT, nw = _noise_samples(noise, n)
    zero = jnp.zeros(())
    h = ts / substeps
    # eq. 9 with a fitted low-speed law (SPEC §4b) as in `simulate`
    p_dyn, vc = stepper_friction(p, effects, smoothing)
    geometry = (zero, zero, zero, None)  # at rest at zero angles; the plant's own angle
    plant_at = plant_steps(p_dyn, drive, reference.free, zero, geometry, effects, vc, h, VelocityImplicit(substeps=substeps))
    at_rest = plant_at(_Held(zero, zero, zero))  # its angle does not depend on the current
    state0 = at_rest.start((zero,) * 4, zero)

    lags = _sensor_lags(effects, ts)

    def step(carry, inputs):
        st, law_state, i_prev, sensed = carry
        k, r_k, nT_k, nw_k = inputs
        t_k = k * ts
        T = st[6]
        ripple = effects.periodic("torque_sensor_ripple", at_rest.theta_m(st[0], st[2], t_k))
        (y_sensed, w_sensed), sensed = _sensed(lags, sensed, k, T + ripple, st[1])
        y_meas = y_sensed + nT_k
        w_meas = w_sensed + nw_k
        law_state, i, u = law(law_state, r_k, y_meas, w_meas)
        steps = plant_at(_Held(t_k, i_prev, i))
        # the new current acts from t_k on: a stuck motor's holding friction follows it
        st1 = steps.with_friction(st, t_k)

        def sub(x, j):
            return steps.step(x, t_k + j * h)

        st_next, conv = jax.lax.scan(sub, st1, jnp.arange(substeps, dtype=float))
        return (st_next, law_state, i, sensed), (T, y_meas, st[1], st[3], i, u, ~jnp.all(conv))

    return _scan_loop(step, (state0, law_state0, zero, (zero, zero)), ts, r, nT, nw)


def closed_loop(
    gains: TorqueGains,
    plant: Plant,
    reference: Reference,
    *,
    controller: TorqueController,
    noise: tuple[ArrayLike, ArrayLike] | None = None,
    substeps: int = 2,
    refine: int = 4,
    smoothing: Smoothing = Smoothing(),
    solver: str = "velocity_implicit",
) -> LoopTrajectory:
    """Simulate the sampled torque loop on `plant` following `reference`; differentiable in all
    array arguments (`jax.grad`, `jax.jacfwd`) and `vmap`-able over plants, references and noise.

    **Arguments:**

    - `gains`: `TorqueGains`.
    - `plant`: `Plant` (the truth being controlled; its effects act, e.g. sensor ripple, and the
      sensor lags of `sensor_bandwidth` low-pass the readings the controller gets).
    - `reference`: `Reference` (torque samples at `controller.sample_period`, locked or free).
    - `controller`: `TorqueController` (feed-forward model, limits, sample period).
    - `noise`: optional `(torque_noise, velocity_noise)` sample sequences (N·m, rad/s) added to
      the measurements; default none.
    - `substeps`: fixed plant steps per sample interval (see the module doc).
    - `refine` (rodas3 only): if > 1, an interval whose step fails the gross error check is redone
      with `refine`x more steps; either way `LoopTrajectory.refined` marks it (see the module doc;
      needed with noisy measurements on HD2).
    - `smoothing`: the smoothing scales of the rodas3 plant (`Smoothing`; the velocity_implicit
      plant is exact and reads only `low_speed_friction`'s scale from it).
    - `solver`: "velocity_implicit" (the default: `hdjax.VelocityImplicit`'s TR-BDF2 steps, exact
      sticking and power-law damping, `LoopTrajectory.refined` marking an interval where a root did
      not converge) or "rodas3" (the smoothed plant, see the module doc).

    **Returns:** a `LoopTrajectory`. The plant starts at rest (zero torsion, velocity and angle).
    """
    ts = controller.sample_period
    N = controller.drive.gear_ratio
    Km = controller.drive.torque_constant
    ff_smoothing = Smoothing(velocity_scale=controller.friction_scale)
    a = jnp.exp(-ts / controller.derivative_filter)
    # N·Jeff/J_L (1/(m·...)): motor-side inertia torque per N·m of free output torque; 0 when locked
    inertia_ff = reference.free * N * controller.friction.Jeff / controller.drive.load_inertia
    kp = gains.kp * (1.0 + reference.free * (gains.kpf - 1.0))
    ki = gains.ki * (1.0 + reference.free * (gains.kif - 1.0))

    inv_load = reference.free / controller.drive.load_inertia

    def law(state, r_k, y_meas, w_meas):
        integ, dfilt, y_prev, first, torsion_ref, v_ref = state
        e = r_k - y_meas
        # derivative of the measured torque; the first sample has no predecessor
        dfilt = a * dfilt + (1.0 - a) * (1.0 - first) * (y_meas - y_prev) / ts
        w_ref, torsion_ref = reference_motor_velocity(r_k, torsion_ref, v_ref, controller.friction, N=N, ts=ts)
        ff = (
            gains.kr * r_k / (N * Km)
            + gains.kj * inertia_ff * r_k / Km
            + gains.kf * friction_torque(controller.friction, w_meas, ff_smoothing) / Km
            + gains.kfr * friction_torque(controller.friction, w_ref, ff_smoothing) / Km
        )
        u = ff + kp * e + integ - gains.kd * dfilt
        i = smooth_saturation(u, controller.current_limit, controller.saturation_scale)
        integ = integ + ki * ts * e + controller.anti_windup * (i - u)
        return (integ, dfilt, y_meas, jnp.zeros(()), torsion_ref, v_ref + ts * r_k * inv_load), i, u

    zero = jnp.zeros(())
    return _run_loop(
        law, (zero, zero, zero, jnp.ones(()), zero, zero), plant, reference, sample_period=ts, noise=noise,
        substeps=substeps, smoothing=smoothing, refine=refine, solver=solver,
    )  # fmt: skip


def reference_torsion_rate(r, torsion, p: Parameters):
    """Flexspline torsion rate (rad/s) that brings the identified compliance to the torque `r` (N·m)
    from the torsion `torsion` (rad): eq. 2 solved for the rate,
    $\\dot{\\Delta\\theta} = \\mathrm{sign}(e)\\,(|e|/T_{st})^{1/\\alpha}$ with $e = r - K_1\\Delta\\theta$
    (the power-law damping carries what the spring does not)."""
    e = r - p.K1 * torsion
    a = jnp.maximum(jnp.abs(e), 1e-12)  # |e|^(1/α) has a zero derivative at 0; keep log|e| finite for α
    return jnp.sign(e) * (a / p.Tst) ** (1.0 / p.alpha)


def reference_motor_velocity(r, torsion, v_ref, p: Parameters, *, N, ts, substeps: int = 4):
    """Wave-generator velocity (rad/s) that a torque reference asks for, and the next reference
    torsion: $\\omega_r = N(\\dot{\\Delta\\theta}_r + v_r)$ with the torsion rate of the identified
    compliance (`reference_torsion_rate`, explicit Euler over `substeps` per sample period `ts`) and
    $v_r$ (rad/s) the output velocity of a free load driven by $r$ (0 with the output locked)."""
    h = ts / substeps
    rate0 = reference_torsion_rate(r, torsion, p)
    th = torsion
    for _ in range(substeps):
        th = th + h * reference_torsion_rate(r, th, p)
    return N * (rate0 + v_ref), th


def relay_test(
    plant: Plant,
    *,
    level: float,
    amplitude: float,
    sample_period: float = 1e-3,
    duration: float = 1.0,
    substeps: int = 2,
    smoothing: Smoothing = Smoothing(),
    solver: str = "velocity_implicit",
) -> LoopTrajectory:
    r"""Åström–Hägglund relay experiment with the output locked: current
    $i = i_0 + d\,\mathrm{sign}(r - y)$ about the torque `level` $r$ (N·m), with
    $i_0 = r/(N K_m)$ and relay `amplitude` $d$ (A). The loop settles into a limit cycle whose
    period and torque amplitude give the ultimate gain and period (`ziegler_nichols_pi`)."""
    N = plant.drive.gear_ratio
    Km = plant.drive.torque_constant
    n = int(round(duration / sample_period))
    ref = Reference(torque=jnp.full(n, float(level)), free=0.0)

    def law(state, r_k, y_meas, w_meas):
        i = r_k / (N * Km) + amplitude * jnp.sign(r_k - y_meas)
        return state, i, i

    return _run_loop(
        law, jnp.zeros(()), plant, ref, sample_period=sample_period, noise=None, substeps=substeps, smoothing=smoothing,
        solver=solver,
    )


def tracking_cost(
    traj: LoopTrajectory, *, scale: ArrayLike, current_scale: ArrayLike = 1.0, effort_weight: float = 0.0
) -> Float[Array, ""]:
    r"""Normalised tracking cost of one closed-loop run (-):
    $\overline{(r - T)^2}/s^2 + w_u\,\overline{i^2}/i_s^2$, with $T$ the true transmitted torque,
    `scale` $s$ (N·m, e.g. the reference amplitude), `current_scale` $i_s$ (A) and `effort_weight`
    $w_u$ (-)."""
    err = jnp.mean((traj.reference - traj.torque) ** 2) / scale**2
    return err + effort_weight * jnp.mean(traj.current**2) / current_scale**2


def ziegler_nichols_pi(traj: LoopTrajectory, *, level: float, amplitude: float) -> tuple[TorqueGains, dict]:
    """The classical rule-tuned PI from a `relay_test` record: ultimate gain
    $K_u = 4d/(\\pi a)$ (A/(N·m)) from the torque oscillation amplitude $a$ over the second half
    of the record, ultimate period $T_u$ (s) from its mean crossing interval, then Ziegler–Nichols
    $k_p = 0.45K_u$, $k_i = k_p/(T_u/1.2)$. Returns the gains and the relay figures."""
    t = np.asarray(traj.time)
    y = np.asarray(traj.measured_torque) - level
    half = t >= 0.5 * t[-1]
    a = 0.5 * (y[half].max() - y[half].min())
    yh, th = y[half], t[half]
    up = np.nonzero((yh[:-1] < 0) & (yh[1:] >= 0))[0]
    if len(up) < 3 or not np.isfinite(a) or a <= 0:
        raise ValueError(
            "relay test: no sustained oscillation in the second half of the record; raise the relay amplitude "
            "(`tune.relay_amplitude`) above the friction level or lengthen the test."
        )
    tc = th[up] - yh[up] * (th[up + 1] - th[up]) / (yh[up + 1] - yh[up])
    Tu = float(np.mean(np.diff(tc)))
    Ku = 4.0 * amplitude / (np.pi * a)
    kp = 0.45 * Ku
    ki = kp / (Tu / 1.2)
    return TorqueGains(kp=kp, ki=ki), {"ultimate_gain": float(Ku), "ultimate_period_s": Tu, "oscillation_amplitude": float(a)}


def step_metrics(
    time: ArrayLike, torque: ArrayLike, *, amplitude: float, start: float, end: float, band: float = 0.05
) -> dict[str, float | None]:
    """Overshoot (% of the step) and settling time (s after the step; into ±`band`·|amplitude| and
    staying until `end`) of a torque step of `amplitude` (N·m) applied from `start` to `end` (s).
    `settling_time_s` is None when the torque never settles before `end`."""
    t = np.asarray(time)
    y = np.asarray(torque)
    win = (t >= start) & (t < end)
    if not win.any():
        raise ValueError(f"`step_metrics`: no sample in the step window [{start:g}, {end:g}) s; give an `end` after `start`.")
    tw, yw = t[win], y[win]
    s = np.sign(amplitude)
    overshoot = max(0.0, float(np.max(s * yw) - abs(amplitude))) / abs(amplitude) * 100.0
    outside = np.abs(yw - amplitude) > band * abs(amplitude)
    if outside[-1]:
        settle = None
    else:
        last = np.nonzero(outside)[0]
        settle = float(tw[last[-1] + 1] - start) if len(last) else 0.0
    return {"overshoot_percent": overshoot, "settling_time_s": settle}


def tracking_rms(traj: LoopTrajectory) -> Float[Array, ""]:
    """RMS of reference minus true transmitted torque (N·m)."""
    return jnp.sqrt(jnp.mean((traj.reference - traj.torque) ** 2))


# ----------------------------------------------------------------------------------------------
# Gradient tuning
# ----------------------------------------------------------------------------------------------


class GainScaling(eqx.Module):
    """Map between the optimiser's unconstrained, O(1) vector θ and `TorqueGains`:
    $k_p = k_{p0}e^{\\theta_0}$, $k_i = k_{i0}e^{\\theta_1}$ (kept positive),
    $k_d = k_{p0}\\,T_d\\,\\theta_2$, $k_r = \\theta_3$, $k_f = \\theta_4$, $k_j = \\theta_5$,
    $k_{pf} = e^{\\theta_6}$, $k_{if} = e^{\\theta_7}$, $k_{fr} = \\theta_8$."""

    kp0: float
    ki0: float
    derivative_time: float

    def parameterisation(self) -> Parameterisation:
        """The map as a `Parameterisation` of `TorqueGains` (log slots relative to kp0, ki0, 1)."""
        return parameterisation(
            (Entry("kp", transform="log"), Entry("ki", transform="log"), Entry("kd"), Entry("kr"), Entry("kf"),
             Entry("kj"), Entry("kpf", transform="log"), Entry("kif", transform="log"), Entry("kfr")),
            np.array([self.kp0, self.ki0, self.kp0 * self.derivative_time, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]))  # fmt: skip

    def gains(self, theta: Float[Array, " 9"]) -> TorqueGains:
        return self.parameterisation().to_model(theta, TorqueGains(kp=0.0, ki=0.0))

    def theta(self, g: TorqueGains) -> Float[Array, " 9"]:
        return self.parameterisation().to_vector(g)


def batch_cost(
    gains: TorqueGains,
    plants: Plant,
    references: Reference,
    *,
    controller: TorqueController,
    scales: Float[Array, " reference"],
    noise: tuple[Float[Array, "reference time"], Float[Array, "reference time"]] | None = None,
    effort_weight: float = 0.0,
    substeps: int = 2,
    refine: int = 4,
    smoothing: Smoothing = Smoothing(),
    solver: str = "velocity_implicit",
    effects_per_plant: bool = False,
) -> tuple[Float[Array, "plant reference"], Float[Array, "plant reference"]]:
    """Tracking and tuning cost of every (plant, reference) pair, `vmap`ped over both.

    `plants` is a `Plant` whose `parameters` leaves carry a leading `plant` axis (drive shared;
    effects shared, or with `effects_per_plant` stacked along the same axis); `references` carries
    a leading `reference` axis, `scales` (N·m) normalise each reference's error, `noise` holds measurement-noise sequences per reference (the same for
    every plant: common random numbers); `substeps`, `refine`, `smoothing`, `solver` as in `closed_loop`.
    Tracking cost: $\\overline{(r-T)^2}/s^2$ (-); tuning cost
    adds `effort_weight`·$\\overline{(\\Delta i)^2}/i_{max}^2$ (-), which charges current chatter.
    Returns `(tracking, tuning)`, both of shape (plant, reference)."""
    if noise is None:
        zeros = jnp.zeros_like(references.torque)
        noise = (zeros, zeros)

    def one(params, effects, ref, scale, nT, nw):
        traj = closed_loop(
            gains, Plant(params, plants.drive, effects), ref, controller=controller, noise=(nT, nw),
            substeps=substeps, refine=refine, smoothing=smoothing, solver=solver,
        )  # fmt: skip
        track = jnp.mean((traj.reference - traj.torque) ** 2) / scale**2
        di = jnp.diff(traj.current)
        effort = jnp.mean(di**2) / controller.current_limit**2
        return track, track + effort_weight * effort

    over_refs = jax.vmap(one, in_axes=(None, None, 0, 0, 0, 0))
    over_plants = jax.vmap(over_refs, in_axes=(0, 0 if effects_per_plant else None, None, None, None, None))
    return over_plants(plants.parameters, plants.effects, references, jnp.asarray(scales), noise[0], noise[1])


@jax.custom_vjp
def _clip_gradient(x, max_norm):
    return x


def _clip_fwd(x, max_norm):
    return x, max_norm


def _clip_bwd(max_norm, g):
    n = jnp.sqrt(jnp.sum(g**2))
    g = jnp.where(jnp.isfinite(n), g * jnp.minimum(1.0, max_norm / jnp.maximum(n, 1e-300)), jnp.zeros_like(g))
    return g, None


_clip_gradient.defvjp(_clip_fwd, _clip_bwd)


class TuneResult(eqx.Module):
    """Result of `tune_gains`: the tuned `gains`, the mean tuning cost at the start and at each
    accepted iterate (`history`, -), the number of optimiser steps and whether it converged."""

    gains: TorqueGains
    history: list = eqx.field(static=True)
    steps: int = eqx.field(static=True)
    converged: bool = eqx.field(static=True)
    runs: list = eqx.field(static=True, default=())
    best_run: int = eqx.field(static=True, default=0)


def tune_gains(
    start,
    cost_fn,
    *,
    scaling: GainScaling,
    max_steps: int = 40,
    rtol: float = 1e-4,
    atol: float = 1e-6,
    max_gradient: float = 1.0,
    cost_scale: float = 1.0,
    log=None,
    progress=None,
) -> TuneResult:
    """Minimise `cost_fn(gains) -> scalar` from `start` with optimistix BFGS (backtracking Armijo
    line search) in the scaled coordinates of `scaling`; gradients by reverse-mode AD through the
    closed loop. Steps are taken one by one so that the cost of every accepted iterate is kept.

    `start` may be a list of `TorqueGains` (multi-start): BFGS runs from each in turn with the same
    compiled step, and the result with the lowest final cost is returned; its `runs` lists every
    start's history.

    `max_gradient` caps the gradient norm in θ (-). Where the closed loop is chaotic (a limit
    cycle in stick-slip, e.g. a free-output step under an aggressive start), the gradient of a
    0.5 s horizon is huge and meaningless (central differences disagree with it and with each
    other); uncapped, BFGS's first trial step lands astronomically far and the line search spends
    its whole budget backtracking. Ordinary gradients here are O(1e-2), so the cap acts only then;
    the Armijo line search still accepts only true decreases of the cost.

    `cost_scale` divides the cost inside the optimiser (costs and history are reported unscaled):
    BFGS's first trial step is the raw gradient, so a cost of O(1e-3) gives steps of O(1e-3) in the
    log-gains and the step budget is spent before the Hessian estimate is any good; pass the start
    cost to make it O(1).

    `log(line)` gets one line per accepted cost; `progress(step, cost)` is called after every step
    (a progress bar)."""
    import optimistix as optx

    starts = list(start) if isinstance(start, (list, tuple)) else [start]
    solver = optx.BFGS(rtol=rtol, atol=atol)
    fn = lambda theta, args: (cost_fn(scaling.gains(_clip_gradient(theta, max_gradient))) / cost_scale, None)  # noqa: E731
    x64 = jax.config.jax_enable_x64  # pyright: ignore[reportAttributeAccessIssue]  jax.config options are dynamic attributes
    f_struct = jax.ShapeDtypeStruct((), jnp.float64 if x64 else jnp.float32)
    init = eqx.filter_jit(lambda th: solver.init(fn, th, None, {}, f_struct, None, frozenset()))
    step = eqx.filter_jit(lambda th, st: solver.step(fn, th, None, {}, st, frozenset()))
    terminate = eqx.filter_jit(lambda th, st: solver.terminate(fn, th, None, {}, st, frozenset()))
    runs = []
    for j, s0 in enumerate(starts):
        theta = scaling.theta(s0)
        state = init(theta)
        history = []
        converged = False
        n = 0
        for n in range(1, max_steps + 1):
            theta, state, _ = step(theta, state)
            f = float(state.f_info.f) * cost_scale
            if progress is not None:
                progress(n, f)
            if not history or f != history[-1]:
                history.append(f)
                if log is not None:
                    log(f"  start {j + 1}, step {n:3d}: cost {f:.5g}")
            done, _ = terminate(theta, state)
            if bool(done):
                converged = True
                break
        # optimistix's BFGS step returns the last accepted iterate, and state.f_info.f is its cost
        runs.append({"theta": theta, "history": history, "steps": n, "converged": converged,
                     "final": history[-1] if history else np.inf})  # fmt: skip
    finals = [r["final"] for r in runs]
    k = int(np.nanargmin(np.where(np.isfinite(finals), finals, np.nan)))
    r = runs[k]
    return TuneResult(
        gains=scaling.gains(r["theta"]), history=r["history"], steps=r["steps"], converged=r["converged"],
        runs=[{"history": x["history"], "steps": x["steps"], "converged": x["converged"], "final_cost": f}
              for x, f in zip(runs, finals)], best_run=k,
    )  # fmt: skip


def numpy_torque_law(gains: list[TorqueGains], controller: TorqueController, free):
    """The control law of `closed_loop` in numpy, vectorised over B columns (one `TorqueGains` per
    column, `free` (B,) flags), as a stateful callable `law(k, r_k, y_k, w_k) -> current` for a
    loop simulated elsewhere (`hdjax._testbench.independent.Bench.closed_loop`). Same derivative filter, smooth
    saturation, back-calculation anti-windup and feed-forward as `closed_loop`."""
    g = {k: np.array([float(getattr(x, k)) for x in gains]) for k in GAIN_NAMES}
    ts = controller.sample_period
    N = float(controller.drive.gear_ratio)
    Km = float(controller.drive.torque_constant)
    a = float(np.exp(-ts / controller.derivative_filter))
    inertia_ff = np.asarray(free, float) * N * float(controller.friction.Jeff) / float(controller.drive.load_inertia)
    ff_sm = Smoothing(velocity_scale=controller.friction_scale)
    st = {"I": np.zeros(len(gains)), "d": np.zeros(len(gains)), "y": np.zeros(len(gains)), "first": 1.0,
          "torsion": np.zeros(len(gains)), "v": np.zeros(len(gains))}
    inv_load = np.asarray(free, float) / float(controller.drive.load_inertia)

    fr = np.asarray(free, float)
    kp = g["kp"] * (1.0 + fr * (g["kpf"] - 1.0))
    ki = g["ki"] * (1.0 + fr * (g["kif"] - 1.0))

    def law(k, r, y, w):
        e = r - y
        st["d"] = a * st["d"] + (1.0 - a) * (1.0 - st["first"]) * (y - st["y"]) / ts
        Tf = np.asarray(friction_torque(controller.friction, jnp.asarray(w), ff_sm))
        w_ref, th = reference_motor_velocity(jnp.asarray(r, float), jnp.asarray(st["torsion"]), jnp.asarray(st["v"]),
                                             controller.friction, N=N, ts=ts)
        st["torsion"] = np.array(th)
        Tfr = np.asarray(friction_torque(controller.friction, w_ref, ff_sm))
        ff = g["kr"] * r / (N * Km) + g["kj"] * inertia_ff * r / Km + g["kf"] * Tf / Km + g["kfr"] * Tfr / Km
        u = ff + kp * e + st["I"] - g["kd"] * st["d"]
        lim, s = controller.current_limit, controller.saturation_scale
        i = u - s * (np.logaddexp(0.0, (u - lim) / s) - np.logaddexp(0.0, (-u - lim) / s))
        st["I"] = st["I"] + ki * ts * e + controller.anti_windup * (i - u)
        st["y"], st["first"] = y, 0.0
        st["v"] = st["v"] + ts * r * inv_load
        return i

    return law
