"""Tuning design pieces: reference feasibility scaling, the Ms margin term (AD vs central
differences), closed-loop stability, the independent bench's closed loop, and the wording of the
validation for a user's data (no bench)."""

import pathlib
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hdjax import TorqueGains, sine_reference, step_reference
from hdjax._control import loopshape as ls
from hdjax._testbench import independent as _bench
from helpers import hd1

jax.config.update("jax_enable_x64", True)


def test_feasibility_scaling_meets_the_headroom_and_leaves_small_references_alone():
    p, drive = hd1()
    ilim = 6.0
    ts = 1e-3
    # free sine: the rigid-body current (1/N + N Jeff/J_L) r/Km plus friction; 40 N·m asks for ~8 A
    big = np.asarray(sine_reference(40.0, 2.0, duration=0.5, free=True).torque)
    s, need = ls.feasible_scale(big, free=True, p=p, drive=drive, ts=ts, current_limit=ilim, headroom=0.7)
    assert need > 0.7 and 0.0 < s < 1.0
    peak = np.max(np.abs(ls.feedforward_current(s * big, free=True, p=p, drive=drive, ts=ts)))
    np.testing.assert_allclose(peak, 0.7 * ilim, rtol=1e-6)
    # a locked step of 10 N·m with a smooth edge needs ~10/(N Km) + friction ≈ 2.7 A < 4.2 A: unscaled
    small = np.asarray(step_reference(10.0, duration=0.3, rise=0.04).torque)
    s2, need2 = ls.feasible_scale(small, free=False, p=p, drive=drive, ts=ts, current_limit=ilim, headroom=0.7)
    assert s2 == 1.0 and need2 < 0.7
    # the static part is the locked inverse: r/(N Km) + friction at rest (zero)
    ff = ls.feedforward_current(small, free=False, p=p, drive=drive, ts=ts)
    np.testing.assert_allclose(ff[-1], 10.0 / (100.0 * 0.0543), rtol=1e-9)


def _loops():
    p, drive = hd1()
    out = [ls.plant_response(p, drive, free=f, ts=1e-3, rate_amplitude=0.2) for f in (False, True)]
    z = out[0][0]
    return z, np.stack([o[1] for o in out]), [o[2] for o in out]


def test_margin_term_gradient_matches_central_differences():
    z, P, _ = _loops()
    zj, Pj = jnp.asarray(z), jnp.asarray(P)

    def term(theta):
        g = TorqueGains(kp=1.0 * jnp.exp(theta[0]), ki=300.0 * jnp.exp(theta[1]), kd=2e-4 * theta[2])
        ms = ls.sensitivity_peak(g, zj, Pj, ts=1e-3, derivative_filter=2e-3)
        return jnp.sum(jnp.maximum(ms - 1.2, 0.0) ** 2)

    th = jnp.array([0.3, 0.2, 0.5])
    assert float(term(th)) > 0.0  # the hinge is active
    g = np.asarray(jax.grad(term)(th))
    h = 1e-6
    fd = np.array([(term(th.at[i].add(h)) - term(th.at[i].add(-h))) / (2 * h) for i in range(3)])
    assert np.all(np.abs(fd) > 0)
    np.testing.assert_allclose(g, fd, rtol=1e-5)


def test_ms_and_stability_agree_with_loop_gain():
    z, P, ss = _loops()
    ms = lambda kp, ki: float(ls.sensitivity_peak(TorqueGains(kp=kp, ki=ki), z, P[0], ts=1e-3, derivative_filter=2e-3))  # noqa: E731
    assert ms(0.01, 5.0) < ms(0.3, 200.0)  # more gain, less margin
    assert ls.closed_loop_radius(0.01, 5.0, 0.0, ss[0], ts=1e-3, derivative_filter=2e-3) < 1.0
    assert ls.closed_loop_radius(0.01, 5.0, 0.0, ss[1], ts=1e-3, derivative_filter=2e-3) < 1.0  # free: z = 1 pair ignored
    assert ls.closed_loop_radius(50.0, 5.0, 0.0, ss[0], ts=1e-3, derivative_filter=2e-3) > 1.0
    m = ls.margins(0.01, 5.0, 0.0, z, P[0], ts=1e-3, derivative_filter=2e-3)
    assert m["Ms"] == pytest.approx(ms(0.01, 5.0)) and m["gain_margin"] > 1.0


