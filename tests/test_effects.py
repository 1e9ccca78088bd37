"""Effects builders and the effect terms act in the plant."""

import jax
import numpy as np

import hdjax
from helpers import hd2, sine_experiment


def test_with_periodic_and_with_values_switch_effects_on():
    e = hdjax.Effects().with_periodic("torque_sensor_ripple", 2, 1.5, 0.7).with_values("nonlinear_stiffness", K3=1e6)
    assert e.active == {"torque_sensor_ripple", "nonlinear_stiffness"}
    orders, amp, phase = e.amplitudes("torque_sensor_ripple")
    np.testing.assert_allclose([float(amp[1]), float(phase[1])], [1.5, 0.7], rtol=1e-12)
    assert float(e.K3) == 1e6


def test_sensor_ripple_changes_measured_torque_only():
    p, drive = hd2()
    exp = sine_experiment("constrained", duration=0.3)
    base = jax.jit(hdjax.simulate)(p, drive, exp)
    eff = hdjax.Effects().with_periodic("torque_sensor_ripple", 2, 1.0, 0.0)
    rip = hdjax.simulate(p, drive, exp, effects=eff)
    expected = np.sin(2 * np.asarray(rip.motor_position))
    np.testing.assert_allclose(np.asarray(rip.torque - base.torque), expected, atol=1e-5)
    np.testing.assert_allclose(np.asarray(rip.motor_velocity), np.asarray(base.motor_velocity), atol=1e-6)


def test_kinematic_error_starts_the_simulation_at_the_measured_torque():
    """The measured torque fixes the true torsion Δθ0 = q0 + e(θm0); the kinematic torsion state
    must start at q0 = Δθ0 − e(θm0). Before, it started at Δθ0, so the simulated torque began
    K1·e(θm0) off the measured one (here 6.0e3 N·m/rad × 3e-4 rad ≈ 1.8 N·m), and a locked test
    kept that offset: on independent-bench seed 5012 the order-1 kinematic error fitted on the free
    tests cost the locked tests 30 % held out."""
    p, drive = hd2()
    exp = sine_experiment("constrained", duration=0.05)
    base = hdjax.simulate(p, drive, exp)
    for phase in (0.0, 1.0, 2.5):  # e(θm0) ≈ 3e-4·sin(phase), θm0 ≈ 0
        ke = hdjax.Effects().with_periodic("kinematic_error", 1, 3e-4, phase)
        sim = hdjax.simulate(p, drive, exp, effects=ke)
        assert abs(float(sim.torque[0] - base.torque[0])) < 1e-6 * float(p.K1) * 3e-4, (phase, float(sim.torque[0]), float(base.torque[0]))
        np.testing.assert_allclose(float(sim.torsion[0]), float(base.torsion[0]), rtol=0, atol=1e-12)


def test_torque_sensor_ripple_starts_the_simulation_at_the_measured_torque():
    """The strain gauge reads true torque + ripple(θm): the initial torsion comes from the reading
    without the ripple, so the simulated reading starts at the measured one. Before, the ripple's
    value at the start entered the torsion too (here 0.42 N·m off at phase 1), and a locked test
    whose motor sticks kept it as an offset."""
    p, drive = hd2()
    exp = sine_experiment("constrained", duration=0.05)
    base = hdjax.simulate(p, drive, exp)
    for phase in (0.0, 1.0, np.pi / 2):  # ripple(θm0) ≈ 0.5·sin(phase), θm0 ≈ 0
        rip = hdjax.Effects().with_periodic("torque_sensor_ripple", 2, 0.5, phase)
        sim = hdjax.simulate(p, drive, exp, effects=rip)
        # not exact: the initial torque is a line fitted to the first samples, and the reference run
        # zeroes its statistically insignificant start value (rest detection); measured: ≤ 0.0062 N·m
        assert abs(float(sim.torque[0] - base.torque[0])) < 0.02 * 0.5, (phase, float(sim.torque[0]), float(base.torque[0]))


def _held_torque_experiment(T0=20.0, duration=0.05):
    """A locked record that holds `T0` N·m at rest (current balancing it), HD2."""
    p, drive = hd2()
    t = np.arange(0.0, duration, 1e-3)
    i = np.full_like(t, T0 / float(drive.gear_ratio * drive.torque_constant))
    z = np.zeros_like(t)
    return p, drive, hdjax.make_experiment(t, i, np.full_like(t, T0), z, mode="constrained", output_position=z)


def test_cubic_and_dead_zone_springs_start_the_simulation_at_the_measured_torque():
    """The initial torsion inverts the modelled spring, not K1 alone. Before, `initial_state`
    inverted the linear spring for every model, so a cubic stiffness started K3·Δθ0³ off the
    measured torque (here 1.9 N·m at 20 N·m) and a dead zone up to K1·backlash (3 N·m), an
    offset a locked test whose motor sticks keeps."""
    p, drive, exp = _held_torque_experiment()
    base = hdjax.simulate(p, drive, exp)
    x_lin = float(base.torsion[0])
    for eff in (hdjax.Effects().with_values("nonlinear_stiffness", K3=5e7),
                hdjax.Effects().with_values("nonlinear_stiffness", K3=-5e6),
                hdjax.Effects().with_values("lost_motion", backlash=5e-4),
                hdjax.Effects().with_values("lost_motion", backlash=5e-4).with_values("nonlinear_stiffness", K3=5e7)):
        sim = hdjax.simulate(p, drive, exp, effects=eff)
        assert abs(float(sim.torque[0] - base.torque[0])) < 1e-9 * 20.0, (eff.active, float(sim.torque[0]), float(base.torque[0]))
        assert float(sim.torsion[0]) != x_lin  # the torsion itself moved to the spring's inverse
    # the linear inverse it replaced is off by the cubic term (the size of the bug, for the record)
    assert abs(5e7 * x_lin**3) > 1.0


def test_spring_inverse_carries_the_implicit_derivative():
    """d(initial torsion)/dK3 from forward mode through the bisection + Newton inverse equals the
    implicit-function value −Δθ³/(K1 + 3·K3·Δθ²) and a central difference, and the initial torque
    does not depend on K3 (it is the measured one); finite at K3 = 0 and backlash = 0, where a
    diagnosis starts its candidates."""
    p, drive, exp = _held_torque_experiment()

    def start(k3, d):
        eff = hdjax.Effects().with_values("nonlinear_stiffness", K3=k3).with_values("lost_motion", backlash=d)
        sim = hdjax.simulate(p, drive, exp, effects=eff)
        return sim.torsion[0], sim.torque[0]

    for k3 in (0.0, 5e7):
        (x, T), (dx, dT) = jax.jvp(lambda k: start(k, 0.0), (k3,), (1.0,))
        expected = -float(x) ** 3 / (float(p.K1) + 3 * k3 * float(x) ** 2)
        h = 1e5
        fd = (float(start(k3 + h, 0.0)[0]) - float(start(k3 - h, 0.0)[0])) / (2 * h)
        np.testing.assert_allclose(float(dx), expected, rtol=1e-6)
        np.testing.assert_allclose(float(dx), fd, rtol=1e-5)
        assert abs(float(dT)) < 1e-6 * abs(float(x)) ** 3 * float(p.K1), float(dT)
    _, (dx_d, dT_d) = jax.jvp(lambda d: start(0.0, d), (0.0,), (1.0,))
    assert np.isfinite(float(dx_d)) and np.isfinite(float(dT_d))
