r"""Spread the experiment axis of a stacked batch over every device with `jax.sharding`.

Every experiment of a campaign is simulated independently (one `vmap` lane each), so the natural
scale-out is data parallel: the leading `experiment` axis of a `stack_experiments` batch is split
over a one-dimensional `jax.sharding.Mesh` named `"exp"` (`NamedSharding(mesh,
PartitionSpec("exp"))`), and `map_experiments` runs each device's share of the `vmap`ped ODE
solves under `jax.shard_map`: every device steps its own experiments with its own while loops, and
no collective sits inside a solver loop. (Leaving the `vmap`ped solver loops to XLA's automatic
partitioner instead made the batched loops' termination test a cross-device reduction; the
sharded fit then deadlocked intermittently on two forced host devices, the devices waiting at
different all-reduces.) Only the reductions of Levenberg–Marquardt (residual norm, $J^\top J$)
cross devices, outside the solver loops.

The batch is padded to a multiple of the device count with *dummy experiments*: zero current and
data on the first experiment's time grid, `mask` all False. A dummy starts at rest, stays at rest,
and its residuals are zeroed by the mask like any padding, so it changes neither the cost nor the
Jacobian's information; `simulate_batch` drops the dummies from its output.

`fit_parameters` and `simulate_batch` call `shard_experiments` themselves when
`jax.device_count() > 1` (one machine with several GPUs, or a CPU run with
`XLA_FLAGS=--xla_force_host_platform_device_count=K`); nothing changes on one device.

**Several hosts.** Start the same script on every host and call, before any other JAX call,

```python
jax.distributed.initialize(coordinator_address="host0:1234", num_processes=P, process_id=k)
```

(on Slurm / Cloud TPU the arguments are found automatically: `jax.distributed.initialize()`).
`jax.devices()` then lists the devices of all hosts and the mesh spans them. Every process loads
the whole dataset (a campaign is a few MB); `shard_experiments` builds the global array with
`jax.make_array_from_callback`, each process supplying only the slices its own devices hold.
`fit_parameters` replicates its final residual and Jacobian on every device so that each process
can read the result. (Tested here on one host with several CPU devices only.)
"""

import os
import pathlib
from typing import Any

import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._data.experiment import Experiment

AXIS = "exp"


#: Environment variable: how many CPU host devices `use_host_devices` asks XLA for (default: the
#: cores this process may run on; 1 switches the spreading off).
HOST_DEVICES_ENV = "HDJAX_HOST_DEVICES"


