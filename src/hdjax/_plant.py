r"""The harmonic-drive plant as a diffrax ODE driven by the measured motor current.

State (SI units): torsion $\Delta\theta$ (rad, output side), wave-generator velocity $\omega_m$
(rad/s), output angle $\theta_o$ (rad) and output velocity $\omega_o$ (rad/s):

$$\dot{\Delta\theta} = \omega_m/N - \omega_o,\quad
J_{eff}\dot\omega_m = K_m i(t) - T/N - T_f(\omega_m),\quad
\dot\theta_o = \omega_o,\quad J_{load}\dot\omega_o = f\,T,$$

with $T$ from eq. 5 and $f = 1$ in free motion, $0$ with the output locked. Torsion is a state
(rather than the motor angle) so that it is never a small difference of large angles. The motor
angle is recovered as $\theta_m = \theta_{m0} + N((\Delta\theta - \Delta\theta_0) + (\theta_o - \theta_{o0}))$.

Numerics (measured, see `benchmarks/solver_choice.py` and the README): the structural damping
$|\dot{\Delta\theta}|^{1/2}$ and the smoothed Coulomb step give the ODE a very large Jacobian near
zero torsion rate and zero velocity; the default is an L-stable Rosenbrock method (`Rodas3`, see
`hdjax._solver`) with a PID step controller, stepping onto every sample instant
(`ClipStepSizeController(step_ts=time)`) so that the kinks of the piecewise-linear current never
fall inside a step.
"""

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._experiment import Experiment
from ._solver import Rodas3
from ._model import Drive, Parameters, Smoothing, compliance_torque, motor_acceleration


class Trajectory(eqx.Module):
    """A simulated experiment at its sample times (SI units).

    **Attributes:**

    - `torque`: transmitted torque (N·m), eq. 5.
    - `motor_velocity`: wave-generator velocity (rad/s).
    - `motor_position`: wave-generator angle (rad).
    - `output_position`: output angle (rad).
    - `output_velocity`: output velocity (rad/s).
    - `torsion`: flexspline torsion (rad).
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

    - `solver`: diffrax solver; default `Rodas3()` (linearly implicit, see `hdjax._solver`).
    - `rtol`, `atol`: PID step-size controller tolerances (atol on states in SI units).
    - `step_to_samples`: clip steps to the sample instants (kinks of the interpolated current).
    - `adjoint`: `ForwardMode()` by default, for LM Jacobians and `jacfwd` sensitivities; use
      `RecursiveCheckpointAdjoint()` for reverse-mode scalar gradients.
    - `max_steps`: step budget per experiment.
    - `smoothing`: scales of the smooth sign/step/power stand-ins (`Smoothing`).
    - `initial_window`: samples used to estimate the initial state by a local linear fit.
    """

    solver: dfx.AbstractSolver = Rodas3()
    rtol: float = 1e-7
    atol: float = 1e-9
    step_to_samples: bool = True
    adjoint: dfx.AbstractAdjoint = dfx.ForwardMode()
    max_steps: int = 200_000
    smoothing: Smoothing = Smoothing()
    initial_window: int = 11


def _line_at_start(t: Array, y: Array, mask: Array, n: int) -> tuple[Array, Array]:
    """Value and slope at t[0] of a least-squares line through the first `n` valid samples."""
    tt = t[:n] - t[0]
    yy = y[:n]
    w = mask[:n].astype(float)
    sw = jnp.sum(w)
    tm = jnp.sum(w * tt) / sw
    ym = jnp.sum(w * yy) / sw
    slope = jnp.sum(w * (tt - tm) * (yy - ym)) / jnp.maximum(jnp.sum(w * (tt - tm) ** 2), 1e-300)
    return ym - slope * tm, slope


