"""The virtual test rig: sensor models, campaign design and effect hiding (the shipped datasets come from the independent bench: `test_bench.py`)."""

import numpy as np
import pytest

import hdjax
from hdjax import load_dataset
from hdjax._testbench import rig as _rig

TINY = {"n_constrained": 2, "n_free": 2, "duration": 0.3}


@pytest.fixture(scope="module")
def tiny_hd1():
    station = _rig.station_hd1()
    return station, _rig.run_campaign(station, seed=7, **TINY)


def test_stations_match_table_i():
    for station, N, Km, Jl in ((_rig.station_hd1(), 100, 0.0543, 0.2), (_rig.station_hd2(), 160, 0.1815, 0.5)):
        d = station.drive
        assert (float(d.gear_ratio), float(d.torque_constant), float(d.load_inertia)) == (N, Km, Jl)
        assert station.sample_rate == 1000.0
    hd2 = _rig.station_hd2().truth
    assert float(hd2.K1) == pytest.approx(104.2 * 180 / np.pi)  # per-degree reading of Table I
    assert float(hd2.Tst) == pytest.approx(7.96 * (180 / np.pi) ** 0.5)


def test_campaign_profiles():
    station = _rig.station_hd1()
    profiles = _rig.campaign(station, seed=3)
    assert [p.mode for p in profiles].count("constrained") == 20
    assert [p.mode for p in profiles].count("free") == 30
    assert len({p.name for p in profiles}) == 50
    assert {p.kind for p in profiles} == {"sine", "chirp", "square", "multisine"}
    regimes = [p.regime for p in profiles if p.mode == "free"]
    assert regimes.count("low_velocity") >= 6 and regimes.count("high_velocity") >= 10
    for p in profiles:
        name, mode, current = p  # unpacks as the triple
        assert current.shape == p.time.shape == (1500,)
        assert current[0] == 0.0 and np.all(np.isfinite(current))
        assert np.max(np.abs(current[:10])) < 0.2 * np.max(np.abs(current))  # ramps up from rest
    assert np.array_equal(profiles[5].current, _rig.campaign(station, seed=3)[5].current)  # seeded


def test_sensor_noise_statistics(tiny_hd1):
    station, runs = tiny_hd1
    assert len(runs) == 4
    err = {"torque": [], "motor_velocity": [], "current": []}
    for r in runs:
        file, mode, exp, start = r  # unpacks as the 4-tuple
        assert file == r.profile.name + ".csv" and float(exp.start_time) == start
        for k in err:
            err[k].append(np.asarray(getattr(exp, k)) - r.clean[k])
    for k, sd in (("torque", station.torque_noise), ("motor_velocity", station.tacho_noise),
                  ("current", station.current_noise)):  # fmt: skip
        e = np.concatenate(err[k])
        assert np.std(e) == pytest.approx(sd, rel=0.2), k
        assert abs(np.mean(e)) < 4 * sd / np.sqrt(len(e)), k  # white, zero mean
    assert [r.start_time for r in runs] == [0.0, 30.0, 60.0, 90.0]


def test_encoder_quantisation(tiny_hd1):
    station, runs = tiny_hd1
    q = station.encoder_step
    assert q == pytest.approx(2 * np.pi / 2**16)
    moved = 0.0
    for r in runs:
        exp = r.experiment
        if r.mode == "constrained":
            assert float(exp.has_output_position) == 0.0  # no output_position column
            continue
        counts = np.asarray(exp.output_position) / q
        np.testing.assert_allclose(counts, np.round(counts), atol=1e-9)
        assert np.max(np.abs(np.asarray(exp.output_position) - r.clean["output_position"])) <= q / 2 + 1e-12
        moved = max(moved, np.ptp(counts))
    assert moved > 20  # through many counts


