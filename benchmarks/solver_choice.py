"""Which diffrax solver for the plant? Explicit (Tsit5, Dopri8), ESDIRK (Kvaerno5) and hdjax's
Rosenbrock `Rodas3`, each with a PID controller at rtol 1e-6 and 1e-7, on a synthetic HD2 batch.

The batch: 20 experiments of 2 s at 1 kHz (sine and square currents, half locked, half free),
built with `hdjax.make_experiment`; their torque / velocity channels come from an initial
simulation (Dopri8 at rtol 1e-10), so the initial state estimated from the records is consistent.
The reference is that same Dopri8 rtol 1e-10 run. For each solver and rtol the table shows: run
time of the jitted, vmapped batch (compile excluded), largest accepted-step count over the batch
(the vmapped loop runs that many), and the largest relative torque error max|T − T_ref| /
max|T_ref| over the experiments.

Usage: `python benchmarks/solver_choice.py [--experiments 20] [--duration 2.0] [--repeats 1]`
(several minutes on a laptop CPU: the explicit solvers need tens of steps per sample).
"""

import argparse
import os
import platform
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax as dfx  # noqa: E402
import equinox as eqx  # noqa: E402
import numpy as np  # noqa: E402

import hdjax  # noqa: E402

DEG = 180.0 / np.pi
# Table I, HD2, K1 and Tst read per degree (SPEC §1)
P_HD2 = hdjax.Parameters(alpha=0.5, K1=104.2 * DEG, Tst=7.96 * DEG**0.5, Jeff=1.0e-4, Tvp=1.8e-3, Tvn=2.1e-3,
                         Tsp=7.5e-2, Tsn=3.3e-2, Tssp1=-0.0487, Tssn1=-0.0450, Tss2=0.1)
DRIVE_HD2 = hdjax.Drive(gear_ratio=160.0, torque_constant=0.1815, load_inertia=0.5)
MAX_STEPS = 1_000_000
SOLVERS = {"Tsit5": dfx.Tsit5, "Dopri8": dfx.Dopri8, "Kvaerno5": dfx.Kvaerno5, "Rodas3": hdjax.Rodas3}
RTOLS = (1e-6, 1e-7)
ATOL_OVER_RTOL = 1e-2  # as the Simulator default (rtol 1e-7, atol 1e-9)


