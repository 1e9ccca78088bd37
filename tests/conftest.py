"""The suite runs as the commands do: float64 on, and the CPU's cores as JAX host devices
(`hdjax._sharding.use_host_devices`, before the first JAX computation), so fits, simulations and
diagnoses spread their experiments over devices. `HDJAX_HOST_DEVICES=1` runs it on one device.

Under pytest-xdist (`-n auto`, the default in pyproject.toml) each worker process takes its share
of the cores, but at least 2 host devices, so that the sharded paths (padding, masked dummy
experiments) run in every worker; measured on 2 cores, 2 workers × 2 devices and 2 workers × 1
device took the same time (191 s / 197 s on test_stepper + test_control).

JAX's strict dtype promotion is on (`jax_numpy_dtype_promotion = "strict"`): an operation that mixes
dtypes (int64 with float64, float with complex) must say so with an explicit cast, in hdjax and
in the tests alike.

**Runtime type checks.** Every hdjax module but the independent bench is imported through
jaxtyping's import hook with beartype (installed below, before anything imports hdjax): each
function and Module is checked on every call against its annotations (shapes and dtypes named by
physical axis, e.g. `Float[Array, "*exp time"]`). `hdjax._bench` is left out (`UNCHECKED`): it is
numpy code written apart from hdjax, with no array annotations to check, and its integrator calls
small functions ~10⁵ times per dataset; the checker's wrapper on each call made it 5.3× slower
(a 4 + 4 × 1.5 s dataset: 28.9 s against 5.5 s), which the suite paid in every test that makes
bench data. `HDJAX_RUNTIME_TYPECHECK=0` runs without the checker."""

import importlib.util
import os
import pkgutil

# the commands keep compiled programs in a persistent cache (`hdjax.use_compilation_cache`); the
# commands that tests run in-process or in a subprocess do not write to the user's cache folder
os.environ.setdefault("HDJAX_COMPILATION_CACHE", "off")

import jaxtyping
import pytest

#: hdjax modules the runtime type checker leaves out, and why (see the module docstring).
UNCHECKED = {"hdjax._bench": "numpy-only independent bench, no array annotations; 5.3x slower when wrapped"}


def checked_modules() -> list[str]:
    """Every module of the hdjax package (found on disk, without importing it) but `UNCHECKED`."""
    spec = importlib.util.find_spec("hdjax")
    assert spec is not None and spec.submodule_search_locations is not None
    found = ["hdjax." + m.name for m in pkgutil.iter_modules(list(spec.submodule_search_locations))]
    return sorted(m for m in found if m not in UNCHECKED)


if os.environ.get("HDJAX_RUNTIME_TYPECHECK", "1") != "0":
    jaxtyping.install_import_hook(checked_modules(), "beartype.beartype")

import jax  # noqa: E402  (after the import hook, so that hdjax is imported through it)

from hdjax import HOST_DEVICES_ENV, available_cores, use_host_devices  # noqa: E402

_workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _workers > 1 and not os.environ.get(HOST_DEVICES_ENV):
    use_host_devices(max(2, available_cores() // _workers))
else:
    use_host_devices()
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


# ----------------------------------------------------------------------------------------------
# Longest first: the order in which the two xdist workers take the suite's work.
#
# Half of the suite's worker time is 15 bench diagnoses (`test_diagnose_bench.py`, 54 % of 3 480
# worker-seconds on 2026-12-02), the longest 460 s. pytest-xdist's `load` scheduling sends tests in
# collection order, so those ran last and one worker finished alone: 2 093 s of wall time against
# 1 740 s of work per worker. Here the work goes out in units (`scope_of`: one test of the bench
# file, otherwise a whole module, so a module-scoped fixture is built once) from the largest to the
# smallest (`SCOPE_COST`), each to the next free worker: longest-processing-time-first, whose
# makespan on the measured costs is the per-worker share. The costs only order the work; a wrong
# or missing figure costs time, never a result.

#: Measured worker-seconds of each test module on the 2-core machine (2026-12-02, two workers,
#: `--durations=0`); a module not listed counts `DEFAULT_TEST_COST` per test.
SCOPE_COST = {
    "test_fit.py": 230, "test_bench.py": 180, "test_sharding.py": 130, "test_model_form.py": 120,
    "test_control.py": 110, "test_stepper.py": 110, "test_friction.py": 100, "test_solver.py": 95,
    "test_plant.py": 90, "test_sensitivity.py": 85, "test_fit_bench.py": 75, "test_diagnose.py": 75,
    "test_effects.py": 70, "test_tune_design.py": 30, "test_model.py": 20,
}  # fmt: skip
#: The files whose tests are scheduled one by one (they share no module fixture); each test counts
#: its `cost(seconds)` mark, else this many seconds.
SPLIT_FILES = {"test_diagnose_bench.py": 120.0}
DEFAULT_TEST_COST = 1.0


def scope_of(nodeid: str) -> str:
    """The unit of work a worker takes whole: the test itself in `SPLIT_FILES`, else its module."""
    path = nodeid.split("::", 1)[0]
    return nodeid if path.rsplit("/", 1)[-1] in SPLIT_FILES else path


def pytest_collection_modifyitems(config, items):
    """Units of work longest first (within a unit, the collection order)."""
    cost: dict[str, float] = {}
    for item in items:
        name = item.nodeid.split("::", 1)[0].rsplit("/", 1)[-1]
        mark = item.get_closest_marker("cost")
        if mark is not None:
            c = float(mark.args[0])
        elif name in SPLIT_FILES:
            c = SPLIT_FILES[name]
        else:
            c = DEFAULT_TEST_COST
        unit = scope_of(item.nodeid)
        cost[unit] = cost.get(unit, 0.0) + c
    for unit in cost:
        name = unit.split("::", 1)[0].rsplit("/", 1)[-1]
        if unit == unit.split("::", 1)[0] and name in SCOPE_COST:
            cost[unit] = float(SCOPE_COST[name])
    order = {unit: k for k, unit in enumerate(dict.fromkeys(scope_of(i.nodeid) for i in items))}
    items.sort(key=lambda i: (-cost[scope_of(i.nodeid)], order[scope_of(i.nodeid)]))


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist, absent under `-p no:xdist`
def pytest_xdist_make_scheduler(config, log):
    """xdist's scope scheduling over `scope_of`'s units, in the collection order that
    `pytest_collection_modifyitems` set (not re-sorted by test count)."""
    from xdist.scheduler import LoadScopeScheduling

    class LongestFirst(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return scope_of(nodeid)

    config.option.loadscopereorder = False
    return LongestFirst(config, log)
