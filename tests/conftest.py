"""The suite runs as the commands do: float64 on, and the CPU's cores as JAX host devices
(`hdjax._sharding.use_host_devices`, before the first JAX computation), so fits, simulations and
diagnoses spread their experiments over devices. `HDJAX_HOST_DEVICES=1` runs it on one device.

Under pytest-xdist (`-n auto`, the default in pyproject.toml) each worker process takes its share
of the cores, but at least 2 host devices, so that the sharded paths (padding, masked dummy
experiments) run in every worker; measured on 2 cores, 2 workers × 2 devices and 2 workers × 1
device took the same time (191 s / 197 s on test_stepper + test_control).

JAX's strict dtype promotion is on (`jax_numpy_dtype_promotion = "strict"`): an operation that mixes
dtypes (int64 with float64, float with complex) must say so with an explicit cast, in hdjax and
in the tests alike."""

import os

import jax

from hdjax import HOST_DEVICES_ENV, available_cores, use_host_devices

_workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _workers > 1 and not os.environ.get(HOST_DEVICES_ENV):
    use_host_devices(max(2, available_cores() // _workers))
else:
    use_host_devices()
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
