"""The trajectory fit on data the package did not make: recovery of the drive's parameters from
clean datasets of the independent bench (`hdjax.bench`), where the paper model is never exact.

What differs from hdjax's plant (all `hdjax.bench.Deviations` on, their defaults): the bench is a
numpy/numba fixed-step (20 kHz) velocity-level integrator written apart from hdjax; its low-speed
friction is exact stick–slip with a breakaway torque above the friction level, and its sliding
friction is eq. 9 with the non-viscous part clipped at zero (not tanh(ω/s)); the current comes from
a simulated PI current loop with PWM ripple and is *sampled*; the sensors are low-pass filtered,
offset and quantised, and the time stamps jitter. The fit knows none of this.

What is asserted, and why:
- K1, Tst, Jeff and the viscous and positive Coulomb terms within 3 % of the bench's drawn truth
  (the bar the independent-bench issue set for clean data; measured 2026-11-28: at most 2.0 %).
- The fitted friction torque at the speeds the free records reached (quartile, median and 90 % of
  |ω| in each direction) within 3 % of the bench's sliding friction (measured: at most 1.5 %).
- The trajectory fit is closer to the truth than the paper's regressions it starts from.
- Its standard errors (`block_covariance`, 0.1 s blocks) put the truth within 5 of them, where
  the white-noise Gauss–Newton ones put it 10 or more away on some parameter (measured: at most 3.9
  block standard errors away; the white ones 42–59 on the worst parameter). This holds for these
  small datasets only: with 8 + 8 records of 2.5 s the errors shrink and a model-form bias does
  not (Jeff up to 23 block errors away on the benchmark's clean datasets, benchmarks/RESULTS.md).

Not asserted: the Stribeck amplitudes Tssp1, Tssn1 (eq. 9's exponential takes up the bench's
stick–slip law; measured 12–62 % off) and Tsn alone (on HD2 seed 11 the bench clips the negative
direction's Tsn + Tssn1 < 0 at zero, which eq. 9 cannot do; Tsn came out 10 % low while the
friction torque it predicts at the measured speeds is within 0.6 %).
"""


import jax
import numpy as np
import pytest

from hdjax import (
    Effects,
    Parameters,
    SensorBandwidth,
    fit_parameters,
    friction_torque,
    identify_paper,
    load_dataset,
    stack_experiments,
)
from hdjax.bench import make_dataset

jax.config.update("jax_enable_x64", True)

CASES = [("hd2", 11), ("hd1", 12)]  # seeds the diagnosis tests and benchmark do not use
RECOVERED = ("K1", "Tst", "Jeff", "Tvp", "Tvn", "Tsp")


@pytest.fixture(scope="module")
def fits(tmp_path_factory):
    out = {}
    for drive, seed in CASES:
        folder = tmp_path_factory.mktemp(f"bench_{drive}") / "ds"
        truth = make_dataset(folder, drive=drive, seed=seed, n_locked=2, n_free=2, duration=1.0)
        ds = load_dataset(folder)
        exps = [ds.experiments[i] for i in ds.dynamic_indices()]
        start = identify_paper(exps, ds.drive).parameters()
        fit = fit_parameters(start, ds.drive, stack_experiments(exps), max_steps=20)
        speeds = np.concatenate([np.asarray(e.motor_velocity) for e in exps if float(e.free) == 1.0])
        true_p = Parameters.from_dict({**start.to_dict(), **truth["parameters"]})
        out[drive] = (true_p, start, fit, speeds)
        # the same fit with the sensors' bandwidth: first-order lags of the simulated torque and
        # velocity, both fitted (what `python -m hdjax.fit` does by default)
        dt = float(np.median(np.diff(np.asarray(exps[0].time))))
        lagged = fit_parameters(start, ds.drive, stack_experiments(exps), max_steps=20, sigma=fit.sigma,
                                effects=Effects().with_term(SensorBandwidth()),
                                free_effects={"sensor_bandwidth.torque_lag": dt, "sensor_bandwidth.velocity_lag": dt})
        out[drive + "_lags"] = (truth, fit, lagged)
    return out


def _rel(p: Parameters, true_p: Parameters, k: str) -> float:
    return abs(float(getattr(p, k)) / float(getattr(true_p, k)) - 1)


