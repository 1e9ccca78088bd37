"""Small checks of the discrepancy loop's numerical helpers (no simulation)."""

import numpy as np

from hdjax import Significance
from hdjax._diagnose import _judge, _solve_normal


def test_gauss_newton_step_solves_the_normal_equations():
    rng = np.random.default_rng(0)
    J = rng.normal(size=(50, 3))
    r = rng.normal(size=50)
    step = _solve_normal(J.T @ J, J.T @ r)
    np.testing.assert_allclose(step, -np.linalg.lstsq(J, r, rcond=None)[0], rtol=1e-6)


def test_gauss_newton_step_is_zero_on_columns_without_information():
    # every simulation failed: the residual is a constant, its Jacobian zero (a column of zeros
    # must neither crash the solve nor move the others)
    rng = np.random.default_rng(1)
    J = rng.normal(size=(40, 3))
    J[:, 1] = 0.0
    r = rng.normal(size=40)
    step = _solve_normal(J.T @ J, J.T @ r)
    assert step[1] == 0.0
    keep = [0, 2]
    np.testing.assert_allclose(step[keep], -np.linalg.lstsq(J[:, keep], r, rcond=None)[0], rtol=1e-6)
    assert np.all(_solve_normal(np.zeros((3, 3)), np.zeros(3)) == 0.0)


def _residuals(gains, n=400, seed=0):
    """Whitened held-out residuals (exp, channel, time) of unit-variance noise plus a misfit, without
    and with a candidate that removes the share `gains[e]` of experiment e's squared error."""
    rng = np.random.default_rng(seed)
    before = rng.normal(size=(len(gains), 3, n)) * 3.0
    after = before * np.sqrt(1.0 - np.asarray(gains))[:, None, None]
    return before, after


MODES = np.array(["constrained"] * 4 + ["free"] * 4)
FOLDS = np.array([0, 1, 0, 1, 0, 1, 0, 1])


def test_significance_names_a_gain_shared_by_most_records_of_its_mode():
    before, after = _residuals([0.2, 0.25, 0.15, 0.2, 0.0, 0.0, 0.0, 0.0])
    s = _judge(before, after, FOLDS, MODES, 2, Significance())
    assert s["significant"] and s["acting_mode"] == "constrained" and s["improved_fraction"] == 1.0
    assert s["delta_chi2"] > Significance().chance(2)


def test_significance_refuses_a_gain_that_rests_on_one_record():
    # the same total gain, all in one record: without it the rest gains nothing
    before, after = _residuals([0.7, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    s = _judge(before, after, FOLDS, MODES, 2, Significance())
    assert not s["significant"] and s["delta_chi2_without_best_experiment"] <= Significance().chance(2)


def test_significance_refuses_a_term_that_trades_one_kind_of_test_for_the_other():
    # locked tests gain 20 %, free tests lose 10 %: more than MODE_TRADE of the gain
    before, after = _residuals([0.2, 0.2, 0.2, 0.2, -0.1, -0.1, -0.1, -0.1])
    s = _judge(before, after, FOLDS, MODES, 2, Significance())
    assert not s["significant"]
    assert s["significant"] != _judge(before, after, FOLDS, MODES, 2, Significance(mode_trade=1.0))["significant"]


def test_significance_needs_both_halves_and_the_effect_size():
    before, after = _residuals([0.2, 0.0, 0.2, 0.0, 0.0, 0.0, 0.0, 0.0])  # half 1 gains nothing (and 2 of 4 records)
    assert not _judge(before, after, FOLDS, MODES, 2, Significance())["significant"]
    before, after = _residuals([0.03] * 4 + [0.0] * 4)  # below min_relative_gain = 5 %
    s = _judge(before, after, FOLDS, MODES, 2, Significance())
    assert not s["significant"] and _judge(before, after, FOLDS, MODES, 2, Significance(min_relative_gain=0.01))["significant"]


def test_friction_rules_need_every_fold_up_to_four_and_all_but_one_of_five():
    """The friction-only diagnosis's fold rule, as one value of the shared `Significance` type."""
    from hdjax import FRICTION_RULES, OUTPUT_ERROR_RULES

    for folds in range(1, 6):
        for improved in range(folds + 1):
            need = folds if folds < 5 else folds - 1
            assert FRICTION_RULES.consistent(improved / folds) == (improved >= need), (folds, improved)
    assert OUTPUT_ERROR_RULES == Significance() and FRICTION_RULES.min_relative_gain == 0.01
