r"""A fixed-cost plant: implicit time stepping on the velocity level, friction and power-law damping
treated exactly (no smoothing scales).

The plant of `hdjax._plant.simulate` (torsion $q$, wave-generator velocity $\omega_m$, output angle and
velocity) is stepped with a constant step $h$ (the sample period divided by `substeps`), in the
manner of Moreau–Jean time stepping and Drake's discrete friction solvers:

- **TR-BDF2** (order 2, L-stable, one-step): a trapezoidal stage to $t + \gamma h$
  ($\gamma = 2 - \sqrt2$), then a BDF2 stage to $t + h$ on $(t, t+\gamma h, t+h)$. Each stage is
  implicit in everything it can be: elastic and damping torque, Coulomb friction with its
  set-valued sticking at $\omega_m = 0$, viscous friction, the Dahl state (an exact update from
  the stage's torsion increment: Dahl's law is rate independent). One-step, so the kinks of the
  piecewise-linear current at the sample instants never fall inside a multistep stencil (plain
  BDF2 was several times less accurate on square-wave records); L-stable, so it does not ring
  across zero velocity as the trapezoidal rule alone does.
- **position- and load-dependent terms** (cogging, kinematic error, position- and load-dependent
  friction) are explicit: evaluated at a stage end predicted at constant speed, then once more at
  the first pass's stage end (a predictor–corrector, `corrector=True`; the second pass is skipped
  where no term reads the predicted state, see `VelocityImplicit`). With
  `Simulator.measured_angle` the wave-generator angle they act at is the record's, interpolated
  between samples, at the stage's end (as the adaptive plant reads it).
- `viscous_friction_law` multiplies the implicit viscous term; Tv·ω·((ω²+ε²)/ωr²)^((κ−1)/2) increases
  with ω for every κ > 0, so the step equation stays monotone.

**The implicit equation of one step is one scalar, monotone equation.** The unknown is
$s = |\dot{\Delta\theta}_{n+1}|^\alpha\,\mathrm{sign}(\dot{\Delta\theta}_{n+1})$, the damping
term itself: in $s$ the torsion rate $|s|^{1/\alpha}\mathrm{sign}(s)$ is $C^1$ and the damping is
linear, so the infinite slope of $|x|^\alpha$ at zero disappears. Given $s$, the output velocity
follows from the load's momentum balance and the motor velocity from $\omega_m = N(r + \omega_o)$;
every term of the motor's momentum balance $G(s)$ then increases with $s$. Sticking is exact:
$s^*$ with $\omega_{m,n+1}(s^*) = 0$ solves a second monotone scalar equation (closed form with the
output locked); the motor sticks when the friction needed to hold it lies inside
$[-(T_{sn}+T_{ssn1}),\; T_{sp}+T_{ssp1}]$, otherwise the root lies on the branch the net torque
points to. Each root is found inside an analytic bracket (from the inertia term alone) by Newton's
method safeguarded by bisection, warm-started from the previous step, for at most `iterations`
iterations (fewer once the iterate stops moving): the cost of a step is bounded whatever the data,
so `vmap`ped experiments wait at most that long for each other (no adaptive step count to follow).

**Stribeck.** With $T_{ss1} > 0$ friction falls with speed (locally non-monotone): $G$ could have
several roots once its inertia term $A = J_{eff}/(\beta h)$ no longer exceeds the steepest fall,
$0.858\,T_{ss1}/T_{ss2}$. While it does (with a 10 % margin) the term is implicit; otherwise the
Stribeck factor $e^{-(\omega/T_{ss2})^2}$ is evaluated at the predicted speed (first pass: the start
of the stage, so breakaway from rest is $T_s + T_{ss1}$; corrector: the first pass's end), a
convex–concave splitting that keeps $G$ monotone and the root unique at any $h$. With
$T_{ss1} \le 0$ (friction rising with speed, as in the paper's HD2) the term is always implicit.

**Friction through zero velocity** (`VelocityImplicit(reversal_quadrature=True)`). A step predicted to come close to zero velocity or to reverse
the motor takes friction's mean over each stage, with the velocity linear on each side of the
estimated crossing, instead of its node values (`_stage_friction`): the jump at zero velocity and
the narrow Stribeck dip then enter the step's impulse at second order (HD1 campaign, 4 substeps:
motor-velocity error 0.27 σ → 0.07 σ). A stuck motor's friction carried to the next step is then
the torque holding it (inside the breakaway interval), not the stage's mean. Off by default: the
stage's Gaussian mean in the Newton loop makes the fit about 40 % slower.

**Derivatives** come from the implicit function theorem at the converged root (`custom_jvp`):
$\partial s/\partial p = -G_p/G_s$, never from differentiating the iterations; $G_s \ge T_{st}/N > 0$,
so they are finite everywhere, at zero velocity and while stuck included.

**`low_speed_friction`** (SPEC §4b): the exact law has no regularisation scale. When the item is
active the Coulomb and Stribeck terms ramp linearly over $|\omega_m| < v_c$ with
$v_c$ = `Smoothing.velocity_scale`·e^`friction_scale` (a creep / presliding width the fit can
adapt), and $T_{ss2}$ is multiplied by e^`stribeck_scale`.

**`presliding_friction`** (a Dahl friction state) is not modelled here: the stepper's exact
set-valued sticking is that law's rigid limit (δ → 0); `simulate` refuses the combination.
"""

import functools
import numbers
from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from .._model.effects import PERIODIC, Effects, stiffness_torque


