"""Which real-bench deviation makes the paper model miss which record: the independent bench
(`hdjax._testbench.independent`) with all its deviations on, all off, and each one switched off alone; hdjax's plant
simulated at the bench's *true* parameters (no fit, so nothing is absorbed by re-fitted
parameters); per record, the RMS of the torque and motor-velocity residuals over the record's own
sensor-noise level (`noise_levels`, 1 = noise only).

A deviation whose removal brings a record's figures down to the all-off row is what the base
model lacks there. Usage: `python benchmarks/bench_deviations.py [--seed 801] [--drive hd1]`
(4 locked + 4 free records of 1.5 s, the size of the diagnosis tests; about a minute).
"""

import argparse
import dataclasses
import pathlib
import tempfile

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
import yaml  # noqa: E402

from hdjax import Parameters, load_dataset, noise_levels, simulate_batch, stack_experiments  # noqa: E402
from hdjax.bench import Deviations, make_dataset  # noqa: E402

#: each deviation's "off" value (`Deviations.none()` switches all of them off)
OFF = {"stiction": None, "current_loop": False, "pwm_ripple": 0.0, "sensor_dynamics": False, "tacho_ripple": 0.0,
       "quantisation": False, "offsets": None, "jitter": 0.0, "drive_spread": 0.0}  # fmt: skip


def misfit(dev: Deviations, *, seed: int, drive: str) -> list[tuple[str, float, float]]:
    """(mode, torque RMS / σ_T, motor-velocity RMS / σ_ω) per record, hdjax's plant at the truth."""
    with tempfile.TemporaryDirectory() as tmp:
        make_dataset(tmp, drive=drive, seed=seed, n_locked=4, n_free=4, duration=1.5, deviations=dev)
        ds = load_dataset(tmp)
        truth = yaml.safe_load((pathlib.Path(tmp) / "truth.yaml").read_text())
    exps = [ds.experiments[i] for i in ds.dynamic_indices()]
    batch = stack_experiments(exps)
    traj = simulate_batch(Parameters.from_dict(truth["parameters"]), ds.drive, batch)
    sig, m = np.asarray(noise_levels(batch)), np.asarray(batch.mask)
    out = []
    for i in range(len(exps)):
        rT = np.asarray(traj.torque[i] - batch.torque[i])[m[i]]
        rw = np.asarray(traj.motor_velocity[i] - batch.motor_velocity[i])[m[i]]
        mode = "free" if float(batch.free[i]) > 0 else "locked"
        out.append((mode, float(np.sqrt(np.mean(rT**2)) / sig[0]), float(np.sqrt(np.mean(rw**2)) / sig[1])))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=801)
    ap.add_argument("--drive", default="hd1", choices=("hd1", "hd2"))
    args = ap.parse_args()
    variants = {"all on": Deviations(), "all off": Deviations.none()}
    variants |= {f"{k} off": dataclasses.replace(Deviations(), **{k: v}) for k, v in OFF.items()}
    rows = {name: misfit(dev, seed=args.seed, drive=args.drive) for name, dev in variants.items()}
    modes = [md for md, _, _ in rows["all on"]]
    print(f"seed {args.seed}, {args.drive.upper()}: residual RMS / sensor noise at the true parameters, torque / motor velocity")
    print("| bench | " + " | ".join(f"{md} {j + 1}" for j, md in enumerate(modes)) + " |")
    print("|---" * (len(modes) + 1) + "|")
    for name, r in rows.items():
        print(f"| {name} | " + " | ".join(f"{t:.1f} / {w:.1f}" for _, t, w in r) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
