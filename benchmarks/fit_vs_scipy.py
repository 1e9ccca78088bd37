"""Benchmark (not a test): hdjax's joint trajectory-error fit against the same fit written the way a
user without hdjax would write it — scipy `solve_ivp` (implicit, stiff) + scipy `least_squares`
with a finite-difference Jacobian — timed in one run on the same experiments.

What is compared (both sides identical except for the numerics engine):

- data: a subset of `data/hd2` (default 2 constrained + 2 free experiments, the first
  `--samples` samples = 0.5 s at 1 kHz of each record; change with the options);
- model: eqs. 5, 8, 9 with the same smoothing as `hdjax._model` (tanh sign/step at 1e-3 rad/s,
  x(x²+s²)^((α-1)/2) power at 1e-5 rad/s), the same states (torsion, motor velocity, output angle,
  output velocity), the same initial state (local line fits with rest detection, as
  `hdjax.initial_state`), piecewise-linear current;
- residuals: torque, motor velocity and (free motion) output position, each divided by the same
  noise levels (`hdjax._fit.noise_levels`, computed once and given to both), the output-position
  residual projected off {offset, slope} per experiment, as `hdjax._fit.experiment_residuals`;
- unknowns: the same nine parameters (`DEFAULT_FREE`) in the same unconstrained coordinates (log
  of the positive ones, Stribeck amplitudes scaled by their start value); alpha, Tss2 fixed;
- start point: the paper's identification on all 50 HD2 experiments (`identify_paper`);
- ODE tolerances rtol 1e-6, atol 1e-8 on both sides (hdjax `Simulator(rtol=1e-6, atol=1e-8)`,
  scipy `solve_ivp(rtol=1e-6, atol=1e-8)`); `--ode-rtol` changes both (atol = rtol/100; the fit
  command's joint fit uses rtol 1e-5);
- stopping: optimistix LM `rtol = atol = 1e-6` (relative step and cost change) vs scipy
  `xtol = ftol = 1e-6`; the same cap on LM iterations (`--max-steps`; scipy: `max_nfev` =
  max_steps·(1 + 9) evaluations, because each finite-difference Jacobian costs 9 of them).

The finite-difference step is set to 1e-3 (relative), about the square root of the ODE tolerance,
as a careful user would: with scipy's default step (~1.5e-8) the differences are dominated by the
adaptive solver's tolerance-level noise, and least_squares stopped after 5 evaluations on an
`xtol` test with the cost unchanged (measured; `--diff-step 0` gives scipy's default).
LSODA is the default integrator because it was the fastest of the three on these records
(0.5 s per 500-sample record, against 3.5–4.3 s for BDF and 5.9–6.8 s for Radau, measured).

hdjax's time includes its compilation (a user pays it; `fit_parameters` compiles once per call).
An observer on the LM iterations (a `jax.debug.callback` timestamping each step) splits hdjax's
time into compilation, per-step time and the final covariance, and gives the time at which
hdjax's accepted cost first reached scipy's final cost (printed as the equal-cost ratio).
Both final costs are ½·Σr² evaluated with the *same* scipy residual function, so they are
directly comparable. The last line printed is `speedup_vs_scipy: <scipy time / hdjax time>`.

Usage: `python benchmarks/fit_vs_scipy.py [--constrained 2] [--free 2] [--samples 500]
[--max-steps 20] [--method LSODA] [--data data/hd2]`
"""

import argparse
import math
import os
import pathlib
import platform
import time

import jax


jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402
import scipy  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

import hdjax  # noqa: E402
from hdjax._data import load_dataset  # noqa: E402
from hdjax._experiment import Experiment  # noqa: E402
from hdjax._fit import DEFAULT_FREE, POSITIVE, experiment_residuals, fit_parameters, noise_levels  # noqa: E402
from hdjax._paper_id import identify_paper  # noqa: E402


ROOT = pathlib.Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------------------------------
# The reference: plain numpy/scipy, written from the paper's equations (no hdjax inside)
# ---------------------------------------------------------------------------------------------

VEL_SCALE, RATE_SCALE = 1e-3, 1e-5  # the smoothing scales of hdjax.Smoothing()


def _line_at_start(t, y, n=11):
    """Value/slope at t[0] of a line through the first n samples; zeroed when below 3 std errors."""
    tt, yy = t[:n] - t[0], y[:n]
    tm, ym = tt.mean(), yy.mean()
    sxx = max(np.sum((tt - tm) ** 2), 1e-300)
    slope = np.sum((tt - tm) * (yy - ym)) / sxx
    value = ym - slope * tm
    s2 = np.sum((yy - value - slope * tt) ** 2) / max(n - 2.0, 1.0)
    if abs(value) < 3 * math.sqrt(s2 * (1 / n + tm**2 / sxx)):
        value = 0.0
    if abs(slope) < 3 * math.sqrt(s2 / sxx):
        slope = 0.0
    return value, slope


