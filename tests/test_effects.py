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
