"""Rodas3: its coefficients satisfy the Rosenbrock order conditions, and the diffrax solver built on
them shows order 3, L-stability on a stiff problem and adaptive control to the requested rtol."""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hdjax
from hdjax._plant.rosenbrock import GAMMA, RODAS3, ROS34PW2
from helpers import hd2, host_callbacks, sine_experiment

# ------------------------------------------------------------------------------------------------
# Coefficients (Hairer & Wanner, Solving ODEs II, §IV.7, order conditions for Rosenbrock methods)
# ------------------------------------------------------------------------------------------------

S = 4


def _tableau(tab=RODAS3):
    a = np.zeros((S, S))
    g = np.zeros((S, S))
    for i in range(S):
        assert len(tab.alpha[i]) == len(tab.gammas[i]) == i
        a[i, :i] = tab.alpha[i]
        g[i, :i] = tab.gammas[i]
    return a, g, np.array(tab.b), np.array(tab.b_hat)


def test_order_conditions_up_to_three():
    a, g, b, _ = _tableau()
    beta = a + g  # β_ij = α_ij + γ_ij (j < i)
    beta_i = beta.sum(axis=1)  # β'_i = Σ_j β_ij
    alpha_i = a.sum(axis=1)  # α_i = Σ_j α_ij
    tol = 1e-14
    assert abs(b.sum() - 1.0) < tol  # order 1
    assert abs(b @ beta_i - (0.5 - GAMMA)) < tol  # order 2
    assert abs(b @ alpha_i**2 - 1.0 / 3.0) < tol  # order 3 (bushy tree)
    assert abs(b @ beta @ beta_i - (1.0 / 6.0 - GAMMA + GAMMA**2)) < tol  # order 3 (tall tree)


def test_embedded_method_has_order_two_but_not_three():
    a, g, _, bh = _tableau()
    beta = a + g
    beta_i = beta.sum(axis=1)
    alpha_i = a.sum(axis=1)
    assert abs(bh.sum() - 1.0) < 1e-14
    assert abs(bh @ beta_i - (0.5 - GAMMA)) < 1e-14
    # it must fail a third-order condition, or the difference would not estimate the error
    assert abs(bh @ alpha_i**2 - 1.0 / 3.0) > 0.1 or abs(bh @ beta @ beta_i - (1 / 6 - GAMMA + GAMMA**2)) > 0.01


def test_stiffly_accurate():
    a, g, b, bh = _tableau()
    # main method: b_j = α_sj + γ_sj for j < s and b_s = γ, so y1 is the last stage's argument
    np.testing.assert_allclose(b[:-1], (a + g)[-1, :-1], rtol=0, atol=1e-15)
    assert b[-1] == GAMMA
    # embedded method: stiffly accurate on stage 3 (b̂_j = α_3j + γ_3j, b̂_3 = γ, b̂_4 = 0)
    np.testing.assert_allclose(bh[:2], (a + g)[2, :2], rtol=0, atol=1e-15)
    assert bh[2] == GAMMA and bh[3] == 0.0


def _stability_function(z, tab=RODAS3):
    a, g, b, _ = _tableau(tab)
    # y' = λy, z = hλ: (1 − zγ) k_i = z (y0 + Σ_j β_ij k_j)
    k = np.linalg.solve((1 - z * tab.gamma) * np.eye(S) - z * (a + g), z * np.ones(S))
    return 1.0 + b @ k


def test_l_stable():
    # A-stable: |R(iy)| ≤ 1 on the imaginary axis (the boundary of the left half plane) ...
    y = np.concatenate([np.logspace(-3, 6, 400), -np.logspace(-3, 6, 400)])
    assert np.max(np.abs([_stability_function(1j * v) for v in y])) <= 1.0 + 1e-12
    # ... and R(z) → 0 as z → −∞ (stiffly accurate): R(−1e3) ≈ −2.6e-3, R(−1e8) ≈ −2.7e-8
    assert abs(_stability_function(-1e3)) < 5e-3
    assert abs(_stability_function(-1e8)) < 1e-7
    # and the diffrax solver itself: one step of y' = λy with hλ = −1e8 damps y to ~0
    term = dfx.ODETerm(lambda t, y, args: -1e8 * y)
    y1, *_ = hdjax.Rodas3().step(term, 0.0, 1.0, jnp.array(1.0), None, None, False)
    np.testing.assert_allclose(float(y1), _stability_function(-1e8), rtol=1e-6)


