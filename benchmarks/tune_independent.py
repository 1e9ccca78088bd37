"""Benchmark (not a test): controller tuning on drives from the independent bench (`hdjax._testbench.independent`:
its own integrator, stick–slip friction, a current loop, sensor dynamics, offsets; it shares no
code with hdjax's plant).

Each drive (HD1- or HD2-like, seeds from 7000 on, not used by the tests) gets its own dataset
(`--locked` + `--free` records of 2.5 s at 1 kHz), is identified from it by the library's fit
(`hdjax._workflows.fit.run_fit`: paper's regressions, joint trajectory-error LM on `--fit-experiments`
records, per-experiment LM fits for the plant set) and tuned by `hdjax._workflows.tune.run_tune`, which
validates the tuned controller and both baselines (relay + Ziegler–Nichols PI; model-based MIGO PI
with feed-forward) on the bench rebuilt from the dataset's truth.yaml.

Prints per drive: bench tracking cost of the three controllers (each the mean over the tune
command's `validation_runs` noise realisations), the improvement of the tuned one over each
baseline, the tuning cost before/after BFGS (separate from the start search) and the time (dataset,
fit, tune); then median and worst improvements and the time per drive.

Column "PI+ffr": the model-based PI baseline with its friction feed-forward moved from the measured
to the reference's motor velocity (kf = 0, kfr = 1), the controller structure the tuner may choose,
validated on the same bench runs. It is not one of the issue's baselines; it shows how much of the
improvement over the model-based PI comes from that structure and how much from tuning.

`--no-breakaway` tunes without the fit's breakaway torques (`tune.breakaway_friction: false`; the fit
still fits them).

Usage: `python benchmarks/tune_independent.py [--n 10] [--first 0] [--json FILE] [--tune-solver rodas3]
[--no-breakaway]`.
"""

import argparse
import json
import pathlib
import tempfile
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from hdjax import TorqueGains, load_dataset  # noqa: E402
from hdjax.bench import make_dataset  # noqa: E402
from hdjax.fit import run_fit  # noqa: E402
from hdjax.tune import bench_tracking_cost, run_tune  # noqa: E402


