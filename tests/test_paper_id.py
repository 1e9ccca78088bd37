"""The paper's identification (section III) on synthetic records that satisfy eqs. 5, 8 and 9
exactly (no ODE simulation): a smooth motor trajectory is chosen, the torque follows from eq. 5 (or
is an arbitrary load torque in free motion) and the current from eq. 8, then small noise is added."""

import json
import math

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np
import pytest

from hdjax import PAPER_HD2_SI, PARAMETER_NAMES, Drive, PaperIdentification, Parameters, identify_paper, make_experiment
from hdjax._fit.paper import _consistency

# HD2-like values in SI (paper Table I, K1 and Tst read per degree)
TRUE = dict(alpha=0.5, K1=5970.0, Tst=60.2, Jeff=1e-4, Tvp=1.8e-3, Tvn=2.1e-3, Tsp=0.075, Tsn=0.033,
            Tssp1=-0.0487, Tssn1=-0.0450, Tss2=0.1)
N, KM, JLOAD = 160.0, 0.1815, 0.5
FS = 1000.0
NOISE = (0.05, 2e-3, 2e-3)  # torque (N·m), velocity (rad/s), current (A)
DRIVE = Drive(gear_ratio=N, torque_constant=KM, load_inertia=JLOAD)


def friction_exact(w, p=TRUE):
    """Eq. 9 with the exact sign() and u() (u(0) = 0)."""
    pos = (w > 0).astype(float)
    neg = (w < 0).astype(float)
    s = np.sign(w)
    e = np.exp(-((w / p["Tss2"]) ** 2))
    return (p["Tvp"] * w * pos + p["Tvn"] * w * neg + p["Tsp"] * s * pos + p["Tsn"] * s * neg
            + p["Tssp1"] * s * pos * e + p["Tssn1"] * s * neg * e)


def _sines(t, comps):
    """Motor angle θ(t), velocity ω(t) and acceleration ω'(t) of Σ a·sin(2πft + φ)."""
    th = sum(a * np.sin(2 * np.pi * f * t + ph) for a, f, ph in comps)
    w = sum(a * 2 * np.pi * f * np.cos(2 * np.pi * f * t + ph) for a, f, ph in comps)
    dw = sum(-a * (2 * np.pi * f) ** 2 * np.sin(2 * np.pi * f * t + ph) for a, f, ph in comps)
    return th, w, dw


def constrained(rng, comps, duration, theta0=0.0, with_position=False, p=TRUE):
    """Output locked: Δθ = θm/N, T from eq. 5, current from eq. 8. The recorded motor angle (when
    given) and the integrated tachometer both have an origin that differs from the true one."""
    t = np.arange(int(duration * FS)) / FS
    th, w, dw = _sines(t, comps)
    th = th + theta0
    torsion, rate = th / N, w / N
    T = p["K1"] * torsion + p["Tst"] * np.abs(rate) ** p["alpha"] * np.sign(rate)
    i = (p["Jeff"] * dw + T / N + friction_exact(w, p)) / KM
    sT, sw, si = NOISE
    kw = {}
    if with_position:
        kw["motor_position"] = th - theta0 + rng.normal(0, 1e-5, t.size)
    return make_experiment(t, i + rng.normal(0, si, t.size), T + rng.normal(0, sT, t.size),
                           w + rng.normal(0, sw, t.size), mode="constrained", **kw)


def free(rng, comps, duration, p=TRUE):
    """Free motion: any load torque T(t) (here a rigid load's), current from eq. 8."""
    t = np.arange(int(duration * FS)) / FS
    th, w, dw = _sines(t, comps)
    T = JLOAD * dw / N
    i = (p["Jeff"] * dw + T / N + friction_exact(w, p)) / KM
    sT, sw, si = NOISE
    return make_experiment(t, i + rng.normal(0, si, t.size), T + rng.normal(0, sT, t.size),
                           w + rng.normal(0, sw, t.size), mode="free", output_position=th / N - T / p["K1"])