def initial_state(p: Parameters, drive: Drive, exp: Experiment, simulator: Simulator = Simulator()):
    """Initial plant state estimated from the first samples of the measured record.

    Motor velocity, torque and output angle come from local linear fits (unbiased under a linear
    trend, averaging the sensor noise); torsion inverts eq. 5 at the initial torsion rate.
    Returns `(y0, theta_m0)`: the state tuple and the initial motor angle (rad)."""
    n = min(simulator.initial_window, exp.time.shape[0])
    N = drive.gear_ratio
    wm0, _ = _line_at_start(exp.time, exp.motor_velocity, exp.mask, n)
    T0, dT0 = _line_at_start(exp.time, exp.torque, exp.mask, n)
    th_o0, _ = _line_at_start(exp.time, exp.output_position, exp.mask, n)
    th_o0 = th_o0 * exp.free + exp.output_position[0] * (1 - exp.free) * exp.has_output_position
    wo0 = exp.free * (wm0 / N - dT0 / p.K1)
    rate0 = wm0 / N - wo0
    damping = compliance_torque(p, 0.0, rate0, simulator.smoothing)
    torsion0 = (T0 - damping) / p.K1
    th_m0 = jnp.where(exp.has_motor_position > 0, exp.motor_position[0], N * (torsion0 + th_o0))
    return (torsion0, wm0, th_o0, wo0), th_m0


class UniformLinearInput(eqx.Module):
    """Piecewise-linear interpolation of samples on a uniform grid, O(1) per evaluation.

    (diffrax's `LinearInterpolation` searches the whole grid, which under `vmap` costs O(samples)
    per evaluation; here the grid is uniform, so the index is computed directly.)"""

    t0: Float[Array, ""]
    dt: Float[Array, ""]
    values: Float[Array, " time"]

    def evaluate(self, t):
        s = (t - self.t0) / self.dt
        n = self.values.shape[0]
        i = jnp.clip(jnp.floor(s), 0, n - 2).astype(int)
        w = s - i
        return (1.0 - w) * self.values[i] + w * self.values[i + 1]


def _vector_field(t, y, args):
    p, drive, current, free, smoothing = args
    torsion, wm, th_o, wo = y
    rate = wm / drive.gear_ratio - wo
    T = compliance_torque(p, torsion, rate, smoothing)
    dwm = motor_acceleration(p, drive, current.evaluate(t), T, wm, smoothing)
    dwo = free * T / drive.load_inertia
    return (rate, dwm, wo, dwo)


def simulate(p: Parameters, drive: Drive, exp: Experiment, *, simulator: Simulator = Simulator()) -> Trajectory:
    """Simulate one experiment driven by its measured current; outputs at its sample times.

    Padded samples (mask False) are simulated too (with the last current held) and should be
    ignored by the caller. Under `vmap`, failures are reported in `Trajectory.success` rather than
    raised.
    """
    y0, th_m0 = initial_state(p, drive, exp, simulator)
    current = UniformLinearInput(exp.time[0], exp.time[1] - exp.time[0], exp.current)
    pid = dfx.PIDController(rtol=simulator.rtol, atol=simulator.atol)
    controller = dfx.ClipStepSizeController(pid, step_ts=exp.time) if simulator.step_to_samples else pid
    dt = exp.time[1] - exp.time[0]
    sol = dfx.diffeqsolve(
        dfx.ODETerm(_vector_field),
        simulator.solver,
        t0=exp.time[0],
        t1=exp.time[-1],
        dt0=dt / 4,
        y0=y0,
        args=(p, drive, current, exp.free, simulator.smoothing),
        saveat=dfx.SaveAt(ts=exp.time),
        stepsize_controller=controller,
        adjoint=simulator.adjoint,
        max_steps=simulator.max_steps,
        throw=False,
    )
    torsion, wm, th_o, wo = sol.ys
    N = drive.gear_ratio
    T = compliance_torque(p, torsion, wm / N - wo, simulator.smoothing)
    th_m = th_m0 + N * ((torsion - y0[0]) + (th_o - y0[2]))
    return Trajectory(
        torque=T,
        motor_velocity=wm,
        motor_position=th_m,
        output_position=th_o,
        output_velocity=wo,
        torsion=torsion,
        success=sol.result == dfx.RESULTS.successful,
        num_steps=sol.stats["num_accepted_steps"],
    )


def simulate_batch(
    p: Parameters, drive: Drive, batch: Experiment, *, simulator: Simulator = Simulator()
) -> Trajectory:
    """`simulate` over a stacked batch (`stack_experiments`), one shared parameter set."""
    return jax.vmap(lambda e: simulate(p, drive, e, simulator=simulator))(batch)


simulate_batch_jit = eqx.filter_jit(simulate_batch)


