"""Benchmark (not a test): diagnose a 16-experiment dataset (8 constrained + 8 free, 2.5 s at
1 kHz) from the independent bench (`hdjax._testbench.independent`, not hdjax's plant) with one hidden SPEC §4
effect at 4× the sensor noise; goal under 3 minutes on the 2-core CI machine. The many-seed
recall figure is `benchmarks/diagnose_independent.py`; this one times a single dataset.

Usage: `python benchmarks/diagnose_16.py [EFFECT|none] [hd1|hd2]` (default: kinematic_error hd1).
Prints the stage timings, the findings and the truth.
"""

import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

from hdjax import use_host_devices  # noqa: E402

use_host_devices()  # every CPU core simulates its share of the experiments (HDJAX_HOST_DEVICES=1: one)

import tempfile  # noqa: E402

from hdjax import diagnose_effects as diagnose, identify_paper, load_dataset  # noqa: E402
from hdjax.bench import make_dataset  # noqa: E402

effect = sys.argv[1] if len(sys.argv) > 1 else "kinematic_error"
drive = sys.argv[2] if len(sys.argv) > 2 else "hd1"
spec = {"snr": 4.0, "channels": ["torque", "motor_velocity"]}
if effect in ("kinematic_error", "torque_sensor_ripple", "cogging", "position_dependent_friction"):
    spec["orders"] = [2]
t0 = time.perf_counter()
with tempfile.TemporaryDirectory() as tmp:
    make_dataset(tmp, drive=drive, seed=11, n_locked=8, n_free=8, duration=2.5,
                 effects=None if effect == "none" else {effect: spec})
    ds = load_dataset(tmp)
exps = [ds.experiments[i] for i in ds.dynamic_indices()]
t_rig = time.perf_counter() - t0
print(f"bench data: {len(exps)} experiments × 2.5 s in {t_rig:.1f} s (not part of the benchmark)")
t0 = time.perf_counter()
paper = identify_paper(exps, ds.drive)
t_paper = time.perf_counter() - t0
d = diagnose(paper.parameters(), ds.drive, exps, log=print)
total = time.perf_counter() - t0
print(f"paper identification: {t_paper:.1f} s")
for k, v in d.timing.items():
    print(f"timing_{k}_s: {v:.1f}")
print(f"hidden: {effect}; findings: " + ", ".join(f"{f['effect']} {f.get('orders', '')} gain {100 * f['gain']['relative_reduction']:.1f} %"
                                               for f in d.findings) or "none")
print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
print(f"diagnose_total_s: {total:.1f}  (goal < 180)")