@pytest.mark.parametrize("drive", [d for d, _ in CASES])
def test_trajectory_fit_recovers_the_independent_bench(fits, drive):
    true_p, start, fit, _ = fits[drive]
    errors = {k: _rel(fit.params, true_p, k) for k in RECOVERED}
    assert max(errors.values()) < 0.03, errors
    # the fit is worth running: closer to the truth than the regressions it starts from
    assert max(errors.values()) < max(_rel(start, true_p, k) for k in RECOVERED), errors


@pytest.mark.parametrize("drive", [d for d, _ in CASES])
def test_standard_errors_allow_for_the_misfit(fits, drive):
    true_p, _, fit, _ = fits[drive]
    assert fit.std_error_method == "block_sandwich"
    z_block = {k: abs(float(getattr(fit.params, k) - getattr(true_p, k))) / fit.std_error[k] for k in RECOVERED}
    z_white = {k: abs(float(getattr(fit.params, k) - getattr(true_p, k))) / fit.std_error_white[k] for k in RECOVERED}
    assert max(z_block.values()) < 5.0, z_block
    assert max(z_white.values()) > 10.0, z_white  # the bench's misfit is correlated: white errors mislead


def _bench_sliding_friction(p: Parameters, w: np.ndarray) -> np.ndarray:
    """The bench's sliding friction (N·m) at motor speeds `w` (rad/s), as its truth.yaml states
    it: eq. 9 with the non-viscous part clipped at zero, written here apart from hdjax's code."""
    pos = w > 0
    viscous = np.where(pos, float(p.Tvp), float(p.Tvn)) * w
    coulomb = np.where(pos, float(p.Tsp), float(p.Tsn))
    stribeck = np.where(pos, float(p.Tssp1), float(p.Tssn1)) * np.exp(-((w / float(p.Tss2)) ** 2))
    return viscous + np.sign(w) * np.maximum(coulomb + stribeck, 0.0)


@pytest.mark.parametrize("drive", [d for d, _ in CASES])
def test_fitted_friction_matches_the_bench_at_the_measured_speeds(fits, drive):
    true_p, _, fit, speeds = fits[drive]
    for sign in (1.0, -1.0):
        w = sign * np.quantile(np.abs(speeds[np.sign(speeds) == sign]), [0.25, 0.5, 0.9])
        true_t = _bench_sliding_friction(true_p, w)
        assert np.all(np.abs(w) > 0.05)  # beyond the bench's stick band
        err = np.abs(np.asarray(friction_torque(fit.params, w)) / true_t - 1)
        assert np.all(err < 0.03), (sign, w, err)


@pytest.mark.parametrize("drive", [d for d, _ in CASES])
def test_fitted_sensor_lags_match_the_bench_filters_and_lower_the_misfit(fits, drive):
    """The bench low-pass filters its strain gauge and tachometer (first order, on its 20 kHz grid,
    before sampling: its own code); hdjax's `sensor_bandwidth` is a first-order lag of the simulated
    samples. Fitted with the parameters (what `python -m hdjax.fit` does by default):
    - the tachometer's lag, well determined, lands within 20 % of the bench filter's time constant
      1/(2π f_c) and within 3 of its standard errors (measured 2026-12-06: +5.1 % and −0.6 %);
    - the strain gauge's, which these 2 + 2 records of 1 s determine only to about its own size
      (standard error 0.31–0.36 ms against 0.30 ms), within 3 of its standard errors (measured: 0.2
      and 1.8); on the shipped 50-record campaigns it came within 7 % (benchmarks/RESULTS.md);
    - the reduced χ² falls (measured 5.0 → 2.0 and 8.1 → 2.8): without the lags the filters' phase
      lag stays in the residual;
    - K1 and Jeff come closer to the truth (worst of the two 1.26 % → 0.10 %, 1.12 % → 0.82 %): the
      phase lag near the free-motion resonance reads as a softer or heavier drive."""
    truth, plain, lagged = fits[drive + "_lags"]
    dev = truth["deviations"]
    taus = {f: 1.0 / (2.0 * np.pi * float(dev[key])) for f, key in (("torque_lag", "torque_filter_hz"), ("velocity_lag", "tacho_filter_hz"))}
    got = {f: float(getattr(lagged.effects.sensor_bandwidth, f)) for f in taus}
    se = {f: lagged.std_error["sensor_bandwidth." + f] for f in taus}
    assert abs(got["velocity_lag"] / taus["velocity_lag"] - 1) < 0.2, (got, taus)
    for f in taus:
        assert 0 < se[f] and abs(got[f] - taus[f]) < 3 * se[f], (f, got[f], taus[f], se[f])
    assert lagged.free_effects == ("sensor_bandwidth.torque_lag", "sensor_bandwidth.velocity_lag")
    assert lagged.correlation.shape == (len(lagged.free) + 2,) * 2
    assert lagged.chi2_reduced < plain.chi2_reduced, (lagged.chi2_reduced, plain.chi2_reduced)
    tp = truth["parameters"]
    worst = {name: max(abs(float(getattr(fit.params, k)) / tp[k] - 1) for k in ("K1", "Jeff")) for name, fit in (("plain", plain), ("lags", lagged))}
    assert worst["lags"] < worst["plain"], worst


