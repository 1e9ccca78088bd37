"""Figures of the `fit` command that make a claim must hold it: Fig. 3's "optimal α" curve is the
best fit of its own parameter set, so it fits the loop at least as well as the α = ½ curve."""

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np
import pytest

from hdjax import identify_paper
from hdjax._workflows.fit import hysteresis_curves
from test_paper_id import DRIVE, TRUE, constrained


@pytest.mark.parametrize("alpha_true", [0.5, 0.7])
def test_fig3_optimal_alpha_curve_fits_at_least_as_well(alpha_true):
    rng = np.random.default_rng(3)
    exps = [constrained(rng, [(1.0, 1.0, 0.0), (0.3, 2.7, 1.0)], 2.0, theta0=0.3, p=dict(TRUE, alpha=alpha_true))]
    paper = identify_paper(exps, DRIVE)
    loop = hysteresis_curves(paper, exps[0], DRIVE, 0)
    half, opt = loop["curves"]
    assert half["alpha"] == 0.5 and "optimal" in opt["label"]
    assert opt["rms"] <= half["rms"] * (1 + 1e-9)
    assert loop["torsion"].shape == loop["torque"].shape == opt["torque"].shape
    # the curve Fig. 3 used to draw, the optimal α swapped into the α = ½ fit's K1 and Tst, is
    # not that parameter set's fit, and fits visibly worse whenever α moved
    if abs(opt["alpha"] - 0.5) > 0.05:
        from hdjax import smooth_signed_power
        from hdjax._fit.paper import _TORSION_RATE_SCALE, _prepare

        q, _, _ = _prepare(exps, DRIVE, 50.0, 5, [])
        tors, rate, T = (np.asarray(x[0]) for x in (q.torsion, q.torsion_rate, q.torque))
        old = half["K1"] * (tors + half["offset"]) + half["Tst"] * np.asarray(
            smooth_signed_power(rate, opt["alpha"], _TORSION_RATE_SCALE))
        assert np.sqrt(np.mean((old - T) ** 2)) > 1.5 * opt["rms"]


def test_diagnosis_figures_draw_spectra_residuals_and_the_loop(tmp_path):
    """`hdjax diagnose`'s figures (`hdjax._workflows.plots.diagnosis_figures`) from a diagnosis result: the
    order spectra, the torque residual before/after the extension and the constrained test's loop."""
    from types import SimpleNamespace

    import matplotlib.pyplot as plt

    from hdjax import MAX_ORDER, stack_experiments
    from hdjax.plotting import diagnosis_figures
    from helpers import sine_experiment

    exps = [sine_experiment("constrained", duration=0.4), sine_experiment("free", duration=0.3)]
    m = np.asarray(stack_experiments(exps).mask)
    n = m.shape[1]
    t = np.arange(n) * 1e-3
    base, ext = np.stack([np.sin(7 * t)] * 2), np.stack([1.1 * np.sin(7 * t)] * 2)
    resolved = [True] * MAX_ORDER
    d = SimpleNamespace(
        evidence={"order_spectra": {"constrained/torque (per-record normalised)": np.full(MAX_ORDER, 1e8),
                                    "free/torque (per-record normalised)": np.linspace(1.0, 0.1, MAX_ORDER)},
                  "order_spectra_detection": {"constrained/torque (per-record normalised)": {"threshold": 1e9, "resolved": [False] * MAX_ORDER},
                                              "free/torque (per-record normalised)": {"threshold": 0.5, "resolved": resolved}},
                  "torque_balance_spectra": {"e": {"over_median": [1.0] * MAX_ORDER, "over_max": [0.5] * MAX_ORDER}}},
        findings=[{"effect": "cogging", "orders": [1]}],
        traces={"torque_base": base, "torque_extended": ext, "motor_velocity_base": base, "motor_velocity_extended": ext,
                "torsion_extended": 1e-4 * np.stack([np.cos(7 * t)] * 2)})
    names = diagnosis_figures(tmp_path, None, exps, ["locked_01.csv", "free_01.csv"], d)
    assert names == ["residual_spectra.png", "residual_before_after.png", "hysteresis_before_after.png"]
    for name in names:
        img = plt.imread(tmp_path / name)
        assert img.ndim == 3 and min(img.shape[:2]) > 200 and float(img[..., :3].std()) > 0.01  # drawn, not blank
    assert not list(tmp_path.glob(".*"))  # written atomically: no temporary file left behind