class VelocityImplicit(eqx.Module):
    """Fixed-step implicit velocity-level stepper (see `hdjax._plant.stepper`), opt-in:
    `hdjax.Simulator(solver=hdjax.VelocityImplicit())` (the default solver is `Rodas3`).

    **Arguments:**

    - `substeps`: steps per sample interval (the step is the sample period / `substeps`).
    - `iterations`: at most this many safeguarded Newton iterations per scalar root (the step's
      largest cost; the iteration stops earlier once it no longer moves).
    - `corrector`: solve each stage again with the explicit terms at the first pass's stage end,
      where a term reads the predicted state: a position- or load-dependent effect, or a falling
      Stribeck term (an amplitude > 0) that may be too steep to be implicit; otherwise the second
      pass would solve the same equation and is skipped (measured 2026-12-04: simulation and
      Jacobian about 1.6× cheaper on the shipped HD2 data, the same trajectories).
    - `reversal_quadrature`: friction's mean over each stage in a step through the Stribeck dip or a
      motor reversal (`_stage_friction`), instead of eq. 9 at the stage end. Measured 2026-12-06
      (`benchmarks/stepper.py --reversal-quadrature`, 12 shipped records, worst record's RMS against
      128 substeps with it): HD1 motor velocity 0.065 σ at 4 substeps instead of 0.279 σ (0.028
      against 0.142 at 8, 0.003 against 0.098 at 16), HD2 0.019 σ instead of 0.076 σ. Costs: the
      stage's Gaussian mean in the Newton loop, a Jacobian about 1.6× and the HD2 fit command
      about 1.4× the time (32.1 s against 23.1 s inside, cold), so off by default. Use it with 4 substeps
      or more: at 2 it moved a stop on a locked HD1 record (torque 0.30 σ RMS there, 0.08 σ without).
    """

    substeps: int = eqx.field(static=True, default=1)
    iterations: int = eqx.field(static=True, default=48)
    corrector: bool = eqx.field(static=True, default=True)
    reversal_quadrature: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        for name in ("substeps", "iterations"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 1:
                raise ValueError(f"`VelocityImplicit.{name}` must be a whole number >= 1, got {v!r}.")
        for name in ("corrector", "reversal_quadrature"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"`VelocityImplicit.{name}` must be True or False, got {getattr(self, name)!r}.")


#: A step's root counts as converged when the residual of its equation is at most this fraction of
#: the largest torque in it (`Trajectory.success`).
ROOT_RTOL = 1e-7


def _static_bounds(lo, hi, P):
    """The stick interval [lo, hi] (N·m) of eq. 9's friction at rest, widened to
    `breakaway_friction`'s breakaway torques (static friction above eq. 9's limit at zero speed)
    where that term is active; as given otherwise."""
    eff = P["eff"]
    if "breakaway_friction" not in eff.active:
        return lo, hi
    return eff.breakaway_friction.stick_band(lo, hi)


def _safe_abs_pow(x, p):
    """|x|**p with finite derivatives in x and p at x = 0 (value 0 there, for p > 0)."""
    ax = jnp.abs(x)
    pos = ax > 0
    return jnp.where(pos, jnp.exp(p * jnp.log(jnp.where(pos, ax, 1.0))), 0.0)


def _signed_pow(x, p):
    return jnp.sign(x) * _safe_abs_pow(x, p)


# --------------------------------------------------------------------------------------------------
# the step's scalar equations; `P` is a dict of arrays (everything the step depends on), `active` the
# static set of effects
# --------------------------------------------------------------------------------------------------


def _end_state(s, P):
    """End-of-step quantities as functions of the unknown s (damping term |rate|^α sign)."""
    eff = P["eff"]
    r_true = _signed_pow(s, 1.0 / P["alpha"])  # true torsion rate at the end of the step (rad/s)
    r1 = r_true - P["edot1"]  # kinematic rate ω_m/N − ω_o
    q1 = P["q_hist"] + P["bh"] * r1
    tor1 = q1 + P["e1"]
    Tk1 = stiffness_torque(P["K1"], tor1, eff)
    if "rate_independent_hysteresis" in eff.active:
        # exact: Dahl's law is rate independent, z follows the torsion increment of the step
        d = tor1 - P["tor0"]
        sd = jnp.sign(d)
        z1 = sd - (sd - P["z0"]) * jnp.exp(-jnp.abs(d) / jnp.abs(eff.rate_independent_hysteresis.sigma))
        Tz = eff.rate_independent_hysteresis.Th * z1
    else:
        z1 = P["z0"]
        Tz = 0.0
    Tbar = Tk1 + P["Tst"] * s + Tz  # transmitted torque at the end of the step (N·m)
    wo1 = P["wo_hist"] + P["fh_J"] * Tbar
    wm1 = P["N"] * (r1 + wo1)
    return r1, q1, tor1, Tk1, z1, Tbar, wo1, wm1


def _stribeck_fall(A, Tss2, coef):
    """Steepest fall of coef·e^{−(ω/Tss2)²} (N·m per rad/s) if the Stribeck term is taken
    implicitly, else 0; implicit while the inertia term A keeps G monotone:
    A > max|d/dω coef·e^{−(ω/Tss2)²}| = coef·√2·e^{−½}/Tss2, with a 10 % margin."""
    fall = jnp.maximum(coef, 0.0) * 0.8578 / Tss2
    return fall, A > 1.1 * fall


def _friction_parts(w, sign, P):
    """Eq. 9 on the branch `sign` (+1: ω_m ≥ 0, −1: ω_m ≤ 0) at velocity w, in parts: the viscous
    torque, the Coulomb torque Tc, the Stribeck amplitude, the Stribeck term's factor at w (its
    lagged value where it is explicit), whether it is implicit, and the creep ramp (1 without it)."""
    pos = sign > 0
    Tv = jnp.where(pos, P["Tvp"], P["Tvn"])
    Tc = jnp.where(pos, P["Tcp"], P["Tcn"])
    coef = jnp.where(pos, P["Tssp1"], P["Tssn1"])
    _, implicit = _stribeck_fall(P["A"], P["Tss2"], coef)
    g = jnp.where(implicit, jnp.exp(-((w / P["Tss2"]) ** 2)), P["g_lag"])
    vc = P["vc"]
    ramp = jnp.where(vc > 0, jnp.minimum(jnp.abs(w) / jnp.where(vc > 0, vc, 1.0), 1.0), 1.0)
    return _viscous(w, Tv, P), Tc, coef, g, implicit, ramp


def _viscous(w, Tv, P):
    viscous = P["visc"] * Tv * w
    if "viscous_friction_law" in P["eff"].active:
        # Tv·ω·((ω² + ε²)/ωr²)^((κ−1)/2) increases with ω for every κ > 0: G stays monotone
        viscous = viscous * P["eff"].viscous_friction_law.factor(w)
    return viscous


def _branch_friction(w, sign, P):
    """Friction (N·m) on the branch `sign` (+1: ω_m ≥ 0, −1: ω_m ≤ 0) at velocity w."""
    return _friction_from_parts(_friction_parts(w, sign, P), sign, P)


def _friction_from_parts(parts, sign, P):
    """Eq. 9 (N·m) from `_friction_parts` on the branch `sign`."""
    viscous, Tc, coef, g, _, ramp = parts
    # under the creep ramp a negative breakaway (T_c + T_ss1 < 0, as HD2's negative direction) would
    # make the ramped term fall with speed and the step equation non-monotone: its magnitude is
    # clamped at zero there (friction never drives the motor)
    mag = Tc + coef * g
    mag = jnp.where(P["vc"] > 0, jnp.maximum(mag, 0.0), mag)
    return viscous + sign * ramp * mag


def _mean_gauss(a, b, erfc_a=None):
    """Mean of e^{−u²} over [a, b] (a, b ≥ 0, or both ≤ 0): the Taylor series about the midpoint where
    the interval is short (no cancellation, whatever its width relative to the values), the erfc
    difference otherwise. `erfc_a`: erfc(|a|) if at hand (the step's cost is mostly erfc)."""
    aa, ab = jnp.abs(a), jnp.abs(b)
    m, d = 0.5 * (aa + ab), 0.5 * jnp.abs(ab - aa)
    short = d * (1.0 + m) < 0.02
    m2, d2 = m * m, d * d
    series = jnp.exp(-m2) * (1.0 + (4.0 * m2 - 2.0) * d2 / 6.0 + (16.0 * m2 * m2 - 48.0 * m2 + 12.0) * d2 * d2 / 120.0)
    erfc = jax.scipy.special.erfc
    ea = erfc(aa) if erfc_a is None else erfc_a
    wide = 0.5 * jnp.sqrt(jnp.pi) * (ea - erfc(ab)) / jnp.where(short, 1.0, ab - aa)
    return jnp.where(short, series, wide)


def _side_mean_friction(a, b, sign, P, parts_b=None, erfc_a=None):
    """Mean friction (N·m) on the branch `sign` while ω_m runs linearly from a to b (both on that
    side, or 0): eq. 9's Coulomb term exactly, the viscous term by its two end values (exact for a
    linear law), the Stribeck term by the mean of e^{−(ω/Tss2)²} (`_mean_gauss`) where it is
    implicit (its lagged value otherwise). `parts_b`: `_friction_parts(b, sign, P)`, `erfc_a`:
    erfc(|a|/Tss2), if at hand."""
    viscous_b, Tc, coef, _, implicit, _ = _friction_parts(b, sign, P) if parts_b is None else parts_b
    Tv = jnp.where(sign > 0, P["Tvp"], P["Tvn"])
    g = jnp.where(implicit, _mean_gauss(a / P["Tss2"], b / P["Tss2"], erfc_a), P["g_lag"])
    return 0.5 * (_viscous(a, Tv, P) + viscous_b) + sign * (Tc + coef * g)


def _stage_friction(w, sign, P):
    """Friction (N·m) in the stage equation on the branch `sign` at end velocity w: eq. 9 at w
    (`_branch_friction`), except in a step through the Stribeck dip or a reversal of the motor.

    Friction jumps at zero velocity (by the two breakaway torques) and has its Stribeck dip of width
    Tss2 there. Taken at the stages' nodes it misses the jump's time and the dip whenever ω_m passes
    through zero within a step (the dip lasts Tss2/|a|, about 0.1 ms on the HD1 campaign): a
    first-order error in the motor's momentum at every reversal, which free motion keeps (measured
    2026-12-06 on the shipped HD1 records: 0.27 σ in motor velocity at 4 substeps, 0.10 σ at 16).

    In a step that the start's velocity ω_m0 and acceleration a_0 predict to come within 4·Tss2 of
    zero or to reverse (`near`), each stage takes the friction's mean M over the stage, with ω_m
    linear in time on each side of zero (`_side_mean_friction`): across a reversal, the old side up
    to t_c = −ω_m0/a_0 (a second-order estimate of the crossing: the end velocity alone would give
    the new side's deceleration, not the old side's), the new side after it. The trapezoidal stage
    on [0, γh] uses 2M_a − F_0, so its quadrature of friction is M_a·γh; the BDF2 stage, whose
    update weighs the first stage's increment by C1, uses (2 − γ)M_b − (1 − γ)(F_0 + F_γ)/2 (F_γ:
    the value the first stage used), so that the step's friction impulse is the integral's. For a
    law linear in ω, with ω linear in time, both forms give eq. 9's node values: switching between
    them changes a step at second order only. The value
    increases with w (a positive multiple of a mean of eq. 9 over an interval ending at w), so the
    stage equation stays monotone; its stick interval (`_solve_step`) is never empty. Off from rest
    (when a stuck motor breaks away inside the step is not known; a mean from the step start moved
    breakaway by half a stage) and under the creep ramp (friction continuous there)."""
    parts = _friction_parts(w, sign, P)
    plain = _friction_from_parts(parts, sign, P)
    ws = P["ws"]
    here = (ws != 0) & ((ws > 0) != (sign > 0))  # this stage reverses the motor
    # the new side's mean: over [0, w] after a reversal, over [ω_s, w] otherwise (one Gaussian mean)
    mean_new = _side_mean_friction(jnp.where(here, 0.0, ws), w, sign, P, parts, jnp.where(here, 1.0, P["erfc_ws"]))
    th = P["theta"]  # the stage's fraction before the reversal; P["m_old"]: the old side's mean
    mean = jnp.where(here, th * P["m_old"] + (1.0 - th) * mean_new, mean_new)
    return _stage_value(mean, plain, P)


def _stage_value(mean, plain, P):
    """The stage's friction from its mean (`_stage_friction`), or eq. 9's value `plain` where off."""
    stage1 = 2.0 * mean - P["F0"]
    stage2 = (2.0 - _GAMMA) * mean - (1.0 - _GAMMA) * 0.5 * (P["F0"] + P["Fa"])
    return jnp.where(_stage_friction_on(P), jnp.where(P["xk"] == 0, stage1, stage2), plain)


def _stage_friction_at_rest(sign, P):
    """`_stage_friction` at w = 0 on the branch `sign` (the stick test's bounds), without the
    Gaussian means: the mean there is the old side's (precomputed) or eq. 9's breakaway torque."""
    plain = _branch_friction(jnp.zeros_like(P["ws"]), sign, P)
    ws = P["ws"]
    here = (ws != 0) & ((ws > 0) != (sign > 0))
    th = P["theta"]
    mean = jnp.where(here, th * P["m_old"] + (1.0 - th) * plain, jnp.where(ws == 0, plain, P["m_old"]))
    return _stage_value(mean, plain, P)


def _stage_friction_on(P):
    """Whether the stage takes the mean-based friction of `_stage_friction`: a step predicted to run
    through the Stribeck dip or to reverse (`near`), not from rest, not under the creep ramp; the
    same on both branches, so that the stick interval is never empty."""
    return (P["vc"] <= 0) & (P["w0"] != 0) & (P["near"] > 0)


def _G_nofriction(s, P):
    *_, Tbar, _, wm1 = _end_state(s, P)
    return P["A"] * (wm1 - P["wm_hist"]) + Tbar / P["N"] - P["drive"]


def _H(s, P):
    """ω_m,n+1 / N as a function of s (its root s* is where the motor stands still)."""
    *_, wm1 = _end_state(s, P)
    return wm1 / P["N"]


def _G_branch(s, P):
    *_, wm1 = _end_state(s, P)
    return _G_nofriction(s, P) + _branch_friction(wm1, P["sign"], P)


def _G_branch_mean(s, P):
    *_, wm1 = _end_state(s, P)
    return _G_nofriction(s, P) + _stage_friction(wm1, P["sign"], P)


def _newton(fn, lo, hi, x0, P, iterations):
    """Root of the increasing scalar function fn(·, P) in [lo, hi]: Newton's method, a bisection
    step whenever Newton would leave the bracket; at most `iterations` iterations, fewer once the
    iterate stops moving (a step below `_X_RTOL` of the bracket's scale, or g = 0). Under `vmap`
    the loop runs until every lane has stopped: every lane pays the same, at most `iterations`."""
    x_scale = jnp.maximum(jnp.abs(lo), jnp.abs(hi))

    def body(c):
        k, x, lo, hi, _ = c
        g, dg = jax.jvp(lambda s: fn(s, P), (x,), (jnp.ones_like(x),))
        lo = jnp.where(g < 0, x, lo)
        hi = jnp.where(g > 0, x, hi)
        xn = x - g / dg
        ok = (xn >= lo) & (xn <= hi) & jnp.isfinite(xn)
        x_new = jnp.where(g == 0, x, jnp.where(ok, xn, 0.5 * (lo + hi)))
        moving = jnp.abs(x_new - x) > _X_RTOL * x_scale
        return k + 1, x_new, lo, hi, moving

    def cond(c):
        k, *_, moving = c
        return (k < iterations) & moving

    x0 = jnp.clip(x0, lo, hi)
    _, x, _, _, _ = jax.lax.while_loop(cond, body, (0, x0, lo, hi, jnp.ones_like(x0, dtype=bool)))
    return x


#: Newton stops once its step is below this fraction of the bracket's scale (Newton converges
#: quadratically: the next step would be far below round-off).
_X_RTOL = 1e-13


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 5))
def _root(fn, lo, hi, x0, P, iterations):
    return _newton(fn, lo, hi, x0, P, iterations)


