"""`hdjax._fit.lm.MarquardtLM`, the friction fits' least-squares solver, as an optimistix solver value."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from hdjax import MarquardtLM

jax.config.update("jax_enable_x64", True)


def _decay_residuals(y, args):
    """Fit a·exp(−t/τ) + c (τ through its logarithm) to noisy data; badly scaled on purpose."""
    t, data = args
    a, log_tau, c = y
    return a * jnp.exp(-t / jnp.exp(log_tau)) + c - data


def _data():
    rng = np.random.default_rng(0)
    t = jnp.linspace(0.0, 5.0, 400)
    return t, 300.0 * jnp.exp(-t / 0.7) + 2.0 + jnp.asarray(rng.normal(size=t.size))


def test_reaches_the_optimum_of_optimistix_levenberg_marquardt():
    args = _data()
    y0 = jnp.array([100.0, 0.0, 0.0])
    ours = optx.least_squares(_decay_residuals, MarquardtLM(), y0, args, max_steps=200)
    ref = optx.least_squares(_decay_residuals, optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12), y0, args,
                             max_steps=2000)
    assert ours.result == optx.RESULTS.successful
    cost = lambda y: float(jnp.sum(_decay_residuals(y, args) ** 2))  # noqa: E731
    assert cost(ours.value) <= cost(ref.value) * (1 + 1e-9)
    np.testing.assert_allclose(ours.value, ref.value, rtol=1e-6, atol=1e-8)


def test_zero_jacobian_columns_stay_put_and_max_steps_is_reported():
    args = _data()

    def held(y, args):  # the third parameter is held at its start through jnp.where, as the friction fits do
        return _decay_residuals(jnp.where(jnp.array([True, True, False]), y, jnp.array([0.0, 0.0, 2.0])), args)

    y0 = jnp.array([100.0, 0.0, 7.0])
    sol = optx.least_squares(held, MarquardtLM(), y0, args, max_steps=200)
    assert sol.result == optx.RESULTS.successful and float(sol.value[2]) == 7.0
    short = optx.least_squares(held, MarquardtLM(), y0, args, max_steps=2, throw=False)
    assert short.result == optx.RESULTS.nonlinear_max_steps_reached


def test_composes_with_cost_stop_like_optimistix_levenberg_marquardt():
    """`CostStop` (the trajectory fit's stopping rules) reads the inner state's `f_info` and
    `num_steps`; with `MarquardtLM` inside it stops a jittery problem by its Gauss–Newton-step rule
    at the optimum, and hands back the residual and Jacobian at the returned point."""
    from hdjax import CostStop
    from hdjax._fit.least_squares import _final_residual_and_jacobian

    A = jnp.array([[1.0, 0.2], [0.3, 2.0], [1.0, 1.0], [0.5, -1.0]])
    b = A @ jnp.array([2.0, -1.0]) + jnp.array([0.01, -0.02, 0.015, -0.005])

    def fn(y, _):  # jitter far under the noise, not differentiated (as an adaptive ODE solve's)
        return A @ y - b + 1e-5 * jax.lax.stop_gradient(jnp.sin(1e7 * y).sum())

    sol = optx.least_squares(fn, CostStop(MarquardtLM()), jnp.zeros(2), max_steps=40, throw=False)
    assert sol.result == optx.RESULTS.successful and int(sol.state.reason) == 1  # Gauss–Newton step small
    assert jnp.allclose(sol.value, jnp.linalg.lstsq(A, b)[0], atol=2e-3)
    r, J = _final_residual_and_jacobian(sol)
    assert jnp.allclose(r, fn(sol.value, None)) and jnp.allclose(J, A, atol=1e-2)


def _cliff_residuals(y, args):
    """A line fit toward y = 2 with a jump of the cost at y = 0.7 that no derivative sees (as a
    simulated motor that sticks at a reversal once a parameter crosses a threshold): 200 residuals
    of noise 0.1, so the standard error of y is about s/√200 with s² the reduced χ²."""
    noise = args
    jump = jax.lax.stop_gradient(jnp.where(y[0] > 0.7, 10.0, 0.0))
    return (y[0] - 2.0) + noise + jump


def test_shrinking_on_rejection_reaches_a_jump_of_the_cost_instead_of_stalling_at_the_start():
    """The Gauss–Newton step from y = 0 crosses the jump at 0.7 and is rejected. Nielsen's λ·ν
    leaves that step almost unchanged for three or four trials (λ from 1e-3), so `CostStop`'s
    stall rule (three evaluations without a lower cost) ends the fit at its start: on the shipped
    HD2 campaign ten per-experiment fits stopped so, 1.5–29 standard errors from their optimum.
    With `shrink_on_reject` each rejection halves the trial, and `reject_se_tol` stops once a trial
    shorter than 0.1 standard errors is rejected: the fit ends within 0.1 standard errors below
    the jump."""
    from hdjax import CostStop
    from hdjax._fit.least_squares import STOP_REASONS

    noise = jnp.asarray(0.1 * np.random.default_rng(3).standard_normal(200))
    y0 = jnp.zeros(1)
    plain = optx.least_squares(_cliff_residuals, CostStop(MarquardtLM()), y0, noise, max_steps=40, throw=False)
    assert float(plain.value[0]) == 0.0 and int(plain.state.reason) == 2  # cost stalled at the start

    solver = CostStop(MarquardtLM(shrink_on_reject=True, reject_se_tol=0.1))
    sol = optx.least_squares(_cliff_residuals, solver, y0, noise, max_steps=40, throw=False)
    r = _cliff_residuals(sol.value, noise)
    se = float(jnp.sqrt(jnp.sum(r**2) / (r.size - 1)) / np.sqrt(r.size))  # J = 1: s/√n
    y = float(sol.value[0])
    assert sol.result == optx.RESULTS.successful and bool(sol.state.inner.blocked)  # the solver's reject_se_tol rule
    assert STOP_REASONS[int(sol.state.reason)] == "cost_jump"  # ... as CostStop reports it
    assert 0.7 - 0.1 * se <= y <= 0.7, (y, se)
    assert int(sol.stats["num_steps"]) <= 20


@pytest.mark.parametrize("shrink", [False, True])
def test_shrink_on_reject_keeps_the_optimum_of_a_smooth_problem(shrink):
    """On a smooth, badly scaled problem both ways reach optimistix's optimum."""
    args = _data()
    y0 = jnp.array([100.0, 0.0, 0.0])
    ours = optx.least_squares(_decay_residuals, MarquardtLM(shrink_on_reject=shrink, reject_se_tol=0.1 * shrink), y0,
                              args, max_steps=200)
    ref = optx.least_squares(_decay_residuals, optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12), y0, args,
                             max_steps=2000)
    np.testing.assert_allclose(ours.value, ref.value, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("solver", [optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12), MarquardtLM()],
                         ids=["optimistix", "marquardt"])
