"""The suite runs as the commands do: float64 on, and the CPU's cores as JAX host devices
(`hdjax._plant.sharding.use_host_devices`, before the first JAX computation), so fits, simulations and
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
physical axis, e.g. `Float[Array, "*exp time"]`). `hdjax._testbench.independent` is left out (`UNCHECKED`): it is
numpy code written apart from hdjax, with no array annotations to check, and its integrator calls
small functions ~10⁵ times per dataset; the checker's wrapper on each call made it 5.3× slower
(a 4 + 4 × 1.5 s dataset: 28.9 s against 5.5 s), which the suite paid in every test that makes
bench data. Its time loop `hdjax._testbench.fine_steps` is left out too: numba compiles the
functions themselves, and cannot compile a checker's wrapper. `HDJAX_RUNTIME_TYPECHECK=0` runs
without the checker."""

import importlib.util
import os
import pathlib

# the commands keep compiled programs in a persistent cache (`hdjax.use_compilation_cache`); the
# commands that tests run in-process or in a subprocess do not write to the user's cache folder
os.environ.setdefault("HDJAX_COMPILATION_CACHE", "off")

import jaxtyping

#: hdjax modules the runtime type checker leaves out, and why (see the module docstring).
UNCHECKED = {
    "hdjax._testbench.independent": "numpy-only independent bench, no array annotations; 5.3x slower when wrapped",
    "hdjax._testbench.fine_steps": "the bench's time loop, compiled by numba: a checker's wrapper cannot be compiled",
}


def checked_modules() -> list[str]:
    """Every module of the hdjax package, sub-packages included (found on disk, without importing
    anything: importing a sub-package would import `hdjax` before the hook), but `UNCHECKED`."""
    spec = importlib.util.find_spec("hdjax")
    assert spec is not None and spec.submodule_search_locations is not None
    found = []
    for root in spec.submodule_search_locations:
        for path in sorted(pathlib.Path(root).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            if parts:
                found.append(".".join(("hdjax", *parts)))
    # the hook matches a name and everything below it: a package that holds an unchecked module is
    # left out itself (its modules are listed one by one)
    def holds_unchecked(m: str) -> bool:
        return any(u == m or u.startswith(m + ".") for u in UNCHECKED)

    return sorted(m for m in found if not holds_unchecked(m))


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