@_root.defjvp
def _root_jvp(fn, iterations, primals, tangents):
    """Implicit function theorem at the converged root: ds = −(∂G/∂P·dP) / (∂G/∂s)."""
    lo, hi, x0, P = primals
    dP = tangents[3]
    x = _root(fn, lo, hi, x0, P, iterations)
    _, g_p = jax.jvp(lambda P_: fn(x, P_), (P,), (dP,))
    _, g_s = jax.jvp(lambda s: fn(s, P), (x,), (jnp.ones_like(x),))
    # G_s = 0 only at a stuck motor with the output locked, where s* = 0 whatever the parameters
    safe = g_s != 0
    return x, jnp.where(safe, -g_p / jnp.where(safe, g_s, 1.0), 0.0)


def _solve_step(P, s_guess, iterations, reversal_quadrature):
    """One implicit stage: returns (s, end-state tuple of `_end_state`, stuck flag, converged flag,
    the friction the stage used less eq. 9's at its end). `reversal_quadrature` (static):
    friction by `_stage_friction`, else eq. 9 at the stage end."""
    sg = jax.lax.stop_gradient
    # s*: the motor stands still at the end of the step. H(s) ≥ r_true(s) + H(0) − r_true(0) on
    # s ≥ 0 (and ≤ on s ≤ 0), since the torque term of ω_o is increasing: bracket [0, b] or [b, 0]
    h0 = sg(_H(jnp.zeros_like(s_guess), P))
    b = sg(_signed_pow(-h0, P["alpha"]))
    s_star = _root(_H, jnp.minimum(0.0, b), jnp.maximum(0.0, b), sg(b), P, iterations)
    # stick test: the friction that would hold the motor must lie inside the breakaway interval, as the
    # stage takes friction (`_stage_friction`: eq. 9's at the stage end, or the mean-based value of a
    # step through the Stribeck dip or a reversal, whose interval is never empty)
    g_star = _G_nofriction(s_star, P)
    zero = jnp.zeros_like(s_star)
    rest = _stage_friction_at_rest if reversal_quadrature else (lambda sign, P: _branch_friction(zero, sign, P))
    f_pos = rest(1.0, P)  # eq. 9 at rest, positive direction
    f_neg = rest(-1.0, P)  # (negative number)
    b_neg, b_pos = _static_bounds(f_neg, f_pos, P)  # the breakaway torques (`breakaway_friction`)
    go_pos = sg(g_star + b_pos < 0)
    go_neg = sg(g_star + b_neg > 0)
    sign = jnp.where(go_pos, 1.0, jnp.where(go_neg, -1.0, 0.0))
    corrected = _stage_friction_on(P) if reversal_quadrature else jnp.zeros((), dtype=bool)
    Pb = dict(P, sign=sign)
    # branch root: G(s) ≥ A(ω_m(s) − ω_m0) + [G − A(ω_m − ω_m0)](s*) on the branch side, and
    # ω_m(s) ≥ N(r_true(s) − ė + ω_o(s*)): a bracket from the inertia term alone
    f_branch0 = jnp.where(sign > 0, f_pos, f_neg)
    # with an implicit falling Stribeck term, friction drops at most L per rad/s: A − L > 0 bounds
    fall, implicit = _stribeck_fall(P["A"], P["Tss2"], jnp.where(sign > 0, P["Tssp1"], P["Tssn1"]))
    # (the mean-based value multiplies eq. 9's slope, or its mean's, by at most 2)
    L = jnp.where(implicit, fall, 0.0) * jnp.where(corrected, 2.0, 1.0)
    w_b = sg(-(g_star + f_branch0) / (P["A"] - L))
    *_, wo_star, _ = _end_state(s_star, P)
    s_b = sg(_signed_pow(w_b / P["N"] + P["edot1"] - sg(wo_star), P["alpha"]))
    s_star_c = sg(s_star)
    lo = jnp.where(sign > 0, s_star_c, jnp.where(sign < 0, s_b, s_star_c))
    hi = jnp.where(sign > 0, s_b, s_star_c)
    lo, hi = jnp.minimum(lo, hi), jnp.maximum(lo, hi)
    s_slip = _root(_G_branch_mean if reversal_quadrature else _G_branch, lo, hi, sg(s_guess), Pb, iterations)
    stuck = sign == 0
    s = jnp.where(stuck, s_star, s_slip)
    out = _end_state(s, P)
    # residual of the solved equation (stuck: A·ω_m; sliding: G), relative to the largest torque in it
    *_, Tbar, _, wm1 = out
    f_used = _stage_friction(wm1, sign, Pb) if reversal_quadrature else _branch_friction(wm1, sign, Pb)
    g_slip = P["A"] * (wm1 - P["wm_hist"]) + Tbar / P["N"] - P["drive"] + f_used
    resid = jnp.where(stuck, P["A"] * wm1, g_slip)
    scale = P["A"] * jnp.abs(P["wm_hist"]) + jnp.abs(P["drive"]) + jnp.abs(Tbar) / P["N"] + P["Tcp"] + P["Tcn"] + 1e-12
    converged = jnp.abs(resid) <= ROOT_RTOL * scale
    if not reversal_quadrature:
        return s, out, stuck, converged, jnp.zeros_like(resid)
    # eq. 9's own friction at the stage end (the next step's F_0) differs from the one the stage used in
    # a step through the dip or a reversal; a stuck motor's is the torque that holds it at rest, inside
    # the breakaway interval (not the stage's mean, which includes the impulse that stopped it)
    net = P["drive"] - Tbar / P["N"]
    hold = jnp.clip(net, *_static_bounds(_branch_friction(zero, -1.0, P), _branch_friction(zero, 1.0, P), P))
    corr = jnp.where(stuck, net - P["A"] * (wm1 - P["wm_hist"]) - hold, f_used - _branch_friction(wm1, sign, Pb))
    return s, out, stuck, converged, corr