# ------------------------------------------------------------------------------------------------
# Convergence on a nonlinear, non-autonomous ODE with a known solution: y' = −2t y², y(0) = 1,
# y(t) = 1 / (1 + t²)
# ------------------------------------------------------------------------------------------------


def _nonlinear(t, y, args):
    return -2.0 * t * y**2


def _exact(t):
    return 1.0 / (1.0 + t**2)


T_END = 2.0


@jax.jit
def _solve_fixed(dt):
    sol = dfx.diffeqsolve(dfx.ODETerm(_nonlinear), hdjax.Rodas3(), 0.0, T_END, dt, jnp.array(1.0),
                          stepsize_controller=dfx.ConstantStepSize(), max_steps=1024)
    return sol.ys[-1]


def test_fixed_step_convergence_order_three():
    ns = (20, 40, 80, 160)
    errors = np.array([abs(float(_solve_fixed(T_END / n)) - _exact(T_END)) for n in ns])
    orders = np.log2(errors[:-1] / errors[1:])
    # measured: errors 1.43e-5, 1.74e-6, 2.14e-7, 2.66e-8; orders 3.04, 3.02, 3.01
    assert np.all(np.abs(orders - 3.0) < 0.15), orders
    assert errors[-1] < 5e-8, errors


def test_embedded_error_estimate_is_third_order_local():
    """Single steps from the exact solution: the local error of y1 is O(h⁴) and the embedded
    estimate |y1 − ŷ1| (the 2nd-order method's local error) O(h³)."""
    term = dfx.ODETerm(_nonlinear)
    t0 = 0.5
    hs = (0.1, 0.05, 0.025)
    local, estimate = [], []
    for h in hs:
        y1, y_err, *_ = hdjax.Rodas3().step(term, t0, t0 + h, jnp.array(_exact(t0)), None, None, False)
        local.append(abs(float(y1) - _exact(t0 + h)))
        estimate.append(abs(float(y_err)))
    local_order = np.log2(np.array(local[:-1]) / np.array(local[1:]))
    est_order = np.log2(np.array(estimate[:-1]) / np.array(estimate[1:]))
    # measured: local 8.2e-6, 3.9e-7, 1.9e-8 (orders 4.39, 4.33); estimate 2.2e-4, 2.9e-5, 3.8e-6
    # (orders 2.89, 2.94)
    assert np.all(local_order > 3.8), local_order
    assert np.all(np.abs(est_order - 3.0) < 0.2), est_order
    assert np.all(np.array(estimate) > np.array(local))  # the estimate does not understate the error


@pytest.mark.parametrize("rtol", [1e-4, 1e-6, 1e-8])
def test_adaptive_pid_reaches_rtol(rtol):
    sol = dfx.diffeqsolve(dfx.ODETerm(_nonlinear), hdjax.Rodas3(), 0.0, T_END, 0.1, jnp.array(1.0),
                          stepsize_controller=dfx.PIDController(rtol=rtol, atol=1e-3 * rtol),
                          saveat=dfx.SaveAt(steps=True), max_steps=4096)
    ts = np.asarray(sol.ts)
    ok = np.isfinite(ts)
    ys = np.asarray(sol.ys)[ok]
    rel = np.abs(ys - _exact(ts[ok])) / np.abs(_exact(ts[ok]))
    # global error at every step, in units of rtol: measured 0.39, 0.41, 0.69 (26, 122, 557 steps)
    assert rel.max() < rtol, (rtol, rel.max() / rtol)
    # and the controller does not get there by wasting steps: steps ∝ rtol^(−1/3) roughly
    steps = int(sol.stats["num_accepted_steps"])
    assert steps < 3.0 * 26 * (1e-4 / rtol) ** (1.0 / 3.0), steps


# ------------------------------------------------------------------------------------------------
# Stiff: Prothero–Robinson y' = λ(y − g(t)) + g'(t), g = sin, y(0) = g(0) + 1, exact g(t) + e^{λt}
# ------------------------------------------------------------------------------------------------


def _pr_field(t, y, lam):
    return lam * (y - jnp.sin(t)) + jnp.cos(t)


def _prothero_robinson(lam, solver, n, y0=1.0):
    term = dfx.ODETerm(_pr_field)
    ts = jnp.linspace(0.0, 1.0, 11)
    # dt0, y0 and λ as arrays: one compilation per solver
    sol = dfx.diffeqsolve(term, solver, 0.0, 1.0, jnp.asarray(1.0 / n), jnp.asarray(y0), args=jnp.asarray(lam),
                          saveat=dfx.SaveAt(ts=ts),
                          stepsize_controller=dfx.ConstantStepSize(), max_steps=4096, throw=False)
    exact = np.sin(np.asarray(ts)) + y0 * np.exp(lam * np.asarray(ts))
    return np.max(np.abs(np.asarray(sol.ys) - exact)[1:])


