"""Sharding the experiment axis over several devices gives the one-device result.

The same small problem (3 experiments, so the batch is padded with one masked dummy to fill 2
devices) is run in two fresh processes: one with a single CPU device and one with
`XLA_FLAGS=--xla_force_host_platform_device_count=2`; the sharded run must place the batch on both
devices and reproduce the simulation and the fitted parameters to round-off."""

import json
import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest

SCRIPT = r"""
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
sys.path.insert(0, sys.argv[1])
from helpers import hd2
import hdjax
from hdjax import fit_parameters
from hdjax._plant.sharding import shard_experiments

p, drive = hd2()
rng = np.random.default_rng(0)
t = np.arange(0.0, 0.1, 1e-3)
sim = hdjax.Simulator(solver=hdjax.VelocityImplicit(substeps=1))  # the fit's fixed-step plant: quick to compile, same sharding path
exps = []
for mode, A, f in (("constrained", 2.0, 5.0), ("free", 1.5, 3.0), ("free", 0.8, 2.0)):
    i = A * np.sin(2 * np.pi * f * t) * np.minimum(1.0, t / 0.05)
    z = np.zeros_like(t)
    tr = hdjax.simulate(p, drive, hdjax.make_experiment(t, i, z, z, mode=mode, output_position=z), simulator=sim)
    pos = np.round(np.asarray(tr.output_position) / 1e-4) * 1e-4 if mode == "free" else None
    exps.append(hdjax.make_experiment(
        t, i + rng.normal(0, 2e-3, len(t)), np.asarray(tr.torque) + rng.normal(0, 0.1, len(t)),
        np.asarray(tr.motor_velocity) + rng.normal(0, 0.03, len(t)), mode=mode, output_position=pos))
batch = hdjax.stack_experiments(exps)
sharded, n = shard_experiments(batch)
traj = hdjax.simulate_batch(p, drive, batch, simulator=sim)
start = p.replace(K1=p.K1 * 1.2, Jeff=p.Jeff * 0.8, Tsp=p.Tsp * 1.3)
res = fit_parameters(start, drive, batch, free=("K1", "Jeff", "Tsp"), simulator=sim, max_steps=4, throw=False)
print(json.dumps({
    "devices": jax.device_count(),
    "batch_devices": len(sharded.time.sharding.device_set),
    "padded": int(sharded.time.shape[0]), "real": n,
    "torque": np.asarray(traj.torque).tolist(),
    "motor_velocity": np.asarray(traj.motor_velocity).tolist(),
    "params": {k: float(getattr(res.params, k)) for k in ("K1", "Jeff", "Tsp")},
    "chi2": res.chi2_reduced, "steps": res.steps,
}))
"""


def _cpu_env(n_devices: int = 1) -> dict:
    """This process's environment on the CPU with `n_devices` host devices (1: no count flag, and
    no `HDJAX_HOST_DEVICES`, so that `use_host_devices` decides)."""
    env = dict(os.environ)
    flags = [f for f in env.get("XLA_FLAGS", "").split() if "device_count" not in f]
    if n_devices > 1:  # first: XLA stops reading flags at a malformed one
        flags.insert(0, f"--xla_force_host_platform_device_count={n_devices}")
    env["XLA_FLAGS"] = " ".join(flags)
    env["JAX_PLATFORMS"] = "cpu"
    env.pop("HDJAX_HOST_DEVICES", None)
    return env