def dataset(seed=0):
    """5 constrained (one slow), 4 fast free, 2 slow free; lengths 3–4 s so the batch is padded."""
    rng = np.random.default_rng(seed)
    return [
        constrained(rng, [(1.0, 1.0, 0.0), (0.3, 2.7, 1.0)], 4.0, theta0=0.3),
        constrained(rng, [(0.8, 0.7, 0.5), (0.2, 3.1, 0.0)], 3.5, theta0=-0.2, with_position=True),
        constrained(rng, [(1.2, 1.3, 0.2)], 3.0, theta0=0.1),
        free(rng, [(3.0, 1.5, 0.0), (0.8, 4.1, 0.3)], 4.0),
        free(rng, [(2.5, 2.0, 1.0), (1.0, 3.3, 0.0)], 3.5),
        constrained(rng, [(0.6, 0.5, 1.0), (0.4, 1.9, 2.0)], 4.0, theta0=0.05, with_position=True),
        free(rng, [(4.0, 1.1, 0.4), (0.5, 5.3, 0.1)], 4.0),
        free(rng, [(2.0, 2.5, 2.0)], 3.0),
        free(rng, [(0.08, 0.6, 0.0), (0.02, 1.7, 0.5)], 4.0),
        free(rng, [(0.06, 0.8, 0.3), (0.03, 1.3, 1.5)], 4.0),
        constrained(rng, [(0.08, 0.5, 0.0), (0.02, 1.1, 0.7)], 4.0, theta0=0.02),
    ]


CONSTRAINED = [0, 1, 2, 5, 10]
FAST_FREE = [3, 4, 6, 7]
SLOW = [8, 9, 10]


@pytest.fixture(scope="module")
def experiments():
    return dataset()


@pytest.fixture(scope="module")
def result(experiments):
    return identify_paper(experiments, DRIVE)


def _rel(name, r):
    return abs(r.estimates[name] - TRUE[name]) / abs(TRUE[name])


def test_compliance_recovery(result):
    for name in ("K1", "Tst"):
        assert _rel(name, result) < 0.02, (name, result.estimates[name])
        assert result.consistency[name] < 0.02
        assert result.experiment_indices[name] == CONSTRAINED
    assert result.estimates["alpha"] == 0.5 and result.consistency["alpha"] == 0.0
    # torsion offsets: the true θm(0)/N minus the recorded origin
    offsets = result.details["torsion_offset"]
    assert offsets[0] == pytest.approx((0.3 + 0.3 * np.sin(1.0)) / N, rel=0.02)
    assert offsets[1] == pytest.approx(-0.2 / N, rel=0.02)


def test_alpha_nonlinear(result):
    nl = result.alpha_nonlinear
    assert nl["indices"] == CONSTRAINED
    assert all(nl["converged"])
    assert all(abs(a - TRUE["alpha"]) < 0.03 for a in nl["alpha"]), nl["alpha"]
    assert abs(nl["mean"] - TRUE["alpha"]) < 0.03
    assert nl["consistency"] < 0.05
    assert all(abs(k - TRUE["K1"]) / TRUE["K1"] < 0.02 for k in nl["K1"])


def test_friction_recovery(result):
    for name in ("Jeff", "Tvp", "Tvn", "Tsp", "Tsn"):
        assert _rel(name, result) < 0.03, (name, result.estimates[name])
        assert result.consistency[name] < 0.05, (name, result.consistency[name])
        assert result.experiment_indices[name] == FAST_FREE
    for name in ("Tssp1", "Tssn1"):
        assert _rel(name, result) < 0.10, (name, result.estimates[name])
        assert result.consistency[name] < 0.10
        assert result.experiment_indices[name] == SLOW
    assert result.details["low_velocity_experiments"] == SLOW
    assert result.estimates["Tss2"] == 0.1


def test_result_layout(result, experiments):
    assert set(result.estimates) == set(PARAMETER_NAMES)
    for name in PARAMETER_NAMES:
        assert len(result.per_experiment[name]) == len(experiments)
        finite = [i for i, v in enumerate(result.per_experiment[name]) if math.isfinite(v)]
        assert finite == result.experiment_indices[name]
    assert result.undetermined() == []
    p = result.parameters()
    assert isinstance(p, Parameters)
    assert float(p.K1) == pytest.approx(result.estimates["K1"])
    json.dumps(result.to_dict(), allow_nan=False)


