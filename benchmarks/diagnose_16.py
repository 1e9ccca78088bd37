"""Benchmark (not a test): diagnose a 16-experiment rig dataset (8 constrained + 8 free, 2.5 s at
1 kHz) with one hidden SPEC §4 effect; goal under 3 minutes on the 2-core CI machine.

Usage: `python benchmarks/diagnose_16.py [EFFECT|none] [hd1|hd2]` (default: kinematic_error hd1).
Prints the stage timings, the findings and the truth.
"""

import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

from hdjax import (  # noqa: E402
    Effects,
    diagnose_effects as diagnose,  # noqa: E402
    identify_paper,
)
from hdjax.rig import campaign, hide_effect, run_campaign, station_hd1, station_hd2  # noqa: E402

effect = sys.argv[1] if len(sys.argv) > 1 else "kinematic_error"
station = {"hd1": station_hd1, "hd2": station_hd2}[sys.argv[2] if len(sys.argv) > 2 else "hd1"]()
effects = Effects() if effect == "none" else hide_effect(effect, None, order=2, phase=0.3, station=station)
t0 = time.perf_counter()
profiles = campaign(station, seed=11, n_constrained=8, n_free=8, duration=2.5)
runs = run_campaign(station, effects=effects, seed=11, profiles=profiles)
exps = [r.experiment for r in runs]
t_rig = time.perf_counter() - t0
print(f"rig data: {len(exps)} experiments × 2.5 s in {t_rig:.1f} s (not part of the benchmark)")
t0 = time.perf_counter()
paper = identify_paper(exps, station.drive)
t_paper = time.perf_counter() - t0
d = diagnose(paper.parameters(), station.drive, exps, log=print)
total = time.perf_counter() - t0
print(f"paper identification: {t_paper:.1f} s")
for k, v in d.timing.items():
    print(f"timing_{k}_s: {v:.1f}")
print(f"hidden: {effect}; findings: " + ", ".join(f"{f['effect']} {f.get('orders', '')} gain {100 * f['gain']['relative_reduction']:.1f} %"
                                               for f in d.findings) or "none")
print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
print(f"diagnose_total_s: {total:.1f}  (goal < 180)")
