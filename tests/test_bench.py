"""The independent virtual test bench (`hdjax._testbench.independent`): physics, deviations, snr calibration, output."""

import ast
import dataclasses
import pathlib
import warnings

import numpy as np
import pytest
import yaml

from hdjax import load_dataset
from hdjax._testbench import independent as _bench

SRC = pathlib.Path(_bench.__file__)
TINY = {"n_locked": 2, "n_free": 2, "duration": 0.6}


def _sigma(truth, ch):
    s = truth["sensors"]
    return {"torque": s["torque_noise"], "motor_velocity": s["tacho_noise"], "current": s["current_noise"],
            "output_position": s["encoder_step"] / np.sqrt(12.0)}[ch]  # fmt: skip


@pytest.mark.parametrize("src", [SRC, SRC.with_name("fine_steps.py")], ids=lambda p: p.name)
def test_imports_nothing_from_hdjax_or_jax(src):
    """The bench and its compiled time loop (`fine_steps`, which the bench imports as its only
    module of the package) import neither hdjax nor JAX."""
    tree = ast.parse(src.read_text())
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level == 1 and node.module is None and [a.name for a in node.names] == ["fine_steps"]:
                assert src == SRC, "only the bench imports its time loop"
                continue
            assert node.level == 0, f"relative import `from {'.' * node.level}{node.module or ''}` in the independent bench"
            names.append(node.module)
    assert names, "no imports found"
    for n in names:
        root = n.split(".")[0]
        assert root not in {"hdjax", "jax", "jaxlib", "equinox", "diffrax", "optimistix", "lineax"}, n


def _both_loops(monkeypatch):
    """Run every `_integrate` call of the bench with the compiled loop and with the numpy reference
    (`_integrate_numpy`, on a copy of the commanded current), recording their largest relative
    difference per history."""
    diffs = []
    compiled = _bench._integrate

    def both(bench, icmd, *args, **kw):
        H = compiled(bench, icmd, *args, **kw)
        ref_kw = dict(kw)
        if kw.get("hook") is not None:  # a controller hook wrote its commands into icmd as the run went: replay them
            ref_kw["hook"] = lambda n, H_: None
        R = _bench._integrate_numpy(bench, icmd.copy(), *args, **ref_kw)
        diffs.append({k: float(np.max(np.abs(H[k] - R[k])) / max(float(np.max(np.abs(R[k]))), 1e-300)) for k in R})
        return H

    monkeypatch.setattr(_bench, "_integrate", both)
    return diffs


@pytest.mark.skipif(not _bench.fine_steps.AVAILABLE, reason="numba is not installed: the numpy loop is the only one")
@pytest.mark.parametrize("case", ["every_effect", "presliding", "lugre", "power_law_viscous", "closed_loop"])
def test_compiled_time_loop_reproduces_the_numpy_loop(case, monkeypatch):
    """`fine_steps.run_steps` (numba, per record, scalars) against `_integrate_numpy` (the
    vectorised loop it replaced, kept as the reference): the same histories to rounding, with every
    effect and deviation on, both low-speed laws and a controller hook. (They differ only in how
    numpy and LLVM round sin, exp and powers; a stick decision that flipped would show as an O(1)
    difference.)"""
    diffs = _both_loops(monkeypatch)
    bench = _bench._draw_bench("hd2", 4, _bench.Deviations(), "per_sensor", 1000.0)
    mag = {e: {"magnitude": 3.0 * _bench._first_guess(e, bench)} for e in _bench.EFFECTS}
    kw = dict(drive="hd2", seed=4, n_locked=2, n_free=2, duration=0.3)
    if case == "every_effect":
        _bench.simulate_dataset(effects={e: v for e, v in mag.items() if e != "presliding_friction"}, **kw)
    elif case == "presliding":
        _bench.simulate_dataset(effects={"presliding_friction": mag["presliding_friction"]}, **kw)
    elif case == "lugre":
        _bench.simulate_dataset(effects={"presliding_friction": mag["presliding_friction"]}, low_speed="lugre", **kw)
    elif case == "power_law_viscous":
        _bench.simulate_dataset(deviations=dataclasses.replace(_bench.Deviations(), viscous_exponent=0.6), **kw)
    else:
        b = _bench.Bench(drive="hd1", seed=5, effects={e: mag[e] for e in ("cogging", "thermal_drift", "input_delay")})
        K = 300
        ref = np.stack([20.0 * np.sin(np.linspace(0, 6, K)), 10.0 * np.sign(np.sin(np.linspace(0, 9, K)))], 1)
        b.closed_loop(_bench.pi_law(0.05, 5.0, sample_period=1e-3), ref, [False, True], current_limit=3.0, seed=1)
    assert diffs
    for d in diffs:
        assert max(d.values()) < 1e-11, d