def _tangent_dependence(*trees):
    """Exactly zero whatever the values (inf and NaN included), with a forward-mode tangent that
    depends on every inexact array of `trees`.

    Added to the scan's initial state. The measured start state (q, ω_m, θ_o, ω_o) and the Dahl
    state have no tangent, so JAX's scan JVP first traces the step with those carries' tangents
    zero, finds them nonzero after one step and traces it again; likewise for the batching rule.
    With this term every carry has a tangent (and a batch axis) from the start and the step is
    traced once: a 9-tangent Jacobian of one shipped HD2 record traced in 1.2 s instead of 2.2 s
    (`substeps=4`), the same arithmetic."""
    total = sum((jnp.sum(x.astype(float)) for x in jax.tree.leaves(eqx.filter(trees, eqx.is_inexact_array))), jnp.zeros(()))
    return jnp.where(jnp.zeros((), dtype=bool), total, 0.0)


_GAMMA = 2.0 - 2.0**0.5  # TR-BDF2's stage point; makes both stages share one Jacobian scale
_C1 = 1.0 / (_GAMMA * (2.0 - _GAMMA))  # BDF2 stage: y1 = C1·y_γ − C0·y0 + C2·h·f(y1)
_C0 = (1.0 - _GAMMA) ** 2 / (_GAMMA * (2.0 - _GAMMA))
_C2 = (1.0 - _GAMMA) / (2.0 - _GAMMA)


