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
from typing import ClassVar, NamedTuple

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float

GAMMA = 0.5
ALPHA = ((), (0.0,), (1.0, 0.0), (0.75, -0.25, 0.5))
GAMMAS = ((), (1.0,), (-0.25, -0.25), (1.0 / 12.0, 1.0 / 12.0, -2.0 / 3.0))
B = (5.0 / 6.0, -1.0 / 6.0, -1.0 / 6.0, 0.5)
B_HAT = (0.75, -0.25, 0.5, 0.0)


class Tableau(NamedTuple):
    """A 4-stage Rosenbrock method in Hairer–Wanner form: γ, α_ij, γ_ij (j < i), b, embedded b̂."""

    gamma: float
    alpha: tuple
    gammas: tuple
    b: tuple
    b_hat: tuple


RODAS3 = Tableau(GAMMA, ALPHA, GAMMAS, B, B_HAT)

# ROS34PW2 (Rang & Angermann 2005, BIT 45; coefficients as PETSc's `TSROSWRA34PW2` lists them):
# a 4-stage, stiffly accurate, L-stable Rosenbrock-W method of order 3 whose order conditions hold
# for *any* matrix in place of J (a W-method), embedded order 2.
ROS34PW2 = Tableau(
    gamma=4.3586652150845900e-01,
    alpha=((), (8.7173304301691801e-01,), (8.4457060015369423e-01, -1.1299064236484185e-01), (0.0, 0.0, 1.0)),
    gammas=(
        (),
        (-8.7173304301691801e-01,),
        (-9.0338057013044082e-01, 5.4180672388095326e-02),
        (2.4212380706095346e-01, -1.2232505839045147e00, 5.4526025533510214e-01),
    ),
    b=(2.4212380706095346e-01, -1.2232505839045147e00, 1.5452602553351020e00, 4.3586652150845900e-01),
    b_hat=(3.7810903145819369e-01, -9.6042292212423178e-02, 5.0000000000000000e-01, 2.1793326075422950e-01),
)


class _Rosenbrock(dfx.AbstractAdaptiveSolver):
    """A 4-stage Rosenbrock method in Hairer–Wanner form (module docstring), time treated as a
    state; the tableau is the subclass's."""

    frozen_jacobian_tangents: eqx.AbstractVar[bool]
    stiff_part: eqx.AbstractVar[Callable | None]

    term_structure: ClassVar = dfx.AbstractTerm
    interpolation_cls: ClassVar[Callable[..., dfx.ThirdOrderHermitePolynomialInterpolation]] = (
        dfx.ThirdOrderHermitePolynomialInterpolation
    )
    _tableau: ClassVar[Tableau]

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
        tab = self._tableau
        J = jax.jacfwd(f)(z0)
        if self.frozen_jacobian_tangents:
            # forward-mode tangents see J as a constant: they are this method applied to the
            # variational equation with the matrix blockdiag(J, J) (see `Ros34PW2`)
            J = jax.lax.stop_gradient(J)
            stiff = self.stiff_part
            if stiff is not None:
                # ... except through `stiff_part`, the terms whose curvature is stiff: the tangent
                # of their Jacobian is kept (the primal J is unchanged: Js − Js = 0)
                def fs(z):
                    dy, _ = ravel_pytree(stiff(z[-1], unravel(z[:-1]), args))
                    return jnp.concatenate([dy, jnp.zeros((1,), dtype=dy.dtype)])

                Js = jax.jacfwd(fs)(z0)
                J = J + (Js - jax.lax.stop_gradient(Js))
        n = z0.shape[0]
        W = jnp.eye(n, dtype=z0.dtype) - (h * tab.gamma) * J
        # the inverse of W, not its LU factors: forward-mode tangents of an inverse are two small
        # matmuls (-W⁻¹ dW W⁻¹), those of `lu_factor` triangular solves and masks; the forward-mode
        # Jacobian of the HD2 fit's residuals is 1.5-1.7x faster this way (benchmarks/RESULTS.md)
        W_inv = jnp.linalg.inv(W)
        ks = []
        for i in range(4):
            zi = z0
            corr = jnp.zeros_like(z0)
            for j in range(i):
                zi = zi + tab.alpha[i][j] * ks[j]
                corr = corr + tab.gammas[i][j] * ks[j]
            rhs = h * f(zi) + h * (J @ corr)
            ks.append(W_inv @ rhs)
        z1 = z0 + sum(b * k for b, k in zip(tab.b, ks))
        z1_hat = z0 + sum(b * k for b, k in zip(tab.b_hat, ks))
        y1 = unravel(z1[:-1])
        y_error = unravel((z1 - z1_hat)[:-1])
        k0 = unravel(h * f(z0)[:-1])  # pyright: ignore[reportArgumentType]  h · Array is an Array (jax's __array_priority__)
        k1 = unravel(h * f(z1)[:-1])  # pyright: ignore[reportArgumentType]  h · Array is an Array (jax's __array_priority__)
        dense_info = dict(y0=y0, y1=y1, k0=k0, k1=k1)
        return y1, y_error, dense_info, None, dfx.RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


