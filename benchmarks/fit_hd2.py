"""Benchmark (not a test): `python -m hdjax.fit configs/hd2.yaml` end to end on the shipped
50-experiment campaign; prints wall time and the timing recorded in fit.json, and the recovery
against truth.yaml."""

import json
import pathlib
import subprocess
import sys
import tempfile
import time

root = pathlib.Path(__file__).resolve().parents[1]
config = sys.argv[1] if len(sys.argv) > 1 else str(root / "configs" / "hd2.yaml")
with tempfile.TemporaryDirectory() as out:
    t0 = time.time()
    subprocess.run([sys.executable, "-m", "hdjax.fit", config, "--out", out], check=True)
    wall = time.time() - t0
    d = json.loads((pathlib.Path(out) / "fit.json").read_text())
print(f"wall_s: {wall:.1f}")
for k, v in d["timing_s"].items():
    print(f"timing_{k}_s: {v:.1f}")
for k, e in d["parameters"].items():
    if "truth" in e and e["truth"]:
        print(f"{k}: fit {e['value']:.5g} paper {e['paper_method']['value']} truth {e['truth']:.5g} "
              f"err {100 * (e['value'] / e['truth'] - 1):+.2f} % consistency {e['consistency']}")
print("nrmse", d["fit"]["nrmse"])