def _ssp(x, alpha):  # smoothed |x|^alpha sign(x)
    return x * (x * x + RATE_SCALE * RATE_SCALE) ** ((alpha - 1.0) / 2.0)


def simulate_scipy(p, drive, e, method, rtol=1e-6):
    """One experiment with solve_ivp; returns (torque, motor velocity, output angle, ok)."""
    N, Km, Jl = drive["N"], drive["Km"], drive["Jload"]
    t = e["time"]
    dt = t[1] - t[0]
    cur = e["current"]
    free = e["free"]
    wm0, _ = _line_at_start(t, e["motor_velocity"])
    T0, dT0 = _line_at_start(t, e["torque"])
    tho0 = _line_at_start(t, e["output_position"])[0] if free else 0.0
    wo0 = (wm0 / N - dT0 / p["K1"]) if free else 0.0
    q0 = (T0 - p["Tst"] * _ssp(wm0 / N - wo0, p["alpha"])) / p["K1"]
    K1, Tst, al, Je = p["K1"], p["Tst"], p["alpha"], p["Jeff"]
    Tvp, Tvn, Tsp, Tsn, Ts1p, Ts1n, Tss2 = (p[k] for k in ("Tvp", "Tvn", "Tsp", "Tsn", "Tssp1", "Tssn1", "Tss2"))
    n = len(t)
    t0 = t[0]

    def f(tk, y):
        q, wm, _, wo = y
        s = (tk - t0) / dt
        i = min(max(int(s), 0), n - 2)
        w = s - i
        current = (1 - w) * cur[i] + w * cur[i + 1]
        rate = wm / N - wo
        T = K1 * q + Tst * rate * (rate * rate + RATE_SCALE * RATE_SCALE) ** ((al - 1) / 2)
        th = math.tanh(wm / VEL_SCALE)
        up = 0.5 * (1 + th)
        un = 1 - up
        strib = math.exp(-((wm / Tss2) ** 2))
        Tf = wm * (Tvp * up + Tvn * un) + th * (Tsp * up + Tsn * un) + th * strib * (Ts1p * up + Ts1n * un)
        return [rate, (Km * current - T / N - Tf) / Je, wo, free * T / Jl]

    sol = solve_ivp(f, (t[0], t[-1]), [q0, wm0, tho0, wo0], method=method, t_eval=t, rtol=rtol, atol=rtol * 1e-2)
    if not sol.success or sol.y.shape[1] != n:
        return None
    q, wm, tho, wo = sol.y
    T = K1 * q + Tst * _ssp(wm / N - wo, al)
    return T, wm, tho


def to_params(theta, p0):
    p = dict(p0)
    for k, v in zip(DEFAULT_FREE, theta):
        p[k] = math.exp(v) if k in POSITIVE else v * max(abs(p0[k]), 1e-3)
    return p


def to_theta(p, p0):
    return np.array([math.log(p[k]) if k in POSITIVE else p[k] / max(abs(p0[k]), 1e-3) for k in DEFAULT_FREE])


def residuals_scipy(theta, p0, drive, exps, sigma, method, rtol=1e-6):
    p = to_params(theta, p0)
    out = []
    for e in exps:
        sim = simulate_scipy(p, drive, e, method, rtol)
        if sim is None:
            out.append(np.full(3 * len(e["time"]), 1e3))
            continue
        T, wm, tho = sim
        r_pos = np.zeros_like(T)
        if e["free"]:
            r_pos = (tho - e["output_position"]) / sigma[2]
            tt = e["time"] - e["time"][0]
            basis = np.stack([np.ones_like(tt), tt - tt.mean()])
            r_pos = r_pos - (basis @ r_pos) / np.sum(basis**2, axis=1) @ basis
        out.append(np.concatenate([(T - e["torque"]) / sigma[0], (wm - e["motor_velocity"]) / sigma[1], r_pos]))
    return np.concatenate(out)


# ---------------------------------------------------------------------------------------------


