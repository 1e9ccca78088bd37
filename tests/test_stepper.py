"""The fixed-step implicit velocity-level stepper (`hdjax.VelocityImplicit`): convergence as the step
shrinks, exact sticking, the smoothed model's limit, finite IFT derivatives (AD against finite
differences), vmap against one-at-a-time.

No inverse crime here: these tests check the numerics of one model against itself and against the
smoothed-model Rodas3 solve, not an identification."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hdjax
from hdjax._model.effects import RateIndependentHysteresis
from helpers import hd1, hd2, sine_experiment

jax.config.update("jax_enable_x64", True)

SIGMA_T, SIGMA_W = 0.5, 0.02  # HD2 sensor noise (N·m, rad/s), the scale the errors are judged on


def _sim(p, drive, exp, m, **kw):
    return hdjax.simulate(p, drive, exp, simulator=hdjax.Simulator(solver=hdjax.VelocityImplicit(substeps=m)), **kw)


def _errors(a, b):
    return (float(jnp.sqrt(jnp.mean((a.torque - b.torque) ** 2))) / SIGMA_T,
            float(jnp.sqrt(jnp.mean((a.motor_velocity - b.motor_velocity) ** 2))) / SIGMA_W)


@pytest.mark.parametrize("mode,amp", [("constrained", 1.0), ("constrained", 0.15), ("free", 0.3)])
def test_converges_as_step_shrinks(mode, amp):
    """RMS error against a 64-substep solve falls with the step (order ≥ 1 through sticking events,
    ≈ 2 between them) and is inside 0.1 noise σ at 4 substeps per 1 ms sample."""
    p, drive = hd2()
    exp = sine_experiment(mode, amplitude=amp, freq=2.0, duration=0.6)
    ref = _sim(p, drive, exp, 64)
    assert bool(ref.success)
    errs = [max(_errors(_sim(p, drive, exp, m), ref)) for m in (1, 2, 4, 8)]
    assert all(e2 < e1 for e1, e2 in zip(errs, errs[1:])), errs
    assert errs[0] / errs[-1] > 8.0, errs  # 8× smaller step: ≥ 8× smaller error
    assert errs[2] < 0.1, errs


def test_sticks_exactly_and_matches_smoothed_model_limit():
    """A small locked test sticks (ω_m = 0 exactly, not a tanh creep); the smoothed Rodas3 model
    approaches it as its velocity scale shrinks."""
    p, drive = hd2()
    exp = sine_experiment("constrained", amplitude=0.15, freq=2.0, duration=0.6)
    tr = _sim(p, drive, exp, 16)
    assert int(jnp.sum(tr.motor_velocity == 0.0)) > 20
    errs = []
    for vs in (1e-2, 1e-3, 1e-4):
        sm = hdjax.Smoothing(velocity_scale=vs, torsion_rate_scale=vs * 1e-2)
        ref = hdjax.simulate(p, drive, exp, simulator=hdjax.Simulator(rtol=1e-9, atol=1e-11, smoothing=sm,
                                                                       max_steps=400_000))
        assert bool(ref.success)
        errs.append(max(_errors(tr, ref)))
    assert errs[0] > errs[1] > errs[2], errs


def test_derivatives_match_finite_differences_and_are_finite_at_rest():
    """Forward-mode derivatives (implicit function theorem at each step's root) against central
    differences, on a record that starts at rest and sticks; every derivative finite."""
    p, drive = hd2()
    exp = sine_experiment("constrained", amplitude=0.3, freq=3.0, duration=0.3)
    names = ("K1", "Tst", "alpha", "Jeff", "Tsp", "Tvp")

    def out(v):
        q = p.replace(**dict(zip(names, v)))
        tr = _sim(q, drive, exp, 2)
        return jnp.concatenate([tr.torque, tr.motor_velocity * 10.0])

    v0 = jnp.array([float(getattr(p, k)) for k in names])
    J = jax.jacfwd(out)(v0)
    assert bool(jnp.all(jnp.isfinite(J)))
    for k in range(len(names)):
        h = 1e-6 * v0[k]
        fd = (out(v0.at[k].add(h)) - out(v0.at[k].add(-h))) / (2 * h)
        rel = float(jnp.linalg.norm(J[:, k] - fd) / jnp.linalg.norm(fd))
        assert rel < 1e-5, (names[k], rel)


def test_vmap_equals_one_at_a_time():
    p, drive = hd2()
    exps = [sine_experiment("constrained", amplitude=a, duration=0.3) for a in (0.2, 1.0)]
    exps += [sine_experiment("free", amplitude=0.3, duration=0.3)]
    sim = hdjax.Simulator(solver=hdjax.VelocityImplicit(substeps=2))
    batch = hdjax.simulate_batch(p, drive, hdjax.stack_experiments(exps), simulator=sim)
    for k, e in enumerate(exps):
        one = hdjax.simulate(p, drive, e, simulator=sim)
        np.testing.assert_allclose(np.asarray(batch.torque[k]), np.asarray(one.torque), rtol=1e-9, atol=1e-9)
    assert bool(jnp.all(batch.success))


def test_every_root_converges_with_the_diagnosis_terms_switched_on():
    """The diagnosis simulates every candidate term at its start value. Two make the step equation
    hard: the Dahl state with a small σ (a steep exponential in the torsion increment) and the creep
    ramp of `low_speed_friction` on HD2's parameters, where T_sn + T_ssn1 < 0 (a negative breakaway
    made the ramped term fall with speed). Every root must still converge (`success`)."""
    p, drive = hd2()
    assert float(p.Tsn + p.Tssn1) < 0.0
    for mode, amp in [("constrained", 0.15), ("constrained", 1.0), ("free", 0.3)]:
        exp = sine_experiment(mode, amplitude=amp, duration=0.5)
        for name in ("rate_independent_hysteresis", "low_speed_friction"):
            eff = hdjax.Effects(active=frozenset([name]), rate_independent_hysteresis=RateIndependentHysteresis(sigma=2e-5))
            tr = _sim(p, drive, exp, 4, effects=eff)
            assert bool(tr.success), (mode, amp, name)
            assert np.all(np.isfinite(np.asarray(tr.torque))), (mode, amp, name)


def test_presliding_friction_is_refused_by_the_stepper():
    """The stepper's exact sticking is the δ → 0 limit of `presliding_friction`'s Dahl state, which it
    does not carry: asked for it, `simulate` says so and names the solvers that do."""
    p, drive = hd2()
    exp = sine_experiment("constrained", duration=0.05)
    eff = hdjax.Effects().with_values("presliding_friction", presliding=0.5)
    with pytest.raises(ValueError, match="presliding_friction.*Rodas3"):
        hdjax.simulate(p, drive, exp, effects=eff, simulator=hdjax.Simulator(solver=hdjax.VelocityImplicit()))


@pytest.mark.parametrize("kw", [{"substeps": 0}, {"substeps": 2.0}, {"iterations": -1}, {"substeps": True},
                                {"reversal_quadrature": 1}, {"corrector": "yes"}])
def test_step_options_out_of_range_are_refused_with_their_name(kw):
    """A step count that is not a whole number >= 1 is refused when the stepper is made, naming the
    option (it would otherwise divide the sample period by zero or loop zero times). Under the suite's
    runtime type checker a float is refused by the checker first, with the option named too."""
    with pytest.raises((ValueError, TypeError), match=next(iter(kw))):
        hdjax.VelocityImplicit(**kw)


def test_tangent_dependence_is_an_exact_zero_with_a_tangent():
    """The term added to the scan's start state (so that JAX traces the step once under `jvp` and
    `vmap`) is exactly zero, whatever the values (inf and NaN included), and its derivative is zero;
    the trajectory's Jacobian is traced with one scan JVP pass less (checked as the same values:
    the 9-tangent Jacobian of a short record equals central differences, `test_derivatives_*`)."""
    from hdjax._plant.stepper import _tangent_dependence

    p, _ = hd2()
    for bad in (jnp.inf, -jnp.inf, jnp.nan):
        z = _tangent_dependence(p.replace(K1=bad), {"a": jnp.array([1.0, bad])})
        assert z.dtype == jnp.float64 and float(z) == 0.0 and not np.signbit(float(z))
    value, tangent = jax.jvp(lambda k: _tangent_dependence(p.replace(K1=k)), (p.K1,), (jnp.ones_like(p.K1),))
    assert float(value) == 0.0 and float(tangent) == 0.0
    # a tangent that is not JAX's symbolic zero: jvp of the term alone gives an array, and the
    # scan's JVP sees the start state's tangents as nonzero from the first pass
    jaxpr = jax.make_jaxpr(lambda k: jax.jvp(lambda k_: _tangent_dependence(p.replace(K1=k_)), (k,), (k,))[1])(p.K1)
    assert any(eqn.primitive.name in ("select_n", "mul", "add", "reduce_sum") for eqn in jaxpr.jaxpr.eqns)


def test_corrector_pass_runs_only_where_a_term_reads_the_predicted_state():
    """With the paper's model and both Stribeck amplitudes ≤ 0 (HD1, HD2) nothing in a stage reads
    the predicted state, so the corrector's second pass is skipped: the same trajectory as
    `corrector=False` (to round-off). With a steep falling Stribeck term (an amplitude > 0, taken at
    the predicted speed at this step) it runs and changes the trajectory."""
    p, drive = hd2()
    assert float(p.Tssp1) <= 0 and float(p.Tssn1) <= 0
    exp = sine_experiment("free", amplitude=1.5, duration=0.4)

    def run(q, corrector):
        sim = hdjax.Simulator(solver=hdjax.VelocityImplicit(substeps=1, corrector=corrector))
        tr = hdjax.simulate(q, drive, exp, simulator=sim)
        assert bool(tr.success) and float(jnp.abs(tr.motor_velocity).max()) > 1.0  # it slides, both ways
        return np.asarray(tr.motor_velocity)

    np.testing.assert_allclose(run(p, True), run(p, False), rtol=0, atol=1e-9 * np.abs(run(p, False)).max())
    steep = p.replace(Tssp1=jnp.asarray(0.05), Tssn1=jnp.asarray(0.05), Tss2=jnp.asarray(0.01))
    assert np.abs(run(steep, True) - run(steep, False)).max() > 1e-3 * np.abs(run(steep, False)).max()


def _with_angles(exp, tr):
    """`exp` with the simulated motor and output angles of `tr` written in as its measured ones."""
    return hdjax.make_experiment(np.asarray(exp.time), np.asarray(exp.current), np.asarray(tr.torque),
                                 np.asarray(tr.motor_velocity), mode="free" if float(exp.free) > 0 else "constrained",
                                 output_position=np.asarray(tr.output_position), motor_position=np.asarray(tr.motor_position))


@pytest.mark.parametrize("mode,amp", [("constrained", 1.0), ("free", 0.3)])
def test_measured_angle_reproduces_the_simulated_one_and_converges(mode, amp):
    """`Simulator.measured_angle` on the stepper (as the diagnosis simulates): the periodic terms act
    at the record's angle, interpolated between samples. Written into the record from a fine
    simulation (64 substeps, the plant's own angle), that angle must give back the same trajectory
    with cogging, kinematic error and position-dependent friction on, to within 0.1 noise σ at 4
    substeps and closer as the step shrinks (the remaining difference is the angle's straight line
    between 1 ms samples). A shifted angle moves the terms' phase: the result must then differ."""
    p, drive = hd2()
    eff = (hdjax.Effects().with_periodic("cogging", 4, 0.03, 0.3).with_periodic("kinematic_error", 2, 2e-4, 0.1)
           .with_periodic("position_dependent_friction", 1, 0.2, 0.5))
    exp = sine_experiment(mode, amplitude=amp, freq=2.0, duration=0.6)
    ref = _sim(p, drive, exp, 64, effects=eff)
    rec = _with_angles(exp, ref)

    def sim(m, record):
        s = hdjax.Simulator(solver=hdjax.VelocityImplicit(substeps=m), measured_angle=True)
        tr = hdjax.simulate(p, drive, record, effects=eff, simulator=s)
        assert bool(tr.success)
        return tr

    errs = [max(_errors(sim(m, rec), ref)) for m in (2, 8, 32)]
    assert errs[0] < 0.1 and errs[2] < errs[0], errs
    np.testing.assert_array_equal(np.asarray(sim(4, rec).motor_position), np.asarray(rec.motor_position))
    shifted = _with_angles(exp, eqx.tree_at(lambda t: t.motor_position, ref, ref.motor_position + np.pi / 4))
    assert max(_errors(sim(4, shifted), ref)) > 1.0


def test_viscous_friction_law_matches_the_smoothed_plant_and_converges():
    """`viscous_friction_law` (a model_form item of the diagnosis) in the stepper: the change it makes
    to the trajectory agrees with the adaptive Rodas3 plant's (which differs from the stepper only in
    the smoothed sticking) to within 5 % of that change, and the stepper's own error falls with the step."""
    p, drive = hd2()
    eff = hdjax.Effects().with_values("viscous_friction_law", viscous_exponent=float(np.log(0.6)), viscous_reference=10.0)
    exp = sine_experiment("free", amplitude=0.6, freq=2.0, duration=0.6)
    tight = hdjax.Simulator(rtol=1e-10, atol=1e-12, max_steps=400_000)
    d_ref = [np.asarray(getattr(hdjax.simulate(p, drive, exp, effects=eff, simulator=tight), c))
             - np.asarray(getattr(hdjax.simulate(p, drive, exp, simulator=tight), c)) for c in ("torque", "motor_velocity")]
    fine = _sim(p, drive, exp, 64, effects=eff)
    d_vi = [np.asarray(getattr(fine, c)) - np.asarray(getattr(_sim(p, drive, exp, 64), c)) for c in ("torque", "motor_velocity")]
    for a, b in zip(d_vi, d_ref):
        assert np.sqrt(np.mean(b**2)) > 0.5 * SIGMA_W  # the law changes the trajectory
        assert np.sqrt(np.mean((a - b) ** 2)) < 0.05 * np.sqrt(np.mean(b**2))
    errs = [max(_errors(_sim(p, drive, exp, m, effects=eff), fine)) for m in (1, 4, 16)]
    assert errs[0] > errs[1] > errs[2] and errs[1] < 0.1, errs


def test_a_start_at_rest_uses_the_exact_plants_breakaway_interval():
    """The paper's HD2 has a negative breakaway torque in the negative direction (Tsn + Tssn1 =
    −0.012 N·m): the exact plant cannot hold a motor at rest against a net drive torque in
    (0, 0.012) N·m, and a locked record started there slides back at once (the damping taking
    about −0.9 N·m). `initial_state` must not start it stuck (as the smoothed plant's rule would,
    putting that torque into the spring, −0.82 N·m): re-simulated from its own estimated start,
    the record (noise-free) is then reproduced to a fraction of the sensor noise."""
    p, drive = hd2()
    assert float(p.Tsn + p.Tssn1) < 0
    t = np.arange(0.0, 0.3, 1e-3)
    i = 2.0 * np.sin(2 * np.pi * 5.0 * t) * np.minimum(1.0, t / 0.05)  # starts as t², from rest
    z = np.zeros_like(t)
    sim = hdjax.Simulator(solver=hdjax.VelocityImplicit(substeps=4))
    truth = hdjax.simulate(p, drive, hdjax.make_experiment(t, i, z, z, mode="constrained"), simulator=sim)
    exp = hdjax.make_experiment(t, i, np.asarray(truth.torque), np.asarray(truth.motor_velocity), mode="constrained")
    (q_s, wm_s, *_), _ = hdjax.initial_state(p, drive, exp, sim, exact_sticking=False)
    assert float(wm_s) == 0.0 and float(p.K1 * q_s) < -0.5  # the smoothed plant's rule: stuck, torque in the spring
    (q_e, wm_e, *_), _ = hdjax.initial_state(p, drive, exp, sim)  # the stepper's own rule
    assert float(wm_e) < -0.01 and abs(float(p.K1 * q_e)) < 0.1
    again = hdjax.simulate(p, drive, exp, simulator=sim)
    err_T, err_w = _errors(again, truth)
    assert err_T < 0.2 and err_w < 0.5, (err_T, err_w)  # measured 0.10 and 0.24


def _hd1_reversals():
    """A free HD1 record whose motor reverses 5 times in 0.6 s at about 1 rad/s per ms: its Stribeck
    dip (Tss2 = 0.1 rad/s) lasts about 0.1 ms, under one step at 2–4 substeps."""
    p, drive = hd1()
    return p, drive, sine_experiment("free", amplitude=2.0, freq=5.0, duration=0.6)


def test_reversal_quadrature_takes_friction_through_reversals():
    """`reversal_quadrature=True` takes friction's mean over each stage through the Stribeck dip and
    motor reversals. Against 256 substeps with it, the motor-velocity error falls with the step, is
    inside 0.1 noise σ at 4 substeps, and at least 5× below that of eq. 9 at the stage end, which keeps
    a first-order momentum error from every reversal (measured 2026-12-06: 0.54, 0.22, 0.096 σ at
    4, 8, 16 substeps against 0.038, 0.020, 0.006 σ with it)."""
    p, drive, exp = _hd1_reversals()

    def sim(m, rq):
        s = hdjax.Simulator(solver=hdjax.VelocityImplicit(substeps=m, reversal_quadrature=rq))
        tr = hdjax.simulate(p, drive, exp, simulator=s)
        assert bool(tr.success)
        return tr

    ref = sim(256, True)

    def err(tr):
        return float(jnp.sqrt(jnp.mean((tr.motor_velocity - ref.motor_velocity) ** 2))) / SIGMA_W

    rq = [err(sim(m, True)) for m in (4, 8, 16)]
    plain = [err(sim(m, False)) for m in (4, 8, 16)]
    assert rq[0] > rq[1] > rq[2], rq
    assert rq[0] < 0.1 < plain[0], (rq, plain)
    assert all(a < b / 5.0 for a, b in zip(rq, plain)), (rq, plain)


def test_reversal_quadrature_derivatives_match_finite_differences():
    """With `reversal_quadrature` the implicit-function derivatives stay exact: AD against central
    differences (step 1e-5 relative; at 1e-6 round-off in the differences reaches 5e-5 on this record,
    with or without the quadrature) on the HD1 record with reversals, every derivative finite."""
    p, drive, _ = _hd1_reversals()
    exp = sine_experiment("free", amplitude=2.0, freq=5.0, duration=0.3)
    names = ("K1", "Tst", "Jeff", "Tsp", "Tsn", "Tssp1", "Tss2", "Tvp")

    def out(v):
        q = p.replace(**dict(zip(names, v)))
        s = hdjax.Simulator(solver=hdjax.VelocityImplicit(substeps=2, reversal_quadrature=True))
        tr = hdjax.simulate(q, drive, exp, simulator=s)
        return jnp.concatenate([tr.torque, tr.motor_velocity * 10.0])

    v0 = jnp.array([float(getattr(p, k)) for k in names])
    J = jax.jacfwd(out)(v0)
    assert bool(jnp.all(jnp.isfinite(J)))
    for k in range(len(names)):
        h = 1e-5 * abs(float(v0[k]))
        fd = (out(v0.at[k].add(h)) - out(v0.at[k].add(-h))) / (2 * h)
        rel = float(jnp.linalg.norm(J[:, k] - fd) / jnp.linalg.norm(fd))
        assert rel < 1e-5, (names[k], rel)


def test_breakaway_friction_holds_the_motor_until_its_static_torque_and_changes_nothing_at_zero():
    """`breakaway_friction` widens the stick band to its breakaway torques (static friction above
    eq. 9's at rest) and leaves sliding friction alone. On a locked HD1 record whose current ramps
    slowly from rest, the motor must stay at rest exactly while the torque that holds it,
    Km·i − T/N, is below B_p, and move once it exceeds it by a margin; torques of 0, or at or below
    eq. 9's at rest, give the plain stepper's trajectory to the bit; the adaptive plant (smoothed friction, no set-valued sticking)
    refuses the term, as does the diagnosis (it does not screen it)."""
    p, drive = hd1()
    t = np.arange(0.0, 0.4, 1e-3)
    i = 5.0 * t  # A: the drive torque Km·i rises by 0.27 N·m per second
    z = np.zeros_like(t)
    exp = hdjax.make_experiment(t, i, z, z, mode="constrained")
    sim = hdjax.Simulator(solver=hdjax.VelocityImplicit(substeps=4))
    plain = hdjax.simulate(p, drive, exp, simulator=sim)
    zero = hdjax.Effects().with_values("breakaway_friction", breakaway_p=0.0, breakaway_n=0.0)
    below = zero.with_values("breakaway_friction", breakaway_p=0.9 * float(p.Tsp + p.Tssp1), breakaway_n=0.5 * float(p.Tsn))
    for eff in (zero, below):
        np.testing.assert_array_equal(np.asarray(hdjax.simulate(p, drive, exp, effects=eff, simulator=sim).torque),
                                      np.asarray(plain.torque))
    static = float(p.Tsp + p.Tssp1) + 0.01
    tr = hdjax.simulate(p, drive, exp, effects=zero.with_values("breakaway_friction", breakaway_p=static), simulator=sim)
    held = drive.torque_constant * i - np.asarray(tr.torque) / drive.gear_ratio  # the torque holding the motor
    wm = np.asarray(tr.motor_velocity)
    k = int(np.argmax(wm != 0.0))  # the first sample in motion
    assert k > 0 and np.all(wm[:k] == 0.0)
    # held at rest up to the static torque, and not released before it (the holding torque rises by
    # 0.27 mN·m per sample)
    assert held[:k].max() <= static + 1e-3 and held[k - 1] >= static - 1e-3, (held[k - 1], static)
    wm_plain = np.asarray(plain.motor_velocity)
    k_plain = int(np.argmax(wm_plain != 0.0))
    assert 0 < k_plain < k  # the plain stepper slips earlier, at eq. 9's breakaway
    held_plain = drive.torque_constant * i - np.asarray(plain.torque) / drive.gear_ratio
    assert abs(held_plain[k_plain - 1] - float(p.Tsp + p.Tssp1)) < 1e-3
    with pytest.raises(ValueError, match="breakaway_friction"):
        hdjax.simulate(p, drive, exp, effects=zero, simulator=hdjax.Simulator())
    with pytest.raises(ValueError, match="breakaway_friction.*not screened"):
        hdjax.diagnose_effects(p, drive, [exp], model_form=["breakaway_friction"])


def test_inputs_read_before_the_scan_give_the_trajectory_read_inside_it():
    """`implicit_trajectory` reads the current (delayed, between samples as `input_between_samples`
    says) and the record's angles at every step's nodes before its scan (`PlantSteps.inputs_at`); the
    closed loop's steps read them inside (`step(state, t0)` without inputs). On a free record with
    every term that reads them on (measured angle, periodic terms, an input delay, the cubic blend
    between samples) both must give the same trajectory to round-off, and the same derivative with
    respect to the delay."""
    import hdjax._plant.simulate as sim_mod
    from hdjax._plant.stepper import plant_steps

    def read_inside(p_dyn, drive, exp, y0, geometry, current, effects, vc, dt, solver):
        """`implicit_trajectory` with every read inside the step."""
        h = dt / solver.substeps
        steps = plant_steps(p_dyn, drive, exp.free, exp.start_time, geometry, effects, vc, h, solver)(current)

        def interval(state, t0):
            state, oks = jax.lax.scan(lambda st, k: steps.step(st, t0 + k * h), state, jnp.arange(solver.substeps, dtype=float))
            return state, (state, jnp.all(oks))

        state0 = tuple(jnp.asarray(x, dtype=float) for x in steps.start(y0, exp.time[0]))
        n = exp.time.shape[0]
        _, (states, oks) = jax.lax.scan(interval, state0, exp.time[0] + dt * jnp.arange(n - 1, dtype=float))
        q, wm, tho, wo, _, _, T, _ = jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), state0, states)
        thm = steps.theta_m(q, tho, exp.time, geometry[3])
        return (q, wm, tho, wo, T, steps.torsion_of(q, thm), thm), jnp.concatenate([jnp.array([True]), oks]), (n - 1) * solver.substeps

    p, drive = hd2()
    eff = (hdjax.Effects().with_periodic("cogging", 4, 0.03, 0.3).with_periodic("kinematic_error", 2, 2e-4, 0.1)
           .with_term(hdjax.InputDelay(delay=3e-4)).with_term(hdjax.InputBetweenSamples(reconstruction=0.7)))
    exp = sine_experiment("free", amplitude=0.3, freq=2.0, duration=0.3)
    rec = _with_angles(exp, _sim(p, drive, exp, 8))
    s = hdjax.Simulator(solver=hdjax.VelocityImplicit(substeps=4), measured_angle=True)

    def run(delay, inside: bool):
        e = eqx.tree_at(lambda x: x.input_delay.delay, eff, delay)
        original = sim_mod.implicit_trajectory
        sim_mod.implicit_trajectory = read_inside if inside else original
        try:
            tr = hdjax.simulate(p, drive, rec, effects=e, simulator=s)
        finally:
            sim_mod.implicit_trajectory = original
        return jnp.stack([tr.torque, tr.motor_velocity])

    d0, t0 = jnp.asarray(3e-4), jnp.asarray(1.0)
    before, d_before = jax.jvp(lambda d: run(d, False), (d0,), (t0,))
    inside, d_inside = jax.jvp(lambda d: run(d, True), (d0,), (t0,))
    assert float(jnp.max(jnp.abs(d_inside))) > 0
    np.testing.assert_allclose(np.asarray(before), np.asarray(inside), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(d_before), np.asarray(d_inside), rtol=0, atol=1e-9 * float(jnp.max(jnp.abs(d_inside))))
