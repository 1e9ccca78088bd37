r"""Model extensions beyond the paper (SPEC §4), as real terms inside the plant.

Each effect has a name from the SPEC vocabulary and parameters in SI units. Periodic effects are
written with cosine/sine coefficients over orders $k = 1..K$ (cycles per wave-generator turn):
$\sum_k s_k \sin(k\theta_m) + c_k \cos(k\theta_m)$, equivalent to $\sum_k a_k\sin(k\theta_m+\varphi_k)$
with $a_k = \sqrt{s_k^2 + c_k^2}$, $\varphi_k = \mathrm{atan2}(c_k, s_k)$; this form is linear in
the coefficients, which keeps the fit well conditioned.

| effect | term |
|---|---|
| `kinematic_error` | true torsion $\Delta\theta = \theta_m/N - \theta_o + e(\theta_m)$, $e$ periodic (rad) |
| `torque_sensor_ripple` | measured $T$ += periodic (N·m); dynamics untouched |
| `cogging` | motor torque $K_m i$ += periodic (N·m) |
| `position_dependent_friction` | Coulomb part × (1 + periodic) (-) |
| `nonlinear_stiffness` | $T_k = K_1\Delta\theta + K_3\Delta\theta^3$ ($K_3$ in N·m/rad³) |
| `lost_motion` | $T_k = K_1\,\mathrm{deadzone}(\Delta\theta, \delta)$ ($\delta$ rad, smooth) |
| `load_dependent_friction` | Coulomb += $\mu |T| / N$ ($\mu$ -) |
| `thermal_drift` | viscous × $(1 + \beta e^{-t_{session}/\tau})$ |
| `input_delay` | $K_m i(t - \tau_d)$ ($\tau_d$ s) |
| `rate_independent_hysteresis` | Dahl state $z$: $\dot z = (\dot{\Delta\theta}/\sigma)(1 - z\,\mathrm{sign}(\dot{\Delta\theta}))$, $T$ += $T_h z$ |
| `presliding_friction` | a Dahl friction state $s$ that a fraction $w$ (`presliding`, -) of the Coulomb and Stribeck terms follows instead of sign(ω): $\dot s = (|\omega|/\delta)(\mathrm{sign}\,\omega - s)$, $\delta$ = `PRESLIDING_DISTANCE` × $e^{\lambda_p}$ (`presliding_scale` = $\lambda_p$; rad, wave-generator side). Not screened by the dynamic diagnosis (`hdjax._diagnose`) |

Base-model assumptions (SPEC §4b, `MODEL_FORM`) are loosened by the same mechanism; they are not
physics of the drive but of the bench and of the paper model's fixed choices:

| assumption | adjustment |
|---|---|
| `low_speed_friction` | friction regularisation scale × $e^{\lambda_s}$ (`friction_scale` = $\lambda_s$) and Stribeck velocity $T_{ss2}$ × $e^{\lambda_v}$ (`stribeck_scale` = $\lambda_v$) |
| `sensor_offset` | measured torque += `torque_offset` (N·m), measured velocity += `velocity_offset` (rad/s), true current = recorded − `current_offset` (A) |
| `sensor_bandwidth` | first-order low-pass of the simulated torque and velocity with time constants `torque_lag`, `velocity_lag` (s) |
| `input_between_samples` | the current between samples: linear + $\lambda$ (Catmull–Rom cubic through the same samples − linear), `reconstruction` = $\lambda$ (-; 0 = straight lines, 1 = the cubic) |
| `viscous_friction_law` | eq. 9's viscous torque $T_v\omega$ × $((\omega^2 + \epsilon^2)/\omega_r^2)^{(\kappa-1)/2}$, $\kappa = e^{\lambda_\kappa}$ (`viscous_exponent` = $\lambda_\kappa$; 0 = the paper's linear law), $\omega_r$ = `viscous_reference` (rad/s; set from the data, not fitted), $\epsilon$ = `VISCOUS_LAW_SCALE`. hdjax's addition to SPEC §4b's four: a drive's running torque often grows slower than linearly with speed |
"""

import dataclasses
import typing

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._smooth import smooth_sign

