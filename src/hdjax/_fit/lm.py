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

Two opt-in rules for residuals that are not smooth in `y` (a simulated stick–slip plant, whose
trajectory jumps where a parameter change decides whether the motor sticks at a reversal):

- `shrink_on_reject`: after a rejected step, λ is raised until the next trial is at most half as
  long as the rejected one, measured as ‖J δ‖ (a trust-region halving, as in Moré's LM, there in
  the metric ‖diag(JᵀJ)^½ δ‖).
  Nielsen's λ·ν alone leaves the step unchanged while λ is far below the scaled normal matrix's
  eigenvalues: from λ = 1e-3, three or four trials of the same step were rejected in turn.
- `reject_se_tol`: stop when a trial shorter than this many standard errors (‖J δ‖/s, s² the
  reduced χ² at the accepted point, as in `hdjax.CostStop`'s Gauss–Newton-step rule) raises the
  cost: what is left to gain lies within that distance of the estimate, behind a jump of the cost
  that no linearisation sees. Without it LM approaches such a jump in ever shorter steps,
  half of them rejected, until a cost-stall rule stops it.

Measured on the shipped HD2 campaign's per-experiment fits (`fit_per_experiment`, 50 records,
2026-12-07): without them, 174 of the 361 residual-and-Jacobian evaluations were rejected trials,
54 of them at the start (λ = 1e-3, the same step three or four times), most of the rest on seven
free records and one locked record that approach such a jump; 20 fits ended on `CostStop`'s
cost-stall rule, ten of them after 6 evaluations with the Gauss–Newton step still 1.5–29
standard errors long. With both: 115 of 362 evaluations rejected (16 at the start), no fit
stalled, 19 stopped by `reject_se_tol`. The first step accepted after a rejection keeps its λ
(Nielsen's update would lengthen the next trial straight back over the jump).
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
    blocked: Bool[Array, ""]  # stopped by `reject_se_tol`: a short trial raised the cost


class MarquardtLM(optx.AbstractLeastSquaresSolver):
    """Levenberg–Marquardt with Marquardt scaling (see the module docstring).

    - `rtol`, `atol`: stop when an accepted step changes ½‖r‖² by at most `rtol`·cost + `atol`.
    - `xtol`: stop when the accepted step is shorter than `xtol`·(‖y‖ + `xtol`).
    - `damping0`: the first λ; `max_damping`: stop when λ exceeds it.
    - `shrink_on_reject`: after a rejected step, raise λ until the next trial is at most half as
      long (‖J δ‖); off: Nielsen's λ·ν alone.
    - `reject_se_tol`: stop when a rejected trial was shorter than this many standard errors
      (0: never).
    """

    rtol: float = 1e-10
    atol: float = 1e-14
    xtol: float = 1e-9
    damping0: float = 1e-3
    max_damping: float = 1e12
    shrink_on_reject: bool = eqx.field(static=True, default=False)
    reject_se_tol: float = 0.0
    norm: Callable = optx.two_norm

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del fn, args, options, aux_struct, tags
        r = jnp.zeros(f_struct.shape, f_struct.dtype)
        jac = lx.MatrixLinearOperator(jnp.zeros(f_struct.shape + y.shape, f_struct.dtype))
        return _MarquardtState(optx.FunctionInfo.ResidualJac(r, jac), jnp.zeros_like(y), jnp.asarray(1.0),
                               jnp.asarray(self.damping0), jnp.asarray(2.0), jnp.asarray(0), jnp.asarray(False),
                               jnp.asarray(False))

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
        rejected = ~first & ~ok
        # the rejected trial's length in standard errors, at the accepted point (r, J)
        blocked = rejected & (_length_in_se(r, J, state.trial) < self.reject_se_tol)
        y, r, J = jnp.where(ok, y + state.trial, y), jnp.where(ok, r_new, r), jnp.where(ok, J_new, J)
        if self.shrink_on_reject:
            lam = jnp.where(rejected, _damping_to_halve(J, r, lam, state.trial, self.max_damping), lam)
            # the first step accepted after a rejection keeps its λ (the next trial about as long)
            lam = jnp.where(ok & ~first & (state.nu > 2.0), state.damping, lam)
        trial, predicted = _marquardt_step(r, J, lam)
        state = _MarquardtState(optx.FunctionInfo.ResidualJac(r, lx.MatrixLinearOperator(J)), trial, predicted, lam,
                                nu, state.num_steps + 1, small | blocked | (lam > self.max_damping), blocked)
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


def _reduced_chi2(r, n_params):
    """s² = ‖r‖²/(n − p) over the n non-zero residuals (zero rows are padding or unmeasured)."""
    n = jnp.sum(r != 0.0)
    return jnp.sum(r**2) / jnp.maximum(n - n_params, 1).astype(r.dtype)


def _length_in_se(r, J, step):
    """‖J·step‖/s (s² `_reduced_chi2`): the step's length in standard errors (Mahalanobis), as
    `hdjax._fit.least_squares._gauss_newton_step_in_se` measures the Gauss–Newton step."""
    return jnp.sqrt(jnp.sum((J @ step) ** 2) / jnp.maximum(_reduced_chi2(r, J.shape[1]), 1e-300))


def _damping_to_halve(J, r, lam, rejected, max_damping):
    """The first of λ, 2λ, 4λ, … (up to `max_damping`) whose Marquardt step is at most half as long
    as the rejected trial `rejected` in the metric ‖J δ‖ (the one `reject_se_tol` reads: in
    Marquardt's own metric ‖diag(JᵀJ)^½ δ‖ damping first removes the poorly determined components,
    and on the HD2 campaign ‖J δ‖ fell only from 4.0 to 3.2 standard errors over three halvings)."""
    target = 0.5 * jnp.linalg.norm(J @ rejected)

    def longer(lam):
        return (jnp.linalg.norm(J @ _marquardt_step(r, J, lam)[0]) > target) & (lam <= max_damping)

    return jax.lax.while_loop(longer, lambda lam: 2.0 * lam, lam)


def _marquardt_step(r, J, lam):
    """The damped Gauss–Newton step and the decrease of ½‖r‖² its linear model predicts."""
    A = J.T @ J
    g = J.T @ r
    diag = jnp.diag(A)
    fixed = diag == 0.0
    d = jnp.where(fixed, 1.0, diag)
    dx = -jnp.linalg.solve(A + jnp.diag(lam * d + fixed.astype(d.dtype)), g) * (~fixed).astype(g.dtype)
    return dx, -(dx @ g) - 0.5 * dx @ (A @ dx)