def test_write_campaign_round_trip(tiny_hd1, tmp_path):
    station, runs = tiny_hd1
    _rig.write_campaign(tmp_path / "tiny", station, runs, name="tiny", truth_extra={"seed": 7})
    ds = load_dataset(tmp_path / "tiny")
    assert ds.files == [r.file for r in runs] and ds.start_times == [r.start_time for r in runs]
    assert ds.truth["parameters"] == station.truth.to_dict() and ds.truth["effects"] == {}
    assert ds.truth["sensors"]["torque_noise"] == station.torque_noise and ds.truth["seed"] == 7
    for r, e in zip(runs, ds.experiments):  # 7 significant digits
        np.testing.assert_allclose(np.asarray(e.torque), np.asarray(r.experiment.torque), rtol=1e-6, atol=1e-9)


def _harmonics(theta, y, orders=(1, 2, 3)):
    """Joint least-squares amplitudes and phases of `a_k·sin(k·θ + φ_k)` in `y` (with an offset)."""
    cols = [f(k * theta) for k in orders for f in (np.sin, np.cos)]
    coef = np.linalg.lstsq(np.column_stack(cols + [np.ones_like(theta)]), y, rcond=None)[0]
    s, c = coef[0:-1:2], coef[1:-1:2]
    return dict(zip(orders, np.hypot(s, c))), dict(zip(orders, np.arctan2(c, s)))


def test_hide_effect_ripple_shows_at_order_2():
    station = _rig.station_hd2()
    effects = _rig.hide_effect("torque_sensor_ripple", None, order=2, phase=0.3, station=station)
    amp = _rig.reference_magnitude("torque_sensor_ripple", station)
    assert amp == pytest.approx(3 * station.torque_noise)
    profiles = [p for p in _rig.campaign(station, seed=5, n_constrained=0, n_free=4, duration=0.8)
                if p.regime != "low_velocity"][:2]  # fmt: skip
    hidden = _rig.run_campaign(station, seed=1, profiles=profiles, effects=effects)
    theta = np.concatenate([r.clean["motor_position"] for r in hidden])
    assert np.ptp(theta) > 2 * np.pi  # at least a wave-generator turn (two ripple periods)
    # the recorded torque minus the flexspline's true torque (eq. 5 on the true states) is the
    # strain-gauge noise plus the ripple, which stands at order 2
    N = float(station.drive.gear_ratio)
    true_T = [hdjax.compliance_torque(station.truth, r.clean["torsion"],
                                      r.clean["motor_velocity"] / N - r.clean["output_velocity"]) for r in hidden]
    resid = np.concatenate([np.asarray(r.experiment.torque) - np.asarray(T) for r, T in zip(hidden, true_T)])
    a, phi = _harmonics(theta, resid)
    assert a[2] == pytest.approx(amp, rel=0.1) and phi[2] == pytest.approx(0.3, abs=0.1)
    assert a[1] < 0.1 * amp and a[3] < 0.1 * amp
    assert np.std(resid - amp * np.sin(2 * theta + 0.3)) == pytest.approx(station.torque_noise, rel=0.1)
    assert _rig.describe_effects(effects) == {"torque_sensor_ripple": {
        "form": "a_k*sin(k*theta_m + phi_k)", "orders": [2], "amplitudes": [pytest.approx(amp)],
        "phases": [pytest.approx(0.3)], "unit": "N·m"}}  # fmt: skip


@pytest.mark.parametrize("name", list(_rig.EFFECT_UNITS))
def test_hide_effect_every_name(name):
    station = _rig.station_hd1()
    e = _rig.hide_effect(name, None, station=station)
    assert e.active == frozenset({name})
    record = _rig.describe_effects(e)[name]
    ref = _rig.reference_magnitude(name, station)
    value = record["amplitudes"][0] if "amplitudes" in record else next(iter(record.values()))
    assert value == pytest.approx(ref) and ref > 0
    assert _rig.hide_effect(name, 2 * ref, station=station, base=e).active == frozenset({name})


def test_hide_effect_rejects_unknown():
    with pytest.raises(ValueError, match="unknown effect"):
        _rig.hide_effect("backlashh", 1e-4, station=_rig.station_hd1())
