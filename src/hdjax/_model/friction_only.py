r"""Friction-only model: eq. 9 and its extensions as pure JAX functions of a measured record.

A `friction` experiment (SPEC §2) holds friction torque against velocity (and optionally position
and session time). The model evaluated along one record is

$$T_f = \underbrace{(T_{vp} u(\omega) + T_{vn} u(-\omega))\,\omega\,(1 + \beta e^{-t_s/\tau})}_{\text{viscous}\,\times\,\text{thermal drift}}
      + \underbrace{C(s)\,\big(1 + \textstyle\sum_k \epsilon_k \sin(k\theta + \phi_k)\big)}_{\text{Coulomb}\,\times\,\text{position ripple}}
      + S(s, \omega) + \textstyle\sum_k b_k \sin(k\theta + \psi_k)$$

with the Coulomb part $C(s) = (T_{sp} u(s) + T_{sn} u(-s))\,s$ and the Stribeck part
$S = (T_{ssp1} u(s) + T_{ssn1} u(-s))\,s\,e^{-(\omega/T_{ss2})^2}$. Without presliding,
$s = \mathrm{sign}(\omega)$ and $u(s) = u(\omega)$: eq. 9 exactly (`hdjax.friction_torque`).

Extensions (each off unless its `FrictionStructure` entry is on):

- `position_dependent_friction`: the Coulomb part times $1 + \sum_k \epsilon_k\sin(k\theta+\phi_k)$,
  orders $k$ in cycles per turn (2π rad) of the recorded `position`.
- `position_dependent_torque`: a direction-independent torque $\sum_k b_k \sin(k\theta+\psi_k)$.
  Not friction: on joint data it is what a rigid-body (gravity) model error left upstream, or a
  torque-sensor ripple, looks like. Both directions are needed to tell it from friction ripple.
- `presliding_friction`: a Dahl state $s \in [-1, 1]$ replaces $\mathrm{sign}(\omega)$ in the
  Coulomb and Stribeck parts, $\dot s = (|\omega|/\delta)\,(\mathrm{sign}(\omega) - s)$, with presliding
  distance $\delta$ (rad; Dahl stiffness $\sigma_0 = T_s/\delta$). This is LuGre with $\sigma_1 = 0$
  and a normalised state; its steady state is eq. 9. It is integrated along the measured velocity
  record exactly for a velocity held over each sample interval (ending at the sample), so it is
  stable for any stiffness: $s_n = e^{-a_n h_n}s_{n-1} + (1 - e^{-a_n h_n})\,\mathrm{sign}(\omega_n)$,
  $a_n = |\omega_n|/\delta$, as a `jax.lax.scan` (an `associative_scan` of the affine recurrence
  took 45 s to compile inside the fit, against 10 s). The record starts in its steady state
  $s_0 = \mathrm{sign}(\omega_0)$.
- `thermal_drift`: viscous part times $1 + \beta e^{-t_s/\tau}$, $t_s$ = `start_time` + `time` (s).

sign() and u() are the smooth stand-ins of `hdjax._model.smooth` with `Smoothing.velocity_scale`
(rad/s); the direction switch on the presliding state uses `STATE_SCALE` (dimensionless).

Each extension is the plant's own term Module (`PositionDependentFriction`, `PositionDependentTorque`,
`PreslidingFriction`, `ThermalDrift`): its parameters, units and law are written once. What differs
from the plant is how a fit switches them: `FrictionStructure` holds array flags and the harmonic
slots' orders as data, so that one compiled friction fit serves every candidate of the diagnosis
(the plant switches terms by the static `Effects.active`), and a periodic term here holds
`HARMONIC_SLOTS` slots of orders chosen from the data (up to 40 cycles per joint turn) instead of
the plant's fixed orders 1 … `MAX_ORDER` per wave-generator turn.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from .effects import (
    PRESLIDING_DISTANCE,
    THERMAL_TAU,
    PositionDependentFriction,
    PositionDependentTorque,
    PreslidingFriction,
    ThermalDrift,
    thermal_factor,
)
from .paper import PARAMETER_UNITS, Parameters, Smoothing, _as_float, friction_parts
from .smooth import smooth_sign, smooth_step

FRICTION_NAMES = ("Tvp", "Tvn", "Tsp", "Tsn", "Tssp1", "Tssn1", "Tss2")
FRICTION_UNITS = {k: PARAMETER_UNITS[k] for k in FRICTION_NAMES}
EXTENSION_NAMES = ("position_dependent_friction", "position_dependent_torque", "presliding_friction", "thermal_drift")
#: Harmonic slots per periodic extension of a friction-only fit. Each slot holds a chosen order
#: (1 … 40 cycles per turn of the joint `position`, picked from the data) and its coefficients, so
#: three slots reach orders far above `hdjax._model.effects.MAX_ORDER` = 8, which is the number of
#: *fixed* orders 1 … 8 (cycles per wave-generator turn) that `Effects` carries for the plant.
HARMONIC_SLOTS = 3


def _f3(x):
    return jnp.broadcast_to(jnp.asarray(x, dtype=float), (HARMONIC_SLOTS,))


#: Table I values that friction-only data do not determine (compliance and inertia): NaN in the
#: `Parameters` a friction-only model carries, so nothing can use them by mistake.
_NOT_IDENTIFIED = {"alpha": float("nan"), "K1": float("nan"), "Tst": float("nan"), "Jeff": float("nan")}


class FrictionParameters(eqx.Module):
    """Eq. 9 plus the extensions of a friction-only model: the plant's own term Modules
    (`hdjax._model.effects`), so each effect's parameters and law exist once.

    - `law`: the paper's `Parameters`; its eq. 9 fields (`FRICTION_NAMES`, SI units) are the
      friction law, the same fields and the same `friction_parts` as the plant's. Friction-only
      data do not determine α, K1, Tst, Jeff: they are NaN.
    - `position_dependent_friction`: a `PositionDependentFriction` with `HARMONIC_SLOTS` slots,
      `sin`/`cos` (-) = $\\epsilon_k\\cos\\phi_k$, $\\epsilon_k\\sin\\phi_k$; the slots' orders are in
      `FrictionStructure.ripple_orders`.
    - `position_dependent_torque`: a `PositionDependentTorque` (N·m), likewise (`torque_orders`).
    - `presliding_friction`: a `PreslidingFriction` with `presliding` = 1 (the Dahl state replaces
      sign(ω) in full) and $\\delta$ = `PRESLIDING_DISTANCE` × e^`presliding_scale` (rad, joint side).
    - `thermal_drift`: a `ThermalDrift` ($\\beta$ -, $\\tau$ s).

    Built from plain values by keyword (`FrictionParameters(Tvp=..., ..., Tss2=..., ripple_sin=...,
    presliding_distance=..., thermal_beta=...)`); a fit's vector reaches them by the paths
    `"law.Tvp"`, `"position_dependent_friction.sin"`, `"presliding_friction.presliding_scale"` and so on.
    """

    law: Parameters
    position_dependent_friction: PositionDependentFriction
    position_dependent_torque: PositionDependentTorque
    presliding_friction: PreslidingFriction
    thermal_drift: ThermalDrift

    def __init__(self, *, Tvp, Tvn, Tsp, Tsn, Tssp1, Tssn1, Tss2, ripple_sin=0.0, ripple_cos=0.0, torque_sin=0.0,
                 torque_cos=0.0, presliding_distance=1e-3, thermal_beta=0.0, thermal_tau=THERMAL_TAU):
        self.law = Parameters(**_NOT_IDENTIFIED, Tvp=Tvp, Tvn=Tvn, Tsp=Tsp, Tsn=Tsn, Tssp1=Tssp1, Tssn1=Tssn1, Tss2=Tss2)
        self.position_dependent_friction = PositionDependentFriction(sin=_f3(ripple_sin), cos=_f3(ripple_cos))
        self.position_dependent_torque = PositionDependentTorque(sin=_f3(torque_sin), cos=_f3(torque_cos))
        scale = jnp.log(jnp.asarray(presliding_distance, dtype=float) / PRESLIDING_DISTANCE)
        self.presliding_friction = PreslidingFriction(presliding=1.0, presliding_scale=scale)
        self.thermal_drift = ThermalDrift(beta=thermal_beta, tau=thermal_tau)

    def eq9(self) -> dict[str, float]:
        """The seven eq. 9 values as Python floats."""
        return {k: float(getattr(self.law, k)) for k in FRICTION_NAMES}


class FrictionStructure(eqx.Module):
    """Which extensions are on (arrays, so one compiled fit serves every candidate).

    - `ripple_orders`, `torque_orders`: orders (cycles per turn of `position`) of the harmonic
      slots of `position_dependent_friction` / `position_dependent_torque`; 0 switches a slot off.
    - `presliding`, `thermal`: 1.0 switches `presliding_friction` / `thermal_drift` on.
    """

    ripple_orders: Float[Array, " 3"] = eqx.field(converter=_f3, default=0.0)
    torque_orders: Float[Array, " 3"] = eqx.field(converter=_f3, default=0.0)
    presliding: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)
    thermal: Float[Array, ""] = eqx.field(converter=_as_float, default=0.0)


def presliding_state(
    velocity: Float[Array, " time"],
    time: Float[Array, " time"],
    distance: ArrayLike,
    smoothing: Smoothing = Smoothing(),
) -> Float[Array, " time"]:
    r"""Dahl state $s$ (-) along a velocity record (rad/s) at times (s), presliding distance (rad).

    Exact for velocity held constant over each interval $(t_{n-1}, t_n]$ at its end value, so
    unconditionally stable (any $\delta > 0$); padding with a repeated time holds the state.
    Velocity and time are measured data and are not differentiated (`stop_gradient`); the
    derivative in $\delta$ is a forward-sensitivity recurrence run alongside the state, so a
    Jacobian with many parameters still costs one scan, not one per parameter.
    """
    v = jax.lax.stop_gradient(jnp.asarray(velocity, dtype=float))
    t = jax.lax.stop_gradient(jnp.asarray(time, dtype=float))
    return _dahl(jnp.asarray(distance, dtype=float), v, t, smoothing.velocity_scale)


def dahl_recurrence(distance, v, t, scale, *, target=None, s0=None):
    """The presliding Dahl recurrence $s_n = a_n s_{n-1} + (1 - a_n) b_n$, $a_n = e^{-|\\omega_n| h_n/\\delta}$,
    and its derivative in $\\delta$, in one scan. The target $b$ is sign(ω) smoothed at `scale`
    unless given; the state before the first sample is `s0` (default $b_0$: the steady state).
    This is `hdjax._model.effects.PreslidingFriction.rate`'s law, $\\dot s = (|\\omega|/\\delta)(\\mathrm{sign}\\,\\omega - s)$,
    solved exactly for a velocity held over each sample interval."""
    h = jnp.diff(t, prepend=t[:1])
    target = smooth_sign(v, scale) if target is None else target
    s0 = target[0] if s0 is None else jnp.asarray(s0, dtype=float)
    rate = jnp.abs(v) * h
    decay = jnp.exp(-rate / distance)
    ddecay = decay * rate / distance**2  # d(decay)/d(distance)

    def step(carry, inputs):
        s, z = carry
        a, da, b = inputs
        return (a * s + (1.0 - a) * b, a * z + da * (s - b)), (s, z)

    (s_last, z_last), (s_prev, z_prev) = jax.lax.scan(step, (s0, jnp.zeros(())), (decay, ddecay, target), unroll=16)
    # outputs are the carries *before* each step: shift by one to get the state after it
    s = jnp.concatenate([s_prev[1:], s_last[None]])
    z = jnp.concatenate([z_prev[1:], z_last[None]])
    return s, z


@jax.custom_jvp
def _dahl(distance, v, t, scale):
    return dahl_recurrence(distance, v, t, scale)[0]


@_dahl.defjvp
def _dahl_jvp(primals, tangents):
    distance, v, t, scale = primals
    s, z = dahl_recurrence(distance, v, t, scale)
    return s, z * tangents[0]


def friction_model_torque(
    p: FrictionParameters,
    structure: FrictionStructure,
    velocity: Float[Array, " time"],
    *,
    time: Float[Array, " time"],
    position: Float[Array, " time"],
    has_position: ArrayLike = 1.0,
    start_time: ArrayLike = 0.0,
    smoothing: Smoothing = Smoothing(),
    at: Int[Array, " sample"] | None = None,
) -> Float[Array, " sample"]:
    """Friction torque (N·m) of eq. 9 with the extensions of `structure`, along one record:
    velocity (rad/s), time (s), position (rad; ignored where `has_position` is 0) and the
    record's `start_time` (s since the session began).

    `at` (sample indices, optional) returns the torque at those samples only; the presliding
    state still runs through every sample, everything else is evaluated only where asked."""
    v_all = jnp.asarray(velocity)
    t_all = jnp.asarray(time)
    take = (lambda a: a) if at is None else (lambda a: jnp.asarray(a)[at])
    v, t, theta = take(v_all), take(t_all), take(position)
    sc = smoothing.velocity_scale
    up = smooth_step(v, sc)
    sg = smooth_sign(v, sc)

    def with_state(_):
        s = take(presliding_state(v_all, t_all, p.presliding_friction.distance(), smoothing))
        return p.presliding_friction.direction(sg, up, s)

    def without_state(_):
        return sg, up

    s, us = jax.lax.cond(structure.presliding > 0.5, with_state, without_state, None)
    viscous, coulomb, stribeck = friction_parts(p.law, v, smoothing, direction=(s, us))
    viscous = viscous * thermal_factor(structure.thermal * p.thermal_drift.beta, p.thermal_drift.tau, start_time + t)
    ripple = has_position * p.position_dependent_friction.value(theta, structure.ripple_orders)
    additive = has_position * p.position_dependent_torque.value(theta, structure.torque_orders)
    return viscous + coulomb * (1.0 + ripple) + stribeck + additive


def amplitude_phase(sin_coef, cos_coef) -> tuple[float, float]:
    """$(A, \\phi)$ with $A\\sin(k\\theta+\\phi) = c^s\\sin k\\theta + c^c\\cos k\\theta$."""
    s, c = float(sin_coef), float(cos_coef)
    return float(jnp.hypot(s, c)), float(jnp.arctan2(c, s))