def test_step_halving_changes_data_far_below_noise():
    kw = dict(n_locked=3, n_free=3, duration=1.0, noise="none", seed=3)
    a, truth = _bench.simulate_dataset(fine_rate=20000.0, **kw)
    b, _ = _bench.simulate_dataset(fine_rate=40000.0, **kw)
    for ch in ("torque", "motor_velocity"):
        d = np.concatenate([x["clean"][ch] - y["clean"][ch] for x, y in zip(a, b)]) / _sigma(truth, ch)
        rms, peak = float(np.sqrt(np.mean(d * d))), float(np.max(np.abs(d)))
        assert rms < 0.1, (ch, rms)
        assert peak < 1.0, (ch, peak)  # single samples at slip events and reversals


def test_motor_sticks_exactly_in_a_small_locked_test():
    recs, truth = _bench.simulate_dataset(n_locked=3, n_free=0, duration=2.0, seed=1)
    small = [r for r in recs if r["regime"] == "locked_stick"]
    assert small
    w = small[0]["clean"]["true_motor_velocity"]
    stuck = w == 0.0
    # at least one stick phase of 50 ms or more, and slipping elsewhere
    runs = np.diff(np.flatnonzero(np.diff(np.concatenate([[0], stuck.astype(int), [0]]))))[::2]
    assert runs.max() >= 50, runs
    assert np.mean(stuck) < 0.98 and np.max(np.abs(w)) > 0.02
    # the holding torque stays inside the breakaway band while stuck: |N(Km i) - T| / N <= breakaway
    c = small[0]["clean"]
    N, Km = truth["drive"]["gear_ratio"], truth["drive"]["torque_constant"]
    held = Km * c["current"][stuck] - c["true_torque"][stuck] / N
    brk = truth["low_speed"]["breakaway_torque"]
    assert np.all(held <= 1.05 * brk["p"] + 0.002) and np.all(held >= -1.05 * brk["n"] - 0.002)


DEV_KW = dict(n_locked=1, n_free=1, duration=0.5, seed=5)


@pytest.fixture(scope="module")
def all_on():
    return _bench.simulate_dataset(**DEV_KW)[0]


@pytest.mark.parametrize(
    "change",
    [
        {"drive_spread": 0.0},
        {"stiction": None},
        {"current_loop": False},
        {"pwm_ripple": 0.0},
        {"sensor_dynamics": False},
        {"tacho_ripple": 0.0},
        {"quantisation": False},
        {"offsets": None},
        {"jitter": 0.0},
    ],
)
def test_each_deviation_switch_changes_the_data(change, all_on):
    recs, truth = _bench.simulate_dataset(deviations=_bench.Deviations(**change), **DEV_KW)
    cols = ("time", "current", "motor_velocity", "torque", "output_position")
    differs = [c for r0, r1 in zip(all_on, recs) for c in cols if c in r0 and not np.array_equal(r0[c], r1[c])]
    assert differs, change
    assert truth["deviations"][next(iter(change))] == (list(change.values())[0])


def test_all_deviations_off_leaves_the_papers_model_plus_white_noise():
    recs, truth = _bench.simulate_dataset(deviations=_bench.Deviations.none(), seed=2, **TINY)
    for r in recs:
        assert np.allclose(np.diff(r["time"]), 1e-3, rtol=0, atol=1e-12)
        assert np.allclose(r["clean"]["current"], r["clean"]["commanded_current"], atol=1e-9)
        assert np.array_equal(r["clean"]["torque"], r["clean"]["true_torque"])
    assert truth["parameters"] == {k: v for k, v in truth["nominal_parameters"].items()}


@pytest.mark.parametrize("effect", ["kinematic_error", "thermal_drift", "input_delay"])
def test_calibrated_snr_is_met(effect):
    kw = dict(n_locked=2, n_free=2, duration=0.8, seed=4, noise="none")
    _, truth = _bench.simulate_dataset(effects={effect: {"snr": 3.0}}, **kw)
    e = truth["effects"][effect]
    assert e["magnitude"] > 0 and abs(e["snr"] / 3.0 - 1) < 0.05
    # check independently: simulate with the recorded physical magnitude and without the effect
    with_e, _ = _bench.simulate_dataset(effects={effect: {"magnitude": e["magnitude"], **(
        {"orders": e["orders"], "phases": e["phases"]} if "orders" in e else {}),
        **({"tau": e["tau"]} if "tau" in e else {})}}, **kw)  # fmt: skip
    without, _ = _bench.simulate_dataset(**kw)
    best = 0.0
    for ch in ("torque", "motor_velocity", "output_position"):
        x = np.array([np.sqrt(np.mean((a["clean"][ch] - b["clean"][ch]) ** 2)) for a, b in zip(with_e, without)
                      if ch != "output_position" or a["mode"] == "free"]) / _sigma(truth, ch)  # fmt: skip
        acts = x >= 0.1 * x.max()
        best = max(best, float(np.sqrt(np.mean(x[acts] ** 2))))
    assert best == pytest.approx(3.0, rel=0.15)