def _start(n_devices: int) -> subprocess.Popen:
    here = str(pathlib.Path(__file__).resolve().parent)
    return subprocess.Popen([sys.executable, "-c", SCRIPT, here], env=_cpu_env(n_devices), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _result(proc: subprocess.Popen) -> dict:
    try:
        out, err = proc.communicate(timeout=300)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    assert proc.returncode == 0, err[-3000:]
    return json.loads(out.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def runs():
    """Both processes at once (each compiles on one thread most of its time)."""
    procs = [_start(1), _start(2)]
    try:
        return tuple(_result(p) for p in procs)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.communicate()


def test_batch_is_padded_and_spread_over_both_devices(runs):
    one, two = runs
    assert one["devices"] == 1 and one["padded"] == 3 and one["batch_devices"] == 1
    assert two["devices"] == 2 and two["padded"] == 4 and two["real"] == 3 and two["batch_devices"] == 2


def test_sharded_simulation_matches_one_device(runs):
    one, two = runs
    for k in ("torque", "motor_velocity"):
        a, b = np.asarray(one[k]), np.asarray(two[k])
        assert a.shape == b.shape == (3, 100)  # dummies dropped
        np.testing.assert_allclose(b, a, rtol=1e-10, atol=1e-10 * np.max(np.abs(a)))


def test_sharded_fit_matches_one_device(runs):
    one, two = runs
    assert one["steps"] == two["steps"]
    for k, v in one["params"].items():
        assert abs(two["params"][k] / v - 1) < 1e-8, (k, v, two["params"][k])
    assert abs(two["chi2"] / one["chi2"] - 1) < 1e-8
    # the fit moved away from the perturbed start (the comparison is not of two untouched starts)
    assert abs(one["params"]["K1"] / (1.2 * 104.2 * 180 / np.pi) - 1) > 0.05


def test_use_host_devices_sets_the_count_before_jax_starts_and_import_starts_nothing():
    """`import hdjax` must not start JAX's backends (else the commands could not spread experiments
    over the cores), nor import matplotlib (only `hdjax.plotting` and the commands' figure step
    do); `use_host_devices(3)` then gives three CPU devices, and a second call (flag already set)
    changes nothing. The CPU compile flags are added once, and a user's own setting of them is kept."""
    script = (
        "import os, sys, hdjax, hdjax.bench, hdjax.fit, hdjax.diagnose\n"
        "from jax._src import xla_bridge\n"
        "started = xla_bridge.backends_are_initialized() or 'matplotlib' in sys.modules\n"
        "from hdjax._plant.sharding import use_host_devices\n"
        "n = use_host_devices(3)\n"
        "again = use_host_devices(5)\n"
        "import jax\n"
        "print(started, n, again, jax.device_count(), [f for f in os.environ['XLA_FLAGS'].split() if 'fusion_emitters' in f])\n"
    )
    env = _cpu_env()
    env["XLA_FLAGS"] = " ".join(f for f in env["XLA_FLAGS"].split() if "fusion_emitters" not in f)
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.split() == ["False", "3", "None", "3", "['--xla_cpu_use_fusion_emitters=false']"], out.stdout
    env["XLA_FLAGS"] = "--xla_cpu_use_fusion_emitters=true"  # the user's own setting is kept
    own = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
    assert own.returncode == 0, own.stderr[-3000:]
    assert own.stdout.split() == ["False", "3", "None", "3", "['--xla_cpu_use_fusion_emitters=true']"], own.stdout


def test_the_compilation_cache_folder_follows_the_environment(tmp_path):
    """`HDJAX_COMPILATION_CACHE` names the commands' cache folder or switches it off; else it is
    `$XDG_CACHE_HOME/hdjax/xla`, else `~/.cache/hdjax/xla`."""
    import pathlib

    from hdjax import COMPILATION_CACHE_ENV, compilation_cache_dir

    assert compilation_cache_dir({COMPILATION_CACHE_ENV: str(tmp_path)}) == tmp_path
    for off in ("off", "0", "OFF", "none"):
        assert compilation_cache_dir({COMPILATION_CACHE_ENV: off}) is None
    assert compilation_cache_dir({"XDG_CACHE_HOME": "/x/cache"}) == pathlib.Path("/x/cache/hdjax/xla")
    assert compilation_cache_dir({}) == pathlib.Path.home() / ".cache" / "hdjax" / "xla"
    assert compilation_cache_dir({COMPILATION_CACHE_ENV: " "}) == pathlib.Path.home() / ".cache" / "hdjax" / "xla"


def test_lapack_in_a_device_map_is_mapped_on_the_cpu_whatever_the_batching(monkeypatch):
    """A function that calls LAPACK inside the device map runs one experiment after the other on the
    CPU even where `HDJAX_EXPERIMENT_BATCHING=vmap` asks for lock-step lanes: a batched LAPACK call
    there waits on the thread pool every device's program occupies (the per-experiment fits of
    `hdjax fit` hung on two CPU devices, 2026-12-04). Without LAPACK the override is followed."""
    import jax
    import jax.numpy as jnp

    from hdjax._plant.sharding import for_each_experiment

    monkeypatch.setenv("HDJAX_EXPERIMENT_BATCHING", "vmap")
    x = jnp.stack([jnp.eye(3) * (k + 1.0) for k in range(4)])
    fn = lambda a: jnp.linalg.solve(a, jnp.ones(3))
    mapped = str(jax.make_jaxpr(lambda a: for_each_experiment(fn, a, lapack_in_device_map=True))(x))
    batched = str(jax.make_jaxpr(lambda a: for_each_experiment(fn, a))(x))
    assert jax.default_backend() == "cpu"
    assert "scan" in mapped and "scan" not in batched
    np.testing.assert_allclose(for_each_experiment(fn, x, lapack_in_device_map=True), for_each_experiment(fn, x))
