"""The discrepancy loop where the base model is exact: rig data made by hdjax's own plant
(`hdjax._testbench.rig`). Kept only for what needs an exact model: clean data must give neither a finding
nor a model_form item, and the noise model must whiten the process noise that the recorded
current drives through the simulation.

Whether the loop names hidden effects is judged on data the package did not make:
`tests/test_diagnose_bench.py` (the independent bench, `hdjax._testbench.independent`).
"""

import numpy as np

from hdjax import Effects, Simulator, diagnose_effects as diagnose, identify_paper
from hdjax.rig import campaign, run_campaign, station_hd1

N_LOCKED, N_FREE, DURATION = 4, 4, 1.0


def _dataset(effects: Effects, *, seed: int, free_first: bool = False):
    station = station_hd1()
    profiles = campaign(station, seed=seed, n_constrained=N_LOCKED, n_free=N_FREE, duration=DURATION)
    spacing = 30.0
    if free_first:
        # a session whose friction tests spread over the warm-up (thermal drift shows as time goes)
        profiles = profiles[N_LOCKED:] + profiles[:N_LOCKED]
        spacing = 150.0
    runs = run_campaign(station, effects=effects, seed=seed, profiles=profiles, spacing=spacing)
    exps = [r.experiment for r in runs]
    return station, exps


def _summary(d) -> str:
    """Per round: each simulated candidate's held-out gain, fold gains and harm ratio."""
    out = []
    for i, rnd in enumerate(d.rounds):
        out.append(f"round {i + 1}: " + "; ".join(
            f"{c} {100 * s['gain']:+.1f}%" + (f" folds {[round(100 * g, 1) for g in s['fold_gains']]} harm {s['harm_ratio']:.2f}"
                                              if s["simulated"] else " (predicted)")
            for c, s in sorted(rnd.items(), key=lambda x: -x[1]["gain"])[:4]))
    return "\n".join(out)


def _diagnose(station, exps, **kw):
    """The loop on the rig's own model and numerics (the adaptive Rodas3 solve of the smoothed model
    that `hdjax._testbench.rig` records with), so that the base model is exact here; the diagnosis's
    default, the fixed-step `VelocityImplicit` plant with exact sticking, is judged on the
    independent bench (`tests/test_diagnose_bench.py`)."""
    start = identify_paper(exps, station.drive).parameters()
    return diagnose(start, station.drive, exps, simulator=Simulator(rtol=1e-6, atol=1e-8, measured_angle=True), **kw)


def test_clean_data_gives_no_finding():
    """Where the base model is exact (rig data from hdjax's own plant), neither an effect nor a
    loosened base-model assumption (model_form) may be named."""
    station, exps = _dataset(Effects(), seed=7)
    d = _diagnose(station, exps, max_findings=2)
    print(_summary(d))
    assert d.findings == [], _summary(d)
    assert d.model_form == [], [f["assumption"] for f in d.model_form]


def test_process_noise_measures_the_current_noise_that_drives_the_simulation():
    """The noise model's process-noise samples: for a simulation whose residual responds to the
    current as gain·current (two channels), their variance is gain²·σ² with σ the current's
    white-noise level, estimated from the data (sine + noise of std 0.02 A); zero where the residual
    ignores it."""
    import jax.numpy as jnp

    from hdjax import make_experiment, stack_experiments
    from hdjax._discrepancy.loop import _process_noise

    rng = np.random.default_rng(3)
    t = np.arange(4000) * 1e-3
    exps = [make_experiment(t, np.sin(2 * np.pi * f * t) + 0.02 * rng.standard_normal(t.size), 0 * t, 0 * t,
                            mode="constrained") for f in (1.0, 3.0)]
    batch = stack_experiments(exps)
    gain = np.array([5.0, 0.0, 2.0])

    def simulate(b):
        return jnp.asarray(gain)[None, :, None] * b.current[:, None, :]

    d = _process_noise(simulate, batch, np.asarray(simulate(batch)), realisations=4)
    assert d.shape == (4, 2, 3, 4000)
    got = (d**2).mean(axis=(0, 1, 3))
    np.testing.assert_allclose(got[[0, 2]], gain[[0, 2]] ** 2 * 0.02**2, rtol=0.1)
    assert got[1] == 0.0


def test_noise_model_whitens_random_walk_process_noise():
    """Free-motion position wanders as a random walk driven by the current's noise, with a level
    that differs by orders of magnitude between records. The AR noise model, fitted to two process
    noise realisations plus unit sensor noise, must whiten a fresh realisation of each record to unit
    variance with no correlation at lags 1–10 (the raw residual is far from that), and leave a record with
    sensor noise only as it is."""
    from hdjax._discrepancy.loop import _noise_model

    rng = np.random.default_rng(5)
    n = 3000
    scales = np.array([0.0, 0.05, 0.3])  # random-walk increments per sample, in sensor-noise units

    def realisation():
        return scales[:, None] * np.cumsum(rng.standard_normal((3, n)), axis=1)

    proc = np.stack([realisation() for _ in range(2)])[:, :, None, :]  # (realisations, exp, channel, time)
    mask = np.ones((3, n), bool)
    model = _noise_model(proc, mask)
    fresh = (realisation() + rng.standard_normal((3, n)))[:, None, :]
    white = model.whiten(fresh)[:, 0]
    for e in range(3):
        assert abs(np.mean(white[e] ** 2) - 1.0) < 0.1, (e, np.mean(white[e] ** 2))
        for lag in (1, 2, 3, 5, 10):
            assert abs(np.corrcoef(white[e, lag:], white[e, :-lag])[0, 1]) < 0.06, (e, lag)
    assert np.mean(fresh[2, 0] ** 2) > 10.0  # the raw residual is far from white unit noise
    np.testing.assert_allclose(model.s[0, 0], 1.0, atol=0.05)
    assert np.all(np.abs(model.a[0, 0]) < 0.1)
