"""Write the datasets the project ships: `data/hd1/` and `data/hd2/` from the virtual test rig.

Each is the paper's campaign (20 constrained + 30 free-motion experiments, 1.5 s at 1 kHz) on one
of the paper's stations (`hdjax._rig.station_hd1` / `station_hd2`, truth = Table I), recorded
through the station's sensors, with fixed seeds so that the files are reproducible:

- `data/hd1/`: the paper's model only, no extra effect.
- `data/hd2/`: plus `torque_sensor_ripple` at order 2 (two cycles per wave-generator turn, the
  strain gauges seeing the wave generator's ellipse), amplitude 1.5 N·m = 3× the strain-gauge
  noise: the paper reports torque ripple in free motion that its model does not capture.

The truth (parameters, drive constants, sensor noise, active effects, per-experiment profiles) is
written to `truth.yaml` beside each `dataset.yaml`. CSV values have 7 significant digits.

Usage: `python scripts/make_datasets.py [--out DATA_DIR]` (default: `data/` at the repo root).
"""

import argparse
import pathlib
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import hdjax  # noqa: E402
from hdjax import _rig  # noqa: E402

SEEDS = {"hd1": 1001, "hd2": 2002}
RIPPLE = {"order": 2, "amplitude": 1.5, "phase": 0.7}  # N·m, rad: HD2 strain-gauge ripple


def _summary(station, runs) -> None:
    """Measured ranges of the campaign's truth (what the issue asks the campaign to cover)."""
    locked = [r.clean for r in runs if r.mode == "constrained"]
    free = [r.clean for r in runs if r.mode == "free"]
    T_locked = [np.max(np.abs(c["torque"])) for c in locked]
    w_free = [np.max(np.abs(c["motor_velocity"])) for c in free]
    slow = sum(np.median(np.abs(c["motor_velocity"])) < 0.4 for c in free)
    both = sum(np.mean(c["motor_velocity"] > 1) > 0.25 and np.mean(c["motor_velocity"] < -1) > 0.25 for c in free)
    print(
        f"  constrained: peak |T| {min(T_locked):.1f}..{max(T_locked):.1f} N·m (rated {station.rated_torque:g}), "
        f"peak |wm| {min(np.max(np.abs(c['motor_velocity'])) for c in locked):.2f}.."
        f"{max(np.max(np.abs(c['motor_velocity'])) for c in locked):.1f} rad/s\n"
        f"  free: peak |wm| {min(w_free):.2f}..{max(w_free):.1f} rad/s, peak |T| "
        f"{max(np.max(np.abs(c['torque'])) for c in free):.1f} N·m; {slow} runs with median |wm| < 0.4 rad/s, "
        f"{both} runs beyond ±1 rad/s for > 25 % of the time in each direction"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path(__file__).resolve().parents[1] / "data")
    args = parser.parse_args()
    t_all = time.perf_counter()

    hd2 = _rig.station_hd2()
    ripple = _rig.hide_effect(
        "torque_sensor_ripple", RIPPLE["amplitude"], order=RIPPLE["order"], phase=RIPPLE["phase"], station=hd2
    )
    jobs = [
        ("hd1", _rig.station_hd1(), hdjax.Effects(), "paper's model only, no extra effect"),
        ("hd2", hd2, ripple, "paper's model plus order-2 strain-gauge torque ripple (not in the paper's model)"),
    ]
    for key, station, effects, note in jobs:
        t0 = time.perf_counter()
        runs = _rig.run_campaign(station, effects=effects, seed=SEEDS[key])
        for old in (args.out / key).glob("*.csv"):  # no stale experiments from an earlier campaign
            old.unlink()
        folder = _rig.write_campaign(
            args.out / key,
            station,
            runs,
            name=f"{key}-virtual-rig",
            effects=effects,
            truth_extra={"seed": SEEDS[key], "note": note, "generator": "scripts/make_datasets.py"},
            digits=7,
        )
        size = sum(p.stat().st_size for p in folder.iterdir() if p.is_file())
        print(f"{key}: {len(runs)} experiments -> {folder} ({size / 1e6:.2f} MB) in {time.perf_counter() - t0:.1f} s")
        _summary(station, runs)
    print(f"total {time.perf_counter() - t_all:.1f} s")


if __name__ == "__main__":
    main()
