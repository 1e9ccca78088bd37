r"""Smooth stand-ins for the kinks of the paper's model.

The paper's friction (eq. 9) uses $\mathrm{sign}(\omega)$ and the unit step $u(\omega)$, and its
structural damping (eq. 5) uses $|\dot{\Delta\theta}|^\alpha\,\mathrm{sign}(\dot{\Delta\theta})$,
whose slope is infinite at zero for $\alpha < 1$. Both make the ODE non-smooth (adaptive solvers
stall, Jacobians jump). hdjax replaces them with smooth functions controlled by an explicit
*scale* (same unit as the argument):

- $\mathrm{sign}(x) \approx \tanh(x/s)$;
- $u(x) \approx \tfrac12(1 + \tanh(x/s))$;
- $|x|^\alpha\,\mathrm{sign}(x) \approx x\,(x^2 + s^2)^{(\alpha-1)/2}$.

Each tends to the exact function pointwise as $s \to 0$ (for $x \neq 0$) and all are infinitely
differentiable, with finite derivatives at $x = 0$ in $x$ and in $\alpha$. `tests/test_model.py`
shows that simulated torque converges as the scales shrink.
"""

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float


def smooth_sign(x: ArrayLike, scale: ArrayLike) -> Float[Array, "..."]:
    r"""$\mathrm{sign}(x) \approx \tanh(x / s)$; `scale` $s > 0$ in the unit of `x`."""
    return jnp.tanh(jnp.asarray(x) / scale)


def smooth_step(x: ArrayLike, scale: ArrayLike) -> Float[Array, "..."]:
    r"""Unit step $u(x) \approx \frac12(1 + \tanh(x/s))$; `scale` $s > 0$ in the unit of `x`."""
    return 0.5 * (1.0 + jnp.tanh(jnp.asarray(x) / scale))


def smooth_signed_power(x: ArrayLike, alpha: ArrayLike, scale: ArrayLike) -> Float[Array, "..."]:
    r"""$|x|^\alpha\,\mathrm{sign}(x) \approx x\,(x^2 + s^2)^{(\alpha - 1)/2}$.

    Exact for $\alpha = 1$; for $|x| \gg s$ the relative error is about
    $\frac{1-\alpha}{2}(s/x)^2$. The slope at zero is $s^{\alpha - 1}$ (finite).
    """
    x = jnp.asarray(x)
    return x * (x * x + scale * scale) ** ((alpha - 1.0) / 2.0)
