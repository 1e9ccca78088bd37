"""Benchmark (not a test): how hdjax's joint trajectory-error fit scales with the number of
experiments and the record length; compile time; peak memory; where an LM step spends its time.

Each configuration (N experiments × L samples) runs in a fresh subprocess, so that its peak memory
is its own: `resource.getrusage(RUSAGE_SELF).ru_maxrss` (peak resident set of the process, host
memory incl. XLA's buffers on the CPU backend, not a tracemalloc count, which misses XLA's
allocations). Per configuration it prints:

- `compile_s`: `jax.jit(jax.jacfwd(residuals)).lower(...).compile()` wall time (the residual and
  its forward-mode Jacobian through the Rodas3 plant, over the experiments as the fit evaluates them:
  `hdjax.for_each_experiment`, i.e. `lax.map` on the CPU, `vmap` on accelerators);
- `residual_s`, `jacobian_s`: one compiled evaluation of the noise-weighted residuals of all
  experiments and of their 9-column Jacobian (median of 3);
- `fit_s`: `fit_parameters(..., max_steps=K)` wall time including its own compilation, and the
  LM steps it took;
- `rss_MB`: peak resident memory of the subprocess.

Experiments: the 50 of `data/hd2` (20 constrained, 30 free), taken in an interleaved order
(constrained and free alternate); N = 200 tiles them 4× (identical copies: the same compute per
experiment, but no new information, and each copy's solver takes the same steps as the original,
which slightly favours the tiled size), each record cut to its first L samples (1 kHz). Start
point: `identify_paper` on all 50 experiments.

Usage: `python benchmarks/scaling.py [--experiments 10 50 200] [--lengths 250 500 1000 1500]
[--length 300] [--max-steps 2]`
"""

import argparse
import json
import os
import pathlib
import platform
import subprocess
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]


def one(n_exp: int, n_samples: int, max_steps: int) -> dict:
    import resource
    import statistics

    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    import hdjax
    from hdjax import (
        DEFAULT_FREE,
        experiment_batching,
        experiment_residuals,
        fit_parameters,
        for_each_experiment,
        identify_paper,
        load_dataset,
        make_parameter_map,
        noise_levels,
    )

    ds = load_dataset(ROOT / "data" / "hd2")
    dyn = ds.dynamic_indices()
    cons = [i for i in dyn if ds.modes[i] == "constrained"]
    free = [i for i in dyn if ds.modes[i] == "free"]
    order = [x for pair in zip(cons, free) for x in pair] + free[len(cons):]
    sel = [order[k % len(order)] for k in range(n_exp)]

    p0 = identify_paper([ds.experiments[i] for i in dyn], ds.drive).parameters()
    batch = hdjax.stack_experiments([ds.experiments[i].first(n_samples) for i in sel])
    sim = hdjax.Simulator(rtol=1e-6, atol=1e-8)
    sigma = noise_levels(batch)
    pmap = make_parameter_map(p0, DEFAULT_FREE)
    theta0 = pmap.to_vector(p0)

    def residuals(theta, b):
        p = pmap.to_model(theta, p0)
        # as the fit evaluates them: `vmap` on accelerators, `lax.map` on the CPU
        return for_each_experiment(lambda e: experiment_residuals(p, ds.drive, e, sigma, sim), b).reshape(-1)

    t0 = time.perf_counter()
    jac = jax.jit(jax.jacfwd(residuals)).lower(theta0, batch).compile()
    compile_s = time.perf_counter() - t0
    res = jax.jit(residuals).lower(theta0, batch).compile()

    def timed(f):
        out = []
        for _ in range(3):
            t = time.perf_counter()
            jax.block_until_ready(f(theta0, batch))
            out.append(time.perf_counter() - t)
        return statistics.median(out)

    residual_s, jacobian_s = timed(res), timed(jac)
    t0 = time.perf_counter()
    fit = fit_parameters(p0, ds.drive, batch, simulator=sim, max_steps=max_steps, sigma=sigma, throw=False)
    fit_s = time.perf_counter() - t0
    steps = np.asarray(hdjax.simulate_batch(p0, ds.drive, batch, simulator=sim).num_steps)
    return {
        "experiments": n_exp, "samples": n_samples, "compile_s": compile_s, "residual_s": residual_s,
        "jacobian_s": jacobian_s, "fit_s": fit_s, "lm_steps": fit.steps, "solver_steps_max": int(steps.max()),
        "solver_steps_mean": float(steps.mean()),
        "batching": experiment_batching(), "rss_MB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def run_sub(n_exp, n_samples, max_steps):
    out = subprocess.run([sys.executable, __file__, "--one", str(n_exp), str(n_samples), "--max-steps", str(max_steps)],
                         capture_output=True, text=True)
    if out.returncode != 0:
        return {"experiments": n_exp, "samples": n_samples, "error": out.stderr.strip().splitlines()[-1:]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--experiments", type=int, nargs="+", default=[10, 50, 200])
    ap.add_argument("--length", type=int, default=300, help="samples per record in the experiment sweep")
    ap.add_argument("--lengths", type=int, nargs="+", default=[250, 500, 1000, 1500])
    ap.add_argument("--length-experiments", type=int, default=10, help="experiments in the length sweep")
    ap.add_argument("--max-steps", type=int, default=2)
    ap.add_argument("--one", type=int, nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(one(*args.one, args.max_steps)))
        return

    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.2f} at start, XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}", flush=True)
    head = (f"{'exps':>5} {'samples':>7} {'compile_s':>9} {'residual_s':>10} {'jacobian_s':>10} {'fit_s':>7} "
            f"{'LM':>3} {'ode_steps':>9} {'rss_MB':>7}  jacobian_s per 1000 experiment-samples")
    rows = [("experiments", n, args.length) for n in args.experiments]
    rows += [("length", args.length_experiments, L) for L in args.lengths if (args.length_experiments, L) not in
             [(n, args.length) for n in args.experiments]]
    print(head, flush=True)
    for kind, n, L in rows:
        r = run_sub(n, L, args.max_steps)
        if "error" in r:
            print(f"{n:5d} {L:7d} failed: {r['error']}", flush=True)
            continue
        per = 1000 * r["jacobian_s"] / (n * L)
        print(f"{n:5d} {L:7d} {r['compile_s']:9.1f} {r['residual_s']:10.3f} {r['jacobian_s']:10.3f} {r['fit_s']:7.1f} "
              f"{r['lm_steps']:3d} {r['solver_steps_max']:9d} {r['rss_MB']:7.0f}  {per:.4f}  ({kind} sweep)", flush=True)
    print(f"load average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