def test_spectra_figure_shows_each_spectrum_in_units_of_its_detection_threshold():
    """The spectra panel of `hdjax diagnose` (`_spectrum_panels`): output-error spectra divided by the
    loop's own threshold, unresolved orders flagged (a locked test's fit over a fraction of a turn is
    ill-conditioned, its amplitudes meaningless), torque-balance spectra as the smaller of their two
    threshold ratios, so a bar above 1 is exactly an order the loop screens."""
    from hdjax import MAX_ORDER
    from hdjax._discrepancy.evidence import TB_MAX_RATIO, TB_MEDIAN_RATIO
    from hdjax._workflows.plots import _spectrum_panels

    amp = np.linspace(0.1, 0.8, MAX_ORDER)
    over_median = np.linspace(1.0, 9.0, MAX_ORDER)
    over_max = np.full(MAX_ORDER, 2.0)
    evidence = {"order_spectra": {"free/torque (per-record normalised)": amp.tolist(), "free/torque": (10 * amp).tolist(),
                                  "constrained/torque (per-record normalised)": [1e8] * MAX_ORDER},
                "order_spectra_detection": {"free/torque (per-record normalised)": {"threshold": 0.4, "resolved": [True] * MAX_ORDER},
                                            "constrained/torque (per-record normalised)": {"threshold": 5e8, "resolved": [False] * MAX_ORDER}},
                "torque_balance_spectra": {"e": {"over_median": over_median.tolist(), "over_max": over_max.tolist()}}}
    panels = dict(_spectrum_panels(evidence))
    locked = next(v for t, v in panels.items() if t.startswith("locked"))
    assert not locked["torque T"][1].any()
    ratio, resolved = next(v for t, v in panels.items() if t.startswith("free-motion tests: simulated"))["torque T"]
    np.testing.assert_allclose(ratio, amp / 0.4)
    assert resolved.all()
    tb, _ = next(v for t, v in panels.items() if "torque balance" in t)["e (cogging, torque-sensor ripple)"]
    np.testing.assert_allclose(tb, np.minimum(over_median / TB_MEDIAN_RATIO, over_max / TB_MAX_RATIO))
    # above 1 exactly where the loop's torque-balance rule finds a peak
    assert np.array_equal(tb > 1.0, (over_median > TB_MEDIAN_RATIO) & (over_max > TB_MAX_RATIO))


def test_before_after_figure_shows_the_record_and_channel_where_the_extension_gains_most():
    """`residual_before_after.png` shows, per kind of test, the record and channel whose squared
    residual the extended model reduces most (`most_improved_records`), not simply the first record:
    a cogging acts on the free tests' velocity, a ripple on the torque."""
    from hdjax import stack_experiments
    from hdjax._workflows.plots import most_improved_records
    from helpers import sine_experiment

    exps = [sine_experiment("constrained", duration=0.3), sine_experiment("constrained", duration=0.3),
            sine_experiment("free", duration=0.3), sine_experiment("free", duration=0.3)]
    batch = stack_experiments(exps)
    T, w = np.asarray(batch.torque), np.asarray(batch.motor_velocity)
    rng = np.random.default_rng(0)
    # the paper model misses a term the extension has: in locked record 1's torque (most), free record 3's velocity
    miss_T, miss_w = np.zeros_like(T), np.zeros_like(w)
    miss_T[0], miss_T[1] = 0.1, 1.0
    miss_w[3] = 2.0
    ext_T, ext_w = T + 0.01 * rng.standard_normal(T.shape), w + 0.01 * rng.standard_normal(w.shape)
    traces = {"torque_base": ext_T - miss_T, "torque_extended": ext_T, "motor_velocity_base": ext_w - miss_w,
              "motor_velocity_extended": ext_w}
    picks = most_improved_records(batch, traces)
    assert [(j, ch) for j, ch, _ in picks] == [(1, "torque"), (3, "motor_velocity")]
    assert all(0.99 < share <= 1.0 for _, _, share in picks)