class StepInputs(NamedTuple):
    """What a step reads from the record at its three nodes t0, t0 + γh, t0 + h (last axis; leading
    axes as the times given to `PlantSteps.inputs_at`): the motor torque Km·i(t − τd) (N·m) and, where
    a periodic term acts at the measured angle, the record's (output, motor) angles (rad; None
    otherwise). Read for every step at once, before the scan: inside it each read is an
    interpolation in the record (an index and gathers) that the step repeats in every pass of
    every stage. Measured 2026-12-07 on a 16 × 2.5 s independent-bench diagnosis (two host
    devices): its 24-tangent Jacobian 6.8–7.4 s → 2.2–2.4 s, its base-model simulation 0.21 → 0.175 s;
    the HD2 fit command 18.5–19.0 → 14.8–15.7 s warm, the same estimates."""

    electric: Any
    angles: Any = None


class PlantSteps(NamedTuple):
    """The stepper's functions for one plant with the current bound (`plant_steps(...)(current)`):
    `start(y0, t0)` the step state at the sample `t0` from the plant state `y0` = (q, ω_m, θ_o,
    ω_o); `step(state, t0)` one TR-BDF2 step of length h from `t0`, returning the new state and
    whether its roots converged; `with_friction(state, t0)` the state with its friction taken again
    at t0 (after a jump of the drive); `theta_m(q, θ_o, t[, angles])` the wave-generator angle (rad);
    `torsion_of(q, θ_m)` the true torsion (rad); `inputs_at(t)` the `StepInputs` at the node times
    `t` (..., 3) for `step(state, t0, inputs)`. The step state is (q, ω_m, θ_o, ω_o, z, s, T, F):
    kinematic torsion, velocities and output angle, the Dahl state, the damping unknown, the
    transmitted torque (N·m) and the friction (N·m)."""

    start: Callable
    step: Callable
    with_friction: Callable
    theta_m: Callable
    torsion_of: Callable
    inputs_at: Callable