def test_model_pi_meets_its_ms_bound():
    z, P, ss = _loops()
    kp, ki, info = ls.model_pi([(z, P[0]), (z, P[1])], ss, static_gain=5.43, ts=1e-3, derivative_filter=2e-3, ms_max=1.4)
    assert kp > 0 and ki > 0 and info["Ms"] <= 1.4
    for Pj in P:
        assert float(ls.sensitivity_peak(TorqueGains(kp=kp, ki=ki), z, Pj, ts=1e-3, derivative_filter=2e-3)) <= 1.4 + 1e-12


def test_p_controller_on_a_locked_bench_reaches_the_static_torque():
    b = _bench.Bench(drive="hd1", seed=3)
    st = b.station
    kp = 0.5
    r = np.full((300, 2), 20.0)
    r[:, 1] = 10.0
    o = b.closed_loop(_bench.pi_law(kp, 0.0, sample_period=1e-3), r, np.zeros(2, bool), current_limit=6.0, seed=1,
                      tare_samples=200)  # fmt: skip
    g = st.gear_ratio * st.torque_constant * kp
    expected = g / (1 + g) * r[-1]
    # friction holds the stuck motor anywhere within its breakaway band: T = N(Km i − F), |F| ≤ breakaway
    band = st.gear_ratio * max(b.bench["breakaway"].values()) / (1 + g) + 0.3  # + tare and noise (σ_T = 0.1 N·m)
    T = o["torque"][-50:].mean(axis=0)
    assert np.all(T <= expected + 0.3) and np.all(T >= expected - band), (T, expected, band)
    # the command is held: the current loop's actual current follows it, and the limit is enforced
    np.testing.assert_allclose(o["current"][-1], o["current_command"][-2], rtol=0.05)
    o2 = b.closed_loop(_bench.pi_law(50.0, 0.0, sample_period=1e-3), r[:20], np.zeros(2, bool), current_limit=6.0)
    assert np.max(np.abs(o2["current_command"])) <= 6.0 and np.max(np.abs(o2["command"])) > 6.0


def test_bench_is_rebuilt_from_its_truth(tmp_path):
    truth = _bench.make_dataset(tmp_path / "d", drive="hd2", seed=11, n_locked=1, n_free=1, duration=0.3,
                                effects={"torque_sensor_ripple": {"magnitude": 1.0, "orders": [2]}})  # fmt: skip
    b = _bench.Bench.from_truth(truth)
    assert b.parameters == truth["parameters"]
    assert b.magnitudes == {"torque_sensor_ripple": 1.0}
    np.testing.assert_allclose(b.specs["torque_sensor_ripple"]["phi"], truth["effects"]["torque_sensor_ripple"]["phases"])
    with pytest.raises(ValueError, match="not written by hdjax._bench"):
        _bench.Bench.from_truth({"source": "hdjax virtual test rig"})