MAX_ORDER = 8
#: rad, wave-generator side: the presliding distance δ of `presliding_friction`'s Dahl state at
#: `presliding_scale` = 0. A bearing's presliding displacement of a few µm at a wave-generator
#: radius of 10–20 mm is 1e-4–1e-3 rad; fitted on clean independent-bench data δ came out
#: 1.5e-4–2.5e-4 rad (stick–slip and LuGre laws), from a start of 1e-3
PRESLIDING_DISTANCE = 2e-4
THERMAL_TAU = 600.0  # s: default time constant of `thermal_drift` (the lubricant's warm-up), shared by every path
#: rad/s: the velocity scale ε below which `viscous_friction_law`'s power law |ω|^κ turns into a
#: linear law of slope $T_v(\epsilon/\omega_r)^{\kappa-1}$, so that its derivative stays finite at
#: ω = 0. Against the exact power law the torque differs by at most 0.5·|κ−1|·(ε/ω)² relative
#: (0 < κ ≤ 3; tests/test_model_form.py shows the convergence as ε shrinks); Coulomb friction
#: dominates below 0.1 rad/s on the drives here
VISCOUS_LAW_SCALE = 1e-2
PERIODIC = ("kinematic_error", "torque_sensor_ripple", "cogging", "position_dependent_friction")
SCALAR = {
    "nonlinear_stiffness": ("K3",),
    "lost_motion": ("backlash",),
    "load_dependent_friction": ("mu",),
    "thermal_drift": ("beta", "tau"),
    "input_delay": ("delay",),
    "rate_independent_hysteresis": ("Th", "sigma"),
    "presliding_friction": ("presliding", "presliding_scale"),
}
EFFECT_NAMES = PERIODIC + tuple(SCALAR)
#: SPEC §4b: base-model assumptions the diagnosis may loosen before it screens effects.
MODEL_FORM = {
    "low_speed_friction": ("friction_scale", "stribeck_scale"),
    "sensor_offset": ("torque_offset", "velocity_offset", "current_offset"),
    "sensor_bandwidth": ("torque_lag", "velocity_lag"),
    "input_between_samples": ("reconstruction",),
    "viscous_friction_law": ("viscous_exponent", "viscous_reference"),
}
MODEL_FORM_NAMES = tuple(MODEL_FORM)
#: Units of the amplitude of each periodic effect (its phases are in rad).
PERIODIC_UNITS = {"kinematic_error": "rad", "torque_sensor_ripple": "N·m", "cogging": "N·m",
                  "position_dependent_friction": "-"}
#: Units of every scalar field of `SCALAR` and `MODEL_FORM` ("-": dimensionless; the `*_scale`
#: fields and `viscous_exponent` are natural logarithms of a factor).
FIELD_UNITS = {
    "K3": "N·m/rad³", "backlash": "rad", "mu": "-", "beta": "-", "tau": "s", "delay": "s", "Th": "N·m",
    "sigma": "rad", "presliding": "-", "presliding_scale": "-", "friction_scale": "-", "stribeck_scale": "-",
    "torque_offset": "N·m", "velocity_offset": "rad/s", "current_offset": "A", "torque_lag": "s",
    "velocity_lag": "s", "reconstruction": "-", "viscous_exponent": "-", "viscous_reference": "rad/s",
}  # fmt: skip
#: The scalar fields of every non-periodic term, effects and model_form alike.
SCALAR_FIELDS = {**SCALAR, **MODEL_FORM}


_ORDERS = np.arange(1, MAX_ORDER + 1, dtype=float)  # the orders of `Effects`' harmonic slots


def harmonic_sum(angle, orders, sin_coef, cos_coef):
    """$\\sum_k s_k\\sin(k\\theta) + c_k\\cos(k\\theta)$ over harmonic slots (last axis of
    `orders`, `sin_coef`, `cos_coef`); a slot of order 0 is off. `angle` θ (rad) of any shape.
    The one periodic term of the package: `Effects`' fixed orders 1..`MAX_ORDER` and the
    friction-only fits' free slots both evaluate it."""
    orders = jnp.asarray(orders, dtype=float)
    on = (orders > 0).astype(float)
    ang = orders * jnp.asarray(angle)[..., None]
    return jnp.sum(on * (sin_coef * jnp.sin(ang) + cos_coef * jnp.cos(ang)), axis=-1)


