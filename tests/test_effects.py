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
