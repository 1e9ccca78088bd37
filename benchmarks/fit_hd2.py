"""Benchmark (not a test): `python -m hdjax.fit configs/hd2.yaml` end to end on the shipped
50-experiment campaign; prints wall time and the timing recorded in fit.json, the recovery
against truth.yaml, and the fitted sensor lags against the bench's filters (truth.yaml's
`deviations`: first-order low-passes, time constant 1/(2π f_c))."""

import json
import math
import pathlib
import subprocess
import sys
import tempfile
import time

import yaml

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
sb = (d.get("model_form") or {}).get("sensor_bandwidth")
dataset = (pathlib.Path(config).parent / yaml.safe_load(pathlib.Path(config).read_text())["dataset"]).resolve()
dev = (yaml.safe_load((dataset / "truth.yaml").read_text()) or {}).get("deviations", {}) if (dataset / "truth.yaml").exists() else {}
for field, key in (("torque_lag", "torque_filter_hz"), ("velocity_lag", "tacho_filter_hz")):
    if sb:
        e = sb[field]
        true = f", the bench's filter {1e3 / (2 * math.pi * float(dev[key])):.4f} ms" if dev.get(key) else ""
        print(f"{field}: {1e3 * e['value']:.4f} ± {1e3 * e['std_error']:.4f} ms{true}")
print("chi2_reduced", d["fit"]["chi2_reduced"])
truth_low = ((yaml.safe_load((dataset / "truth.yaml").read_text()) or {}).get("low_speed") or {}) if (dataset / "truth.yaml").exists() else {}
for field, e in ((d.get("model_form") or {}).get("breakaway_friction") or {}).items():
    if field != "note":
        b = (truth_low.get("breakaway_torque") or {}).get(field.rsplit("_", 1)[-1])
        true = f", the bench's {float(b):.4g} N·m ({100 * (e['value'] / float(b) - 1):+.1f} %)" if b else ""
        print(f"breakaway {field}: {e['value']:.4g} N·m (grid search){true}")
