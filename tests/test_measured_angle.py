"""`Simulator.measured_angle`: the periodic terms act at the measured wave-generator angle.

These tests check the plant's plumbing, not an identification: the "records" are made by hdjax's
own plant (the model is exact on them on purpose), then simulated again with other friction so
that the simulated angle drifts away from the recorded one, as on a real bench.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hdjax
from helpers import hd1

jax.config.update("jax_enable_x64", True)

SIM = hdjax.Simulator(rtol=1e-8, atol=1e-10)


def _record(*, motor_position: bool):
    """A free-motion record of HD1 (1 s, a sine current that turns the wave generator many
    times), made by the plant at the true parameters, with its true angles as encoder readings."""
    p, drive = hd1()
    t = np.arange(0.0, 1.0, 1e-3)
    i = 0.3 + 1.2 * np.sin(2 * np.pi * 1.5 * t) * np.minimum(1.0, t / 0.05)
    z = np.zeros_like(t)
    driver = hdjax.make_experiment(t, i, z, z, mode="free", output_position=z)
    truth = hdjax.simulate(p, drive, driver, simulator=SIM)
    exp = hdjax.make_experiment(
        t, i, np.asarray(truth.torque), np.asarray(truth.motor_velocity), mode="free",
        output_position=np.asarray(truth.output_position),
        motor_position=np.asarray(truth.motor_position) if motor_position else None,
    )  # fmt: skip
    return p, drive, exp, truth


def test_free_motion_takes_the_wave_generator_angle_from_the_output_encoder():
    p, drive, exp, truth = _record(motor_position=False)
    assert float(np.ptp(np.asarray(truth.motor_position))) > 10.0  # over a turn and a half
    off = dataclasses.replace(p, Tvp=p.Tvp * 1.5, Tvn=p.Tvn * 1.5, Tsp=p.Tsp * 1.3)  # a friction misfit
    drifted = hdjax.simulate(off, drive, exp, simulator=SIM)
    measured = hdjax.simulate(off, drive, exp, simulator=dataclasses.replace(SIM, measured_angle=True))
    err_drift = float(np.max(np.abs(np.asarray(drifted.motor_position) - np.asarray(truth.motor_position))))
    err_meas = float(np.max(np.abs(np.asarray(measured.motor_position) - np.asarray(truth.motor_position))))
    # the simulated angle drifts by radians; the measured one is off only by N times the torsion error
    # measured 7.6 and 0.0007 rad (2026-12-03)
    assert err_drift > 1.0, err_drift
    assert err_meas < 0.05, err_meas
    # the paper's model has no term of the angle: its torque and velocity do not change
    np.testing.assert_allclose(measured.torque, drifted.torque, rtol=0, atol=1e-12)
    np.testing.assert_allclose(measured.motor_velocity, drifted.motor_velocity, rtol=0, atol=1e-12)


def test_a_periodic_term_then_acts_in_phase_with_the_drive():
    """Cogging of order 4 on the true drive; simulated with a friction misfit, the cogging's
    imprint on the motor velocity is followed only where the angle is the measured one."""
    p, drive, exp0, _ = _record(motor_position=False)
    cog = hdjax.Effects().with_periodic("cogging", 4, 0.02, 0.3)
    truth = hdjax.simulate(p, drive, exp0, effects=cog, simulator=SIM)
    exp = hdjax.make_experiment(
        np.asarray(exp0.time), np.asarray(exp0.current), np.asarray(truth.torque), np.asarray(truth.motor_velocity),
        mode="free", output_position=np.asarray(truth.output_position),
    )  # fmt: skip
    off = dataclasses.replace(p, Tvp=p.Tvp * 1.5, Tvn=p.Tvn * 1.5)
    plain_truth = hdjax.simulate(p, drive, exp0, simulator=SIM)
    imprint = np.asarray(truth.motor_velocity) - np.asarray(plain_truth.motor_velocity)

    def cogging_share(simulator):
        """The part of the recorded velocity's cogging imprint the simulation reproduces (1: all)."""
        with_cog = hdjax.simulate(off, drive, exp, effects=cog, simulator=simulator)
        without = hdjax.simulate(off, drive, exp, simulator=simulator)
        model = np.asarray(with_cog.motor_velocity) - np.asarray(without.motor_velocity)
        return float(np.dot(imprint, model) / np.dot(imprint, imprint))

    share_sim = cogging_share(SIM)
    share_meas = cogging_share(dataclasses.replace(SIM, measured_angle=True))
    # measured 0.885 and 0.482 (2026-12-03): the measured angle follows the drive; what it leaves is
    # the friction misfit's own change of how the velocity responds to a torque
    assert share_meas > 0.8, share_meas
    assert share_sim < 0.6, share_sim


def test_the_motor_encoder_is_used_where_the_record_has_one():
    p, drive, exp, truth = _record(motor_position=True)
    off = dataclasses.replace(p, Tvp=p.Tvp * 1.5, Tvn=p.Tvn * 1.5)
    tr = hdjax.simulate(off, drive, exp, simulator=dataclasses.replace(SIM, measured_angle=True))
    np.testing.assert_allclose(tr.motor_position, exp.motor_position, rtol=0, atol=1e-12)


@pytest.mark.parametrize("solver", ["rodas3", "velocity_implicit"])
def test_derivatives_through_the_measured_angle_match_finite_differences(solver):
    """Forward-mode AD of a simulation with cogging at the measured angle, against central
    differences (fixed steps, so the discrete solution is smooth in the parameters): fixed-step
    Rodas3, and the implicit stepper (`VelocityImplicit`, derivatives by the implicit function theorem)."""
    p, drive, exp, _ = _record(motor_position=False)
    exp = jax.tree.map(lambda x: x[:300] if getattr(x, "ndim", 0) == 1 else x, exp)
    sim = (hdjax.Simulator(fixed_step=2.5e-4, measured_angle=True) if solver == "rodas3"
           else hdjax.Simulator(solver=hdjax.VelocityImplicit(substeps=2), measured_angle=True))

    eff0 = hdjax.Effects().with_periodic("cogging", 4, 0.01, 0.3)

    def out(x):
        q = dataclasses.replace(p, K1=p.K1 * jnp.exp(x[0]), Tvp=p.Tvp * jnp.exp(x[1]))
        scale = jnp.exp(x[2])  # the cogging's amplitude
        eff = eqx.tree_at(lambda e: (e.cogging.sin, e.cogging.cos), eff0, (eff0.cogging.sin * scale, eff0.cogging.cos * scale))
        tr = hdjax.simulate(q, drive, exp, effects=eff, simulator=sim)
        return jnp.concatenate([tr.torque, tr.motor_velocity])

    x0 = jnp.zeros(3)
    J = jax.jit(jax.jacfwd(out))(x0)
    f = jax.jit(out)
    # the differences' round-off dominates at small steps (K1's column: 5.4e-5 at h = 3e-5, 2.4e-5 at
    # 1e-4, 1.4e-6 at 1e-3; the same without the measured angle), so a wide step
    h = 1e-3
    for j in range(3):
        e = jnp.zeros(3).at[j].set(h)
        fd = (8 * (f(x0 + e) - f(x0 - e)) - (f(x0 + 2 * e) - f(x0 - 2 * e))) / (12 * h)
        assert bool(jnp.all(jnp.isfinite(J[:, j])))
        rel = float(jnp.max(jnp.abs(J[:, j] - fd)) / jnp.max(jnp.abs(fd)))
        assert rel < 1e-5, (j, rel)
