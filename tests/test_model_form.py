"""The base-model assumptions that the diagnosis may loosen (SPEC §4b, `hdjax._model.effects.MODEL_FORM`):
each is the identity at its start value, acts as documented, and has finite, correct derivatives
there (they are fitted from zero)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from scipy.signal import lfilter

import hdjax
from hdjax._model.effects import viscous_law_factor
from hdjax._plant.simulate import UniformCubicBlendInput, UniformLinearInput, _first_order_lag
from helpers import hd1, sine_experiment

SIM = hdjax.Simulator(fixed_step=2.5e-4)  # fixed steps: the discrete solution is smooth in the parameters


def _run(effects, mode="constrained"):
    p, drive = hd1()
    exp = sine_experiment(mode, amplitude=1.5, duration=0.3)
    return hdjax.simulate(p, drive, exp, effects=effects, simulator=SIM)


def test_model_form_terms_are_the_identity_at_their_start_values():
    base = _run(hdjax.Effects())
    on = hdjax.Effects(active=frozenset({"low_speed_friction", "sensor_offset", "sensor_bandwidth",
                                         "input_between_samples", "viscous_friction_law"}))
    tr = _run(on)
    np.testing.assert_allclose(np.asarray(tr.torque), np.asarray(base.torque), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(tr.motor_velocity), np.asarray(base.motor_velocity), rtol=0, atol=1e-12)


def test_sensor_offsets_shift_the_measured_channels_only():
    """Readings = base simulation + offsets: the offset model reproduces them (its initial state is
    taken from the offset-free readings)."""
    p, drive = hd1()
    exp = sine_experiment("constrained", amplitude=1.5, duration=0.3)
    base = hdjax.simulate(p, drive, exp, simulator=SIM)
    meas = hdjax.make_experiment(np.asarray(exp.time), np.asarray(exp.current), np.asarray(base.torque) + 0.3,
                                 np.asarray(base.motor_velocity) - 0.05, mode="constrained",
                                 output_position=np.asarray(base.output_position))
    eff = hdjax.Effects().with_values("sensor_offset", torque_offset=0.3, velocity_offset=-0.05)
    tr = hdjax.simulate(p, drive, meas, effects=eff, simulator=SIM)
    np.testing.assert_allclose(np.asarray(tr.torque - base.torque), 0.3, atol=1e-6)
    np.testing.assert_allclose(np.asarray(tr.motor_velocity - base.motor_velocity), -0.05, atol=1e-6)


def test_current_offset_acts_as_a_constant_motor_torque():
    """Recorded current = true current + offset: the plant sees i − offset, so a current offset
    equals a current record shifted by the same amount."""
    p, drive = hd1()
    exp = sine_experiment("constrained", amplitude=1.5, duration=0.3)
    off = 0.2
    shifted = hdjax.make_experiment(np.asarray(exp.time), np.asarray(exp.current) - off, np.asarray(exp.torque),
                                    np.asarray(exp.motor_velocity), mode="constrained",
                                    output_position=np.asarray(exp.output_position))
    a = hdjax.simulate(p, drive, exp, effects=hdjax.Effects().with_values("sensor_offset", current_offset=off), simulator=SIM)
    b = hdjax.simulate(p, drive, shifted, simulator=SIM)
    np.testing.assert_allclose(np.asarray(a.torque), np.asarray(b.torque), atol=1e-9)


def test_first_order_lag_matches_scipy_and_is_identity_at_zero():
    x = np.random.default_rng(0).standard_normal(200)
    dt, tau = 1e-3, 2.5e-3
    a = tau / (tau + dt)
    # y[n] = a y[n-1] + (1 - a) x[n], started at y[0] = x[0]
    ref = lfilter([1 - a], [1, -a], x[1:], zi=[a * x[0]])[0]
    got = np.asarray(_first_order_lag(jnp.asarray(x), tau, dt))
    np.testing.assert_allclose(got[1:], ref, rtol=1e-12, atol=1e-12)
    assert got[0] == x[0]
    np.testing.assert_array_equal(np.asarray(_first_order_lag(jnp.asarray(x), 0.0, dt)), x)


def test_input_reconstruction_is_the_line_at_zero_and_the_catmull_rom_cubic_at_one():
    """`input_between_samples`: λ = 0 is the straight line between samples, λ = 1 the cubic Hermite
    spline with central-difference slopes (scipy's `CubicHermiteSpline` with `np.gradient` slopes,
    one-sided at the ends), and every λ passes through the samples."""
    from scipy.interpolate import CubicHermiteSpline

    rng = np.random.default_rng(3)
    dt, n = 2e-3, 40
    t = 0.1 + dt * np.arange(n)
    v = np.cumsum(rng.standard_normal(n))
    tq = np.sort(rng.uniform(t[0], t[-1], 300))
    line = np.asarray(UniformLinearInput(jnp.asarray(t[0]), jnp.asarray(dt), jnp.asarray(v)).evaluate(jnp.asarray(tq)))
    blend = lambda lam, x: np.asarray(UniformCubicBlendInput(jnp.asarray(t[0]), jnp.asarray(dt), jnp.asarray(v),
                                                             jnp.asarray(lam)).evaluate(jnp.asarray(x)))
    np.testing.assert_array_equal(blend(0.0, tq), line)
    cubic = CubicHermiteSpline(t, v, np.gradient(v, dt))(tq)
    np.testing.assert_allclose(blend(1.0, tq), cubic, rtol=0, atol=1e-12)
    np.testing.assert_allclose(blend(0.4, tq), line + 0.4 * (cubic - line), rtol=0, atol=1e-12)
    np.testing.assert_allclose(blend(2.5, t[:-1]), v[:-1], rtol=0, atol=1e-12)


def test_input_reconstruction_follows_an_independent_bench_current_between_samples():
    """On data hdjax did not make (`hdjax._testbench.independent`: its own fixed-step integrator and exact
    stick–slip; every other deviation off so that only the input path between samples differs),
    a 500 Hz locked chirp and square wave simulated at the bench's true parameters from the
    sampled current: the Catmull–Rom path (λ = 1) follows the bench's continuous current where
    straight lines between samples leave the motor velocity several noise levels off at the
    square wave's edges and the chirp's fast end (measured 2026-11-28: chirp 1.14 → 0.02 σ RMS,
    square 0.72 → 0.45 σ RMS; peak square-edge misfit 4.6 → 0.6 σ)."""
    from hdjax._testbench.independent import Deviations, simulate_dataset

    recs, truth = simulate_dataset(drive="hd1", seed=6008, n_locked=8, n_free=0, sample_rate=500.0,
                                   low_speed="stick_slip", deviations=Deviations.none())
    p = hdjax.Parameters(**{k: float(v) for k, v in truth["parameters"].items()})
    d = truth["drive"]
    drive = hdjax.Drive(gear_ratio=d["gear_ratio"], torque_constant=d["torque_constant"], load_inertia=d["load_inertia"])
    sw = truth["sensors"]["tacho_noise"]
    rms = {}
    for r in recs:
        if r["kind"] not in ("chirp", "square"):
            continue
        c = r["clean"]
        exp = hdjax.make_experiment(r["time"], c["current"], c["true_torque"], c["true_motor_velocity"],
                                    mode="constrained", start_time=r["start_time"])
        for lam in (0.0, 1.0):
            eff = hdjax.Effects().with_values("input_between_samples", reconstruction=lam)
            w = np.asarray(hdjax.simulate(p, drive, exp, effects=eff).motor_velocity)
            rms[r["kind"], lam] = float(np.sqrt(np.mean(((w - c["true_motor_velocity"]) / sw) ** 2)))
    assert set(rms) == {("chirp", 0.0), ("chirp", 1.0), ("square", 0.0), ("square", 1.0)}, rms
    assert rms["chirp", 0.0] > 0.5 and rms["chirp", 1.0] < 0.2 * rms["chirp", 0.0], rms
    assert rms["square", 1.0] < 0.75 * rms["square", 0.0], rms


def test_model_form_derivatives_at_zero_match_finite_differences():
    """Forward-mode AD through the solve w.r.t. each model-form parameter at its start value (0),
    against 4-point central differences."""
    p, drive = hd1()
    exp = sine_experiment("constrained", amplitude=1.5, duration=0.2)
    on = hdjax.Effects(active=frozenset({"low_speed_friction", "sensor_offset", "sensor_bandwidth",
                                         "input_between_samples", "viscous_friction_law"}))
    fields = ("friction_scale", "stribeck_scale", "torque_offset", "current_offset", "torque_lag", "reconstruction",
              "viscous_exponent")
    scale = {"friction_scale": 1.0, "stribeck_scale": 1.0, "torque_offset": 0.1, "current_offset": 0.05,
             "torque_lag": 1e-3, "reconstruction": 1.0, "viscous_exponent": 0.3}

    def torque(v, field):
        eff = jax.tree_util.tree_map(lambda x: x, on)
        eff = eqx_set(eff, field, v * scale[field])
        return hdjax.simulate(p, drive, exp, effects=eff, simulator=SIM).torque

    for field in fields:
        ad = np.asarray(jax.jvp(lambda v: torque(v, field), (0.0,), (1.0,))[1])
        h = 1e-3
        fd = (-torque(2 * h, field) + 8 * torque(h, field) - 8 * torque(-h, field) + torque(-2 * h, field)) / (12 * h)
        fd = np.asarray(fd)
        assert np.all(np.isfinite(ad)), field
        assert np.linalg.norm(ad) > 0, f"{field}: zero derivative at the start value"
        err = np.linalg.norm(ad - fd) / np.linalg.norm(fd)
        assert err < 1e-4, f"{field}: AD vs FD relative error {err:.2e}"


def eqx_set(effects, field, value):
    """`effects` with the parameter `field` set, in the term that has a field of that name (the
    scalar field names are unique over the terms); the active set is left as it is."""
    import equinox as eqx

    from hdjax._model.effects import SCALAR_FIELDS

    owner = next(name for name, fields in SCALAR_FIELDS.items() if field in fields)
    return eqx.tree_at(lambda e: getattr(e.term(owner), field), effects, jnp.asarray(value, dtype=float))


def test_viscous_law_converges_to_the_power_law_as_its_scale_shrinks():
    """`viscous_friction_law`'s factor against the exact power law (|ω|/ωr)^(κ−1): the relative
    error is within the documented bound 0.5·|κ−1|·(ε/ω)² and falls 100× per decade of ε; at
    λκ = 0 the factor is exactly 1 (eq. 9), and its derivative is finite at ω = 0."""
    w = np.concatenate([-np.logspace(-1, 2.5, 30), np.logspace(-1, 2.5, 30)])
    wr = 20.0
    for kappa in (0.6, 0.8, 1.3):
        exact = (np.abs(w) / wr) ** (kappa - 1.0)
        errs = []
        for eps in (1e-1, 1e-2, 1e-3):
            got = np.asarray(viscous_law_factor(jnp.asarray(w), np.log(kappa), wr, scale=eps))
            rel = np.abs(got / exact - 1.0)
            assert np.all(rel <= 0.5 * abs(kappa - 1.0) * (eps / w) ** 2 * (1 + 1e-9) + 1e-13), (kappa, eps)  # + round-off
            errs.append(rel.max())
        assert errs[1] < 0.02 * errs[0] and errs[2] < 0.02 * errs[1], (kappa, errs)
    np.testing.assert_array_equal(np.asarray(viscous_law_factor(jnp.asarray(w), 0.0, wr)), 1.0)
    dw = jax.grad(lambda v: v * viscous_law_factor(v, np.log(0.7), wr))(0.0)
    assert np.isfinite(float(dw)) and float(dw) > 0


def test_viscous_law_reaches_the_power_law_steady_speed():
    """Free motion at a constant current: the wave generator settles where K_m·i equals Coulomb +
    T_v·ωr^(1−κ)·ω^κ (no transmitted torque at constant speed; the Stribeck term is gone at tens of
    rad/s), solved here by bisection, apart from the plant."""
    p, drive = hd1()
    p = dataclasses.replace(p, Tvp=1.5e-3, Tvn=1.5e-3)
    kappa, wr, current = 0.7, 10.0, 1.5
    t = np.arange(0.0, 2.5, 1e-3)
    z = np.zeros_like(t)
    exp = hdjax.make_experiment(t, np.full_like(t, current), z, z, mode="free", output_position=z)
    eff = hdjax.Effects().with_values("viscous_friction_law", viscous_exponent=np.log(kappa), viscous_reference=wr)
    w_end = float(np.asarray(hdjax.simulate(p, drive, exp, effects=eff, simulator=SIM).motor_velocity)[-1])
    lo, hi = 1.0, 1e3
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        net = drive.torque_constant * current - p.Tsp - p.Tvp * wr ** (1 - kappa) * mid**kappa
        lo, hi = (mid, hi) if net > 0 else (lo, mid)
    assert abs(w_end / lo - 1.0) < 1e-4, (w_end, lo)
    linear = (drive.torque_constant * current - p.Tsp) / p.Tvp
    assert abs(w_end / linear - 1.0) > 0.3  # the law matters here: 34 rad/s against 24 linear
