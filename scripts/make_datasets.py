"""Write the datasets the project ships: `data/hd1/` and `data/hd2/` from the independent bench.

Each is a campaign of 20 constrained + 30 free-motion records, 1.5 s at 1 kHz, made by
`hdjax._testbench.independent` (issue 18): a numpy fixed-step integrator written apart from hdjax's plant, with the
deviations of a real bench switched on at their defaults — exact stick–slip friction with a
breakaway (not tanh(ω/s)), the current from a simulated PI current loop with PWM ripple and
*sampled*, strain-gauge and tachometer bandwidth, tachometer ripple, encoder quantisation, DC
offsets and time-stamp jitter, and the drive drawn around the paper's station (Table I, ±8 %
typical). The paper's model is therefore never exact on these data, as on a real bench; the
drawn truth is in `truth.yaml`. Fixed seeds make the files reproducible:

- `data/hd1/`: no SPEC §4 effect beyond the bench's deviations.
- `data/hd2/`: plus `torque_sensor_ripple` at order 2 (two cycles per wave-generator turn, the
  strain gauges seeing the wave generator's ellipse) at 3× the strain-gauge noise (RMS change of
  the recorded torque): the paper reports torque ripple that its model does not capture.

(Until 2026-11-26 these folders were made by `hdjax._testbench.rig`, which records hdjax's own plant: the
fit then ran where its model is exact.)

Usage: `python scripts/make_datasets.py [--out DATA_DIR]` (default: `data/` at the repo root).
"""

import argparse
import pathlib
import time

import numpy as np

from hdjax import load_dataset
from hdjax.bench import make_dataset

SEEDS = {"hd1": 1001, "hd2": 2002}
CAMPAIGN = {"n_locked": 20, "n_free": 30, "duration": 1.5}
RIPPLE = {"torque_sensor_ripple": {"snr": 3.0, "orders": [2], "channels": ["torque"]}}


def _summary(folder: pathlib.Path) -> None:
    """Measured ranges of the campaign as written (read back through `load_dataset`)."""
    ds = load_dataset(folder)
    peak_T, peak_w = {"constrained": [], "free": []}, {"constrained": [], "free": []}
    for e, mode in zip(ds.experiments, ds.modes):
        peak_T[mode].append(float(np.max(np.abs(np.asarray(e.torque)))))
        peak_w[mode].append(float(np.max(np.abs(np.asarray(e.motor_velocity)))))
    for mode in ("constrained", "free"):
        print(f"  {mode}: {len(peak_T[mode])} records, peak |T| {min(peak_T[mode]):.1f}..{max(peak_T[mode]):.1f} N·m, "
              f"peak |wm| {min(peak_w[mode]):.2f}..{max(peak_w[mode]):.1f} rad/s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path(__file__).resolve().parents[1] / "data")
    args = parser.parse_args()
    t_all = time.perf_counter()
    jobs = [("hd1", None), ("hd2", RIPPLE)]
    for key, effects in jobs:
        t0 = time.perf_counter()
        folder = args.out / key
        for old in list(folder.glob("*.csv")) + list(folder.glob("*.yaml")):  # no stale record of an earlier campaign
            old.unlink()
        make_dataset(folder, drive=key, seed=SEEDS[key], effects=effects, name=f"{key}-bench", **CAMPAIGN)
        size = sum(p.stat().st_size for p in folder.iterdir() if p.is_file())
        print(f"{key}: -> {folder} ({size / 1e6:.2f} MB) in {time.perf_counter() - t0:.1f} s")
        _summary(folder)
    print(f"total {time.perf_counter() - t_all:.1f} s")


if __name__ == "__main__":
    main()