def test_prothero_robinson_stiff_stability():
    lam = -1e4
    # h = 0.1, hλ = −1000: an explicit method explodes (measured Tsit5 error ~1e151) ...
    explicit = _prothero_robinson(lam, dfx.Tsit5(), 10)
    assert not np.isfinite(explicit) or explicit > 1e10, explicit
    # ... Rodas3 damps the initial transient e^{λt} in one step (L-stable) and tracks g(t).
    errors = np.array([_prothero_robinson(lam, hdjax.Rodas3(), n) for n in (10, 20, 40, 80)])
    # measured: 2.6e-3 (h = 0.1, the transient not yet gone at t = 0.1), 2.8e-5, 6.6e-7, 3.2e-7.
    # In the stiff regime Rosenbrock methods show order reduction (here to 1, error ≈ 0.25 h/|λ|,
    # Hairer & Wanner II §VI.3), the price of stage order 1; the error stays far below h³.
    assert np.all(np.isfinite(errors))
    assert errors[1] < 1e-4 and errors[-1] < 1e-6, errors


def test_prothero_robinson_error_uniform_in_stiffness():
    """At fixed h = 0.05, the error falls as λ grows (≈ 0.27 h/|λ| once |hλ| ≫ 1): stiffness costs
    no accuracy."""
    lams = (-1e2, -1e4, -1e6)
    errors = np.array([_prothero_robinson(lam, hdjax.Rodas3(), 20, y0=0.0) for lam in lams])
    # measured: 3.8e-5, 1.3e-6, 1.3e-8
    assert np.all(errors[1:] < errors[:-1] / 10), errors
    assert errors[-1] < 1e-7, errors


# ------------------------------------------------------------------------------------------------
# Ros34PW2, the Rosenbrock-W method of the diagnosis's Jacobians: cheap tangents that keep order 3
# ------------------------------------------------------------------------------------------------


def test_ros34pw2_coefficients_are_l_stable_and_stiffly_accurate():
    a, g, b, _ = _tableau(ROS34PW2)
    # stiffly accurate: b_j = α_4j + γ_4j (j < 4) and b_4 = γ, as PETSc's RA34PW2 table has it
    np.testing.assert_allclose(b[:3], (a + g)[-1, :3], rtol=0, atol=1e-15)
    assert b[3] == ROS34PW2.gamma
    y = np.concatenate([np.logspace(-3, 6, 400), -np.logspace(-3, 6, 400)])
    assert np.max(np.abs([_stability_function(1j * v, ROS34PW2) for v in y])) <= 1.0 + 1e-12
    assert abs(_stability_function(-1e8, ROS34PW2)) < 1e-7


def _two_states(t, y, p):
    """A nonlinear, non-autonomous, mildly stiff ODE with two parameters."""
    return jnp.stack([-p[0] * y[0] ** 3 + jnp.sin(3.0 * t) - 5.0 * (y[0] - y[1]), -50.0 * p[1] * (y[1] - jnp.cos(t))])


def _end_state(p, solver, n):
    # the step as an array: one compilation per solver
    sol = dfx.diffeqsolve(dfx.ODETerm(_two_states), solver, 0.0, 1.0, jnp.asarray(1.0 / n), jnp.array([1.0, 0.5]), args=p,
                          stepsize_controller=dfx.ConstantStepSize(), max_steps=16384,
                          adjoint=dfx.ForwardMode(), saveat=dfx.SaveAt(t1=True))
    return sol.ys[-1]


