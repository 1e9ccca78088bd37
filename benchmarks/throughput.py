"""Benchmark (not a test): simulation throughput in one `vmap`, on whatever JAX backend is present
(CPU here; run the same script on a GPU to compare, issue 19).

Two batch shapes, both one jitted `vmap`:

- **experiments**: N records of the shipped HD2 campaign (its 50 dynamic records tiled to N and
  each cut to its first L samples at 1 kHz; the copies are identical, so every lane does the same
  work as in a campaign of N distinct records), one shared parameter set;
- **parameter sets**: one record (the first free one), N parameter sets drawn around the truth
  (K1, Tst, Jeff, Tvp, Tvn, Tsp, Tsn each scaled by an independent factor in [0.8, 1.2], seed 0),
  the shape of a Monte-Carlo or a parameter sweep.

Solvers: `VelocityImplicit(substeps=m)` (fixed cost, the same work in every lane) and, for the
experiment shape only, the adaptive `Rodas3` (rtol 1e-6), whose lanes under `vmap` run as many steps
as the slowest one. Per row: compile time, the best of 3 timed runs after compilation, and the
throughput in experiment-samples per second (N·L / time). The 9-tangent forward-mode Jacobian
(what one Levenberg–Marquardt step needs) is timed for the experiment shape too.

Usage: `python benchmarks/throughput.py [--sizes 1 10 100 1000] [--samples 1000] [--substeps 4]
[--rodas-max 100] [--jacobian-max 1000] [--json PATH]`
"""

import argparse
import json
import os
import pathlib
import platform
import time

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import hdjax  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
VARIED = ("K1", "Tst", "Jeff", "Tvp", "Tvn", "Tsp", "Tsn")
JAC_FREE = ("K1", "Tst", "Jeff", "Tvp", "Tvn", "Tsp", "Tsn", "Tssp1", "Tssn1")


def _timed(f, *args, repeat: int = 3) -> tuple[float, float]:
    """(compile-and-first-run seconds, best of `repeat` later runs)."""
    t0 = time.perf_counter()
    jax.block_until_ready(f(*args))
    first = time.perf_counter() - t0
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        jax.block_until_ready(f(*args))
        best = min(best, time.perf_counter() - t0)
    return first, best


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 10, 100, 1000])
    ap.add_argument("--samples", type=int, default=1000, help="samples per record (1 kHz)")
    ap.add_argument("--substeps", type=int, default=4)
    ap.add_argument("--rodas-max", type=int, default=100, help="largest N run with Rodas3")
    ap.add_argument("--jacobian-max", type=int, default=1000, help="largest N whose Jacobian is timed")
    ap.add_argument("--json", type=pathlib.Path, help="also write the rows here")
    args = ap.parse_args()

    dev = jax.devices()[0]
    print(f"backend {jax.default_backend()}, device {dev.device_kind}, {jax.device_count()} device(s), "
          f"{os.cpu_count()} CPUs, jax {jax.__version__}, {platform.machine()}", flush=True)
    ds = hdjax.load_dataset(ROOT / "data" / "hd2")
    idx = ds.dynamic_indices()
    records = [ds.experiments[i].first(args.samples) for i in idx]
    p = hdjax.Parameters.from_dict(ds.truth["parameters"])
    drive = ds.drive
    vi = hdjax.Simulator(solver=hdjax.VelocityImplicit(substeps=args.substeps))
    rodas = hdjax.Simulator(rtol=1e-6, atol=1e-8)

    @eqx.filter_jit
    def sim_experiments(p, batch, simulator):
        return jax.vmap(lambda e: hdjax.simulate(p, drive, e, simulator=simulator))(batch)

    @eqx.filter_jit
    def jac_experiments(v, batch, simulator):
        def out(v):
            q = p.replace(**dict(zip(JAC_FREE, v)))
            tr = jax.vmap(lambda e: hdjax.simulate(q, drive, e, simulator=simulator))(batch)
            return jnp.concatenate([tr.torque.ravel(), tr.motor_velocity.ravel()])
        return jax.jacfwd(out)(v)

    @eqx.filter_jit
    def sim_parameters(scales, e, simulator):
        def one(s):
            q = p.replace(**{k: getattr(p, k) * s[j] for j, k in enumerate(VARIED)})
            return hdjax.simulate(q, drive, e, simulator=simulator)
        return jax.vmap(one)(scales)

    v0 = jnp.array([float(getattr(p, k)) for k in JAC_FREE])
    first_free = next(r for r, i in zip(records, idx) if ds.modes[i] == "free")
    rng = np.random.default_rng(0)
    rows = []
    head = f"{'shape':>14} {'solver':>12} {'N':>5} {'compile_s':>9} {'run_s':>8} {'Msamples/s':>10} {'ok':>4}"
    print(head, flush=True)

    def report(shape, solver, n, first, best, ok, extra=""):
        thr = n * args.samples / best / 1e6
        row = {"shape": shape, "solver": solver, "N": n, "samples": args.samples, "compile_s": first - best,
               "run_s": best, "Msamples_per_s": thr, "all_converged": ok}
        rows.append(row)
        print(f"{shape:>14} {solver:>12} {n:5d} {first - best:9.2f} {best:8.4f} {thr:10.3f} {'yes' if ok else 'NO':>4}{extra}",
              flush=True)

    for n in args.sizes:
        batch = hdjax.stack_experiments([records[k % len(records)] for k in range(n)])
        first, best = _timed(sim_experiments, p, batch, vi)
        tr = sim_experiments(p, batch, vi)
        report("experiments", f"VI m={args.substeps}", n, first, best, bool(jnp.all(tr.success)))
        if n <= args.jacobian_max:
            first, best = _timed(jac_experiments, v0, batch, vi, repeat=2)
            report("exp. Jacobian", f"VI m={args.substeps}", n, first, best, True, "  (9 tangents)")
        if n <= args.rodas_max:
            first, best = _timed(sim_experiments, p, batch, rodas, repeat=2)
            tr = sim_experiments(p, batch, rodas)
            report("experiments", "Rodas3 1e-6", n, first, best, bool(jnp.all(tr.success)),
                   f"  (steps per lane: max {int(jnp.max(tr.num_steps))}, mean {float(jnp.mean(tr.num_steps)):.0f})")
        scales = jnp.asarray(rng.uniform(0.8, 1.2, size=(n, len(VARIED))))
        first, best = _timed(sim_parameters, scales, first_free, vi)
        tr = sim_parameters(scales, first_free, vi)
        report("parameter sets", f"VI m={args.substeps}", n, first, best, bool(jnp.all(tr.success)))
    if args.json:
        tmp = args.json.with_suffix(".tmp")
        tmp.write_text(json.dumps({"device": dev.device_kind, "backend": jax.default_backend(), "rows": rows}, indent=1))
        os.replace(tmp, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