@pytest.mark.parametrize("drive,seed", CASES)
def test_breakaway_search_finds_the_bench_breakaway_torques(drive, seed, tmp_path):
    """The bench's motor sticks until the holding torque leaves [−B_n, B_p], its breakaway torques
    1.1–1.3× the friction level, above eq. 9's limit at rest (its own stick–slip code). After the
    fit (fixed-step exact plant, sensor lags freed), `fit_breakaway_friction` (`hdjax fit`'s
    `fit.trajectory.breakaway_friction`: grid search, LM with the torques held, search again) must
    put each direction's breakaway torque within 15 % of the bench's, where eq. 9 at rest alone is
    34–85 % below it, and lower the reduced χ²."""
    from hdjax import BreakawayFriction, Simulator, VelocityImplicit, fit_breakaway_friction

    truth = make_dataset(tmp_path / "ds", drive=drive, seed=seed, n_locked=2, n_free=2, duration=1.0)
    ds = load_dataset(tmp_path / "ds")
    exps = [ds.experiments[i] for i in ds.dynamic_indices()]
    start = identify_paper(exps, ds.drive).parameters()
    dt = float(np.median(np.diff(np.asarray(exps[0].time))))
    sim = Simulator(solver=VelocityImplicit(substeps=4))
    batch = stack_experiments(exps)
    lags = {"sensor_bandwidth.torque_lag": dt, "sensor_bandwidth.velocity_lag": dt}
    fit = fit_parameters(start, ds.drive, batch, max_steps=20, simulator=sim,
                         effects=Effects().with_term(SensorBandwidth()).with_term(BreakawayFriction()), free_effects=lags)
    with pytest.raises(ValueError, match="free_effects"):
        fit_breakaway_friction(fit, ds.drive, batch, simulator=sim)
    out, report = fit_breakaway_friction(fit, ds.drive, batch, simulator=sim, free_effects=lags, max_steps=20)
    found = out.effects.breakaway_friction
    got = float(found.breakaway_p), float(found.breakaway_n)
    at_rest = float(fit.params.Tsp + fit.params.Tssp1), float(fit.params.Tsn + fit.params.Tssn1)
    bench = truth["low_speed"]["breakaway_torque"]["p"], truth["low_speed"]["breakaway_torque"]["n"]
    for d in range(2):
        assert abs(got[d] / bench[d] - 1) < 0.15, (d, got[d], at_rest[d], bench[d])
        assert abs(got[d] / bench[d] - 1) < abs(at_rest[d] / bench[d] - 1)
    assert report["sse_end"] <= report["sse_start"] and out.chi2_reduced < fit.chi2_reduced, (out.chi2_reduced, fit.chi2_reduced)
    assert out.free_effects == fit.free_effects and out.steps >= fit.steps
    # the search's lanes (one vmapped program per grid) give the squared error of one plain evaluation
    # at the same values: a one-point grid at the found torques reproduces the report's end value
    from hdjax import profile_effect_parameters
    _, one = profile_effect_parameters(out, ds.drive, batch, {"breakaway_friction.breakaway_p": [got[0]]}, simulator=sim)
    np.testing.assert_allclose(one["paths"]["breakaway_friction.breakaway_p"]["sse"][0], one["sse_start"], rtol=1e-10)