def structure_only(ds, out: pathlib.Path, r: dict) -> float:
    """Bench cost (mean over the same validation runs as `run_tune`) of the model-based PI with the
    reference-velocity friction feed-forward instead of the measured one."""
    g = TorqueGains(**{**r["baselines"]["model_pi"]["gains"], "kf": 0.0, "kfr": 1.0})
    return bench_tracking_cost(ds, g, sample_period=r["controller"]["sample_period_s"],
                               current_limit=r["controller"]["current_limit_A"], out=out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=10)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--locked", type=int, default=5)
    ap.add_argument("--free", type=int, default=5)
    ap.add_argument("--fit-experiments", type=int, default=6)
    ap.add_argument("--json", type=str, default=None)
    ap.add_argument("--tune-solver", default=None, choices=("velocity_implicit", "rodas3"),
                    help="plant of the tuning model (`tune.solver`; default: the package's, velocity_implicit)")
    ap.add_argument("--no-breakaway", action="store_true",
                    help="tune without the fit's breakaway torques (`tune.breakaway_friction: false`)")
    ap.add_argument("--keep", type=str, default=None, help="folder to keep the datasets and outputs in")
    a = ap.parse_args()
    root = pathlib.Path(a.keep or tempfile.mkdtemp(prefix="tune_independent_"))
    rows = []
    quiet = lambda s: None  # noqa: E731
    print(f"{'drive':>12} | {'ZN':>8} {'MIGO PI':>8} {'tuned':>8} | {'vs ZN':>7} {'vs PI':>7} | {'PI+ffr':>8} {'vs it':>7} | "
          f"{'BFGS before':>11} {'after':>9} | {'data':>5} {'fit':>5} {'tune':>5} {'total':>6} s")  # fmt: skip
    for j in range(a.first, a.first + a.n):
        drive = "hd1" if j % 2 == 0 else "hd2"
        seed = 7000 + j
        d = root / f"{drive}-{seed}"
        t0 = time.time()
        make_dataset(d, drive=drive, seed=seed, n_locked=a.locked, n_free=a.free)
        t_data = time.time() - t0
        ds = load_dataset(d)
        t0 = time.time()
        cfg = {"fit": {"trajectory": {"max_experiments": a.fit_experiments, "max_steps": 10, "per_experiment_max_steps": 8}}}
        run_fit(ds, cfg, d / "out", log=quiet)
        t_fit = time.time() - t0
        t0 = time.time()
        tune_cfg = {} if a.tune_solver is None else {"solver": a.tune_solver}
        if a.no_breakaway:
            tune_cfg["breakaway_friction"] = False
        r = run_tune(ds, {"tune": tune_cfg}, d / "out", log=quiet)
        t_tune = time.time() - t0
        v = r["validation"]
        assert v["on"] == "bench", v["on"]
        c_ffr = structure_only(ds, d / "out", r)
        row = {
            "drive": drive, "seed": seed, "model_pi_reference_ff": c_ffr,
            "cost": {c: v[c]["tracking_cost"] for c in ("relay_zn", "model_pi", "tuned")},
            "improvement": v["improvement_over"],
            "bfgs_before": r["tuning"]["cost_before_optimiser"], "bfgs_after": r["tuning"]["cost_after_optimiser"],
            "start_search_best": r["tuning"]["start_search_best"],
            "model_cost": {c: r["model"][c]["cost"] for c in ("relay_zn", "model_pi", "tuned")},
            "time": {"data": t_data, "fit": t_fit, "tune": t_tune, "total": t_data + t_fit + t_tune},
            "gains": r["gains"],
        }  # fmt: skip
        rows.append(row)
        c, im, tt = row["cost"], row["improvement"], row["time"]
        print(f"{drive + '-' + str(seed):>12} | {c['relay_zn']:8.4g} {c['model_pi']:8.4g} {c['tuned']:8.4g} | "
              f"{100 * im['relay_zn']:6.1f}% {100 * im['model_pi']:6.1f}% | {c_ffr:8.4g} {100 * (1 - c['tuned'] / c_ffr):6.1f}% | "
              f"{row['bfgs_before']:11.4g} "
              f"{row['bfgs_after']:9.4g} | {tt['data']:5.1f} {tt['fit']:5.1f} {tt['tune']:5.1f} {tt['total']:6.1f}",
              flush=True)  # fmt: skip
    zn = np.array([r["improvement"]["relay_zn"] for r in rows])
    pi = np.array([r["improvement"]["model_pi"] for r in rows])
    better = np.array([1 - r["cost"]["tuned"] / min(r["cost"]["relay_zn"], r["cost"]["model_pi"]) for r in rows])
    gd = np.array([1 - r["bfgs_after"] / r["bfgs_before"] for r in rows])
    tot = np.array([r["time"]["total"] for r in rows])
    print()
    print(f"improvement over relay/ZN:        median {100 * np.median(zn):.1f} %, worst {100 * zn.min():.1f} %")
    print(f"improvement over model-based PI:  median {100 * np.median(pi):.1f} %, worst {100 * pi.min():.1f} %")
    print(f"improvement over the better one:  median {100 * np.median(better):.1f} %, worst {100 * better.min():.1f} % "
          f"({int(np.sum(better < 0))} drive(s) worse)")  # fmt: skip
    ffr = np.array([1 - r["cost"]["tuned"] / r["model_pi_reference_ff"] for r in rows])
    print(f"over the PI with reference-velocity friction ff (structure only): median {100 * np.median(ffr):.1f} %, "
          f"worst {100 * ffr.min():.1f} %")
    print(f"BFGS step alone (tuning model):   median {100 * np.median(gd):.1f} % lower cost, min {100 * gd.min():.1f} %")
    print(f"time per drive (dataset + fit + tune): median {np.median(tot):.0f} s, max {tot.max():.0f} s")
    if a.json:
        pathlib.Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