class Rodas3(_Rosenbrock):
    """L-stable 3rd-order Rosenbrock solver (4 stages, embedded 2nd order) for small stiff ODEs.

    Works with `ConstantStepSize` (fixed steps, fastest) and with `PIDController` (adaptive).
    Dense output is cubic Hermite between steps (one extra vector-field evaluation per step).

    **Arguments:**

    - `frozen_jacobian_tangents`: if True, forward-mode tangents treat each step's J as a constant.
      Rodas3's order conditions need the exact J, so such tangents are only first order (relative
      errors of 3e-3 to 9e-2 at rtol 1e-5 in `benchmarks/jacobian_accuracy.py --frozen`; see
      `Ros34PW2`). Default False: tangents are the exact derivative of the discrete solve.
    - `stiff_part`: with frozen tangents, terms whose J-tangent is kept (see `Ros34PW2`).
    """

    frozen_jacobian_tangents: bool = eqx.field(static=True, default=False)
    stiff_part: Callable | None = eqx.field(static=True, default=None)
    _tableau: ClassVar[Tableau] = RODAS3


class Ros34PW2(_Rosenbrock):
    r"""ROS34PW2 (Rang & Angermann 2005): a stiffly accurate, L-stable Rosenbrock-**W** method of
    order 3 (4 stages, embedded order 2): its order conditions hold whatever matrix stands in for J.

    With `frozen_jacobian_tangents=True` (the default here) forward-mode tangents do not
    differentiate J (no second derivatives of the vector field, no tangent of $W^{-1}$): they are
    then this same W-method applied to the variational equation $\dot s = J s + f_p$ with the
    matrix blockdiag(J, J) in place of the exact one, so they keep its third order where the
    problem is smooth (`tests/test_solver.py`), at about a quarter of the cost of exact tangents
    through `Rodas3` (the diagnosis's Jacobians: 78 s → 17 s on one benchmark dataset).

    **Frozen tangents alone are not enough for the plant:** the dropped coupling
    $(\partial J/\partial z)\,s$ is stiff wherever the plant's curvature is extreme (the power-law
    damping near zero torsion rate, the friction step near zero speed). In free motion the
    tangents of the torsion parameters (K1, cubic stiffness, kinematic error) were then 3–1 200 %
    off at rtol 1e-5 (`benchmarks/jacobian_accuracy.py --w-method`), and a diagnosis given such
    Jacobians no longer named a hidden kinematic error (bench seed 5000; `benchmarks/RESULTS.md`,
    2026-11-27).

    **`stiff_part`** (a function like a diffrax vector field, `(t, y, args) -> dy`): the tangent of
    *its* Jacobian is kept, so the second derivatives of those terms are exact and only the rest is
    frozen. `hdjax.plant_stiff_part` holds the plant's transmitted torque and eq. 9 (everything
    nonlinear in the state in the paper's model, so there the tangents equal the exact ones,
    `tests/test_solver.py`); the current, cogging and the smooth friction factors stay frozen.
    With it the diagnosis names seed 5000's kinematic error again. It is the default of
    `diagnose`'s Jacobians (`jacobian_solver`): on all 20 benchmark datasets and the 13 cases of
    `tests/test_diagnose_bench.py` it names exactly what exact `Rodas3` tangents name, 1.3–1.4×
    faster on full-size datasets and 6 % faster on the test file's small ones.

    The primal solution is an ordinary 3rd-order Rosenbrock solve (not bit-identical to `Rodas3`'s).
    """

    frozen_jacobian_tangents: bool = eqx.field(static=True, default=True)
    stiff_part: Callable | None = eqx.field(static=True, default=None)
    _tableau: ClassVar[Tableau] = ROS34PW2