def plant_steps(p, drive, free, start_time, geometry, effects: Effects, vc, h, solver: VelocityImplicit):
    """The TR-BDF2 stages of the module docstring for one plant (`free`: 1.0 free output, 0.0
    locked; `start_time`: the record's session time, s, for `thermal_drift`; step `h`, s).
    Returns `bind(current) -> PlantSteps`, `current` anything with `evaluate(t)` (A): the
    recorded current of a record (`implicit_trajectory`) or the held current of one sample
    interval of a sampled loop (`hdjax._control.closed_loop`).

    It stays long (about 150 lines) on purpose: the nested `stage`, `step` and `start` closures
    form one `lax.scan` body over the plant's constants (N, h, geometry, current, effects);
    lifting them to module level would thread a dozen arguments through every call."""
    N = drive.gear_ratio
    q_g, tho_g, thm_g, measured_out = geometry
    # the steps read the measured angle only where a periodic term acts at it; the reported angle is
    # the measured one either way (as the adaptive plant's vector field and outputs)
    measured = measured_out if set(effects.active) & set(PERIODIC) else None
    f = free
    eff = effects
    Km = drive.torque_constant
    delay = effects.input_delay.delay if "input_delay" in effects.active else 0.0
    ke = "kinematic_error" in effects.active

    def theta_m(q, tho, t, angles=measured, node=None):
        """θm (rad) at time t (s): the plant's own angle, or the record's where `angles` (a
        `MeasuredAngle`, `Simulator.measured_angle`) holds it, as in the adaptive plant. `node`:
        the record's (output, motor) angles at t, read before the scan (`StepInputs`), or None."""
        if angles is None:
            return thm_g + N * ((q - q_g) + (tho - tho_g))
        out_reading, motor_reading = (None, None) if node is None else (node[0], node[1])
        thm = thm_g + N * ((q - q_g) + (angles.output_angle(t, tho, out_reading) - tho_g))
        return angles.motor_angle(t, thm, motor_reading)

    def predicted_angle(t1, tau, q0, tho0, wo0, thm0, wm0, node=None):
        """θm at the stage end t1 = t0 + tau, predicted at constant speed (or read from the record)."""
        if measured is None:
            return thm0 + tau * wm0
        return theta_m(q0, tho0 + tau * wo0, t1, node=node)

    def torsion_of(q, thm):
        return q + (eff.periodic("kinematic_error", thm) if ke else 0.0)

    def viscous_factor(t):
        if "thermal_drift" in eff.active:
            return eff.thermal_drift.factor(start_time + t)
        return 1.0

    # the effects whose explicit terms read the state predicted at the stage end (`stage_parameters`);
    # without them only a falling Stribeck term too steep to be implicit does, which needs an amplitude > 0
    explicit_state_terms = bool(
        {"cogging", "kinematic_error", "position_dependent_friction", "load_dependent_friction"} & set(eff.active))
    stribeck_may_lag = (p.Tssp1 > 0) | (p.Tssn1 > 0)

    def bind(current) -> PlantSteps:
        def electric(t, reading=None):
            """Km·i(t − τd) (N·m), or `reading` where it was taken before the scan (`StepInputs`)."""
            return Km * current.evaluate(t - delay) if reading is None else reading

        def stage_parameters(t1, hist, thm1, wm1, T1, tor0, z0, crossing=None, electric_t1=None):
            """The stage equation's data: `hist` = (A, ω_m, q, ω_o history, bh, fh/J); the explicit
            terms (position- and load-dependent) evaluated at the predicted stage end (θ_m1, ω_m1, T1);
            `crossing` = (ω_m at the step start, ω_m at the stage start, stage k, the stage's fraction
            before a reversal, F_0, the first stage's F, whether the step is `near` zero velocity) for
            `_stage_friction` (None: off)."""
            A, wm_hist, q_hist, wo_hist, bh, fh_J = hist
            pdf = 1.0 + eff.periodic("position_dependent_friction", thm1)
            load = (jnp.abs(eff.load_dependent_friction.mu) * jnp.sqrt(T1 * T1 + 1e-6) / N
                    if "load_dependent_friction" in eff.active else 0.0)
            P: dict[str, Any] = dict(
                alpha=p.alpha, K1=p.K1, Tst=p.Tst, N=N, A=A, bh=bh, fh_J=fh_J,
                wm_hist=wm_hist, wo_hist=wo_hist, q_hist=q_hist, tor0=tor0, z0=z0,
                Tvp=p.Tvp, Tvn=p.Tvn, Tssp1=p.Tssp1, Tssn1=p.Tssn1, Tss2=p.Tss2, vc=vc,
                visc=viscous_factor(t1),
                Tcp=p.Tsp * pdf + load,
                Tcn=p.Tsn * pdf + load,
                g_lag=jnp.exp(-((wm1 / p.Tss2) ** 2)),
                e1=eff.periodic("kinematic_error", thm1) if ke else 0.0,
                edot1=eff.periodic_rate("kinematic_error", thm1, wm1) if ke else 0.0,
                drive=electric(t1, electric_t1) + eff.periodic("cogging", thm1),
            )
            if crossing is not None:
                w0, ws, xk, theta, F0, Fa, near = crossing
                P.update(w0=w0, ws=ws, xk=xk, theta=theta, F0=F0, Fa=Fa, near=near)
            P = {k: jnp.asarray(v, dtype=float) for k, v in P.items()}
            P["eff"] = eff
            # friction's mean over the stage's part before a reversal, from ω_m at its start to 0 on
            # that side (`_stage_friction`); the same for both branches, so taken once per stage
            if crossing is None:
                return P
            side = jnp.where(P["ws"] > 0, 1.0, -1.0)
            P["erfc_ws"] = jax.scipy.special.erfc(jnp.abs(P["ws"]) / P["Tss2"])
            P["m_old"] = _side_mean_friction(P["ws"], jnp.zeros_like(P["ws"]), side, P, erfc_a=P["erfc_ws"])
            return P

        def stage(t1, hist, tho_hist, thm_pred, start, s_guess, crossing, end_node=(None, None)):
            """Solve one stage ending at t1; `start` = (θ_m, ω_m, T, torsion, z) at the stage start, from
            which the explicit terms are predicted (θ_m at the stage end: `thm_pred`); `crossing` =
            (ω_m at the step start, stage k, the stage's fraction before a reversal, F_0, the first
            stage's F, `near`) for `_stage_friction`, None without `reversal_quadrature`; `end_node` =
            (Km·i, the record's angles) at t1 where read before the scan (`StepInputs`), else Nones.

            The corrector's second pass is the same `_solve_step` as the first, with the explicit terms
            at the first pass's stage end: both passes are one traced pass in a two-iteration
            `lax.scan`, so the stage's solve is compiled once."""
            thm0, wm0, T0, tor0, z0 = start

            def one_pass(carry):
                """Solve the stage with the explicit terms at `carry`'s (θ_m, ω_m, T); the next pass's."""
                s, _, _, conv, thm_e, wm_e, T_e, _, _ = carry
                P = stage_parameters(t1, hist, thm_e, wm_e, T_e, tor0, z0,
                                     None if crossing is None else (crossing[0], wm0, *crossing[1:]), end_node[0])
                s, out, stuck, conv_k, corr = _solve_step(P, s, solver.iterations, solver.reversal_quadrature)
                r1, q1, tor1, Tk1, z1, T1, wo1, wm1 = out
                thm1 = theta_m(q1, tho_hist + hist[4] * wo1, t1, node=end_node[1])
                return s, out, stuck, conv & conv_k, thm1, wm1, 0.5 * (T0 + T1), P["drive"], corr

            # placeholders for the first pass's outputs, with the tangents and batch axes of the state
            # (so that the scan is traced once, see `_tangent_dependence`)
            zero = 0.0 * (s_guess + T0 + wm0 + thm_pred)
            init = (s_guess, (zero,) * 8, jnp.zeros(jnp.shape(zero), dtype=bool), jnp.ones(jnp.shape(zero), dtype=bool),
                    thm_pred, wm0, T0, zero, zero)
            if not solver.corrector:
                carry = one_pass(init)
            else:
                # Without a position- or load-dependent effect only a falling Stribeck term too steep to
                # be implicit reads the predicted state; with both amplitudes ≤ 0 (friction rising with
                # speed, as HD1's and HD2's) it is always implicit and the second pass would solve the
                # same equation again: skipped. The predicate depends on the parameters alone, so under
                # the experiment `vmap` it stays a branch.
                needed = jnp.asarray(True) if explicit_state_terms else stribeck_may_lag

                def body(c, k):
                    return jax.lax.cond((k == 0) | needed, one_pass, lambda c: c, c), None

                carry, _ = jax.lax.scan(body, init, jnp.arange(2))
            s, out, stuck, conv, *_, drive_t1, corr = carry
            r1, q1, tor1, Tk1, z1, T1, wo1, wm1 = out
            wm1 = jnp.where(stuck, 0.0, wm1)
            tho1 = tho_hist + hist[4] * wo1
            A, wm_hist = hist[0], hist[1]
            # friction, sliding or holding: the one the stage used after the first stage (the second's
            # data), eq. 9's own at the step's end (the next step's F_0; `_stage_friction`)
            F1 = drive_t1 - T1 / N - A * (wm1 - wm_hist)
            if crossing is not None:
                F1 = F1 - jnp.where(crossing[1] == 0, 0.0, corr)
            return (q1, wm1, tho1, wo1, z1, s, T1, F1), tor1, conv

        def step(state, t0, inputs=None):
            """One TR-BDF2 step from t0 to t0 + h: a trapezoidal stage to t0 + γh, then BDF2 to t0 + h.

            Both stages are one `stage` call in a two-iteration `lax.scan` (stage k = 0, 1; their
            coefficients selected by k): the stage, the step's whole cost, is traced and compiled once
            instead of twice. `inputs`: the current and the record's angles at the step's three
            nodes, read before the scan (`PlantSteps.inputs_at`), or None to read them here."""
            q0, wm0, tho0, wo0, z0, s0, T0, F0 = state

            def node(j):
                """(Km·i, the record's angles or None) at node j (0: t0, 1: t0 + γh, 2: t0 + h), or Nones."""
                if inputs is None:
                    return None, None
                return inputs.electric[j], (None if inputs.angles is None else inputs.angles[j])

            electric0, angles0 = node(0)
            thm0 = theta_m(q0, tho0, t0, node=angles0)
            tor0 = torsion_of(q0, thm0)
            drive0 = electric(t0, electric0) + eff.periodic("cogging", thm0)

            def crossing(k, tp, t1, Fp):
                """The data of `_stage_friction` for stage k on [tp, t1] (None without
                `reversal_quadrature`): when ω_m would reach zero at the step start's acceleration, and
                whether the step runs through the Stribeck dip (|ω_m| within 4 Tss2) or reverses by
                that prediction."""
                if not solver.reversal_quadrature:
                    return None
                a0 = (drive0 - T0 / N - F0) / p.Jeff
                towards = wm0 * a0 < 0
                tc = jnp.where(towards, -wm0 / jnp.where(towards, a0, 1.0), 2.0 * h)
                w_pred = wm0 + a0 * h
                near = (jnp.minimum(jnp.abs(wm0), jnp.abs(w_pred)) < 4.0 * p.Tss2) | (wm0 * w_pred < 0)
                return wm0, k, jnp.clip((tc - (tp - t0)) / (t1 - tp), 0.0, 1.0), F0, Fp, near

            def one_stage(prev, k):
                """Stage k from the end of the one before (k = 0: the step start; k = 1: t0 + γh)."""
                (qp, wmp, thop, wop, zp, sp, Tp, Fp), torp = prev
                first = k == 0
                tp = t0 + jnp.where(first, 0.0, _GAMMA * h)
                t1 = t0 + jnp.where(first, _GAMMA * h, h)
                # trapezoidal stage: the start's forces enter through the histories; BDF2 stage on
                # (t0, t0 + γh, t0 + h)
                bh = jnp.where(first, 0.5 * _GAMMA * h, _C2 * h)
                A = p.Jeff / bh
                hist = (
                    A,
                    jnp.where(first, wm0 + (drive0 - T0 / N - F0) / A, _C1 * wmp - _C0 * wm0),
                    jnp.where(first, q0 + bh * (wm0 / N - wo0), _C1 * qp - _C0 * q0),
                    jnp.where(first, wo0 + bh * f * T0 / drive.load_inertia, _C1 * wop - _C0 * wo0),
                    bh,
                    bh * f / drive.load_inertia,
                )
                tho_hist = jnp.where(first, tho0 + bh * wo0, _C1 * thop - _C0 * tho0)
                start_node, end_node = node(k), node(k + 1)
                thmp = theta_m(qp, thop, tp, node=start_node[1])
                thm_pred = predicted_angle(t1, t1 - tp, qp, thop, wop, thmp, wmp, node=end_node[1])
                out, tor1, conv = stage(t1, hist, tho_hist, thm_pred, (thmp, wmp, Tp, torp, zp), sp,
                                        crossing(k, tp, t1, Fp), end_node)
                return (out, tor1), conv

            (out, _), conv = jax.lax.scan(one_stage, (state, tor0), jnp.arange(2))
            return out, jnp.all(conv)

        def with_friction(state, t0):
            """`state` with its friction F taken at t0 for the bound current: eq. 9 while sliding; at
            rest the holding torque (zero acceleration), within the breakaway interval. Where the
            drive jumps at t0 (a sampled loop's held current) this is its right limit, the friction
            a stuck motor meets as the new current acts."""
            q0, wm0, tho0, wo0, z0, s0, T0, _ = state
            thm0 = theta_m(q0, tho0, t0)
            P0 = stage_parameters(t0, (1.0, wm0, q0, wo0, 0.0, 0.0), thm0, wm0, T0, 0.0, z0)
            hold = P0["drive"] - T0 / N
            F0 = jnp.where(
                wm0 > 0, _branch_friction(wm0, 1.0, P0),
                jnp.where(wm0 < 0, _branch_friction(wm0, -1.0, P0),
                          jnp.clip(hold, *_static_bounds(_branch_friction(0.0 * wm0, -1.0, P0),
                                                         _branch_friction(0.0 * wm0, 1.0, P0), P0))),
            )
            return (q0, wm0, tho0, wo0, z0, s0, T0, F0)

        def start(y0, t0):
            """The step state at the sample t0 from the plant state y0 = (q, ω_m, θ_o, ω_o)."""
            q0, wm0, tho0, wo0 = y0[:4]
            z0 = jnp.zeros_like(q0)
            thm0 = theta_m(q0, tho0, t0)
            rate0 = wm0 / N - wo0 + (eff.periodic_rate("kinematic_error", thm0, wm0) if ke else 0.0)
            s0 = _signed_pow(rate0, p.alpha)
            T0 = stiffness_torque(p.K1, torsion_of(q0, thm0), eff) + p.Tst * s0
            return with_friction((q0, wm0, tho0, wo0, z0, s0, T0, 0.0 * T0), t0)

        def inputs_at(t):
            """`StepInputs` at the node times `t` (s; any shape): what `step` would read there."""
            return StepInputs(electric=electric(t), angles=None if measured is None else measured.readings(t))

        return PlantSteps(start=start, step=step, with_friction=with_friction, theta_m=theta_m, torsion_of=torsion_of,
                          inputs_at=inputs_at)

    return bind