def test_folder_loads_with_hdjax_load_dataset(tmp_path):
    truth = _bench.make_dataset(tmp_path / "ds", drive="hd2", seed=6, effects={"cogging": {"snr": 3.0}}, **TINY)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = load_dataset(tmp_path / "ds")
    assert len(ds.experiments) == 4 and ds.modes == ["constrained"] * 2 + ["free"] * 2
    assert float(ds.drive.gear_ratio) == 160.0 and float(ds.drive.load_inertia) == 0.5
    assert len(set(ds.start_times)) == 4 and min(ds.start_times) > 0
    for exp, mode in zip(ds.experiments, ds.modes):
        t = np.asarray(exp.time)[np.asarray(exp.mask)]
        dt = np.diff(t)
        assert np.max(np.abs(dt / np.median(dt) - 1)) < 0.01 and np.std(dt) > 0  # jittered, inside the SPEC
    header = (tmp_path / "ds" / truth["experiments"][3]["file"]).read_text().splitlines()[0]
    assert header == "time,current,motor_velocity,torque,output_position"
    t = yaml.safe_load((tmp_path / "ds" / "truth.yaml").read_text())
    assert set(t["parameters"]) == {"alpha", "K1", "Tst", "Jeff", "Tvp", "Tvn", "Tsp", "Tsn", "Tssp1", "Tssn1", "Tss2"}
    assert "independent" in t["generator"] and t["seed"] == 6
    assert t["effects"]["cogging"]["orders"] == [6] and t["effects"]["cogging"]["snr"] > 0
    assert not list((tmp_path / "ds").glob("*.tmp"))


def test_same_seed_same_bytes(tmp_path):
    kw = dict(seed=11, effects={"torque_sensor_ripple": {"snr": 2.0}}, noise="per_record", **TINY)
    _bench.make_dataset(tmp_path / "a", **kw)
    _bench.make_dataset(tmp_path / "b", **kw)
    files = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert files == sorted(p.name for p in (tmp_path / "b").iterdir()) and len(files) == 6
    for f in files:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    _bench.make_dataset(tmp_path / "c", **{**kw, "seed": 12})
    assert (tmp_path / "c" / "truth.yaml").read_bytes() != (tmp_path / "a" / "truth.yaml").read_bytes()


def test_lugre_and_per_record_noise_run():
    recs, truth = _bench.simulate_dataset(low_speed="lugre", noise="per_record", seed=8, **TINY)
    assert truth["low_speed"]["law"] == "lugre"
    for r in recs:
        assert all(np.all(np.isfinite(r[c])) for c in ("current", "motor_velocity", "torque"))
    assert len({r["noise"]["torque"] for r in recs}) > 1  # scaled per record (floored at 0.1 x the sensor's)


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="unknown effect"):
        _bench.simulate_dataset(effects={"backlash": {"snr": 2}}, **TINY)
    with pytest.raises(ValueError, match="orders"):
        _bench.simulate_dataset(effects={"cogging": {"orders": [0]}}, **TINY)
    with pytest.raises(ValueError, match="drive"):
        _bench.simulate_dataset(drive="hd3", **TINY)
    with pytest.raises(ValueError, match="jitter"):
        _bench.simulate_dataset(deviations=dataclasses.replace(_bench.Deviations(), jitter=0.02), **TINY)


@pytest.mark.parametrize("drive", ["hd1", "hd2"])
def test_shipped_dataset_is_made_by_the_bench(drive):
    """`data/hd1`, `data/hd2` (what the README's quick start fits) come from this bench, not from
    hdjax's plant: the generator, the deviations (all on), the drive drawn around Table I, and for
    HD2 the order-2 strain-gauge ripple at 3× the torque noise (`scripts/make_datasets.py`)."""
    folder = pathlib.Path(__file__).resolve().parents[1] / "data" / drive
    ds = load_dataset(folder)
    truth = ds.truth
    assert truth["generator"].startswith("hdjax._bench") and truth["seed"] == {"hd1": 1001, "hd2": 2002}[drive]
    assert len(ds.indices("constrained")) == 20 and len(ds.indices("free")) == 30
    assert float(ds.drive.gear_ratio) == {"hd1": 100.0, "hd2": 160.0}[drive]
    dev = truth["deviations"]
    assert dev["current_loop"] and dev["sensor_dynamics"] and dev["quantisation"] and dev["stiction"] and dev["drive_spread"] > 0
    assert truth["low_speed"]["law"] == "stick_slip"
    nominal, drawn = truth["nominal_parameters"], truth["parameters"]
    assert 0.8 < drawn["K1"] / nominal["K1"] < 1.2 and drawn["K1"] != nominal["K1"]
    if drive == "hd1":
        assert truth["effects"] == {}
    else:  # the strain-gauge ripple the paper saw but did not model
        ripple = truth["effects"]["torque_sensor_ripple"]
        assert ripple["orders"] == [2] and ripple["snr"] == pytest.approx(3.0, rel=0.02)
    for e in ds.experiments:
        t = np.asarray(e.time)
        assert np.median(np.diff(t)) == pytest.approx(1e-3, rel=1e-3) and 1.0 <= t[-1] <= 2.0
