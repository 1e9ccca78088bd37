r"""The harmonic-drive model of Taghirad & Bélanger as pure JAX functions (SI units).

- compliance, eq. 5: $T = K_1\,\Delta\theta + T_{st}\,|\dot{\Delta\theta}|^\alpha\,\mathrm{sign}(\dot{\Delta\theta})$;
- friction on the wave-generator velocity, eqs. 9–10 (direction-dependent viscous, Coulomb and
  Stribeck terms);
- motor torque balance, eq. 8: $J_{eff}\,\dot\omega_m = K_m i - T/N - T_f(\omega_m)$;
- free-motion load: $J_{load}\,\dot\omega_o = T$; constrained motion: $\theta_o \equiv 0$.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .smooth import smooth_sign, smooth_signed_power, smooth_step

PARAMETER_NAMES = ("alpha", "K1", "Tst", "Jeff", "Tvp", "Tvn", "Tsp", "Tsn", "Tssp1", "Tssn1", "Tss2")
EQ9_COEFFICIENTS = ("Tvp", "Tvn", "Tsp", "Tsn", "Tssp1", "Tssn1")  # the torques eq. 9 is linear in (`friction_basis` columns)
PARAMETER_UNITS = {
    "alpha": "-",
    "K1": "N·m/rad",
    "Tst": "N·m/(rad/s)^α",
    "Jeff": "kg·m²",
    "Tvp": "N·m·s/rad",
    "Tvn": "N·m·s/rad",
    "Tsp": "N·m",
    "Tsn": "N·m",
    "Tssp1": "N·m",
    "Tssn1": "N·m",
    "Tss2": "rad/s",
}

def _as_float(x):
    return jnp.asarray(x, dtype=float)



class Parameters(eqx.Module):
    """The eleven parameters of the paper's Table I, in SI units (see `PARAMETER_UNITS`).

    Every field is an array leaf, so it can be fitted, differentiated and `vmap`ped.
    """

    alpha: Float[Array, ""] = eqx.field(converter=_as_float)
    K1: Float[Array, ""] = eqx.field(converter=_as_float)
    Tst: Float[Array, ""] = eqx.field(converter=_as_float)
    Jeff: Float[Array, ""] = eqx.field(converter=_as_float)
    Tvp: Float[Array, ""] = eqx.field(converter=_as_float)
    Tvn: Float[Array, ""] = eqx.field(converter=_as_float)
    Tsp: Float[Array, ""] = eqx.field(converter=_as_float)
    Tsn: Float[Array, ""] = eqx.field(converter=_as_float)
    Tssp1: Float[Array, ""] = eqx.field(converter=_as_float)
    Tssn1: Float[Array, ""] = eqx.field(converter=_as_float)
    Tss2: Float[Array, ""] = eqx.field(converter=_as_float)

    def to_dict(self) -> dict[str, float]:
        return {k: float(getattr(self, k)) for k in PARAMETER_NAMES}

    @classmethod
    def from_dict(cls, d: dict) -> "Parameters":
        missing = [k for k in PARAMETER_NAMES if k not in d]
        if missing:
            raise ValueError(f"`Parameters.from_dict`: missing parameter(s) {missing}; give all of {list(PARAMETER_NAMES)}.")
        return cls(**{k: d[k] for k in PARAMETER_NAMES})

    def replace(self, **values) -> "Parameters":
        d = {k: getattr(self, k) for k in PARAMETER_NAMES}
        d.update(values)
        return Parameters(**d)


class Drive(eqx.Module):
    """Drive constants that are known, not fitted: gear ratio `N` (-), torque constant `Km`
    (N·m/A) and load inertia `Jload` (kg·m², used by free-motion experiments only)."""

    gear_ratio: Float[Array, ""] = eqx.field(converter=_as_float)
    torque_constant: Float[Array, ""] = eqx.field(converter=_as_float)
    load_inertia: Float[Array, ""] = eqx.field(converter=_as_float)


class Smoothing(eqx.Module):
    """Scales of the smooth stand-ins (see `hdjax._model.smooth`).

    - `velocity_scale` (rad/s, wave-generator velocity): for sign() and u() in friction, eq. 9.
      Default 1e-3 rad/s, 1 % of the paper's Stribeck velocity `Tss2` = 0.1 rad/s.
    - `torsion_rate_scale` (rad/s, output-side torsion rate): for $|\\dot{\\Delta\\theta}|^\\alpha$
      in eq. 5. Default 1e-5 rad/s, below the torsion rate of a 0.1 N·m, 1 Hz locked test.
    """

    velocity_scale: float | Float[Array, ""] = 1e-3  # an array where traced (scale sweeps, vmap)
    torsion_rate_scale: float | Float[Array, ""] = 1e-5


def compliance_torque(
    p: Parameters, torsion: ArrayLike, torsion_rate: ArrayLike, smoothing: Smoothing = Smoothing()
) -> Float[Array, "..."]:
    r"""Eq. 5: transmitted torque (N·m) from torsion $\Delta\theta$ (rad) and its rate (rad/s)."""
    damping = smooth_signed_power(torsion_rate, p.alpha, smoothing.torsion_rate_scale)
    return p.K1 * torsion + p.Tst * damping


def friction_basis(
    velocity: ArrayLike,
    Tss2: ArrayLike,
    smoothing: Smoothing = Smoothing(),
    *,
    direction: tuple[ArrayLike, ArrayLike] | None = None,
) -> Float[Array, "... 6"]:
    """The six regressors of eq. 9 (columns: Tvp, Tvn, Tsp, Tsn, Tssp1, Tssn1), so that
    `Tf = friction_basis(ω) @ [Tvp, Tvn, Tsp, Tsn, Tssp1, Tssn1]`.

    `direction` = (s, u), optional: a friction state $s \\in [-1, 1]$ and its direction switch
    $u \\in [0, 1]$ that replace sign(ω) and u(ω) in the Coulomb and Stribeck columns (the
    presliding Dahl state of friction-only fits); the viscous columns always switch on ω. This is
    the one place eq. 9 is written: the plant, the paper regressions and the friction-only fits
    all evaluate it here."""
    w = jnp.asarray(velocity)
    up = smooth_step(w, smoothing.velocity_scale)
    un = 1.0 - up
    if direction is None:
        sg, us = smooth_sign(w, smoothing.velocity_scale), up
    else:
        sg, us = jnp.asarray(direction[0]), jnp.asarray(direction[1])
    uns = 1.0 - us
    stribeck = jnp.exp(-((w / Tss2) ** 2))
    return jnp.stack([w * up, w * un, sg * us, sg * uns, sg * us * stribeck, sg * uns * stribeck], axis=-1)


def friction_parts(
    p: Parameters, velocity: ArrayLike, smoothing: Smoothing = Smoothing(), *, direction: tuple[ArrayLike, ArrayLike] | None = None
) -> tuple[Float[Array, "..."], Float[Array, "..."], Float[Array, "..."]]:
    """Eq. 9 split into its (viscous, Coulomb, Stribeck) torques (N·m), for the extensions that
    act on one part (thermal drift on the viscous, position-dependent friction on the Coulomb
    part). `p`: the eq. 9 fields of `Parameters` (a friction-only model's `FrictionParameters.law`); `direction` as
    in `friction_basis`."""
    b = friction_basis(velocity, p.Tss2, smoothing, direction=direction)
    return (b[..., 0] * p.Tvp + b[..., 1] * p.Tvn, b[..., 2] * p.Tsp + b[..., 3] * p.Tsn,
            b[..., 4] * p.Tssp1 + b[..., 5] * p.Tssn1)


def friction_torque(p: Parameters, velocity: ArrayLike, smoothing: Smoothing = Smoothing()) -> Float[Array, "..."]:
    """Eq. 9: friction torque (N·m) at wave-generator velocity (rad/s)."""
    coeffs = jnp.stack([getattr(p, k) for k in EQ9_COEFFICIENTS])
    return friction_basis(velocity, p.Tss2, smoothing) @ coeffs


def motor_acceleration(
    p: Parameters,
    drive: Drive,
    current: ArrayLike,
    torque: ArrayLike,
    velocity: ArrayLike,
    smoothing: Smoothing = Smoothing(),
) -> Float[Array, "..."]:
    """Eq. 8: wave-generator acceleration (rad/s²) from current (A), transmitted torque (N·m) and
    wave-generator velocity (rad/s)."""
    net = drive.torque_constant * current - torque / drive.gear_ratio - friction_torque(p, velocity, smoothing)
    return net / p.Jeff
