"""The diffrax plant against an independent scipy reference, vmap with padding, and AD checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import hdjax
import hdjax._plant.sharding
from helpers import hd1, hd2, sine_experiment


def _reference(p, drive, exp, smoothing=hdjax.Smoothing()):
    """The paper's equations written out again in numpy, integrated by scipy's Radau at 1e-11."""
    P = {k: float(v) for k, v in p.to_dict().items()}
    N, Km, Jl = float(drive.gear_ratio), float(drive.torque_constant), float(drive.load_inertia)
    t = np.asarray(exp.time)
    cur = np.asarray(exp.current)
    free = float(exp.free)
    vs, ts = smoothing.velocity_scale, smoothing.torsion_rate_scale

    def torque(q, rate):
        return P["K1"] * q + P["Tst"] * rate * (rate**2 + ts**2) ** ((P["alpha"] - 1) / 2)

    def rhs(tt, y):
        q, w, _, wo = y
        rate = w / N - wo
        T = torque(q, rate)
        up = 0.5 * (1 + np.tanh(w / vs))
        sg = np.tanh(w / vs)
        st = np.exp(-((w / P["Tss2"]) ** 2))
        Tf = (P["Tvp"] * w * up + P["Tvn"] * w * (1 - up) + P["Tsp"] * sg * up + P["Tsn"] * sg * (1 - up)
              + (P["Tssp1"] * sg * up + P["Tssn1"] * sg * (1 - up)) * st)
        i = np.interp(tt, t, cur)
        return [rate, (Km * i - T / N - Tf) / P["Jeff"], wo, free * T / Jl]

    y0, _ = hdjax.initial_state(p, drive, exp)
    y0 = [float(v) for v in y0]
    # integrate sample to sample so the kinks of the interpolated current sit on step boundaries
    ys = [y0]
    for k in range(len(t) - 1):
        sol = solve_ivp(rhs, (t[k], t[k + 1]), ys[-1], method="Radau", rtol=1e-11, atol=1e-13)
        ys.append(sol.y[:, -1])
    ys = np.array(ys)
    rate = ys[:, 1] / N - ys[:, 3]
    return torque(ys[:, 0], rate), ys[:, 1]


@pytest.mark.parametrize("drive_fn", [hd1, hd2])
@pytest.mark.parametrize("mode", ["constrained", "free"])
def test_plant_matches_scipy_reference(drive_fn, mode):
    p, drive = drive_fn()
    exp = sine_experiment(mode, amplitude=2.0, freq=3.0, duration=0.4)
    traj = jax.jit(hdjax.simulate)(p, drive, exp)
    T_ref, w_ref = _reference(p, drive, exp)
    assert bool(traj.success)
    err = np.max(np.abs(np.asarray(traj.torque) - T_ref)) / np.max(np.abs(T_ref))
    err_w = np.max(np.abs(np.asarray(traj.motor_velocity) - w_ref)) / np.max(np.abs(w_ref))
    # issue requirement: max relative torque error below 1e-4
    assert err < 1e-4, err
    assert err_w < 1e-4, err_w


def test_batch_with_padding_matches_single_runs():
    p, drive = hd2()
    exps = [sine_experiment("constrained", duration=0.3), sine_experiment("free", freq=5.0, duration=0.2)]
    batch = hdjax.stack_experiments(exps)
    trajs = jax.jit(hdjax.simulate_batch)(p, drive, batch)
    for k, e in enumerate(exps):
        single = jax.jit(hdjax.simulate)(p, drive, e)
        n = e.time.shape[0]
        ref = np.asarray(single.torque)
        # same solver tolerance (rtol 1e-7) in both; vmapped arithmetic may round differently and so
        # pick slightly different adaptive steps, hence agreement to the solver tolerance, not to 1e-15
        np.testing.assert_allclose(np.asarray(trajs.torque[k, :n]), ref, rtol=0, atol=1e-6 * np.max(np.abs(ref)))


@pytest.mark.parametrize("how", ["vmap", "map"])
def test_both_batchings_give_the_single_runs(how, monkeypatch):
    """`vmap` (accelerators) and `lax.map` (CPU default) over experiments: same trajectories."""
    monkeypatch.setenv("HDJAX_EXPERIMENT_BATCHING", how)
    assert hdjax._plant.sharding.experiment_batching() == how
    p, drive = hd2()
    exps = [sine_experiment("constrained", duration=0.2), sine_experiment("free", freq=5.0, duration=0.15)]
    trajs = jax.jit(lambda p_, b: hdjax.simulate_batch(p_, drive, b))(p, hdjax.stack_experiments(exps))
    for k, e in enumerate(exps):
        ref = np.asarray(jax.jit(hdjax.simulate)(p, drive, e).torque)
        n = e.time.shape[0]
        np.testing.assert_allclose(np.asarray(trajs.torque[k, :n]), ref, rtol=0, atol=1e-6 * np.max(np.abs(ref)))


def test_samples_read_off_the_clipped_steps_match_interpolated_saving(monkeypatch):
    """With steps clipped to the samples, `simulate` reads the samples off the saved steps
    (`SaveAt(steps=True)`, used when experiments run one at a time) instead of diffrax's
    interpolation at `SaveAt(ts)` (used under `vmap`): same solver steps, same values."""
    p, drive = hd2()
    e = sine_experiment("free", freq=5.0, duration=0.15)
    out = {}
    for how in ("map", "vmap"):  # map: step read-off; vmap: SaveAt(ts)
        monkeypatch.setenv("HDJAX_EXPERIMENT_BATCHING", how)
        # a fresh function per setting: the setting is read when tracing, and a cached trace would hide it
        out[how] = jax.jit(lambda p_, d_, e_: hdjax.simulate(p_, d_, e_))(p, drive, e)
    assert int(out["map"].num_steps) == int(out["vmap"].num_steps)
    for name in ("torque", "motor_velocity", "output_position", "output_velocity"):
        a, b = np.asarray(getattr(out["map"], name)), np.asarray(getattr(out["vmap"], name))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9 * np.max(np.abs(b)), err_msg=name)


def test_at_sample_times_takes_the_nearest_step():
    """Steps that end a few ulps off a sample, steps between samples and unused (inf) slots."""
    time = jnp.asarray([0.0, 0.001, 0.002, 0.003])
    ts = jnp.asarray([0.0, 0.0004, np.nextafter(0.001, 0.0), 0.0015, np.nextafter(0.002, 1.0), 0.003, np.inf, np.inf])
    ys = (jnp.arange(8.0),)
    (got,) = hdjax._plant.simulate._at_sample_times(ts, ys, time)
    np.testing.assert_array_equal(np.asarray(got), [0.0, 2.0, 4.0, 5.0])


def test_bad_batching_setting_is_named(monkeypatch):
    monkeypatch.setenv("HDJAX_EXPERIMENT_BATCHING", "pmap")
    with pytest.raises(ValueError, match="HDJAX_EXPERIMENT_BATCHING"):
        hdjax._plant.sharding.experiment_batching()


def test_jacfwd_matches_central_differences_for_all_parameters():
    """Forward-mode AD through the solve vs 4-point central differences, in log-parameters.

    A fixed step grid is used so that the discrete solution is a smooth function of the
    parameters (an adaptive controller changes its step sequence discontinuously, which
    finite differences see as noise of order tolerance / h)."""
    p, drive = hd2()
    exp = sine_experiment("free", amplitude=1.5, freq=4.0, duration=0.25)
    sim = hdjax.Simulator(fixed_step=1e-4)
    names = hdjax.PARAMETER_NAMES
    x0 = jnp.log(jnp.abs(jnp.array([getattr(p, k) for k in names])))
    signs = jnp.sign(jnp.array([getattr(p, k) for k in names]))

    def out(logx):
        q = hdjax.Parameters(**{k: s * jnp.exp(v) for k, s, v in zip(names, signs, logx)})
        tr = hdjax.simulate(q, drive, exp, simulator=sim)
        return jnp.concatenate([tr.torque, tr.motor_velocity])

    J = jax.jit(jax.jacfwd(out))(x0)
    f = jax.jit(out)
    h = 1e-4
    for j, name in enumerate(names):
        e = jnp.zeros_like(x0).at[j].set(h)
        fd = (8 * (f(x0 + e) - f(x0 - e)) - (f(x0 + 2 * e) - f(x0 - 2 * e))) / (12 * h)
        rel = float(jnp.max(jnp.abs(J[:, j] - fd)) / jnp.max(jnp.abs(fd)))
        # issue requirement: AD vs central differences within 1e-4 relative
        assert rel < 1e-4, (name, rel)
        assert bool(jnp.all(jnp.isfinite(J[:, j])))


def test_a_record_that_starts_stuck_starts_at_rest(tmp_path):
    """Independent bench (`hdjax._testbench.independent`: its own integrator and exact stick–slip; all deviations off,
    so the paper model with the true parameters is exact up to white sensor noise). In this locked
    record (seed 801, HD1, record 1) the motor is at rest for the first 0.2 s, but the tachometer's
    first samples happen to trend from −0.05 rad/s: a line fit calls that motion (3.3 standard
    errors), and the power-law damping turned it into a 1.3 N·m torsion error that sticking then
    froze (torque RMS 5× its noise). The start test (net drive torque inside the breakaway
    interval, friction would stop the estimate within one sample) starts it at rest."""
    import yaml

    from hdjax import load_dataset, noise_levels
    from hdjax.bench import Deviations, make_dataset

    jax.config.update("jax_enable_x64", True)
    make_dataset(tmp_path, drive="hd1", seed=801, n_locked=4, n_free=4, duration=1.5, deviations=Deviations.none())
    truth = yaml.safe_load((tmp_path / "truth.yaml").read_text())
    ds = load_dataset(tmp_path)
    exps = [ds.experiments[i] for i in ds.dynamic_indices()]
    p = hdjax.Parameters.from_dict(truth["parameters"])
    sig = np.asarray(noise_levels(hdjax.stack_experiments(exps)))
    exp = exps[1]
    y0, _ = hdjax.initial_state(p, ds.drive, exp)
    assert float(y0[1]) == 0.0
    for sim in (hdjax.Simulator(rtol=1e-7, atol=1e-9), hdjax.Simulator(solver=hdjax.VelocityImplicit(substeps=8))):
        tr = hdjax.simulate(p, ds.drive, exp, simulator=sim)
        rms = float(np.sqrt(np.mean((np.asarray(tr.torque) - np.asarray(exp.torque))[np.asarray(exp.mask)] ** 2)))
        assert rms < 1.3 * sig[0], (sim.solver, rms / sig[0])


def test_select_experiments_spreads_half_constrained_half_free():
    modes = ["constrained"] * 20 + ["free"] * 30
    sel = hdjax.select_experiments(modes, 12)
    assert len(sel) == 12 and sel == sorted(set(sel))
    cons = [j for j in sel if modes[j] == "constrained"]
    assert len(cons) == 6 and cons[0] == 0 and cons[-1] == 19  # evenly spread, both ends kept
    free = [j for j in sel if modes[j] == "free"]
    assert free[0] == 20 and free[-1] == 49
    # the other mode fills the places one mode cannot; all are kept when there are no more
    few = ["constrained"] * 2 + ["free"] * 30
    assert [few[j] for j in hdjax.select_experiments(few, 12)].count("constrained") == 2
    assert hdjax.select_experiments(modes[:5], 12) == list(range(5))
    with pytest.raises(ValueError, match="max_n"):
        hdjax.select_experiments(modes, 0)
    # take_experiments picks the same experiments out of a stacked batch
    exps = [sine_experiment(m, amplitude=0.5, freq=1.0 + j, duration=0.1) for j, m in enumerate(["constrained", "free", "free"])]
    batch = hdjax.take_experiments(hdjax.stack_experiments(exps), [0, 2])
    np.testing.assert_array_equal(np.asarray(batch.current), np.asarray(hdjax.stack_experiments([exps[0], exps[2]]).current))