def make_currents(n_exp: int, duration: float, dt: float = 1e-3, seed: int = 0):
    """Sine and square currents (A) starting from rest (50 ms ramp), alternating locked / free."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration, dt)
    ramp = np.minimum(1.0, t / 0.05)
    out = []
    for k in range(n_exp):
        mode = "constrained" if k % 2 == 0 else "free"
        shape = "sine" if (k // 2) % 2 == 0 else "square"
        # locked: up to ~90 N·m; free: keep the 0.5 kg·m² load below ~10 rad/s
        amp = rng.uniform(0.5, 3.0) if mode == "constrained" else rng.uniform(0.2, 0.8)
        freq = rng.uniform(0.5, 5.0) if mode == "constrained" else rng.uniform(3.0, 8.0)
        phase = np.sin(2 * np.pi * freq * t)
        wave = phase if shape == "sine" else np.sign(phase)
        out.append((mode, shape, amp * wave * ramp))
    return t, out


def build_batch(n_exp: int, duration: float, reference: hdjax.Simulator):
    """Experiments whose measured channels are an initial simulation of the plant."""
    t, currents = make_currents(n_exp, duration)
    z = np.zeros_like(t)
    blank = [hdjax.make_experiment(t, i, z, z, mode=m, output_position=z) for m, _, i in currents]
    traj = eqx.filter_jit(hdjax.simulate_batch)(P_HD2, DRIVE_HD2, hdjax.stack_experiments(blank), simulator=reference)
    assert bool(np.all(np.asarray(traj.success))), "initial simulation failed"
    exps = [
        hdjax.make_experiment(t, i, np.asarray(traj.torque[k]), np.asarray(traj.motor_velocity[k]), mode=m,
                              output_position=np.asarray(traj.output_position[k]) if m == "free" else z)
        for k, (m, _, i) in enumerate(currents)
    ]
    return hdjax.stack_experiments(exps), [(m, s) for m, s, _ in currents]


def timed_run(simulator, batch, repeats):
    """(trajectory, first-call time, median of `repeats` later calls; the first call's if 0)."""
    sim = eqx.filter_jit(hdjax.simulate_batch)
    t0 = time.perf_counter()
    traj = jax.block_until_ready(sim(P_HD2, DRIVE_HD2, batch, simulator=simulator))
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(sim(P_HD2, DRIVE_HD2, batch, simulator=simulator))
        runs.append(time.perf_counter() - t0)
    return traj, first, statistics.median(runs) if runs else first


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experiments", type=int, default=20)
    parser.add_argument("--duration", type=float, default=2.0, help="s per experiment")
    parser.add_argument("--repeats", type=int, default=1, help="timed calls after the compiling one (median)")
    parser.add_argument("--solvers", default=",".join(SOLVERS), help="comma-separated subset of " + ",".join(SOLVERS))
    args = parser.parse_args()
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")

    reference = hdjax.Simulator(solver=dfx.Dopri8(), rtol=1e-10, atol=1e-12, max_steps=MAX_STEPS)
    t0 = time.perf_counter()
    batch, kinds = build_batch(args.experiments, args.duration, reference)
    ref, _, ref_s = timed_run(reference, batch, 0)
    print(f"batch: {args.experiments} experiments x {args.duration:g} s at 1 kHz "
          f"({sum(m == 'constrained' for m, _ in kinds)} locked, {sum(m == 'free' for m, _ in kinds)} free; "
          f"sine and square), built in {time.perf_counter() - t0:.1f} s")
    print(f"reference: Dopri8 rtol 1e-10 atol 1e-12, run {ref_s:.1f} s, max steps {int(np.max(ref.num_steps))}, "
          f"all succeeded {bool(np.all(np.asarray(ref.success)))}")
    T_ref = np.asarray(ref.torque)
    scale = np.max(np.abs(T_ref), axis=1)
    locked = np.array([m == "constrained" for m, _ in kinds])
    # How good is the reference? An independent method (Rodas3) at a tight tolerance must agree.
    check = hdjax.Simulator(rtol=1e-9, atol=1e-11, max_steps=MAX_STEPS)
    chk, _, chk_s = timed_run(check, batch, 0)
    chk_err = np.max(np.abs(np.asarray(chk.torque) - T_ref), axis=1) / scale
    print(f"reference check: Rodas3 rtol 1e-9 atol 1e-11 vs reference, max rel torque difference "
          f"{chk_err.max():.1e} (locked {chk_err[locked].max():.1e}, free {chk_err[~locked].max():.1e}), "
          f"{chk_s:.1f} s incl. compile")

    header = (f"{'solver':9s} {'rtol':>6s} {'atol':>6s} {'run s':>8s} {'compile s':>9s} {'max steps':>10s} "
              f"{'steps/sample':>12s} {'max rel err':>11s} {'locked':>9s} {'free':>9s} {'ok':>3s}")
    print(header)
    print("-" * len(header))
    for name in args.solvers.split(","):
        for rtol in RTOLS:
            sim = hdjax.Simulator(solver=SOLVERS[name](), rtol=rtol, atol=ATOL_OVER_RTOL * rtol, max_steps=MAX_STEPS)
            traj, first, run_s = timed_run(sim, batch, args.repeats)
            err = np.max(np.abs(np.asarray(traj.torque) - T_ref), axis=1) / scale
            steps = np.asarray(traj.num_steps)
            ok = bool(np.all(np.asarray(traj.success)))
            print(f"{name:9s} {rtol:6.0e} {ATOL_OVER_RTOL * rtol:6.0e} {run_s:8.2f} {first - run_s:9.1f} "
                  f"{int(steps.max()):10d} {steps.mean() / batch.time.shape[1]:12.2f} {err.max():11.2e} "
                  f"{err[locked].max():9.2e} {err[~locked].max():9.2e} {'yes' if ok else 'NO':>3s}", flush=True)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"jax {jax.__version__} on {jax.devices()[0].platform}")


if __name__ == "__main__":
    main()