def test_user_data_is_validated_on_the_identified_model_and_says_so(tmp_path, monkeypatch):
    """A dataset without a truth.yaml from hdjax._testbench.independent (here the shipped HD1 records without their
    truth file): report and figure titles say 'identified model', never 'bench'. The
    heavy numerics are replaced by stand-ins; only the wording path is exercised."""
    import matplotlib.figure

    from hdjax import LoopTrajectory, TuneResult, load_dataset
    from hdjax._workflows import tune as _tune

    # a dataset without the bench's truth (the shipped ones come from the bench since 2026-11-26)
    src = pathlib.Path(__file__).parents[1] / "data" / "hd1"
    folder = tmp_path / "own-bench"
    folder.mkdir()
    for f in src.iterdir():
        if f.name != "truth.yaml":
            shutil.copy(f, folder / f.name)
    meta = folder / "dataset.yaml"
    meta.write_text(meta.read_text().replace("name: hd1-bench", "name: my-drive"))
    ds = load_dataset(folder)
    assert _tune._bench_from_truth(ds) is None

    def fake_batch_cost(g, plants, R, **kw):
        n = R.torque.shape[0]
        c = jnp.full((1, n), 0.01) * (1.0 + 0.0 * g.kp)
        return c, c

    def fake_tune(starts, cost_fn, **kw):
        return TuneResult(gains=starts[0], history=[0.01], steps=1, converged=True,
                          runs=[{"history": [0.01], "steps": 1, "converged": True, "final_cost": 0.01}], best_run=0)

    def fake_loop(g, plant, r, **kw):
        z = jnp.zeros_like(r.torque)
        return LoopTrajectory(time=jnp.arange(r.torque.shape[0], dtype=float) * 1e-3, reference=r.torque, torque=0.9 * r.torque,
                              measured_torque=r.torque, motor_velocity=z, output_velocity=z, current=z, command=z,
                              refined=z > 0)  # fmt: skip

    def fake_relay(*a, **k):
        return None

    monkeypatch.setattr(_tune, "batch_cost", fake_batch_cost)
    monkeypatch.setattr(_tune, "tune_gains", fake_tune)
    monkeypatch.setattr(_tune, "relay_test", fake_relay)
    monkeypatch.setattr(_tune, "ziegler_nichols_pi", lambda *a, **k: (TorqueGains(kp=0.1, ki=50.0), {
        "ultimate_gain": 0.2, "ultimate_period_s": 0.02, "oscillation_amplitude": 1.0}))
    monkeypatch.setattr(jax, "jit", lambda f, **k: f)
    monkeypatch.setattr(_tune, "closed_loop", fake_loop)
    titles = []
    orig = matplotlib.figure.Figure.suptitle

    def spy(self, t, *a, **k):
        titles.append(t)
        for ax in self.axes:
            titles.extend(ln.get_label() for ln in ax.get_lines())
            titles.append(ax.get_title())
        return orig(self, t, *a, **k)

    monkeypatch.setattr(matplotlib.figure.Figure, "suptitle", spy)
    r = _tune.run_tune(ds, {"tune": {"plants": 1, "start_factors": [1.0], "starts": 1}}, tmp_path, log=lambda s: None)
    assert r["validation"]["on"] == "identified model"
    text = (tmp_path / "report.md").read_text()
    heads = [ln for ln in text.splitlines() if ln.startswith("#")]
    assert any("identified model" in h for h in heads), heads
    assert not any("bench" in h.lower() for h in heads), heads
    assert "(on the identified model)" in text
    assert titles and any("identified model" in t for t in titles)
    assert not any("bench" in t.lower() for t in titles), titles


def test_plant_sets_carry_the_friction_uncertainty():
    """Plant set 0 is the identified plant; the others have every eq. 9 friction term scaled by one
    common factor spread evenly over 1 ± u, and the rest of the parameters untouched."""
    from hdjax._model.paper import EQ9_COEFFICIENTS
    from hdjax._workflows.tune import draw_parameter_sets

    p, _ = hd1()
    sets = draw_parameter_sets(p, {}, 6, seed=0, friction_uncertainty=0.2)
    ratio = np.asarray(sets.Tsp) / float(p.Tsp)
    assert ratio[0] == 1.0
    np.testing.assert_allclose(np.sort(ratio[1:]), [0.8, 0.9, 1.0, 1.1, 1.2])
    for k in EQ9_COEFFICIENTS:
        np.testing.assert_allclose(np.asarray(getattr(sets, k)), float(getattr(p, k)) * ratio)
    np.testing.assert_allclose(np.asarray(sets.K1), float(p.K1))
    none = draw_parameter_sets(p, {}, 6, seed=0)
    np.testing.assert_allclose(np.asarray(none.Tsp), float(p.Tsp))


