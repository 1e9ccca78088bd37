"""The suite runs as the commands do: float64 on, and the CPU's cores as that many JAX host devices
(`hdjax._sharding.use_host_devices`, before the first JAX computation), so fits, simulations and
diagnoses spread their experiments over the cores. `HDJAX_HOST_DEVICES=1` runs it on one device."""

import jax

from hdjax._sharding import use_host_devices

use_host_devices()
jax.config.update("jax_enable_x64", True)