def implicit_trajectory(
    p,
    drive,
    exp,
    y0,
    geometry,
    current,
    effects: Effects,
    vc,
    dt,
    solver: VelocityImplicit,
):
    """Step one experiment through its sample times with TR-BDF2 stages (`plant_steps`, see the
    module docstring). Returns per-sample arrays (q, ω_m, θ_o, ω_o, torque T, torsion Δθ, θ_m),
    whether every step's root converged, and the number of steps."""
    m = solver.substeps
    h = dt / m
    steps = plant_steps(p, drive, exp.free, exp.start_time, geometry, effects, vc, h, solver)(current)

    substep = jnp.arange(m, dtype=float)

    def sample_interval(state, xs):
        t0, inputs = xs

        def body(st, k_inputs):
            k, inp = k_inputs
            return steps.step(st, t0 + k * h, inp)

        state, conv = jax.lax.scan(body, state, (substep, inputs))
        return state, (state, jnp.all(conv))

    state0 = steps.start(y0, exp.time[0])
    zero = _tangent_dependence(p, effects)
    state0 = tuple(jnp.asarray(x, dtype=float) + zero for x in state0)
    n = exp.time.shape[0]
    t_starts = exp.time[0] + dt * jnp.arange(n - 1, dtype=float)
    # every step's node times, with the step's own arithmetic (t0 + k·h, then + γh or + h)
    t_sub = t_starts[:, None] + substep * h
    inputs = steps.inputs_at(jnp.stack([t_sub, t_sub + _GAMMA * h, t_sub + h], axis=-1))
    _, (states, oks) = jax.lax.scan(sample_interval, state0, (t_starts, inputs))
    states = jax.tree.map(lambda a, b: jnp.concatenate([jnp.asarray(a)[None], b]), state0, states)
    q, wm, tho, wo, z, s, T, _ = states
    thm = steps.theta_m(q, tho, exp.time, geometry[3])
    oks = jnp.concatenate([jnp.array([True]), oks])
    return (q, wm, tho, wo, T, steps.torsion_of(q, thm), thm), oks, (n - 1) * m
