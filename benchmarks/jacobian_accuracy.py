"""Benchmark (not a test): how accurate are the forward-mode Jacobians that the fit and the
diagnosis take through the adaptive Rodas3 solve, per ODE tolerance and per active effect?

`jax.jacfwd` through `diffeqsolve` differentiates the discrete solve with the step sizes frozen
(diffrax stops gradients through the step-size controller); the controller's error test sees only
the states, not the tangents. So a tangent can be far less accurate than the state it rides on.
This script measures it: the relative error of each Jacobian column of `experiment_residuals`
(whitened torque, motor velocity, output position of one record) at rtol 1e-4, 1e-5 and 1e-6
(atol = rtol/100) against rtol 1e-8, on a 16-record dataset of the independent bench (the one
`benchmarks/diagnose_16.py` diagnoses: HD1, seed 11, an order-2 kinematic error at 4× noise),
for the paper model alone and with one SPEC §4 effect (or §4b `sensor_bandwidth`) switched on at a
typical magnitude.

Columns: K1 (relative change) and the effect's own parameter. Usage:
`python benchmarks/jacobian_accuracy.py [record index ...] [--frozen | --w-method [--stiff]]` (default: a
locked and two free records; exact tangents through `Rodas3`). `--frozen`: `Rodas3` with tangents that
hold each step's J constant; `--w-method`: `Ros34PW2`, whose such tangents keep its order; `--stiff`:
with the J-tangent of `hdjax.plant_stiff_part` kept.
"""

import sys
import tempfile

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from hdjax import (  # noqa: E402
    Effects,
    Rodas3,
    Ros34PW2,
    Simulator,
    experiment_residuals,
    identify_paper,
    load_dataset,
    noise_levels,
    plant_stiff_part,
    stack_experiments,
)
from hdjax.bench import make_dataset  # noqa: E402

with tempfile.TemporaryDirectory() as tmp:
    spec = {"snr": 4.0, "channels": ["torque", "motor_velocity"], "orders": [2]}
    make_dataset(tmp, drive="hd1", seed=11, n_locked=8, n_free=8, duration=2.5, effects={"kinematic_error": spec})
    ds = load_dataset(tmp)
dyn = ds.dynamic_indices()
exps = [ds.experiments[i] for i in dyn]
p0 = identify_paper(exps, ds.drive).parameters()
sigma = noise_levels(stack_experiments(exps))

# one effect at a time, its parameter as x[1] (magnitudes about those the bench hides at 4x noise)
CASES = {
    "paper model": lambda x: Effects(),
    "kinematic_error [2]": lambda x: Effects().with_periodic("kinematic_error", 2, 5e-5 * (1 + x[1])),
    "torque_sensor_ripple [2]": lambda x: Effects().with_periodic("torque_sensor_ripple", 2, 0.5 * (1 + x[1])),
    "cogging [2]": lambda x: Effects().with_periodic("cogging", 2, 2e-3 * (1 + x[1])),
    "sensor_bandwidth": lambda x: Effects().with_values("sensor_bandwidth", torque_lag=3e-4 * (1 + x[1]), velocity_lag=5e-4),
    "thermal_drift": lambda x: Effects().with_values("thermal_drift", tau=600.0, beta=0.01 * (1 + x[1])),
    "nonlinear_stiffness": lambda x: Effects().with_values("nonlinear_stiffness", K3=1e3 * (1 + x[1])),
}
RTOLS = (1e-4, 1e-5, 1e-6)
REFERENCE = 1e-8

# --frozen: Rodas3 tangents with the step matrix held constant; --w-method: `Ros34PW2` (frozen, its default)
FROZEN = "--frozen" in sys.argv
W_METHOD = "--w-method" in sys.argv
STIFF = "--stiff" in sys.argv  # with --w-method: keep the second derivatives of the plant's stiff terms
records = [int(a) for a in sys.argv[1:] if not a.startswith("--")] or [0, 8, 11]
print(f"dataset: independent bench, HD1, seed 11, {len(exps)} records; columns K1 and the effect's parameter; "
      f"relative column error against rtol {REFERENCE:g} (exact tangents)"
      + ("; Ros34PW2 with frozen-J tangents" + (" except the stiff terms" if STIFF else "") if W_METHOD
         else "; Rodas3 tangents with J frozen" if FROZEN else ""))
print("| record | effect | " + " | ".join(f"rtol {r:g}" for r in RTOLS) + " |")
print("|---|---|" + "---|" * len(RTOLS))
for k in records:
    e = exps[k]
    name = ds.files[dyn[k]]
    for case, effects_of in CASES.items():

        def residual(x, sim, e=e, effects_of=effects_of):
            p = p0.replace(K1=p0.K1 * (1 + x[0]))
            return experiment_residuals(p, ds.drive, e, sigma, sim, effects_of(x)).ravel()

        jac = {}
        for rt in RTOLS + (REFERENCE,):
            if rt == REFERENCE:
                solver = Rodas3()
            else:
                w = Ros34PW2(stiff_part=plant_stiff_part) if STIFF else Ros34PW2()
                solver = w if W_METHOD else Rodas3(frozen_jacobian_tangents=FROZEN)
            sim = Simulator(rtol=rt, atol=rt * 1e-2, solver=solver)
            jac[rt] = np.asarray(jax.jit(jax.jacfwd(lambda x, sim=sim: residual(x, sim)))(jnp.zeros(2)))
        ref = jac[REFERENCE]
        cells = []
        for rt in RTOLS:
            err = np.linalg.norm(jac[rt] - ref, axis=0) / np.maximum(np.linalg.norm(ref, axis=0), 1e-300)
            cells.append(f"K1 {err[0]:.1e}" + ("" if case == "paper model" else f", own {err[1]:.1e}"))
        print(f"| {name} | {case} | " + " | ".join(cells) + " |", flush=True)
