r"""Rodas3: an L-stable, stiffly accurate 3rd-order Rosenbrock method as a diffrax solver.

Why a Rosenbrock method: the plant is small (four states) but stiff — in free motion the power-law
structural damping $T_{st}|\dot{\Delta\theta}|^{1/2}$ pins the torsion rate near zero with a
Jacobian eigenvalue of order $10^4$–$10^5\,\mathrm{s^{-1}}$, and the smoothed Coulomb step adds
another near zero velocity. Explicit solvers (Tsit5, Dopri8) then take 4–22 steps per 1 ms sample
and are 3–11× less accurate in free motion at equal tolerance (Tsit5 blows up on a
Prothero–Robinson test at λ = −1e4, h = 0.1); diffrax's ESDIRK solvers (Kvaerno3/5) handle the
stiffness but spend most of their time in the Newton iterations' bookkeeping (slowest in
`benchmarks/solver_choice.py`). A Rosenbrock method is linearly implicit: one small Jacobian and
one matrix inverse per step, no iteration, so it is cheap, branch-free under `vmap`, and
differentiable in forward mode. Measurements: `benchmarks/solver_choice.py`.

Method (Hairer–Wanner form, Sandu et al. 1997 "Rodas3"), with time treated as a state so that the
non-autonomous current input is handled exactly:

$$(I - h\gamma J)\,k_i = h\,f\Big(y_0 + \sum_{j<i}\alpha_{ij}k_j\Big) + hJ\sum_{j<i}\gamma_{ij}k_j,
\qquad y_1 = y_0 + \sum_i b_i k_i,$$

$\gamma = 1/2$; the embedded 2nd-order solution ($\hat b$) gives the error estimate for adaptive
step control. Order conditions up to 3 and stiff accuracy are checked in `tests/test_solver.py`.
"""

from collections.abc import Callable
from typing import ClassVar

import diffrax as dfx
import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

GAMMA = 0.5
ALPHA = ((), (0.0,), (1.0, 0.0), (0.75, -0.25, 0.5))
GAMMAS = ((), (1.0,), (-0.25, -0.25), (1.0 / 12.0, 1.0 / 12.0, -2.0 / 3.0))
B = (5.0 / 6.0, -1.0 / 6.0, -1.0 / 6.0, 0.5)
B_HAT = (0.75, -0.25, 0.5, 0.0)


class Rodas3(dfx.AbstractAdaptiveSolver):
    """L-stable 3rd-order Rosenbrock solver (4 stages, embedded 2nd order) for small stiff ODEs.

    Works with `ConstantStepSize` (fixed steps, fastest) and with `PIDController` (adaptive).
    Dense output is cubic Hermite between steps (one extra vector-field evaluation per step).
    """

    term_structure: ClassVar = dfx.AbstractTerm
    interpolation_cls: ClassVar[Callable[..., dfx.ThirdOrderHermitePolynomialInterpolation]] = (
        dfx.ThirdOrderHermitePolynomialInterpolation
    )

    def order(self, terms):
        del terms
        return 3

    def error_order(self, terms):
        del terms
        return 2

    def init(self, terms, t0, t1, y0, args):
        del terms, t0, t1, y0, args
        return None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del solver_state, made_jump
        y0_flat, unravel = ravel_pytree(y0)
        h = t1 - t0

        def f(z):  # autonomous form: z = (y, t)
            y = unravel(z[:-1])
            dy, _ = ravel_pytree(terms.vf(z[-1], y, args))
            return jnp.concatenate([dy, jnp.ones((1,), dtype=dy.dtype)])

        z0 = jnp.concatenate([y0_flat, jnp.reshape(jnp.asarray(t0, dtype=y0_flat.dtype), (1,))])
        J = jax.jacfwd(f)(z0)
        n = z0.shape[0]
        W = jnp.eye(n, dtype=z0.dtype) - (h * GAMMA) * J
        # the inverse of W, not its LU factors: forward-mode tangents of an inverse are two small
        # matmuls (-W⁻¹ dW W⁻¹), those of `lu_factor` triangular solves and masks; the forward-mode
        # Jacobian of the HD2 fit's residuals is 1.5-1.7x faster this way (benchmarks/RESULTS.md)
        W_inv = jnp.linalg.inv(W)
        ks = []
        for i in range(4):
            zi = z0
            corr = jnp.zeros_like(z0)
            for j in range(i):
                zi = zi + ALPHA[i][j] * ks[j]
                corr = corr + GAMMAS[i][j] * ks[j]
            rhs = h * f(zi) + h * (J @ corr)
            ks.append(W_inv @ rhs)
        z1 = z0 + sum(b * k for b, k in zip(B, ks))
        z1_hat = z0 + sum(b * k for b, k in zip(B_HAT, ks))
        y1 = unravel(z1[:-1])
        y_error = unravel((z1 - z1_hat)[:-1])
        k0 = unravel(h * f(z0)[:-1])  # pyright: ignore[reportArgumentType]  h · Array is an Array (jax's __array_priority__)
        k1 = unravel(h * f(z1)[:-1])  # pyright: ignore[reportArgumentType]  h · Array is an Array (jax's __array_priority__)
        dense_info = dict(y0=y0, y1=y1, k0=k0, k1=k1)
        return y1, y_error, dense_info, None, dfx.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)