def test_plant_sets_leave_out_a_per_experiment_estimate_that_ran_off():
    """A per-experiment fit that runs off along a flat direction (the shipped HD2 campaign: one
    record's Tssp1 at -1.2e5 N·m beside -0.64 ... +0.32) must not set the plant sets: recentred on
    the mean it gave every drawn plant Tssp1 near +8 000 N·m. Outliers (beyond 5 scaled MADs of
    the median) are left out and the draws are recentred on the median: every drawn value lies
    within the spread of the other estimates around the nominal one."""
    from hdjax._workflows.tune import _without_outliers, draw_parameter_sets

    p, _ = hd1()
    good = [-0.149, -0.124, -0.053, -0.057, -0.076, -0.061, -0.090, -0.070]
    sets = draw_parameter_sets(p, {"Tssp1": good + [-1.19e5]}, 40, seed=3)
    drawn = np.asarray(sets.Tssp1)
    v, med = float(p.Tssp1), float(np.median(good))
    assert drawn[0] == v
    lo, hi = sorted((v * max(good) / med, v * min(good) / med))
    assert np.all(drawn[1:] >= lo - 1e-12) and np.all(drawn[1:] <= hi + 1e-12), (drawn, lo, hi)
    assert len(set(np.round(drawn[1:], 12))) > 3  # still spread
    np.testing.assert_array_equal(_without_outliers(np.array(good)), np.array(good))  # nothing left out of clean data
    assert list(_without_outliers(np.array([1.0, 1.0, 1.0, 50.0]))) == [1.0, 1.0, 1.0, 50.0]  # MAD 0: all kept


def test_a_torque_sensor_lag_enters_the_linearised_loop_as_a_low_pass_before_the_sampler():
    """`plant_response(..., sensor_lag=τ)`: the strain gauge's continuous first-order low-pass
    appended to the plant before it is sampled. At low frequency the response is the lag-free
    one times 1/(1 + iωτ); near the Nyquist frequency it lags more than the sample-level filter
    (1 − a) z / (z − a) of the fit (which has none there); the returned state space gives the
    response; the same PI has less phase margin. A lead (τ < 0) takes the sample-level form."""
    p, drive = hd1()
    ts, tau = 1e-3, 6e-4
    for free in (False, True):
        z, P0, _ = ls.plant_response(p, drive, free=free, ts=ts, rate_amplitude=0.01)
        z, P1, (Ad, Bd, C) = ls.plant_response(p, drive, free=free, ts=ts, rate_amplitude=0.01, sensor_lag=tau)
        w = np.angle(z) / ts  # rad/s
        low = w < 2 * np.pi * 1.0
        np.testing.assert_allclose(P1[low] / P0[low], 1.0 / (1.0 + 1j * w[low] * tau), atol=2e-3)  # unit DC gain
        a = tau / (tau + ts)
        be = (1 - a) * z / (z - a)
        k = int(np.argmin(np.abs(w - 0.6 * np.pi / ts)))  # 0.6 of the Nyquist frequency
        print(f"phase at 0.6 Nyquist: before the sampler {np.degrees(np.angle(P1[k] / P0[k])):.1f} deg, "
              f"sample-level {np.degrees(np.angle(be[k])):.1f} deg")
        assert np.angle(P1[k] / P0[k]) < np.angle(be[k]) - (0.0 if free else 0.2)  # rad (locked: -37 against -18 deg)
        n = Ad.shape[0]
        P_ss = np.array([(C @ np.linalg.solve(zz * np.eye(n) - Ad, Bd))[0, 0] for zz in z])
        np.testing.assert_allclose(P_ss, P1, rtol=1e-9)
        pm = [ls.margins(0.2, 100.0, 0.0, z, P, ts=ts, derivative_filter=2e-3)["phase_margin_deg"] for P in (P0, P1)]
        print(f"free={free}: phase margin without / with the lag {pm[0]:.1f} / {pm[1]:.1f} deg")
        assert pm[1] < pm[0] - 1.0
        assert ls.closed_loop_radius(0.2, 100.0, 0.0, (Ad, Bd, C), ts=ts, derivative_filter=2e-3) < 1.0
        z, P2, _ = ls.plant_response(p, drive, free=free, ts=ts, rate_amplitude=0.01, sensor_lag=-2e-4)
        a = -2e-4 / (-2e-4 + ts)
        np.testing.assert_allclose(P2, P0 * (1 - a) * z / (z - a), rtol=1e-9)
