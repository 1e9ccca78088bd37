"""Benchmark (not a test): `python -m hdjax.sensitivity configs/hd2.yaml` end to end on the shipped
50-experiment HD2 campaign, into a temporary folder (so no results/hd2/fit.json is picked up: the
parameters come from the paper's identification, the slower path). Prints the wall time, the
timing recorded in sensitivity.json, and the headline numbers.

Usage: `python benchmarks/sensitivity_hd2.py [CONFIG] [extra command arguments, e.g. --fit FIT_JSON]`
"""

import json
import os
import pathlib
import platform
import subprocess
import sys
import tempfile
import time

root = pathlib.Path(__file__).resolve().parents[1]
config = sys.argv[1] if len(sys.argv) > 1 else str(root / "configs" / "hd2.yaml")
extra = sys.argv[2:]
with tempfile.TemporaryDirectory() as tmp:
    out = pathlib.Path(tmp) / "hd2-sensitivity"
    t0 = time.time()
    subprocess.run([sys.executable, "-m", "hdjax.sensitivity", config, "--out", str(out), *extra], check=True)
    wall = time.time() - t0
    d = json.loads((out / "sensitivity.json").read_text())
print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load average "
      f"{os.getloadavg()[0]:.2f}" if hasattr(os, "getloadavg") else "")
print(f"wall_s: {wall:.1f}")
for k, v in d["timing_s"].items():
    print(f"timing_{k}_s: {v:.1f}")
print(f"parameters from: {d['parameter_source']['kind']}; experiments: {len(d['experiments'])}, "
      f"simulated ok: {sum(e['simulation_ok'] for e in d['experiments'])}")
print("relative SE:", {k: f"{100 * v['relative']:.3g} %" for k, v in d["standard_errors"].items() if v["estimated"]})
for c in d["ablation"]["changes"]:
    for mode, e in c["per_mode"].items():
        inc = {k: f"{100 * v:+.0f} %" for k, v in e["rms_increase"].items()}
        print(f"ablation {c['change']:13s} {mode:11s} RMS increase {inc} failed {len(e['failed'])}")
con = d["ablation"]["conclusions"]
print("paper conclusions reproduced: free-motion friction", con["free_motion_friction_reproduced"],
      "| constrained-motion compliance", con["constrained_motion_compliance_reproduced"])
print("worst determined:", d["advice"].get("worst_determined"))