class FirstStep(dfx.AbstractAdaptiveStepSizeController):
    """An adaptive step-size controller that takes its first step size from itself, so that
    `diffeqsolve` is called with `dt0=None`.

    Only that: `first_step` (s, positive, traced or not) is handed to the wrapped controller's
    `init` as the `dt0` that `diffeqsolve` would have given it (times the direction of
    integration), so the steps are the same as with `dt0=first_step`. Why: given a traced `dt0`,
    `diffeqsolve` checks `(t1 - t0)·dt0 ≥ 0` with `equinox.error_if`, a host callback, and JAX
    does not write a program with host callbacks to its persistent compilation cache. The plant's
    solves start from a quarter of the sample step, which is traced (measured from the record), so
    every simulation program was kept out of that cache."""

    controller: dfx.AbstractAdaptiveStepSizeController
    first_step: jax.Array
    direction: jax.Array | int

    def __init__(self, controller: dfx.AbstractAdaptiveStepSizeController, first_step, direction: jax.Array | int = 1):
        self.controller, self.first_step, self.direction = controller, jnp.asarray(first_step), direction

    @property
    def rtol(self):  # pyright: ignore[reportIncompatibleVariableOverride]
        return self.controller.rtol

    @property
    def atol(self):  # pyright: ignore[reportIncompatibleVariableOverride]
        return self.controller.atol

    @property
    def norm(self):  # pyright: ignore[reportIncompatibleMethodOverride]
        return self.controller.norm

    def wrap(self, direction):
        return eqx.tree_at(lambda s: (s.controller, s.direction), self, (self.controller.wrap(direction), direction))

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        if dt0 is not None:
            raise ValueError("`FirstStep` sets the first step itself: call `diffeqsolve` with `dt0=None`.")
        first = jnp.asarray(self.first_step, dtype=jnp.result_type(t0)) * self.direction
        return self.controller.init(terms, t0, t1, y0, first, args, func, error_order)

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        return self.controller.adapt_step_size(t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state)


class StepToSamples(dfx.AbstractAdaptiveStepSizeController):
    """An adaptive step-size controller that makes every step end on the next sample instant it
    would cross: the steps of `diffrax.ClipStepSizeController(controller, step_ts=sample_times)`,
    at a cost per step that does not grow with the record.

    `ClipStepSizeController` compares the next step's start with every one of `step_ts` on every
    step (its `_bump_next_t0`, written for jump times, where the hint index is not trusted), so a
    record of n samples costs O(n) per step and O(n²) per solve: on the plant's 1 500-sample
    records at rtol 1e-5 that was 4–5 µs of a 8 µs step on this 2-core CPU (the Rosenbrock step
    itself about 3.5 µs; `benchmarks/RESULTS.md`, forty-first session). Here the index of the next
    sample is state: a step that ends on it moves it on by one, so each step costs O(1). The
    steps, and the solution, are the same to the bit (`tests/test_solver.py`).

    **Arguments:** `controller` the adaptive controller proposing the steps (a `PIDController`),
    `sample_times` (s) the instants to step onto, increasing.
    """

    controller: dfx.AbstractAdaptiveStepSizeController
    sample_times: Float[Array, " time"]

    def __init__(self, controller: dfx.AbstractAdaptiveStepSizeController, sample_times):
        self.controller, self.sample_times = controller, jnp.asarray(sample_times)

    @property
    def rtol(self):  # pyright: ignore[reportIncompatibleVariableOverride]
        return self.controller.rtol

    @property
    def atol(self):  # pyright: ignore[reportIncompatibleVariableOverride]
        return self.controller.atol

    @property
    def norm(self):  # pyright: ignore[reportIncompatibleMethodOverride]
        return self.controller.norm

    def wrap(self, direction):
        # forward in time only (the plant's solves run from the first sample to the last)
        return eqx.tree_at(lambda s: s.controller, self, self.controller.wrap(direction))

    def _clip(self, t1, index):
        n = self.sample_times.shape[0]
        target = jnp.where(index < n, self.sample_times[jnp.minimum(index, n - 1)], jnp.inf)
        return jnp.minimum(target, t1)

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        t1, inner = self.controller.init(terms, t0, t1, y0, dt0, args, func, error_order)
        index = jnp.searchsorted(self.sample_times, t0, side="right")  # the first sample after t0
        return self._clip(t1, index), (index, inner)

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        index, inner = controller_state
        keep, next_t0, next_t1, made_jump, inner, result = self.controller.adapt_step_size(
            t0, t1, y0, y1_candidate, args, y_error, error_order, inner)
        n = self.sample_times.shape[0]
        # steps never pass a sample (they are clipped to it), so the next start is on or before the
        # sample at `index`: on it, the next target is the one after
        on_sample = (index < n) & (next_t0 >= self.sample_times[jnp.minimum(index, n - 1)])
        index = index + on_sample.astype(index.dtype)
        return keep, next_t0, self._clip(next_t1, index), made_jump, (index, inner), result
