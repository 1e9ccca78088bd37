"""Numerics of the sampled torque loop (`hdjax._control.closed_loop.closed_loop`): substeps per sample vs
accuracy vs time, with and without the step-failure refinement, and the AD gradient vs central
differences at the tuning model's smoothing. HD2 truth (Table I, per-degree reading), 1 kHz, locked
step and free doublet under a Ziegler–Nichols-like PI and under the model feed-forward with
softer gains. Prints a table; no files written.

Run: python benchmarks/tune_numerics.py [--duration 0.3]
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from hdjax import Plant, Smoothing, TorqueController, TorqueGains, closed_loop, doublet_reference, step_reference
from hdjax.rig import station_hd2


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=0.3, help="s per reference")
    args = ap.parse_args()
    st = station_hd2()
    plant = Plant(st.truth, st.drive)
    ctrl = TorqueController(friction=st.truth, drive=st.drive, sample_period=1e-3, current_limit=5.6)
    sm = Smoothing(velocity_scale=0.03, torsion_rate_scale=1e-3)  # tuning-model smoothing (hdjax._workflows.tune)
    refs = {
        "locked step 82 N·m": step_reference(82.0, duration=args.duration),
        "free doublet 5 N·m": doublet_reference(5.0, 0.055, duration=args.duration),
    }
    gains = {
        "ZN PI": TorqueGains(kp=0.144, ki=86.5),
        "soft PI + FF": TorqueGains(kp=0.072, ki=21.6, kr=1.0, kf=1.0, kj=1.0),
    }
    print("substeps vs accuracy vs time (reference solution: 64 substeps, no refinement)")
    print(f"{'reference':20s} {'gains':13s} {'substeps':>8s} {'refine':>6s} {'max|dT| (N·m)':>14s} {'rel. RMS':>9s} "
          f"{'refined':>8s} {'run (ms)':>9s}")  # fmt: skip
    for rn, ref in refs.items():
        for gn, g in gains.items():
            run = lambda s, r: closed_loop(g, plant, ref, controller=ctrl, substeps=s, refine=r, smoothing=sm)  # noqa: E731
            truth = jax.jit(lambda: run(64, 1))().torque
            for s in (1, 2, 4, 16):
                for r in (1, 4):
                    f = jax.jit(lambda s=s, r=r: run(s, r))
                    tr = f()
                    jax.block_until_ready(tr.torque)
                    t0 = time.perf_counter()
                    for _ in range(3):
                        tr = f()
                        jax.block_until_ready(tr.torque)
                    dt = (time.perf_counter() - t0) / 3
                    err = np.asarray(tr.torque - truth)
                    rel = np.sqrt(np.mean(err**2)) / np.sqrt(np.mean(np.asarray(truth) ** 2))
                    print(f"{rn:20s} {gn:13s} {s:8d} {r:6d} {np.abs(err).max():14.3g} {rel:9.2e} "
                          f"{int(np.sum(np.asarray(tr.refined))):8d} {dt * 1e3:9.1f}")  # fmt: skip

    print("\nAD gradient vs central differences (substeps 2, refine 1, tuning smoothing), d cost / d theta")
    names = ("log kp", "log ki", "kr", "kf", "kj")
    for rn, ref in refs.items():
        for gn, g0 in gains.items():

            def cost(th, g0=g0, ref=ref):
                g = TorqueGains(kp=g0.kp * jnp.exp(th[0]), ki=g0.ki * jnp.exp(th[1]), kr=g0.kr + th[2], kf=g0.kf + th[3],
                                kj=g0.kj + th[4])  # fmt: skip
                tr = closed_loop(g, plant, ref, controller=ctrl, substeps=2, refine=1, smoothing=sm)
                return jnp.mean((tr.reference - tr.torque) ** 2) / jnp.max(jnp.abs(ref.torque)) ** 2

            th = jnp.zeros(5)
            ad = np.asarray(jax.jit(jax.grad(cost))(th))
            f = jax.jit(cost)
            for h in (1e-4, 1e-6):
                fd = np.array([(f(th.at[i].add(h)) - f(th.at[i].add(-h))) / (2 * h) for i in range(5)])
                rel = np.abs(ad - fd) / np.maximum(np.abs(fd), 1e-12)
                print(f"{rn:20s} {gn:13s} h={h:.0e}: " + ", ".join(
                    f"{n} AD {a:+.3e} FD {d:+.3e} (rel {e:.1e})" for n, a, d, e in zip(names, ad, fd, rel)))  # fmt: skip


if __name__ == "__main__":
    main()
