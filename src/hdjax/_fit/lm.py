"""`MarquardtLM`: Levenberg–Marquardt with Marquardt's diagonal scaling and a materialised
Jacobian, as an optimistix least-squares solver.

The friction-only fits (`hdjax._fit.friction`) run hundreds of small least-squares problems (a
few thousand residuals, about 20 parameters) in one diagnosis. There, one step of
`optimistix.LevenbergMarquardt` (linearise, `FunctionLinearOperator`, materialise, QR of the
augmented system) costs far more than the residual and its forward-mode Jacobian, and its
identity damping ignores the columns' scales. This solver does the textbook step instead, on the
normal equations (Moré 1978; Nielsen's damping update):

$$ (J^\\top J + \\lambda\\,\\mathrm{diag}(J^\\top J))\\,\\Delta = -J^\\top r, $$

with one residual-and-Jacobian evaluation per step (at the trial point, so the model appears once
in the compiled loop). It is a solver *value* for `optx.least_squares`, not a second fitting
pipeline: `optx.least_squares(fn, MarquardtLM(), y0, args, max_steps=..., throw=False)`, and it
composes with `hdjax._fit.least_squares.CostStop` (the state carries `f_info` like optimistix's own LM).

Columns of the Jacobian that are exactly zero (parameters held fixed through `jnp.where`, or
switched-off terms) get a unit diagonal, so they stay where they are.

Stops (`RESULTS.successful`) when an accepted step changes ½‖r‖² by at most
`rtol`·cost + `atol`, when the step is shorter than `xtol`·(‖y‖ + `xtol`), or when λ exceeds
`max_damping` (no step lowers the cost any more). `y` is a flat vector.
"""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int


class _MarquardtState(eqx.Module):
    f_info: optx.FunctionInfo.ResidualJac  # pyright: ignore[reportInvalidTypeForm]  a ClassVar alias of the class; residual and Jacobian at the accepted y
    trial: Float[Array, " param"]  # step to try next
    predicted: Float[Array, ""]  # the linear model's predicted decrease of ½‖r‖² for `trial`
    damping: Float[Array, ""]
    nu: Float[Array, ""]
    num_steps: Int[Array, ""]
    done: Bool[Array, ""]


class MarquardtLM(optx.AbstractLeastSquaresSolver):
    """Levenberg–Marquardt with Marquardt scaling (see the module docstring).

    - `rtol`, `atol`: stop when an accepted step changes ½‖r‖² by at most `rtol`·cost + `atol`.
    - `xtol`: stop when the accepted step is shorter than `xtol`·(‖y‖ + `xtol`).
    - `damping0`: the first λ; `max_damping`: stop when λ exceeds it.
    """

    rtol: float = 1e-10
    atol: float = 1e-14
    xtol: float = 1e-9
    damping0: float = 1e-3
    max_damping: float = 1e12
    norm: Callable = optx.two_norm

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del fn, args, options, aux_struct, tags
        r = jnp.zeros(f_struct.shape, f_struct.dtype)
        jac = lx.MatrixLinearOperator(jnp.zeros(f_struct.shape + y.shape, f_struct.dtype))
        return _MarquardtState(optx.FunctionInfo.ResidualJac(r, jac), jnp.zeros_like(y), jnp.asarray(1.0),
                               jnp.asarray(self.damping0), jnp.asarray(2.0), jnp.asarray(0), jnp.asarray(False))

    def step(self, fn, y, args, options, state, tags):
        del options, tags
        first = state.num_steps == 0  # evaluates the start point and always accepts it
        (r_new, aux), J_new = _linearise(fn, y + state.trial, args)
        r, J = state.f_info.residual, state.f_info.jac.as_matrix()
        cost = jnp.where(first, jnp.inf, 0.5 * r @ r)
        cost_new = 0.5 * r_new @ r_new
        rho = (cost - cost_new) / jnp.maximum(state.predicted, 1e-300)
        ok = first | (jnp.isfinite(cost_new) & (rho > 1e-4))
        small = ~first & ok & ((jnp.abs(cost - cost_new) <= self.rtol * cost + self.atol)
                               | (jnp.linalg.norm(state.trial) <= self.xtol * (jnp.linalg.norm(y) + self.xtol)))
        lam = jnp.where(first, state.damping,
                        jnp.where(ok, state.damping * jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3),
                                  state.damping * state.nu))
        nu = jnp.where(ok, 2.0, 2.0 * state.nu)
        y, r, J = jnp.where(ok, y + state.trial, y), jnp.where(ok, r_new, r), jnp.where(ok, J_new, J)
        trial, predicted = _marquardt_step(r, J, lam)
        state = _MarquardtState(optx.FunctionInfo.ResidualJac(r, lx.MatrixLinearOperator(J)), trial, predicted, lam,
                                nu, state.num_steps + 1, small | (lam > self.max_damping))
        return y, state, aux

    def terminate(self, fn, y, args, options, state, tags):
        del fn, y, args, options, tags
        return state.done, optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        del fn, args, options, state, tags, result
        return y, aux, {}


def _linearise(fn, y, args):
    """((residual, aux), Jacobian) at `y`, the Jacobian materialised in forward mode."""

    def f(y):
        r, aux = fn(y, args)
        return r, (r, aux)

    J, out = jax.jacfwd(f, has_aux=True)(y)
    return out, J


def _marquardt_step(r, J, lam):
    """The damped Gauss–Newton step and the decrease of ½‖r‖² its linear model predicts."""
    A = J.T @ J
    g = J.T @ r
    diag = jnp.diag(A)
    fixed = diag == 0.0
    d = jnp.where(fixed, 1.0, diag)
    dx = -jnp.linalg.solve(A + jnp.diag(lam * d + fixed.astype(d.dtype)), g) * (~fixed).astype(g.dtype)
    return dx, -(dx @ g) - 0.5 * dx @ (A @ dx)
