"""The CasADi + SUNDIALS CVODES column of `fit_vs_scipy.py` (see that module's docstring).

`build_casadi_fit` writes the smoothed model of `fit_vs_scipy.simulate_scipy` symbolically and
returns two `casadi.Function`s of the unconstrained unknowns theta: the stacked whitened residual
vector and its exact Jacobian. No hdjax inside: only numbers (data, drive constants, start point,
noise levels, the initial-state line fits) come in.

The Jacobian is `casadi.jacobian` of the symbolic residual (an MX graph around one CVODES
integrator call per record) with respect to theta. CasADi evaluates it in forward mode: it builds
the forward-sensitivity equations of the ODE by AD (SX, exact) and integrates states and the
sensitivity directions together with CVODES (BDF, Newton with the state Jacobian factorised once
and reused for every sensitivity block; sensitivities are states of the augmented system, so they
take part in the error test). The initial state depends on theta (q0 on K1, Tst; wo0 on K1) and
is part of the same graph, so its derivative is included.
"""

import casadi as ca
import numpy as np

VEL_SCALE, RATE_SCALE = 1e-3, 1e-5  # as fit_vs_scipy (hdjax.Smoothing())
MODEL = ("K1", "Tst", "alpha", "Jeff", "Tvp", "Tvn", "Tsp", "Tsn", "Tssp1", "Tssn1", "Tss2")


def _ssp(x, alpha):  # smoothed |x|^alpha sign(x), as fit_vs_scipy._ssp
    return x * (x * x + RATE_SCALE * RATE_SCALE) ** ((alpha - 1.0) / 2.0)


def _integrator(tout, drive, rtol, opts):
    """CVODES (BDF) integrator of the smoothed model with output at one record's sample times
    `tout` (t0 = 0), the current piecewise linear between the samples.

    DAE parameters: the 11 model parameters and the free-motion flag. Control u = (a, b), constant
    on each sample interval (CasADi's piecewise-constant `u` on the output grid), current = a + b·t:
    the straight line through the interval's two current samples. CasADi re-initialises CVODES
    wherever u changes, i.e. at every sample, so no step straddles a kink of the current."""
    N, Km, Jl = drive["N"], drive["Km"], drive["Jload"]
    x = ca.SX.sym("x", 4)
    t = ca.SX.sym("t")
    u = ca.SX.sym("u", 2)
    prm = ca.SX.sym("prm", len(MODEL) + 1)
    K1, Tst, al, Je, Tvp, Tvn, Tsp, Tsn, Ts1p, Ts1n, Tss2, free = ca.vertsplit(prm)
    current = u[0] + u[1] * t
    q, wm, wo = x[0], x[1], x[3]
    rate = wm / N - wo
    T = K1 * q + Tst * _ssp(rate, al)
    th = ca.tanh(wm / VEL_SCALE)
    up = 0.5 * (1 + th)
    un = 1 - up
    strib = ca.exp(-((wm / Tss2) ** 2))
    Tf = wm * (Tvp * up + Tvn * un) + th * (Tsp * up + Tsn * un) + th * strib * (Ts1p * up + Ts1n * un)
    ode = ca.vertcat(rate, (Km * current - T / N - Tf) / Je, wo, free * T / Jl)
    o = {"reltol": rtol, "abstol": rtol * 1e-2, "linear_multistep_method": "bdf", "max_num_steps": 100000} | opts
    return ca.integrator("F", "cvodes", {"x": x, "t": t, "u": u, "p": prm, "ode": ode}, 0.0, list(tout), o)


def _current_lines(tout, cur):
    """u = (a, b) per output interval k (from tout[k-1] to tout[k]; column 0 covers the empty
    interval [0, tout[0]] = [0, 0]) with a + b·t through (tout[k-1], cur[k-1]), (tout[k], cur[k])."""
    b = np.r_[0.0, np.diff(cur) / np.diff(tout)]
    a = np.r_[cur[0], cur[:-1] - tout[:-1] * b[1:]]
    return np.vstack([a, b])


def build_casadi_fit(p0, drive, exps, starts, sigma, rtol, free_names, positive, opts=None):
    """Residual and Jacobian `casadi.Function`s of theta (same coordinates as fit_vs_scipy.to_params).

    exps: the plain-dict experiments of fit_vs_scipy; starts: per experiment (wm0, T0, dT0, tho0),
    the line fits that `simulate_scipy` makes; sigma: the three noise levels."""
    theta = ca.MX.sym("theta", len(free_names))
    p = {k: ca.MX(float(v)) for k, v in p0.items()}
    for j, k in enumerate(free_names):
        p[k] = ca.exp(theta[j]) if k in positive else theta[j] * max(abs(p0[k]), 1e-3)
    N = drive["N"]
    cache = {}
    res = []
    for e, (wm0, T0, dT0, tho0) in zip(exps, starts):
        t = np.asarray(e["time"], dtype=float)
        n = len(t)
        tout = t - t[0]
        key = tout.tobytes()
        if key not in cache:
            cache[key] = _integrator(tout, drive, rtol, opts or {})
        F = cache[key]
        fr = float(e["free"])
        wo0 = (wm0 / N - dT0 / p["K1"]) if fr else ca.MX(0.0)
        q0 = (T0 - p["Tst"] * _ssp(wm0 / N - wo0, p["alpha"])) / p["K1"]
        x0 = ca.vertcat(q0, wm0, tho0, wo0)
        prm = ca.vertcat(*[p[k] for k in MODEL], fr)
        X = F(x0=x0, p=prm, u=_current_lines(tout, np.asarray(e["current"], dtype=float)))["xf"]  # 4 x n
        q, wm, tho, wo = (X[i, :].T for i in range(4))
        T = p["K1"] * q + p["Tst"] * _ssp(wm / N - wo, p["alpha"])
        r_T = (T - np.asarray(e["torque"])) / sigma[0]
        r_w = (wm - np.asarray(e["motor_velocity"])) / sigma[1]
        if fr:
            r_pos = (tho - np.asarray(e["output_position"])) / sigma[2]
            tt = t - t[0]
            basis = np.stack([np.ones_like(tt), tt - tt.mean()])
            coef = ca.mtimes(ca.DM(basis), r_pos) / np.sum(basis**2, axis=1)
            r_pos = r_pos - ca.mtimes(ca.DM(basis.T), coef)
        else:
            r_pos = ca.DM.zeros(n, 1)
        res.append(ca.vertcat(r_T, r_w, r_pos))
    r = ca.vertcat(*res)
    R = ca.Function("R", [theta], [r])
    J = ca.Function("J", [theta], [ca.jacobian(r, theta)])
    return R, J