def _trim(e: Experiment, n: int) -> Experiment:
    return Experiment(**{k: (getattr(e, k)[:n] if getattr(e, k).ndim == 1 else getattr(e, k))
                         for k in Experiment.__dataclass_fields__})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=pathlib.Path, default=ROOT / "data" / "hd2")
    ap.add_argument("--constrained", type=int, default=2)
    ap.add_argument("--free", type=int, default=2)
    ap.add_argument("--samples", type=int, default=500, help="samples kept from the start of each record")
    ap.add_argument("--max-steps", type=int, default=20, help="cap on LM iterations (both sides)")
    ap.add_argument("--method", default="LSODA", help="solve_ivp method (Radau, BDF, LSODA)")
    ap.add_argument("--diff-step", type=float, default=1e-3,
                    help="relative finite-difference step of least_squares (default 1e-3 ≈ sqrt(ODE rtol))")
    ap.add_argument("--scipy-tol", type=float, default=1e-6,
                    help="least_squares xtol and ftol (default 1e-6, optimistix LM's rtol/atol)")
    ap.add_argument("--ode-rtol", type=float, default=1e-6, help="ODE rtol on both sides (atol = rtol/100)")
    args = ap.parse_args()

    ds = load_dataset(args.data)
    dyn = ds.dynamic_indices()
    cons = [i for i in dyn if ds.modes[i] == "constrained"]
    free = [i for i in dyn if ds.modes[i] == "free"]
    pick = lambda lst, k: [lst[int(round(j))] for j in np.linspace(0, len(lst) - 1, k)] if k else []  # noqa: E731
    sel = pick(cons, args.constrained) + pick(free, args.free)
    exps = [_trim(ds.experiments[i], args.samples) for i in sel]
    batch = hdjax.stack_experiments(exps)
    p0 = identify_paper([ds.experiments[i] for i in dyn], ds.drive).parameters()
    sigma = noise_levels(batch)

    d = ds.drive
    drive = {"N": float(d.gear_ratio), "Km": float(d.torque_constant), "Jload": float(d.load_inertia)}
    p0d = p0.to_dict()
    sig = np.asarray(sigma)
    plain = [{k: np.asarray(getattr(e, k)) for k in ("time", "current", "torque", "motor_velocity", "output_position")}
             | {"free": float(e.free)} for e in exps]
    n_samples = sum(len(e["time"]) for e in plain)
    print(f"problem: {len(sel)} HD2 experiments ({args.constrained} constrained, {args.free} free): "
          f"{', '.join(ds.files[i] for i in sel)}; first {args.samples} samples each ({n_samples} samples, "
          f"{3 * n_samples} residuals); {len(DEFAULT_FREE)} free parameters; start = identify_paper on all "
          f"{len(dyn)} experiments; ODE rtol {args.ode_rtol:g}; noise levels {', '.join(f'{s:.3g}' for s in sig)}", flush=True)

    simulator = hdjax.Simulator(rtol=args.ode_rtol, atol=args.ode_rtol * 1e-2)  # atol as in simulate_scipy
    # the reference must simulate the same model: compare both simulations at the start point
    tr = eqx.filter_jit(hdjax.simulate_batch)(p0, ds.drive, batch, simulator=simulator)
    worst = 0.0
    for k, e in enumerate(plain):
        T, wm, tho = simulate_scipy(p0d, drive, e, args.method, args.ode_rtol)
        worst = max(worst, np.max(np.abs(T - np.asarray(tr.torque[k]))) / sig[0],
                    np.max(np.abs(wm - np.asarray(tr.motor_velocity[k]))) / sig[1])
    print(f"check: hdjax vs scipy simulation at the start point, max |difference| = {worst:.3g} noise std "
          f"(torque, motor velocity)", flush=True)

    theta0 = to_theta(p0d, p0d)
    cost0 = 0.5 * np.sum(residuals_scipy(theta0, p0d, drive, plain, sig, args.method, args.ode_rtol) ** 2)

    # --- scipy ---
    scipy_log = []  # (seconds since start, cost) of every residual evaluation, finite differences included

    def residuals_logged(theta, *a):
        r = residuals_scipy(theta, *a)
        scipy_log.append((time.perf_counter() - t0, 0.5 * float(np.sum(r**2))))
        return r

    t0 = time.perf_counter()
    ref = least_squares(residuals_logged, theta0, args=(p0d, drive, plain, sig, args.method, args.ode_rtol), method="lm",
                        jac="2-point", diff_step=args.diff_step or None, xtol=args.scipy_tol, ftol=args.scipy_tol,
                        gtol=1e-10, max_nfev=args.max_steps * (1 + len(DEFAULT_FREE)))
    t_scipy = time.perf_counter() - t0
    print(f"scipy: solve_ivp({args.method}) + least_squares(lm, 2-point): {t_scipy:.1f} s, {ref.nfev} residual "
          f"evaluations (incl. finite differences), status {ref.status} ({ref.message})", flush=True)

    # --- hdjax ---
    # fit_parameters' default LM, with an observer that timestamps every LM step on the host (a
    # jax.debug.callback; it reads the loss, it does not change the iteration)
    log = []

    def observe(**kw):
        def record(step, loss_eval, loss_accepted):
            log.append((time.perf_counter(), int(step), float(loss_eval), float(loss_accepted)))

        jax.debug.callback(record, kw["num_steps"][1], kw["loss_this_step"][1], kw["loss_last_accepted_step"][1])

    lm = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-6, verbose=observe)
    t0 = time.perf_counter()
    res = fit_parameters(p0, ds.drive, batch, free=DEFAULT_FREE, simulator=simulator, solver=lm,
                         max_steps=args.max_steps, sigma=sigma)
    t_hdjax = time.perf_counter() - t0
    print(f"hdjax: fit_parameters (optimistix LM, jacfwd through Rodas3): {t_hdjax:.1f} s incl. compilation, "
          f"{res.steps} LM steps, converged {res.converged}", flush=True)
    if log:
        first = log[0][0] - t0
        per_step = (log[-1][0] - log[0][0]) / max(len(log) - 1, 1)
        print(f"hdjax profile: {first:.1f} s until the first LM step reported (compilation + first residual and "
              f"linearisation), then {per_step:.2f} s per LM step ({len(log)} steps), "
              f"{t_hdjax - (log[-1][0] - t0):.1f} s after the last step (final residual, Jacobian, covariance)")
        print("hdjax LM accepted cost by step: " + ", ".join(f"{k}:{acc:.6g}" for _, k, _, acc in log if k >= 1))
        # equal-cost comparison: the first accepted hdjax iterate at or below scipy's final cost,
        # both costs from hdjax's residual function
        p_ref = hdjax.Parameters.from_dict(to_params(ref.x, p0d))
        r_ref = eqx.filter_jit(lambda p, b: jax.vmap(lambda e: experiment_residuals(p, ds.drive, e, sigma, simulator))(b))(
            p_ref, batch)
        cost_ref_h = 0.5 * float(np.sum(np.asarray(r_ref) ** 2))
        # (step 0 reports no accepted cost yet: optimistix's placeholder is 0)
        hit = next(((t, k) for t, k, _, acc in log if k >= 1 and 0 < acc <= cost_ref_h), None)
        if hit:
            print(f"equal cost: hdjax's accepted cost first fell to scipy's final cost ({cost_ref_h:.6g} in hdjax's "
                  f"residuals) after {hit[1]} LM steps, {hit[0] - t0:.1f} s incl. compilation: ratio "
                  f"{t_scipy / (hit[0] - t0):.2f}")
        else:
            print(f"equal cost: hdjax's accepted cost never fell to scipy's final cost ({cost_ref_h:.6g})")

    theta_h = to_theta(res.params.to_dict(), p0d)
    cost_h = 0.5 * np.sum(residuals_scipy(theta_h, p0d, drive, plain, sig, args.method, args.ode_rtol) ** 2)
    cost_s = 0.5 * np.sum(ref.fun**2)
    hit = next((t for t, c in scipy_log if c <= cost_h * (1 + 1e-4)), None)
    print(f"scipy's evaluated cost reached hdjax's final cost (+0.01 %): "
          + (f"after {hit:.1f} s" if hit is not None else f"never within its {t_scipy:.1f} s (lowest "
             f"{min(c for _, c in scipy_log):.6g}, {len(scipy_log)} evaluations)"))
    print(f"start cost:  {cost0:.6g}   (1/2 sum r^2, scipy residual function)")
    print(f"final cost:  scipy {cost_s:.6g}   hdjax {cost_h:.6g}   (relative difference "
          f"{(cost_h - cost_s) / cost_s:+.2e}; both evaluated with the scipy residual function)")
    ps = to_params(ref.x, p0d)
    for k in DEFAULT_FREE:
        print(f"  {k:6s} scipy {ps[k]:.6g}  hdjax {float(getattr(res.params, k)):.6g}")
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.2f}, jax {jax.__version__}, scipy {scipy.__version__}, XLA_FLAGS="
          f"{os.environ.get('XLA_FLAGS', '')!r}")
    print(f"time: scipy {t_scipy:.1f} s, hdjax {t_hdjax:.1f} s")
    print(f"speedup_vs_scipy: {t_scipy / t_hdjax:.2f}")


if __name__ == "__main__":
    main()