def thermal_factor(beta, tau, t_session):
    """`thermal_drift`'s factor on the viscous torque, $1 + \\beta e^{-t_{session}/|\\tau|}$
    ($\\beta$ -, $\\tau$ s, session time s)."""
    return 1.0 + beta * jnp.exp(-t_session / jnp.abs(tau))


def _zeros():
    return np.zeros(MAX_ORDER)


@typing.no_type_check  # returns a numpy array standing in for an `Array` field (below); runtime checks skip it
def _as_float(x) -> Array:
    # numbers become numpy arrays, so that building an `Effects` (a default argument at import)
    # does not start JAX's backends: `hdjax._sharding.use_host_devices` must run before that
    if isinstance(x, jax.Array):
        return jnp.asarray(x, dtype=float)
    # the numpy array stands in for the field's `Array`; jax.config options are dynamic attributes
    return np.asarray(x, dtype=np.float64 if jax.config.jax_enable_x64 else np.float32)  # pyright: ignore[reportReturnType, reportAttributeAccessIssue]


class Effects(eqx.Module):
    """Parameters of the active model extensions; `active` (static) names the effects switched on.

    Periodic effects: `<name>_sin`, `<name>_cos` arrays of length `MAX_ORDER` (order k at index
    k−1). Scalars as in the table of `hdjax._effects`. Inactive fields are ignored.
    """

    active: frozenset = eqx.field(static=True, default=frozenset())
    kinematic_error_sin: Float[Array, " order"] = eqx.field(default_factory=_zeros, converter=_as_float)
    kinematic_error_cos: Float[Array, " order"] = eqx.field(default_factory=_zeros, converter=_as_float)
    torque_sensor_ripple_sin: Float[Array, " order"] = eqx.field(default_factory=_zeros, converter=_as_float)
    torque_sensor_ripple_cos: Float[Array, " order"] = eqx.field(default_factory=_zeros, converter=_as_float)
    cogging_sin: Float[Array, " order"] = eqx.field(default_factory=_zeros, converter=_as_float)
    cogging_cos: Float[Array, " order"] = eqx.field(default_factory=_zeros, converter=_as_float)
    position_dependent_friction_sin: Float[Array, " order"] = eqx.field(default_factory=_zeros, converter=_as_float)
    position_dependent_friction_cos: Float[Array, " order"] = eqx.field(default_factory=_zeros, converter=_as_float)
    K3: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    backlash: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    mu: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    beta: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    tau: Float[Array, ""] = eqx.field(default=THERMAL_TAU, converter=_as_float)
    delay: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    Th: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    sigma: Float[Array, ""] = eqx.field(default=1e-4, converter=_as_float)
    friction_scale: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    stribeck_scale: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    presliding: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    presliding_scale: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    torque_offset: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    velocity_offset: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    current_offset: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    torque_lag: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    velocity_lag: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    reconstruction: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    viscous_exponent: Float[Array, ""] = eqx.field(default=0.0, converter=_as_float)
    viscous_reference: Float[Array, ""] = eqx.field(default=10.0, converter=_as_float)

    def __check_init__(self):
        unknown = set(self.active) - set(EFFECT_NAMES) - set(MODEL_FORM)
        if unknown:
            raise ValueError(f"`Effects`: unknown effect(s) {sorted(unknown)}; known: "
                             f"{list(EFFECT_NAMES) + list(MODEL_FORM)}.")

    def periodic(self, name: str, theta_m):
        """$\\sum_k s_k\\sin(k\\theta_m) + c_k\\cos(k\\theta_m)$ for a periodic effect (0 if inactive)."""
        if name not in self.active:
            return jnp.zeros_like(theta_m)
        return harmonic_sum(theta_m, _ORDERS, getattr(self, f"{name}_sin"), getattr(self, f"{name}_cos"))

    def periodic_rate(self, name: str, theta_m, omega_m):
        """Time derivative of `periodic(name, θm)` along θm' = ωm."""
        if name not in self.active:
            return jnp.zeros_like(theta_m)
        s, c = getattr(self, f"{name}_sin"), getattr(self, f"{name}_cos")
        return harmonic_sum(theta_m, _ORDERS, -_ORDERS * c, _ORDERS * s) * omega_m

    def amplitudes(self, name: str):
        """(orders, amplitudes, phases) of a periodic effect for reports, as numpy-ready arrays."""
        s = getattr(self, f"{name}_sin")
        c = getattr(self, f"{name}_cos")
        return jnp.arange(1, MAX_ORDER + 1), jnp.hypot(s, c), jnp.arctan2(c, s)

    def with_periodic(self, name: str, order: int, amplitude: float, phase: float = 0.0) -> "Effects":
        """A copy with `a·sin(k·θm + φ)` added to effect `name` at order `k`, and the effect switched on."""
        s = jnp.asarray(getattr(self, f"{name}_sin")).at[order - 1].add(amplitude * jnp.cos(phase))
        c = jnp.asarray(getattr(self, f"{name}_cos")).at[order - 1].add(amplitude * jnp.sin(phase))
        new = eqx.tree_at(lambda e: (getattr(e, f"{name}_sin"), getattr(e, f"{name}_cos")), self, (s, c))
        return dataclasses.replace(new, active=frozenset(self.active | {name}))

    def with_values(self, name: str, **values) -> "Effects":
        """A copy with the scalar parameters of effect `name` set and the effect switched on."""
        allowed = SCALAR_FIELDS[name]
        bad = set(values) - set(allowed)
        if bad:
            raise ValueError(f"`Effects.with_values`: {name} takes {allowed}, got {sorted(bad)}.")
        new = self
        for k, v in values.items():
            new = eqx.tree_at(lambda e: getattr(e, k), new, jnp.asarray(v, dtype=float))
        return dataclasses.replace(new, active=frozenset(self.active | {name}))