def test_frozen_jacobian_tangents_keep_order_three_only_with_the_w_method():
    """Tangents that hold each step's J constant are the method applied to the variational equation
    with blockdiag(J, J) in place of the exact matrix: a W-method (Ros34PW2) keeps its order 3 there,
    Rodas3 (whose order conditions need the exact J) falls to order 1. Reference: exact tangents
    through Rodas3 at 8 192 steps."""
    p = jnp.array([1.3, 0.7])
    ref = jax.jacfwd(lambda q: _end_state(q, hdjax.Rodas3(), 8192))(p)
    ns = (32, 64, 128, 256)

    def errors(solver):
        jac = jax.jit(jax.jacfwd(lambda q, dt: _end_state(q, solver, 1.0 / dt)))
        return np.array([float(jnp.max(jnp.abs(jac(p, 1.0 / n) - ref))) for n in ns])

    w = errors(hdjax.Ros34PW2())  # frozen tangents: its default
    r = errors(hdjax.Rodas3(frozen_jacobian_tangents=True))
    w_orders, r_orders = np.log2(w[:-1] / w[1:]), np.log2(r[:-1] / r[1:])
    # measured: Ros34PW2 1.2e-5 ... 3.9e-7 at n = 32 ... 128 (orders 2.3, 2.65, ...), Rodas3
    # frozen 5.7e-4 ... 1.5e-4 (orders 0.98, 0.99, ...)
    assert w_orders[-1] > 2.6 and np.all(w_orders > 2.0), (w, w_orders)
    assert np.all(np.abs(r_orders - 1.0) < 0.2), (r, r_orders)
    assert np.all(w < r / 20), (w, r)
    # exact tangents (no freezing) of the W-method: the derivative of its discrete solve, order 3
    e = errors(hdjax.Ros34PW2(frozen_jacobian_tangents=False))
    assert np.all(np.abs(np.log2(e[:-1] / e[1:]) - 3.0) < 0.2), e


def test_ros34pw2_fixed_step_order_three():
    ns = (40, 80, 160, 320)

    @jax.jit
    def solve(dt):
        sol = dfx.diffeqsolve(dfx.ODETerm(_nonlinear), hdjax.Ros34PW2(), 0.0, T_END, dt, jnp.array(1.0),
                              stepsize_controller=dfx.ConstantStepSize(), max_steps=1024)
        return sol.ys[-1]

    errors = np.array([abs(float(solve(T_END / n)) - _exact(T_END)) for n in ns])
    orders = np.log2(errors[:-1] / errors[1:])
    # measured from n = 20: orders 3.26, 3.15, 3.09 (approaching 3 from above)
    assert np.all(np.abs(orders - 3.0) < 0.2), (errors, orders)


def test_plant_stiff_part_carries_every_second_derivative_of_the_paper_models_states():
    """`Ros34PW2(stiff_part=plant_stiff_part)` keeps the tangent of J through the transmitted
    torque and eq. 9. In the paper's model those are the only terms of the plant that are
    nonlinear in the state or depend on K1, Tst, α or the friction coefficients. The tangents of
    these parameters must therefore equal the W-method's exact tangents (J not frozen) to
    round-off. Without the correction they do not: that gap is what the correction exists for.
    Free motion: where the frozen tangents fail (`benchmarks/RESULTS.md`, 2026-11-27)."""
    p, drive = hd2()
    exp = sine_experiment("free", amplitude=0.4, freq=3.0, duration=0.3)
    names = ("K1", "Tst", "Tsp", "Tssp1")

    def column(solver):
        sim = hdjax.Simulator(solver=solver, rtol=1e-6, atol=1e-8)

        def out(x):
            q = p.replace(**{k: getattr(p, k) * (1.0 + x[j]) for j, k in enumerate(names)})
            tr = hdjax.simulate(q, drive, exp, simulator=sim)
            return jnp.stack([tr.torque, tr.motor_velocity])

        return np.asarray(jax.jit(jax.jacfwd(out))(jnp.zeros(len(names))))

    exact = column(hdjax.Ros34PW2(frozen_jacobian_tangents=False))
    corrected = column(hdjax.Ros34PW2(stiff_part=hdjax.plant_stiff_part))
    frozen = column(hdjax.Ros34PW2())
    scale = np.linalg.norm(exact.reshape(-1, len(names)), axis=0)
    gap = lambda J: np.linalg.norm((J - exact).reshape(-1, len(names)), axis=0) / scale  # noqa: E731
    assert np.all(gap(corrected) < 1e-9), gap(corrected)
    assert gap(frozen).max() > 1e-6, gap(frozen)