def test_the_joint_fits_lm_programs_trace_the_residuals_once_and_fit_as_they_do(solver):
    """`hdjax.fit_parameters`' LM programs (`_stepped_least_squares`: a start program and a step
    program, with `_lm_objective`'s residual and Jacobian from one jitted function) trace the
    residual function once between them. optimistix's start asks for the objective's output shape;
    with the plain residuals as the objective's primal that traced the whole simulated plant a
    second time (2026-12-07: the 12-record HD2 joint fit's tracing 2.25 s → 1.48 s without it).
    The fit is the plain residuals' fit."""
    from hdjax._fit.least_squares import CostStop, _lm_objective, _stepped_least_squares

    args = _data()
    y0 = jnp.array([100.0, 0.0, 0.0])
    traced = []

    def residuals(y, args):
        traced.append(1)
        return _decay_residuals(y, args)

    lm = CostStop(solver)  # pyright: ignore[reportCallIssue]
    run = _stepped_least_squares(_lm_objective(residuals), lm, max_steps=200,
                                 finish=lambda y, state, result, num_steps, args: (y, result))
    ours, result = run(y0, args)
    assert len(traced) == 1
    plain = optx.least_squares(_decay_residuals, lm, y0, args, max_steps=200, throw=False)
    assert result == plain.result == optx.RESULTS.successful
    np.testing.assert_allclose(ours, plain.value, rtol=1e-10, atol=1e-12)