def viscous_law_factor(velocity, exponent, reference, *, scale: float = VISCOUS_LAW_SCALE):
    r"""`viscous_friction_law`'s factor on eq. 9's linear viscous torque (-):
    $((\omega^2+\epsilon^2)/\omega_r^2)^{(\kappa-1)/2}$ with $\kappa = e^{\lambda_\kappa}$; 1 at
    `exponent` λκ = 0. `velocity` ω and `reference` ωr (rad/s), `scale` ε (rad/s)."""
    kappa = jnp.exp(exponent)
    return jnp.exp(0.5 * (kappa - 1.0) * jnp.log((jnp.square(velocity) + scale**2) / jnp.square(reference)))


def stiffness_torque(K1, torsion, effects: Effects):
    """Elastic torque $T_k(\\Delta\\theta)$ (N·m): linear, or with cubic / dead-zone extensions."""
    x = torsion
    if "lost_motion" in effects.active:
        d = jnp.abs(effects.backlash)
        s = d / 20.0 + 1e-9
        x = s * (jnp.logaddexp(0.0, (x - d) / s) - jnp.logaddexp(0.0, (-x - d) / s))
    t = K1 * x
    if "nonlinear_stiffness" in effects.active:
        t = t + effects.K3 * x**3
    return t


def presliding_rate(s, velocity, effects: Effects, scale):
    r"""`presliding_friction`'s Dahl friction state derivative (1/s),
    $\dot s = (|\omega|/\delta)(\mathrm{sign}\,\omega - s)$ with $\delta$ =
    `PRESLIDING_DISTANCE`·e^`presliding_scale` (rad), the law of the friction-only fits
    (`hdjax._friction.dahl_recurrence`). sign and |·| are smoothed at `scale` (rad/s, the friction's
    regularisation scale): $\tanh(\omega/v_s)$ and $\omega\tanh(\omega/v_s)$, which is $|\omega|$
    beyond a few $v_s$ and has no kink at rest (a stuck state keeps its value)."""
    sg = smooth_sign(velocity, scale)
    distance = PRESLIDING_DISTANCE * jnp.exp(effects.presliding_scale)
    return velocity * sg / distance * (sg - s)


def dahl_rate(z, torsion_rate, effects: Effects, scale):
    """Dahl hysteresis state derivative $\\dot z = (\\dot{\\Delta\\theta}/\\sigma)(1 - z\\,\\mathrm{sign}(\\dot{\\Delta\\theta}))$."""
    return torsion_rate / jnp.abs(effects.sigma) * (1.0 - z * smooth_sign(torsion_rate, scale))