def available_cores() -> int:
    """The CPU cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


COMPILATION_CACHE_ENV = "HDJAX_COMPILATION_CACHE"
#: Programs that compile faster than this (s) are not written to the persistent cache: the eager
#: host operations (0.01–0.1 s each) would cost more to read than to compile.
CACHE_MIN_COMPILE_S = 0.5
#: Most bytes the persistent cache holds; the least recently used programs go first.
CACHE_MAX_BYTES = 2**30


def compilation_cache_dir(environ=None) -> pathlib.Path | None:
    """Where the commands keep compiled programs: `$HDJAX_COMPILATION_CACHE` (a folder; `off` or
    `0` switches the cache off), else `$XDG_CACHE_HOME/hdjax/xla`, else `~/.cache/hdjax/xla`."""
    env = os.environ if environ is None else environ
    value = env.get(COMPILATION_CACHE_ENV, "").strip()
    if value.lower() in ("0", "off", "false", "none", "no"):
        return None
    if value:
        return pathlib.Path(value).expanduser()
    base = env.get("XDG_CACHE_HOME", "").strip() or os.path.join(os.path.expanduser("~"), ".cache")
    return pathlib.Path(base) / "hdjax" / "xla"


def use_compilation_cache(path: str | os.PathLike | None = None) -> pathlib.Path | None:
    """Switch on JAX's persistent compilation cache in `path` (default `compilation_cache_dir()`),
    so that a later run of a command reads the programs this one compiled instead of compiling them
    again. The commands call it; a library import never does. It leaves a cache folder that is
    already set (`JAX_COMPILATION_CACHE_DIR`) as it is. Returns the folder, or None when the cache
    is off or its folder cannot be made (then it warns and nothing is cached).

    JAX writes no program that holds a host callback. The simulations hold none (`FirstStep`
    keeps diffrax's check of a traced `dt0` out of them), and the LM fits report their progress
    from Python between compiled steps (`hdjax._fit.least_squares._stepped_least_squares`), so the batch
    simulation, the process-noise residuals, the paper's regressions, both LM programs and the
    diagnosis's simulation and Jacobian programs are read back. Tracing is not cached: a run still
    traces its programs (about 8 s for the HD2 joint fit's start). Measured on the 2-core machine,
    with the same results to the last bit: the shipped HD2 fit command 98.5 s with an empty cache
    and 73–80 s on later runs (2026-12-02; 109 s and 89 s on 2026-12-01, when the LM programs were
    compiled on every run); a diagnosis of a 4 + 4-record bench dataset 143 s, then 103 s
    (2026-12-01, before the LM change; its Jacobians 36 s, then 18 s)."""
    import warnings

    configured = jax.config.jax_compilation_cache_dir  # pyright: ignore[reportAttributeAccessIssue]  a jax.config option
    if configured:
        return pathlib.Path(configured)
    folder = compilation_cache_dir() if path is None else pathlib.Path(path)
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        warnings.warn(f"hdjax: the compilation cache is off: cannot make {folder} ({e}); set "
                      f"{COMPILATION_CACHE_ENV} to a writable folder, or to off.", stacklevel=2)
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", CACHE_MIN_COMPILE_S)
    jax.config.update("jax_compilation_cache_max_size", CACHE_MAX_BYTES)  # LRU, with a file lock (`filelock`)
    return folder


#: XLA flags `use_host_devices` adds for the CPU: XLA's former CPU code generator instead of its
#: fusion emitters, which compiles hdjax's programs in about 60 % of the time for up to ~10 % more
#: run time. Measured on the 2-core machine (2026-12-05): a diagnosis's Jacobian program
#: 9.4 s → 6.4 s to compile, 0.62 s → 0.66 s to run; its simulation program 4.2 s → 2.7 s, 0.29 s →
#: 0.33 s; `test_model_form_derivatives_at_zero_match_finite_differences` 15.3 s → 9.2 s of XLA
#: compilation. Compilation is most of a command's first run and of the test suite's time.
_FUSION_EMITTERS = "xla_cpu_use_fusion_emitters"
CPU_COMPILE_FLAGS = f"--{_FUSION_EMITTERS}=false"


def use_host_devices(n: int | None = None) -> int | None:
    """Let JAX see the CPU as `n` host devices (default: `$HDJAX_HOST_DEVICES`, else the cores this
    process may run on), so that `fit_parameters`, `simulate_batch` and `diagnose` spread their
    experiments over all cores. On the CPU an experiment's ODE solve runs on one core (`lax.map`,
    see `experiment_batching`), so one device leaves the other cores idle.

    It sets `XLA_FLAGS=--xla_force_host_platform_device_count=n`, which XLA reads when its
    backends start: call it before the first JAX computation. It sets no count where the flag is
    already set or for `n` ≤ 1, and does nothing once the backends have started. The commands (`hdjax fit`, ...)
    and the test suite call it; a library import never does. Returns the count set, or None.

    Before the backends start it also adds `CPU_COMPILE_FLAGS` to `XLA_FLAGS` (whatever `n`),
    unless `XLA_FLAGS` already says `xla_cpu_use_fusion_emitters` (set it `=true` there to keep
    XLA's default CPU code generator).

    Measured on the 2-core machine (`benchmarks/RESULTS.md`, 2026-11-26): a 16-record diagnosis
    363 s → 241 s with the same result; accelerators are not affected (their devices are used)."""
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        return None
    flags = os.environ.get("XLA_FLAGS", "")
    if _FUSION_EMITTERS not in flags:
        flags = f"{flags} {CPU_COMPILE_FLAGS}".strip()
        os.environ["XLA_FLAGS"] = flags
    if "xla_force_host_platform_device_count" in flags:
        return None
    if n is None:
        env = os.environ.get(HOST_DEVICES_ENV, "").strip()
        if env:
            try:
                n = int(env)
            except ValueError:
                raise ValueError(f"{HOST_DEVICES_ENV}={env!r}: give a whole number of CPU devices (1 switches spreading off).") from None
        else:
            n = available_cores()
    if n <= 1:
        return None
    # first: XLA stops reading flags at a malformed one
    os.environ["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={int(n)} {flags}".strip()
    return int(n)


def experiment_mesh(devices=None) -> Mesh:
    """A one-dimensional `Mesh` with axis name `"exp"` over `devices` (default: `jax.devices()`,
    all devices of all processes)."""
    devices = jax.devices() if devices is None else list(devices)
    return Mesh(np.asarray(devices), (AXIS,))


def pad_experiments(batch: Experiment, multiple: int) -> tuple[Experiment, int]:
    """Append masked dummy experiments so that the batch size is a multiple of `multiple`.

    A dummy has the first experiment's time grid, zero current and data, `mask` all False and
    `free = 0` (output locked): it simulates at rest and its residuals are zero.

    **Returns:** `(padded batch, number of real experiments)`.
    """
    n = int(batch.time.shape[0])
    extra = (-n) % int(multiple)
    if extra == 0:
        return batch, n

    def dummy(name, x):
        x = np.asarray(x)
        if name == "time":
            fill = np.broadcast_to(x[:1], (extra,) + x.shape[1:])
        else:
            fill = np.zeros((extra,) + x.shape[1:], dtype=x.dtype)
        return np.concatenate([x, fill])

    fields = {name: jnp.asarray(dummy(name, getattr(batch, name))) for name in Experiment.__dataclass_fields__}
    return Experiment(**fields), n


def shard_experiments(batch: Experiment, mesh: Mesh | None = None) -> tuple[Experiment, int]:
    """Pad `batch` to a multiple of the mesh size (`pad_experiments`) and place its experiment
    axis on `mesh` (default `experiment_mesh()`) with `NamedSharding(mesh, PartitionSpec("exp"))`.

    Works across processes (`jax.distributed`): every process passes the same whole batch and
    supplies the slices its devices hold.

    **Returns:** `(sharded batch, number of real experiments)`.
    """
    mesh = experiment_mesh() if mesh is None else mesh
    padded, n = pad_experiments(batch, mesh.size)
    sharding = NamedSharding(mesh, PartitionSpec(AXIS))

    def place(x):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])

    return jax.tree.map(place, padded), n


def replicated(mesh: Mesh) -> NamedSharding:
    """The sharding that keeps a whole array on every device of `mesh`."""
    return NamedSharding(mesh, PartitionSpec())


def is_concrete(batch: Any) -> bool:
    """True when the batch (an `Experiment`, or any PyTree) holds concrete arrays (not tracers inside
    `jit`/`vmap`/`grad`), i.e. when it can be padded and placed on devices."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(batch))


def map_experiments(fn, mesh: Mesh | None):
    """`fn(shared, batch)` → per-experiment outputs (leading `experiment` axis), run with
    `jax.shard_map` so that each device of `mesh` maps `fn` over its own experiments; `shared` (a
    PyTree, e.g. parameters) is replicated. With `mesh=None`, `fn` itself."""
    if mesh is None:
        return fn
    return jax.shard_map(
        fn,
        mesh=mesh,
        in_specs=(PartitionSpec(), PartitionSpec(AXIS)),
        out_specs=PartitionSpec(AXIS),
        check_vma=False,  # equinox's error branches (eqx.error_if) carry no varying-axis types
    )


def experiment_batching(*, fixed_cost: bool = False) -> str:
    """How a device runs its experiments: `"vmap"` (all at once, in lock-step) or `"map"` (one
    after the other, `jax.lax.map`).

    Default: `"map"` on the CPU, `"vmap"` on accelerators; override with the environment variable
    `HDJAX_EXPERIMENT_BATCHING=vmap|map`. Why (measured, `benchmarks/RESULTS.md`): an adaptive ODE
    solve under `vmap` runs every lane for as many steps as its slowest lane (and a vmapped
    Levenberg–Marquardt loop for as many iterations as its slowest fit), and on a CPU a batched
    step costs as much per lane as a single one — so on the CPU `vmap` pays the slowest
    experiment's cost for every experiment. On a GPU the lanes run in parallel and `vmap` wins.
    With `fixed_cost=True` (a solver whose steps cost the same in every lane, such as
    `hdjax.VelocityImplicit`) there is no slowest lane, and `vmap` is the default everywhere."""
    how = os.environ.get("HDJAX_EXPERIMENT_BATCHING", "").strip().lower()
    if how in ("vmap", "map"):
        return how
    if how:
        raise ValueError(f"HDJAX_EXPERIMENT_BATCHING={how!r}: use 'vmap' or 'map' (or leave it unset).")
    return "map" if jax.default_backend() == "cpu" and not fixed_cost else "vmap"


def for_each_experiment(fn, *batched, fixed_cost: bool = False, lapack_in_device_map: bool = False):
    """`fn(*slices)` for every index of the leading (experiment) axis of `batched`, stacked; run by
    `vmap` or `jax.lax.map` as `experiment_batching(fixed_cost=...)` says (same results either way).

    `lapack_in_device_map`: `fn` calls LAPACK (a linear solve, a least-squares step, an SVD) and
    runs inside `map_experiments` on several devices. On the CPU it is then always mapped: a
    batched LAPACK call splits its batch over XLA's CPU thread pool and waits for the parts, and
    with every device's program running on that same pool, each waiting, nothing is left to run
    them. (Measured 2026-12-04: `HDJAX_EXPERIMENT_BATCHING=vmap hdjax fit configs/hd2.yaml` on the
    2-core machine hung in the per-experiment fits, both pool threads waiting, the batched SVD of
    the LM's stopping rule waiting for its parts.)"""
    how = experiment_batching(fixed_cost=fixed_cost)
    if how == "vmap" and not (lapack_in_device_map and jax.default_backend() == "cpu"):
        return jax.vmap(fn)(*batched)
    return jax.lax.map(lambda xs: fn(*xs), batched)
