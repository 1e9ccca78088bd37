"""Time one simulation of a whole test campaign: `data/hd2/` (20 locked + 30 free experiments),
vmapped and jitted (`eqx.filter_jit(hdjax.simulate_batch)`), with the default `Simulator`.

Prints one line per figure: compile time (first call minus a later call), run time (median of 3
calls), solver steps per experiment, and the machine.

With `--substeps M` the plant is stepped by the fixed-step `hdjax.VelocityImplicit(substeps=M)`
(the fit command's numerics since 2026-12-04) instead of the adaptive default.

Usage: `python benchmarks/simulate_campaign.py [--rtol RTOL | --substeps M] [--data FOLDER]`
"""

import argparse
import os
import pathlib
import platform
import statistics
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import numpy as np  # noqa: E402

import hdjax  # noqa: E402
from hdjax import load_dataset  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
DEG = 180.0 / np.pi
# Table I, HD2, with K1 and Tst read per degree (SPEC §1); used when the dataset has no truth.yaml
HD2_TABLE_I = dict(alpha=0.5, K1=104.2 * DEG, Tst=7.96 * DEG**0.5, Jeff=1.0e-4, Tvp=1.8e-3, Tvn=2.1e-3,
                   Tsp=7.5e-2, Tsn=3.3e-2, Tssp1=-0.0487, Tssn1=-0.0450, Tss2=0.1)


def _timed(f, *args):
    t0 = time.perf_counter()
    out = jax.block_until_ready(f(*args))
    return time.perf_counter() - t0, out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rtol", type=float, default=hdjax.Simulator().rtol,
                        help="PID controller rtol (default: the Simulator default, %(default)g)")
    parser.add_argument("--substeps", type=int, default=None,
                        help="step with hdjax.VelocityImplicit at this many steps per sample instead (default: the adaptive Simulator)")
    parser.add_argument("--data", type=pathlib.Path, default=ROOT / "data" / "hd2", help="dataset folder")
    args = parser.parse_args()

    if not (args.data / "dataset.yaml").is_file():
        print(f"No dataset at {args.data}. Create it first with `python scripts/make_datasets.py`.")
        return 1
    ds = load_dataset(args.data)
    idx = ds.dynamic_indices()
    if not idx:
        print(f"{args.data} has no constrained or free experiments to simulate.")
        return 1
    batch = hdjax.stack_experiments([ds.experiments[i] for i in idx])
    truth = (ds.truth or {}).get("parameters")
    p = hdjax.Parameters.from_dict(truth if truth else HD2_TABLE_I)
    simulator = (hdjax.Simulator(rtol=args.rtol) if args.substeps is None
                 else hdjax.Simulator(solver=hdjax.VelocityImplicit(substeps=args.substeps)))
    sim = eqx.filter_jit(hdjax.simulate_batch)

    def run(batch):
        return sim(p, ds.drive, batch, simulator=simulator)

    first, traj = _timed(run, batch)
    runs = [_timed(run, batch)[0] for _ in range(3)]
    run_s = statistics.median(runs)
    steps = np.asarray(traj.num_steps)
    n_samples = np.asarray(batch.mask).sum(axis=1)
    modes = [ds.modes[i] for i in idx]

    print(f"dataset:              {ds.name} ({args.data})")
    print(f"experiments:          {len(idx)} ({modes.count('constrained')} constrained, {modes.count('free')} free), "
          f"{int(n_samples.sum())} samples, padded to {batch.time.shape[1]}")
    print(f"parameters:           {'truth.yaml' if truth else 'Table I (HD2, per-degree reading)'}")
    numerics = (f"{args.substeps} steps per sample" if args.substeps is not None
                else f"PID rtol {simulator.rtol:g}, atol {simulator.atol:g}")
    print(f"solver:               {type(simulator.solver).__name__}, {numerics}")
    print(f"all succeeded:        {bool(np.all(np.asarray(traj.success)))}")
    print(f"compile time:         {first - run_s:.2f} s (first call {first:.2f} s)")
    print(f"run time:             {run_s:.3f} s (median of 3: {', '.join(f'{r:.3f}' for r in runs)})")
    print(f"run time/experiment:  {1e3 * run_s / len(idx):.1f} ms")
    for mode in ("constrained", "free"):
        s = steps[[m == mode for m in modes]]
        if s.size:
            print(f"steps/experiment {mode + ':':12s} median {int(np.median(s))}, min {s.min()}, max {s.max()}")
    print(f"steps/sample:         {steps.sum() / n_samples.sum():.2f}")
    print(f"machine:              {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"jax {jax.__version__} on {jax.devices()[0].platform}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