def test_constrained_only_leaves_friction_undetermined(experiments):
    # same padded length and count as the full run's constrained subset: reuses its compilation
    r = identify_paper([experiments[i] for i in CONSTRAINED], DRIVE)
    assert _rel("K1", r) < 0.02 and _rel("Tst", r) < 0.02
    for name in ("Jeff", "Tvp", "Tvn", "Tsp", "Tsn", "Tssp1", "Tssn1"):
        assert math.isnan(r.estimates[name])
        assert r.experiment_indices[name] == []
        assert all(math.isnan(v) for v in r.per_experiment[name])
    text = "\n".join(r.notes)
    assert "no free-motion experiments" in text and "Jeff, Tvp, Tvn, Tsp, Tsn undetermined" in text
    assert "Tssp1, Tssn1 undetermined" in text
    p = r.parameters()  # NaN replaced by the documented fallback
    assert float(p.Jeff) == PAPER_HD2_SI["Jeff"] and float(p.K1) == pytest.approx(r.estimates["K1"])
    json.dumps(r.to_dict(), allow_nan=False)


def test_free_only_leaves_compliance_undetermined(experiments):
    r = identify_paper([experiments[i] for i in FAST_FREE], DRIVE)
    assert _rel("Jeff", r) < 0.03 and _rel("Tsp", r) < 0.03
    for name in ("K1", "Tst", "Tssp1", "Tssn1"):
        assert math.isnan(r.estimates[name])
    assert math.isnan(r.alpha_nonlinear["mean"]) and r.alpha_nonlinear["alpha"] == []
    text = "\n".join(r.notes)
    assert "no constrained" in text and "no low-velocity experiments" in text


def test_one_direction_experiment_gives_nan_and_reason():
    rng = np.random.default_rng(3)
    # ω = 6 + 3 sin(...) > 0 throughout: the negative-direction terms cannot be determined
    t = np.arange(2000) / FS
    w = 6.0 + 3.0 * np.sin(2 * np.pi * 2.0 * t)
    dw = 3.0 * 2 * np.pi * 2.0 * np.cos(2 * np.pi * 2.0 * t)
    th = 6.0 * t - 3.0 / (2 * np.pi * 2.0) * np.cos(2 * np.pi * 2.0 * t)
    T = JLOAD * dw / N
    i = (TRUE["Jeff"] * dw + T / N + friction_exact(w)) / KM
    exp = make_experiment(t, i + rng.normal(0, 2e-3, t.size), T + rng.normal(0, 0.05, t.size),
                          w + rng.normal(0, 2e-3, t.size), mode="free", output_position=th / N)
    r = identify_paper([exp], DRIVE, nonlinear=False)
    assert math.isnan(r.estimates["Tvn"]) and math.isnan(r.estimates["Tsn"])
    # one velocity range (3–9 rad/s) still separates Jeff, Tvp, Tsp
    assert _rel("Jeff", r) < 0.03 and _rel("Tvp", r) < 0.03 and _rel("Tsp", r) < 0.03
    assert any("experiment 0 (free): fewer than 50 samples" in n and "Tvn, Tsn" in n for n in r.notes)
    assert math.isnan(r.consistency["Tvp"])  # a single experiment: consistency undefined


def test_no_experiments_does_not_raise():
    r = identify_paper([], DRIVE)
    assert isinstance(r, PaperIdentification)
    assert r.undetermined() == [k for k in PARAMETER_NAMES if k not in ("alpha", "Tss2")]
    assert r.notes


def test_consistency_measure():
    assert _consistency([1.0, 2.0, 3.0, float("nan")]) == pytest.approx(np.std([1, 2, 3], ddof=1) / 2.0)
    assert math.isnan(_consistency([1.0]))
    assert _consistency([-2.0, -2.0]) == 0.0