def test_first_step_in_the_controller_takes_the_same_steps_as_dt0():
    """`FirstStep(controller, h)` with `dt0=None` steps exactly as `controller` with `dt0=h`."""
    term = dfx.ODETerm(lambda t, y, a: jnp.stack([y[1], -1e3 * y[0] - 30.0 * y[1] + jnp.sin(40.0 * t)]))
    y0 = jnp.array([1.0, 0.0])
    pid = dfx.PIDController(rtol=1e-6, atol=1e-9)
    clip = dfx.ClipStepSizeController(pid, step_ts=jnp.linspace(0.0, 0.5, 51))
    for controller in (pid, clip):
        kw = dict(t0=0.0, t1=0.5, y0=y0, saveat=dfx.SaveAt(steps=True), max_steps=4096)
        ref = dfx.diffeqsolve(term, hdjax.Rodas3(), dt0=2.5e-3, stepsize_controller=controller, **kw)
        new = dfx.diffeqsolve(term, hdjax.Rodas3(), dt0=None, stepsize_controller=hdjax.FirstStep(controller, jnp.asarray(2.5e-3)), **kw)
        assert ref.stats["num_steps"] == new.stats["num_steps"] > 10
        np.testing.assert_array_equal(np.asarray(new.ts), np.asarray(ref.ts))
        np.testing.assert_array_equal(np.asarray(new.ys), np.asarray(ref.ys))
    with pytest.raises(ValueError, match="dt0=None"):
        dfx.diffeqsolve(term, hdjax.Rodas3(), dt0=1e-3, stepsize_controller=hdjax.FirstStep(pid, jnp.asarray(1e-3)), t0=0.0,
                        t1=0.1, y0=y0)


def test_step_to_samples_takes_the_steps_of_clip_step_size_controller_to_the_bit():
    """`StepToSamples(pid, ts)` (the next sample's index as state, O(1) per step) steps exactly as
    diffrax's `ClipStepSizeController(pid, step_ts=ts)` (which compares every step with all of
    `ts`): the same accepted and rejected steps, states and forward-mode tangents, on a stiff
    oscillator driven by an input with kinks at jittered sample instants, stepping on past
    rejected steps and ending on the last sample."""
    rng = np.random.default_rng(3)
    ts = jnp.asarray(np.arange(201) * 2.5e-3 + rng.uniform(-2e-5, 2e-5, 201) * (np.arange(201) > 0))
    u = jnp.asarray(np.sign(np.sin(2 * np.pi * 7.0 * np.asarray(ts))))

    def vf(t, y, k):
        i = jnp.clip(jnp.searchsorted(ts, t) - 1, 0, ts.shape[0] - 2)
        w = (t - ts[i]) / (ts[i + 1] - ts[i])
        drive = (1 - w) * u[i] + w * u[i + 1]
        return jnp.stack([y[1], -k * y[0] - 40.0 * jnp.tanh(y[1] / 1e-3) * 0.05 - 30.0 * y[1] + 50.0 * drive])

    pid = dfx.PIDController(rtol=1e-6, atol=1e-9)

    def solve(controller, k):
        return dfx.diffeqsolve(dfx.ODETerm(vf), hdjax.Rodas3(), t0=ts[0], t1=ts[-1], dt0=None, y0=jnp.zeros(2), args=k,
                               stepsize_controller=hdjax.FirstStep(controller, jnp.asarray(6e-4)),
                               saveat=dfx.SaveAt(t0=True, steps=True), adjoint=dfx.ForwardMode(), max_steps=8192)

    ref = solve(dfx.ClipStepSizeController(pid, step_ts=ts), 1e3)
    new = solve(hdjax.StepToSamples(pid, ts), 1e3)
    assert new.stats["num_steps"] == ref.stats["num_steps"] > new.stats["num_accepted_steps"] > ts.shape[0]
    assert int(new.stats["num_accepted_steps"]) == int(ref.stats["num_accepted_steps"])
    np.testing.assert_array_equal(np.asarray(new.ts), np.asarray(ref.ts))
    np.testing.assert_array_equal(np.asarray(new.ys), np.asarray(ref.ys))
    assert set(np.asarray(ts).tolist()) <= set(np.asarray(new.ts).tolist())  # every sample is a step end
    tangent = lambda c: jax.jvp(lambda k: solve(c, k).ys, (1e3,), (1.0,))[1]  # noqa: E731
    np.testing.assert_array_equal(np.asarray(tangent(hdjax.StepToSamples(pid, ts))),
                                  np.asarray(tangent(dfx.ClipStepSizeController(pid, step_ts=ts))))


def test_the_simulation_holds_no_host_callback():
    """JAX writes no program with a host callback to its persistent compilation cache
    (`hdjax.use_compilation_cache`); the plant's simulation has none (diffrax checks a traced
    `dt0` with one, so the first step is set in the controller, `FirstStep`)."""
    p, drive = hd2()
    exp = sine_experiment("free", duration=0.2)
    traced = jax.make_jaxpr(lambda p_: hdjax.simulate(p_, drive, exp).torque)(p)
    assert host_callbacks(traced.jaxpr) == 0
