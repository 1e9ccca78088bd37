r"""An independent virtual test bench: datasets that hdjax's identification and diagnosis are judged on.

Datasets made by a model's own simulator only test that the model can fit itself (the "inverse
crime"). This module writes the harmonic-drive physics (Taghirad & Bélanger, SPEC §1) again, from
scratch, with numpy and scipy (its time loop compiled by numba, `hdjax._testbench.fine_steps`) — it
imports nothing else from hdjax and does not use JAX — and adds
what a real bench does and the paper's model does not. Only the station numbers (Table I, rated
torques, sensor classes) were taken from `hdjax._testbench.rig`; the profiles are generated here.

What differs from hdjax's plant (`hdjax._plant`):

- *Integrator.* hdjax: an adaptive implicit ODE solver on smoothed terms. Here: a fixed step
  (20 kHz) at the velocity level; the flexspline torque (spring and power-law damping), viscous
  friction and positions by the trapezoidal rule, the implicit half solved in closed form (a
  quadratic in √|Δθ'| for α = ½); Coulomb/Stribeck part explicit; velocity reversals and
  breakaways located inside the step.
- *Low-speed friction.* hdjax: tanh(ω/s) regularisation of eq. 9. Here: exact sticking — ωm is
  exactly 0 while the holding torque stays inside the breakaway band; breakaway = 1.1–1.3 ×
  max(Ts, Ts + Tss1) per direction (drawn; both Table I drives have Tss1 < 0, so the eq. 9
  zero-speed limit lies *below* Ts and a real static excess needs the max); sliding on the eq. 9
  curve with its non-viscous part clipped at 0 (friction never drives). Or LuGre
  (`low_speed="lugre"`).
- *Input.* hdjax: the recorded current, interpolated. Here: a PI current loop (20 kHz, 1.5 kHz
  bandwidth) on an R–L winding with back-EMF tracks the commanded profile; the *actual* current
  drives the motor and is sampled at 1 kHz with PWM ripple, offset and noise.
- *Sensors.* hdjax: white noise. Here: strain-gauge and tachometer first-order low-passes,
  tachometer ripple (order 11 per motor turn), 2¹⁶-count encoder (floor), DC offsets, time-stamp
  jitter (samples taken at the jittered instants).
- *Drive.* Each parameter drawn log-normally around Table I (HD1 / HD2) from the seed.

Step-halving check (20 → 40 kHz, 16 records × 2.5 s, HD1): the recorded torque changes by 0.009 σ
RMS (0.4 σ at the worst single sample, at slip events) and the motor velocity by 0.02 σ RMS
(0.13 σ worst), σ the sensor noise.

Effects of SPEC §4 can be hidden by name (`EFFECTS`, units in `EFFECT_UNITS`); each one's size is
given as an `snr`: the RMS, over the records where it acts (change above 10 % of the largest
record's), of the change it makes in the most affected recorded channel (torque, motor_velocity,
output_position; `channels` restricts the choice), over that channel's noise σ (the encoder's
step/√12 for the output angle). It is calibrated with the effect alone, by simulating with and
without it (secant steps, to 2 %); the truth records the snr, the physical magnitude and the snr
per channel. Note that the output angle integrates velocity errors and its σ is tiny, so for
friction-like effects it is usually the most affected channel and the calibrated magnitudes are
small; pass `channels=["torque", "motor_velocity"]` for effects sized on the dynamic channels.

The effects follow SPEC §4's "model extension" column: periodic ones are Σ a·w_k·sin(k·θm + φ_k)
in the wave-generator angle θm (orders = cycles per wave-generator turn); the kinematic error adds
to the torsion (the motor still sees T/N); thermal drift scales the viscous friction by
1 + β·exp(−(start_time + t)/τ); input delay makes the motor torque Km·i_actual(t − delay);
rate-independent hysteresis adds a Dahl torque Th·z to the flexspline torque (the power-law
damping stays); presliding friction lets a stuck motor ride on a bristle spring (elasto-plastic,
displacement `magnitude` at breakaway) or, with `low_speed="lugre"`, widens the LuGre bristle.

Main entry points: `make_dataset(out_dir, ...)` writes a SPEC §2 folder with `truth.yaml`;
`simulate_dataset(...)` returns the same records in memory. Units are SI throughout.
"""

from __future__ import annotations

import dataclasses
import io
import math
import os
import pathlib
import tempfile
from typing import Any

import numpy as np
import yaml
from scipy import signal

from . import fine_steps

__all__ = ["Bench", "Deviations", "EFFECTS", "STATIONS", "make_dataset", "pi_law", "simulate_dataset"]

TWO_PI = 2.0 * math.pi
DEG = 180.0 / math.pi
PARAMETER_KEYS = ("alpha", "K1", "Tst", "Jeff", "Tvp", "Tvn", "Tsp", "Tsn", "Tssp1", "Tssn1", "Tss2")
PERIODIC = ("kinematic_error", "torque_sensor_ripple", "cogging", "position_dependent_friction")
EFFECTS = PERIODIC + (
    "nonlinear_stiffness", "lost_motion", "load_dependent_friction", "thermal_drift", "input_delay",
    "rate_independent_hysteresis", "presliding_friction",
)  # fmt: skip
EFFECT_UNITS = {
    "kinematic_error": "rad (a_k of dtheta += a_k sin(k theta_m + phi_k))",
    "torque_sensor_ripple": "N*m (b_k of measured T += b_k sin(k theta_m + phi_k))",
    "cogging": "N*m (c_k of Km*i += c_k sin(k theta_m + phi_k))",
    "position_dependent_friction": "- (eps_k of Coulomb *= 1 + eps_k sin(k theta_m + phi_k))",
    "nonlinear_stiffness": "N*m/rad^3 (K3 of T_k = K1 x + K3 x^3)",
    "lost_motion": "rad (dead-band half-width of the torsion)",
    "load_dependent_friction": "- (mu of Coulomb += mu |T| / N)",
    "thermal_drift": "- (beta of viscous *= 1 + beta exp(-t_session / tau))",
    "input_delay": "s (motor torque = Km i_actual(t - delay))",
    "rate_independent_hysteresis": "N*m (Th of T += Th z, Dahl z' = (dtheta'/sigma)(1 - z sign dtheta'))",
    "presliding_friction": "rad (presliding displacement of a LuGre bristle at breakaway, motor side)",
}
DEFAULT_ORDERS = {
    "kinematic_error": [2], "torque_sensor_ripple": [2], "cogging": [6], "position_dependent_friction": [1],
}  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Station:
    """Nominal station (Table I of the paper, SI). `params` in SPEC keys; `R` (Ω), `L` (H) of the
    motor winding; `peak_current` (A) of the amplifier; `rated_torque` (N·m) of the gear."""

    name: str
    params: dict
    gear_ratio: float
    torque_constant: float
    load_inertia: float
    rated_torque: float
    peak_current: float
    R: float
    L: float


STATIONS = {
    "hd1": Station("HD1", dict(alpha=0.5, K1=6340.0, Tst=57.2, Jeff=1.0e-4, Tvp=3.7e-4, Tvn=3.5e-4, Tsp=4.6e-2,
                               Tsn=4.4e-2, Tssp1=-0.0076, Tssn1=-0.0203, Tss2=0.1),
                   100.0, 0.0543, 0.2, 40.0, 6.0, 1.2, 2.0e-3),
    "hd2": Station("HD2", dict(alpha=0.5, K1=104.2 * DEG, Tst=7.96 * DEG**0.5, Jeff=1.0e-4, Tvp=1.8e-3, Tvn=2.1e-3,
                               Tsp=7.5e-2, Tsn=3.3e-2, Tssp1=-0.0487, Tssn1=-0.0450, Tss2=0.1),
                   160.0, 0.1815, 0.5, 178.0, 5.0, 3.0, 1.5e-3),
}  # fmt: skip


@dataclasses.dataclass(frozen=True)
class Deviations:
    """Real-bench deviations from the paper's model; each is on by default and off at 0 / None / False.

    - `drive_spread`: log-normal σ of each drawn parameter around Table I (0.08: ±8 % typical,
      clipped at ±2σ, i.e. within −15 %…+17 %). `alpha` stays 0.5.
    - `stiction`: (low, high) of the breakaway factor over max(Ts, Ts + Tss1), drawn per direction;
      None: breakaway = the sliding friction at zero speed (Coulomb-like sticking, no excess).
    - `current_loop`: PI loop of `current_bandwidth` Hz on the R–L winding with back-EMF; False: the
      actual current is the commanded profile.
    - `pwm_ripple`: amplitude of the PWM triangle on the recorded current, × current-noise σ.
    - `sensor_dynamics`: first-order low-passes, strain gauge `torque_filter` Hz and tachometer
      `tacho_filter` Hz ranges, drawn.
    - `tacho_ripple`: amplitude × tacho σ of a ripple of order `tacho_ripple_order` per motor turn.
    - `quantisation`: output encoder with `encoder_counts` per revolution (floor to a count).
    - `offsets`: (low, high) of DC offsets × noise σ on torque, velocity and current; None: off.
    - `jitter`: largest time-stamp jitter as a fraction of the sample step (≤ 0.004 keeps step-to-step
      changes under hdjax's 1 % rule); 0: off.
    - `viscous_exponent`: κ of a viscous friction Tv·ωr^(1−κ)·|ω|^κ·sign(ω) in place of eq. 9's linear
      Tv·ω (equal at ωr = `viscous_reference` rad/s); a drive's no-load running torque often grows
      slower than linearly with speed. Off (1.0) by default, unlike the others: a variant of the
      bench (as `low_speed="lugre"`), so that the shipped datasets and benchmarks keep their draws.
    """

    drive_spread: float = 0.08
    stiction: tuple | None = (1.1, 1.3)
    current_loop: bool = True
    current_bandwidth: float = 1500.0
    pwm_ripple: float = 0.5
    sensor_dynamics: bool = True
    torque_filter: tuple = (300.0, 800.0)
    tacho_filter: tuple = (200.0, 500.0)
    tacho_ripple: float = 0.4
    tacho_ripple_order: int = 11
    quantisation: bool = True
    encoder_counts: int = 2**16
    offsets: tuple | None = (0.5, 1.0)
    jitter: float = 0.004
    viscous_exponent: float = 1.0
    viscous_reference: float = 20.0

    @classmethod
    def none(cls) -> Deviations:
        """All deviations off: the paper's model with white sensor noise only."""
        return cls(drive_spread=0.0, stiction=None, current_loop=False, pwm_ripple=0.0, sensor_dynamics=False,
                   tacho_ripple=0.0, quantisation=False, offsets=None, jitter=0.0)  # fmt: skip


def _rng(seed: int, tag: str) -> np.random.Generator:
    """Independent stream per purpose, so switching one feature does not shift the others' draws."""
    return np.random.default_rng([int(seed), sum((i + 1) * ord(c) for i, c in enumerate(tag))])


# ----------------------------------------------------------------------------------------------
# The drawn bench
# ----------------------------------------------------------------------------------------------


def _draw_bench(drive: str, seed: int, dev: Deviations, noise: str, sample_rate: float) -> dict:
    """Truth parameters, friction levels, motor and sensor realisations for one seed."""
    if drive not in STATIONS:
        raise ValueError(f"`drive` must be one of {sorted(STATIONS)}, got {drive!r}.")
    if noise not in ("per_sensor", "per_record", "none"):
        raise ValueError(f"`noise` must be 'per_sensor', 'per_record' or 'none', got {noise!r}.")
    st = STATIONS[drive]
    rng = _rng(seed, "drive")
    p = dict(st.params)
    for k in PARAMETER_KEYS[1:]:
        z = float(np.clip(rng.standard_normal(), -2.0, 2.0))
        p[k] = float(st.params[k] * math.exp(dev.drive_spread * z))
    rng = _rng(seed, "stiction")
    fac = rng.uniform(*dev.stiction, size=2) if dev.stiction else np.ones(2)
    zero_speed = {d: max(p[f"Ts{d}"] + p[f"Tss{d}1"], 0.0) for d in "pn"}
    brk = {d: float(f * (max(p[f"Ts{d}"], zero_speed[d]) if dev.stiction else zero_speed[d]))
           for d, f in zip("pn", fac)}  # fmt: skip
    rng = _rng(seed, "motor")
    R = st.R * math.exp(0.1 * rng.standard_normal())
    L = st.L * math.exp(0.1 * rng.standard_normal())
    rng = _rng(seed, "sensors")
    sensors = {
        "sample_rate": float(sample_rate),
        "noise": noise,
        "torque_noise": float(rng.uniform(0.0025, 0.003) * st.rated_torque),
        "tacho_noise": float(rng.uniform(0.02, 0.03)),
        "current_noise": float(rng.uniform(0.8, 1.2) * 1e-3 * st.peak_current),
        "encoder_counts": int(dev.encoder_counts),
        "encoder_step": TWO_PI / dev.encoder_counts,
    }
    realised: dict[str, Any] = {
        "torque_filter_hz": float(rng.uniform(*dev.torque_filter)) if dev.sensor_dynamics else None,
        "tacho_filter_hz": float(rng.uniform(*dev.tacho_filter)) if dev.sensor_dynamics else None,
        "tacho_ripple_phase": float(rng.uniform(0, TWO_PI)),
        "pwm_frequency_hz": float(20000.0 * (1.0 + rng.uniform(-1e-3, 1e-3))),
        "pwm_phase": float(rng.uniform(0, 1)),
    }
    signs = rng.choice([-1.0, 1.0], size=3)
    mags = rng.uniform(*dev.offsets, size=3) if dev.offsets else np.zeros(3)
    chans = ("torque", "motor_velocity", "current")
    realised["offset_factors"] = {c: float(s * m) for c, s, m in zip(chans, signs, mags)}
    return {
        "station": st, "params": p, "breakaway": brk, "breakaway_factors": [float(f) for f in fac],
        "zero_speed_friction": zero_speed, "R": float(R), "L": float(L), "sensors": sensors, "realised": realised,
    }  # fmt: skip


# ----------------------------------------------------------------------------------------------
# Current profiles (commanded; continuous functions of time)
# ----------------------------------------------------------------------------------------------

RAMP = 0.08  # s, smoothstep ramp from rest


def _ramp(t):
    x = np.clip(t / RAMP, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _trapezoid(t, f, ph, edge=0.004):
    """Square wave with sinusoidal edges of about `edge` s."""
    e = max(math.sin(math.pi * f * edge), 1e-3)
    return np.clip(np.sin(TWO_PI * f * t + ph) / e, -1.0, 1.0)


def _triangle(t, f, ph):
    return (2.0 / math.pi) * np.arcsin(np.sin(TWO_PI * f * t + ph))


def _logchirp(t, f0, f1, dur, ph):
    k = math.log(f1 / f0) / dur
    return np.sin(TWO_PI * f0 * (np.exp(k * t) - 1.0) / k + ph)


def _multisine(t, freqs, ph0):
    n = len(freqs)
    phases = ph0 - math.pi * np.arange(n) * (np.arange(n) + 1) / n  # Schroeder
    s = np.sum(np.sin(TWO_PI * np.asarray(freqs)[:, None] * t[None, :] + phases[:, None]), axis=0)
    return s / np.max(np.abs(s))


def _levels(t, times, levels, edge):
    """Piecewise-constant `levels` switching at `times` with raised-cosine edges of `edge` s."""
    out = np.full_like(t, levels[0])
    for tk, a, b in zip(times, levels[:-1], levels[1:]):
        x = np.clip((t - tk) / edge, 0.0, 1.0)
        out = out + (b - a) * 0.5 * (1.0 - np.cos(math.pi * x))
    return out


def _kick(t, t0):
    """Breakaway pulse: up over 20 ms from `t0`, held 10 ms, down over 20 ms (unit height); the level
    that follows rises over the same 20 ms, so the two blend without a dip."""
    return _levels(t, [t0, t0 + 0.03], [0.0, 1.0, 0.0], 0.02)


def _profiles(bench: dict, seed: int, n_locked: int, n_free: int, duration: float, t: np.ndarray) -> list[dict]:
    """Commanded currents on the fine grid `t`: list of {name, mode, regime, kind, info, current}.

    Long as a list of test designs (locked sweeps, free-motion regimes), each a few lines drawing from
    one seeded generator; the order of the draws fixes every shipped dataset, and one function keeps
    that order in sight."""
    st, p, brk = bench["station"], bench["params"], bench["breakaway"]
    rng = _rng(seed, "profiles")
    N, Km = st.gear_ratio, st.torque_constant
    Jtot = p["Jeff"] + st.load_inertia / N**2
    i_brk = max(brk.values()) / Km
    f_res = math.sqrt(p["K1"] / (N**2 * p["Jeff"])) / TWO_PI
    ramp = _ramp(t)
    out = []

    def shape(kind, fmax):
        if kind == "sine":
            f = math.exp(rng.uniform(math.log(0.3), math.log(fmax)))
            return np.sin(TWO_PI * f * t + rng.uniform(0, TWO_PI)), {"frequency": f}
        if kind == "triangle":
            f = math.exp(rng.uniform(math.log(0.3), math.log(min(fmax, 3.0))))
            return _triangle(t, f, rng.uniform(0, TWO_PI)), {"frequency": f}
        if kind == "square":
            f = math.exp(rng.uniform(math.log(0.5), math.log(min(fmax, 3.0))))
            return _trapezoid(t, f, rng.uniform(0, TWO_PI)), {"frequency": f}
        if kind == "chirp":
            f0, f1 = rng.uniform(0.3, 0.8), rng.uniform(1.3, 1.8) * f_res
            return _logchirp(t, f0, f1, duration, rng.uniform(0, TWO_PI)), {"f0": f0, "f1": f1}
        freqs = np.geomspace(rng.uniform(0.4, 0.8), rng.uniform(0.5, 0.8) * max(fmax, 2.0), 5)
        return _multisine(t, freqs, rng.uniform(0, TWO_PI)), {"frequencies": freqs.tolist()}

    # locked: the small ones stick (a few times the friction current), the large ones reach ~80 % rated
    n_small = 0 if n_locked == 0 else max(1, round(0.35 * n_locked))
    big_targets = list(rng.permutation(np.geomspace(0.25, 0.8, max(n_locked - n_small, 1))))
    small_kinds, big_kinds = ("sine", "triangle", "multisine"), ("sine", "chirp", "square", "multisine", "triangle")
    # first guess of the locked amplitudes: linear locked model, ζ = 0.3 (the power-law damping is
    # strong); `_pilot_locked` then scales them to their peak-torque targets
    wn = TWO_PI * f_res
    bz, az = signal.bilinear([N * Km * wn**2], [1.0, 0.6 * wn, wn**2], fs=1.0 / (t[1] - t[0]))
    for j in range(n_locked):
        if j < n_small:
            kind = small_kinds[j % 3]
            s, info = shape(kind, 2.0)
            amp, regime = rng.uniform(1.2, 2.5) * i_brk, "locked_stick"
            i = ramp * amp * s
        else:
            kind = big_kinds[(j - n_small) % 5]
            s, info = shape(kind, min(6.0, 0.5 * f_res))
            target = float(big_targets.pop()) * st.rated_torque
            off = rng.uniform(-0.3, 0.3) if j % 2 else 0.0
            i = ramp * (off + (1 - abs(off)) * s) * (target / (N * Km) + i_brk)
            peak = np.max(np.abs(signal.lfilter(bz, az, i)))
            i = i * min(1.0, target / peak)
            amp, regime = float(np.max(np.abs(i))), "locked"
            info["offset_fraction"] = float(off)
            info["target_peak_torque"] = target
        info["peak_current"] = float(np.max(np.abs(i)))
        out.append({"name": f"locked_{j + 1:02d}_{kind}", "mode": "constrained", "regime": regime, "kind": kind,
                    "info": info, "current": i})  # fmt: skip

    # free: Stribeck window (kick past breakaway, then inside the window), plateaus, high velocity
    n_low = round(3 * n_free / 8) if n_free >= 3 else min(n_free, 1)
    n_plat = round(2 * n_free / 8) if n_free >= 3 else max(n_free - 1, 0)
    n_high = n_free - n_low - n_plat
    free = []
    for j in range(n_low):
        d = 1 if j % 2 == 0 else -1
        reverse = j % 3 == 2

        def window(d, x):
            key = "p" if d > 0 else "n"
            lo, hi = bench["zero_speed_friction"][key], p[f"Ts{key}"]
            return d * (lo + x * (hi - lo)) / Km, d * 1.4 * brk[key] / Km

        x0, sw, fsw = rng.uniform(0.35, 0.65), rng.uniform(0.1, 0.25), rng.uniform(0.5, 2.0)
        swing = x0 + sw * np.sin(TWO_PI * fsw * t + rng.uniform(0, TWO_PI))
        if not reverse:
            level, kick = window(d, swing)
            i = kick * _kick(t, 0.0) + level * _levels(t, [0.03], [0.0, 1.0], 0.02)
        else:
            lp, kp = window(d, swing)
            ln, kn = window(-d, swing)
            tm = 0.5 * duration
            i = (kp * _kick(t, 0.0) + lp * _levels(t, [0.03, tm], [0.0, 1.0, 0.0], 0.02)
                 + kn * _kick(t, tm) + ln * _levels(t, [tm + 0.03], [0.0, 1.0], 0.02))  # fmt: skip
        free.append(("window", "low_velocity", i, {"direction": 0 if reverse else d, "window_centre": x0,
                                                   "window_swing": sw, "swing_frequency": fsw}))  # fmt: skip
    for j in range(n_plat):
        periods = 1 + j % 2
        level = rng.uniform(1.4, 2.6) * i_brk * (1 if j % 4 < 2 else -1)
        i = ramp * level * _trapezoid(t, periods / duration, 0.0, edge=0.03)
        free.append(("square", "plateau", i, {"level": float(level), "periods": periods}))
    vpeaks = rng.permutation(np.geomspace(20.0, 200.0, max(n_high, 1)))
    for j in range(n_high):
        kind = ("sine", "multisine", "chirp", "square")[j % 4]
        for _ in range(100):
            if kind == "sine":
                f = rng.uniform(0.8, 3.0)
                s, info = np.cos(TWO_PI * f * t + rng.uniform(-0.5, 0.5)), {"frequency": f}
            elif kind == "chirp":
                f0, f1 = rng.uniform(0.8, 1.5), rng.uniform(3.0, 6.0)
                s, info = _logchirp(t, f0, f1, duration, rng.uniform(0, TWO_PI)), {"f0": f0, "f1": f1}
            elif kind == "square":
                f = rng.uniform(0.8, 2.5)
                s, info = _trapezoid(t, f, rng.uniform(0, TWO_PI), edge=0.01), {"frequency": f}
            else:
                freqs = np.geomspace(rng.uniform(0.8, 1.2), rng.uniform(4.0, 6.0), 4)
                s, info = _multisine(t, freqs, rng.uniform(0, TWO_PI)), {"frequencies": freqs.tolist()}
            u = np.cumsum(ramp * s) * (t[1] - t[0])
            pk = np.max(np.abs(u))
            if np.mean(u > 0.2 * pk) > 0.25 and np.mean(u < -0.2 * pk) > 0.25:
                break
        amp = Jtot * vpeaks[j] / (Km * pk) + 2.0 * i_brk
        info.update(target_peak_velocity=float(vpeaks[j]), amplitude=float(amp))
        free.append((kind, "high_velocity", ramp * amp * s, info))
    for j, k in enumerate(rng.permutation(len(free))):
        kind, regime, i, info = free[k]
        info["peak_current"] = float(np.max(np.abs(i)))
        out.append({"name": f"free_{j + 1:02d}_{kind}", "mode": "free", "regime": regime, "kind": kind,
                    "info": info, "current": i})  # fmt: skip
    return out


# ----------------------------------------------------------------------------------------------
# The integrator
# ----------------------------------------------------------------------------------------------


def _solve_pow(a, b, q):
    """r with a·r + b·sign(r)·√|r| = q (a > 0, b ≥ 0): a quadratic in √|r|, stable form."""
    aq = np.abs(q)
    s = 2.0 * aq / (b + np.sqrt(b * b + 4.0 * a * aq) + 1e-300)
    return np.copysign(s * s, q)


def _periodic(spec, theta):
    """Σ_k w_k sin(k θ + φ_k) and its θ-derivative, for the effect `spec` (orders, phases, weights)."""
    ang = spec["k"][:, None] * theta[None, :] + spec["phi"][:, None]
    return np.sum(spec["w"][:, None] * np.sin(ang), 0), np.sum((spec["w"] * spec["k"])[:, None] * np.cos(ang), 0)


LUGRE_DELTA = 2e-4  # rad, presliding displacement of the LuGre bristle at breakaway (motor side)
TH = 0.5  # trapezoidal weight of the spring, viscous friction and positions (power-law damping: see below)
LOOP_RATE = 20000.0  # Hz, current-loop (PWM) update rate; the integrator's rate is a multiple of it


def _setup(bench, icmd, free, start, mags, specs, dev, fine_rate, low_speed) -> dict:
    """The constants of `_integrate`'s fine steps (both of its loops)."""
    st, p, brk = bench["station"], bench["params"], bench["breakaway"]
    h = 1.0 / fine_rate
    ns, B = icmd.shape
    N, Km = st.gear_ratio, st.torque_constant
    iN = 1.0 / N
    Jeff, K1, Tst, Tss2 = p["Jeff"], p["K1"], p["Tst"], p["Tss2"]
    Jh = Jeff / h
    iJl = np.where(free, 1.0 / st.load_inertia, 0.0)
    on = {k: bool(np.any(v != 0)) for k, v in mags.items()}
    m = {k: np.asarray(v, float) for k, v in mags.items()}
    # LuGre records (low_speed="lugre": presliding_friction widens the bristle), and elasto-plastic
    # presliding on top of stick–slip (presliding_friction with low_speed="stick_slip")
    lug = np.full(B, low_speed == "lugre")
    any_lug = bool(np.any(lug))
    pre = ~lug & (m["presliding_friction"] > 0)
    any_pre = bool(np.any(pre))
    delta = np.where(lug, m["presliding_friction"] + LUGRE_DELTA, np.where(pre, m["presliding_friction"], 1.0))
    sig0 = 0.5 * (brk["p"] + brk["n"]) / delta  # bristle stiffness (N·m/rad, motor side)
    sig1 = np.sqrt(sig0 * Jeff)  # bristle damping (N·m·s/rad), damping ratio ½ on the motor inertia
    wb = 0.1 * Tss2  # velocity scale of the stiction bump in the LuGre g(ω)
    wr = dev.viscous_reference  # speed at which a power-law viscous friction equals the linear one
    tf = None  # thermal drift: viscous multiplier, a function of time only
    if on["thermal_drift"]:
        tt = start[None, :] + h * np.arange(ns)[:, None]
        tf = 1.0 + m["thermal_drift"][None, :] * np.exp(-tt / specs["thermal_tau"])
    # current loop: PI with pole-zero cancellation (first-order closed loop of the given bandwidth),
    # updated at LOOP_RATE; the R–L winding with back-EMF integrated exactly over each step
    wc = TWO_PI * dev.current_bandwidth
    R, L = bench["R"], bench["L"]
    ae = math.exp(-R * h / L)
    be = (1.0 - ae) / R
    sub = int(round(fine_rate / LOOP_RATE))
    if dev.current_loop and abs(sub * LOOP_RATE - fine_rate) > 1e-6 * fine_rate:
        raise ValueError(f"`fine_rate` must be a multiple of the {LOOP_RATE:g} Hz current-loop rate, got {fine_rate}.")
    Kp, KiH = L * wc, R * wc / LOOP_RATE
    delay_steps = m["input_delay"] * fine_rate
    d0 = np.floor(delay_steps).astype(int)
    dfr = delay_steps - d0
    invA_stuck = np.where(pre, 1.0 / (Jh + sig0 * h + sig1), 0.0)  # stuck, or presliding on the bristle
    return dict(p=p, brk=brk, h=h, ns=ns, B=B, Km=Km, iN=iN, K1=K1, Tst=Tst, Tss2=Tss2, Jh=Jh, iJl=iJl, on=on, m=m,
                lug=lug, any_lug=any_lug, pre=pre, any_pre=any_pre, sig0=sig0, sig1=sig1, invA_stuck=invA_stuck,
                wb=wb, wr=wr, tf=tf, ae=ae, be=be, sub=sub, Kp=Kp, KiH=KiH, d0=d0, dfr=dfr,
                hyst_sigma=specs.get("hysteresis_sigma", 1.0))  # fmt: skip


def _integrate(bench, icmd, free, start, mags, specs, dev, fine_rate, low_speed, hook=None, hook_every=1):
    """Fixed-step simulation of B records at once. (One time loop over the fine grid whose state —
    velocities, positions, stick/slip flags, sensor filters, current loop — is updated in place in
    a fixed order; it stays one function so the order of the physics within a step reads top to
    bottom.)

    `hook(n, H)`, if given, is called before fine step n whenever n % `hook_every` == 0, with the
    histories H filled up to row n; it may write `icmd[n:n + hook_every]` (a sampled controller
    closing the loop, `Bench.closed_loop`). The command is then held over the step.

    `icmd` (steps, B) commanded current (A) on the fine grid; `free` (B,) bool; `start` (B,) session
    start times (s); `mags` effect name → (B,) physical magnitudes (0: off); `specs` periodic effect
    shapes. Returns fine-grid histories (steps + 1, B), row n at t = n·h: T (true transmitted torque,
    N·m), wm (rad/s), thm, tho (rad), ia (actual current, A).

    Each step solves, for every record, three candidates at once (rows of a (3, B) stack): sliding
    forward, sliding backward, and stuck (ωm⁺ = 0, the output may still swing; with presliding, the
    motor rides on a bristle spring instead). The momentum balance over the step uses the trapezoidal
    flexspline torque θ·T⁺ + (1−θ)·T (θ = ½) and viscous friction, with T⁺ = Tk + Kt·h·(θ·r⁺ + (1−θ)·r)
    + Tst·sign(r⁺)·√|r⁺|; eliminating the velocities leaves one scalar equation a·r⁺ + b·sign(r⁺)·√|r⁺|
    = q in the new torsion rate, solved in closed form. The non-viscous friction is explicit at the
    old speed and the drive torque uses the current averaged over the step. A moving motor keeps
    sliding while its candidate keeps the sign; otherwise it sticks when the holding torque is inside
    [−breakaway_n, breakaway_p], else it slides the other way (friction flipped part-way through the
    step). A stuck motor breaks away when the holding torque leaves the band, sliding only for the
    part of the step after the crossing. A fourth row holds the LuGre candidate where that law is used.
    """
    if not fine_steps.AVAILABLE:
        return _integrate_numpy(bench, icmd, free, start, mags, specs, dev, fine_rate, low_speed, hook, hook_every)
    c = _setup(bench, icmd, free, start, mags, specs, dev, fine_rate, low_speed)
    p, brk, ns, B, m, on = c["p"], c["brk"], c["ns"], c["B"], c["m"], c["on"]
    # the compiled loop's inputs as arrays, in the orders `fine_steps.PARAMS`, `FLAGS`, `COLUMNS` name
    params = {**{k: c[k] for k in ("h", "iN", "Km", "Jh", "K1", "Tst", "Tss2", "ae", "be", "Kp", "KiH", "wb", "wr",
                                    "hyst_sigma")},
              **{k: p[k] for k in ("Tvp", "Tvn", "Tsp", "Tsn", "Tssp1", "Tssn1")},
              "brk_p": brk["p"], "brk_n": brk["n"], "kappa": dev.viscous_exponent, "TH": TH}  # fmt: skip
    flags = {**{e: on[e] for e in EFFECTS if e in fine_steps.FLAGS}, "current_loop": dev.current_loop,
             "hook": hook is not None, "any_lug": c["any_lug"], "any_pre": c["any_pre"],
             "power_viscous": dev.viscous_exponent != 1.0}  # fmt: skip
    columns = {**{e: m[e] for e in EFFECTS if e in fine_steps.COLUMNS},
               **{k: c[k] for k in ("iJl", "lug", "pre", "sig0", "sig1", "d0", "dfr")}, "invA2": c["invA_stuck"]}
    P = np.array([params[k] for k in fine_steps.PARAMS], float)
    F = np.array([flags[k] for k in fine_steps.FLAGS], np.int64)
    C = np.stack([np.broadcast_to(np.asarray(columns[k], float), (B,)) for k in fine_steps.COLUMNS])
    tf = c["tf"] if c["tf"] is not None else np.ones((1, B))
    shapes = [specs.get(e) for e in ("cogging", "kinematic_error", "position_dependent_friction")]
    width = max([len(s["k"]) for s in shapes if s is not None], default=1)
    pk, pphi, pw = (np.zeros((3, width)) for _ in range(3))
    pn = np.zeros(3, np.int64)
    for i, s in enumerate(shapes):
        if s is not None:
            n = len(s["k"])
            pk[i, :n], pphi[i, :n], pw[i, :n], pn[i] = s["k"], s["phi"], s["w"], n
    Hs = np.empty((5, ns + 1, B))
    Hs[:, 0] = 0.0
    H = dict(zip(("T", "wm", "thm", "tho", "ia"), Hs))
    S = np.zeros((len(fine_steps.STATE), B))
    S[fine_steps.STATE.index("stk")] = 1.0  # stuck (or presliding): starts at rest
    icmd = np.ascontiguousarray(icmd, float) if hook is None else icmd
    every = ns if hook is None else hook_every
    for n0 in range(0, ns, every):
        if hook is not None:
            hook(n0, H)
        fine_steps.run_steps(n0, min(n0 + every, ns), icmd, Hs, S, P, F, C, tf, pk, pphi, pw, pn, c["sub"])
    return H


def _integrate_numpy(bench, icmd, free, start, mags, specs, dev, fine_rate, low_speed, hook=None, hook_every=1):
    """`_integrate`'s loop in numpy, vectorised over the records: the reference that
    `hdjax._testbench.fine_steps.run_steps` (the compiled loop, per record) is checked against, and
    the loop used where numba cannot be imported. About 130 µs per fine step whatever the number of
    records (2-core machine)."""
    c = _setup(bench, icmd, free, start, mags, specs, dev, fine_rate, low_speed)
    p, brk, h, ns, B, Km, iN = (c[k] for k in ("p", "brk", "h", "ns", "B", "Km", "iN"))
    K1, Tst, Tss2, Jh, iJl, on, m = (c[k] for k in ("K1", "Tst", "Tss2", "Jh", "iJl", "on", "m"))
    lug, any_lug, pre, any_pre, sig0, sig1, wb, wr, tf = (
        c[k] for k in ("lug", "any_lug", "pre", "any_pre", "sig0", "sig1", "wb", "wr", "tf"))
    ae, be, sub, Kp, KiH, d0, dfr, hyst_sigma = (c[k] for k in ("ae", "be", "sub", "Kp", "KiH", "d0", "dfr", "hyst_sigma"))
    cols = np.arange(B)
    # candidate rows: 0 slide +, 1 slide −, 2 stuck, (3 LuGre)
    nr = 4 if any_lug else 3
    invA = np.zeros((nr, B))
    invA[0], invA[1] = 1.0 / (Jh + TH * p["Tvp"]), 1.0 / (Jh + TH * p["Tvn"])
    invA[2] = c["invA_stuck"]
    F0 = np.zeros((nr, B))

    thm, wm, tho, wo = (np.zeros(B) for _ in range(4))
    ia, integ, volt, zd, zl, Tprev, idel, Fprev, zp_, rprev = (np.zeros(B) for _ in range(10))
    stk = np.ones(B, bool)  # stuck (or presliding): starts at rest
    H = {k: np.empty((ns + 1, B)) for k in ("T", "wm", "thm", "tho", "ia")}
    for k in H:
        H[k][0] = 0.0
    for n in range(ns):
        if hook is not None and n % hook_every == 0:
            hook(n, H)
        # --- current loop (PI at LOOP_RATE, voltage held) and winding to t_{n+1}, back-EMF at ωm(t_n)
        if dev.current_loop:
            if n % sub == 0:
                e = icmd[n] - ia
                integ = integ + KiH * e
                volt = Kp * e + integ
            ia_new = ia * ae + (volt - Km * wm) * be
        else:
            ia_new = icmd[n] if hook is not None else icmd[min(n + 1, ns - 1)]
        H["ia"][n + 1] = ia_new
        # --- drive torque over the step: current averaged over its ends (2nd order in the input)
        if on["input_delay"]:
            j0 = n + 1 - d0
            hist = H["ia"]
            i1 = (1.0 - dfr) * np.where(j0 >= 0, hist[np.maximum(j0, 0), cols], 0.0) + dfr * np.where(
                j0 >= 1, hist[np.maximum(j0 - 1, 0), cols], 0.0
            )
            tau = 0.5 * Km * (idel + i1)
            idel = i1
        else:
            tau = 0.5 * Km * (ia + ia_new)
        ia = ia_new
        if on["cogging"]:
            tau = tau + m["cogging"] * _periodic(specs["cogging"], thm)[0]
        # --- torsion and elastic torque (Tk, tangent stiffness Kt)
        x = thm * iN - tho
        rho = iN
        if on["kinematic_error"]:
            e, de = _periodic(specs["kinematic_error"], thm)
            x = x + m["kinematic_error"] * e
            rho = iN + m["kinematic_error"] * de
        Kt = K1
        if on["lost_motion"]:
            dl = m["lost_motion"]
            x = x - np.clip(x, -dl, dl)
            Kt = np.where(x != 0.0, K1, 0.0)
        Tk = K1 * x
        if on["nonlinear_stiffness"]:
            Tk = Tk + m["nonlinear_stiffness"] * x**3
            Kt = Kt + 3.0 * m["nonlinear_stiffness"] * x * x
        if on["rate_independent_hysteresis"]:
            Tk = Tk + m["rate_independent_hysteresis"] * zd
        # --- friction (non-viscous part at the old speed; Coulomb modulations)
        aw = np.abs(wm)
        ex = np.exp(-((aw / Tss2) ** 2))
        cmod = 1.0
        if on["position_dependent_friction"]:
            cmod = 1.0 + m["position_dependent_friction"] * _periodic(specs["position_dependent_friction"], thm)[0]
        load = m["load_dependent_friction"] * np.abs(Tprev) * iN if on["load_dependent_friction"] else 0.0
        fp = np.maximum(p["Tsp"] * cmod + p["Tssp1"] * ex + load, 0.0)
        fn = np.maximum(p["Tsn"] * cmod + p["Tssn1"] * ex + load, 0.0)
        F0[0], F0[1] = fp, -fn
        if any_pre:
            F0[2] = np.where(pre, sig0 * zp_, 0.0)
        if on["thermal_drift"]:
            invA[0], invA[1] = 1.0 / (Jh + TH * p["Tvp"] * tf[n]), 1.0 / (Jh + TH * p["Tvn"] * tf[n])
        if any_lug:  # LuGre bristle state zl (motor side): exponential update, linearised implicit force
            sgn = np.sign(wm)
            dl_ = np.where(sgn != 0, sgn, np.where(zl >= 0, 1.0, -1.0))
            bp, bn = brk["p"] * cmod + load, brk["n"] * cmod + load
            bump = np.exp(-((aw / wb) ** 2))
            g = np.where(dl_ > 0, fp + (bp - fp) * bump, fn + (bn - fn) * bump)
            g = np.maximum(g, 0.05 * np.where(dl_ > 0, bp, bn))
            E = np.exp(-sig0 * aw * h / g)
            zss = sgn * g / sig0
            zp = zss + (zl - zss) * E
            cz = h * E
            F0[3] = sig0 * (zp - cz * wm) + sig1 * ex * (zp - zl) / h
            tv = np.where(dl_ > 0, p["Tvp"], p["Tvn"]) * (1.0 if tf is None else tf[n])
            invA[3] = 1.0 / (Jh + TH * tv + sig0 * cz)
        # viscous friction by the trapezoidal rule: its old-speed half goes with the explicit part
        tvf = 1.0 if tf is None else tf[n]
        F0[0] += (1.0 - TH) * p["Tvp"] * tvf * wm
        F0[1] += (1.0 - TH) * p["Tvn"] * tvf * wm
        if any_lug:
            F0[3] += (1.0 - TH) * tv * wm
        if dev.viscous_exponent != 1.0:  # the power law's departure from the linear law, at the old speed
            dv = (wr ** (1.0 - dev.viscous_exponent) * aw**dev.viscous_exponent - aw) * np.sign(wm) * tvf
            F0[0] += p["Tvp"] * dv
            F0[1] += p["Tvn"] * dv
            if any_lug:
                F0[3] += np.where(dl_ > 0, p["Tvp"], p["Tvn"]) * dv
        C = TH * Tk + (TH * (1.0 - TH) * h) * Kt * rprev + (1.0 - TH) * Tprev

        def cands(F0, invA):
            """New motor velocity W, output velocity V, end torque T, rate r for friction F0, 1/A."""
            W0 = (Jh * wm + tau - F0) * invA
            M = rho * iN * invA + h * iJl
            r = _solve_pow(1.0 + M * (TH * TH * h) * Kt, M * (TH * Tst), rho * W0 - wo - M * C)
            phi = Tst * np.copysign(np.sqrt(np.abs(r)), r)
            Teff = C + (TH * TH * h) * Kt * r + TH * phi  # torque over the step: θ·T_{n+1} + (1−θ)·T_n
            return W0 - Teff * iN * invA, wo + h * iJl * Teff, Tk + (h * Kt) * (TH * r + (1.0 - TH) * rprev) + phi, r

        W, V, T, R_ = cands(F0, invA)
        # friction that holds the motor once stopped (a moving motor's momentum is taken by the
        # kinetic friction that stops it within the step); presliding: the bristle's force
        Freq = tau - T[2] * iN
        if any_pre:
            Freq = np.where(pre, sig0 * (zp_ + h * W[2]) + sig1 * W[2], Freq)
        stick = (Freq <= brk["p"] * cmod + load) & (Freq >= -(brk["n"] * cmod + load))
        kn = np.where(Freq > 0, 0, 1)
        mp, mn = ~stk & (wm > 0), ~stk & (wm < 0)
        stick = stick | (mp & (kn == 0)) | (mn & (kn == 1))  # stopped, no slip back
        k = np.where(mp & (W[0] > 0), 0, np.where(mn & (W[1] < 0), 1, np.where(stick, 2, kn)))
        w_new, v_new, T_new, r_new = W[k, cols], V[k, cols], T[k, cols], R_[k, cols]
        # events inside the step, located to O(h²): a reversal straight through zero speed (friction
        # flips part-way) and a breakaway from sticking (slides only after the holding torque crosses)
        rev = (mp & (k == 1)) | (mn & (k == 0))
        if rev.any():
            ko = np.where(wm > 0, 0, 1)
            den = wm - W[ko, cols]  # non-zero where `rev` (the speed changes sign); the rest is discarded
            th = np.clip(np.divide(wm, den, out=np.zeros_like(wm), where=den != 0), 0.0, 1.0)
            f0p = max(p["Tsp"] + p["Tssp1"], 0.0) * cmod + load
            f0n = max(p["Tsn"] + p["Tssn1"], 0.0) * cmod + load
            visc = F0[k, cols] - np.where(k == 0, fp, -fn)
            Fe = th * F0[ko, cols] + (1.0 - th) * (np.where(k == 0, f0p, -f0n) + visc)
            out = cands(Fe, invA[k, cols])
            w_new, v_new, T_new, r_new = (np.where(rev, x, y) for x, y in zip(out, (w_new, v_new, T_new, r_new)))
        brk_ev = stk & (k != 2)
        if brk_ev.any():
            bth = np.where(Freq > 0, brk["p"] * cmod + load, -(brk["n"] * cmod + load))
            th = np.clip((bth - Fprev) / np.where(Freq != Fprev, Freq - Fprev, 1.0), 0.0, 1.0)
            w_new = np.where(brk_ev, (1.0 - th) * w_new, w_new)
            v_new = np.where(brk_ev, th * V[2] + (1.0 - th) * v_new, v_new)
            T_new = np.where(brk_ev, th * T[2] + (1.0 - th) * T_new, T_new)
            r_new = np.where(brk_ev, th * R_[2] + (1.0 - th) * r_new, r_new)
        Fprev = Freq
        stk = k == 2
        if any_pre:  # bristle: deflects while stuck, fully loaded (kinetic level) while sliding
            zp_ = np.where(stk, zp_ + h * w_new, np.where(w_new > 0, fp, np.where(w_new < 0, -fn, 0.0)) / sig0)
        if any_lug:
            w_new, v_new, T_new, r_new = (
                np.where(lug, x[3], y) for x, y in zip((W, V, T, R_), (w_new, v_new, T_new, r_new))
            )
            s2 = np.sign(w_new)
            zss2 = s2 * g / sig0
            zl = np.where(lug, zss2 + (zl - zss2) * np.exp(-sig0 * np.abs(w_new) * h / g), 0.0)
        if on["rate_independent_hysteresis"]:
            rr = rho * w_new - v_new
            s = np.sign(rr)
            zd = s + (zd - s) * np.exp(-np.abs(rr) * h / hyst_sigma)
        thm = thm + h * (TH * w_new + (1.0 - TH) * wm)
        tho = tho + h * (TH * v_new + (1.0 - TH) * wo)
        wm, wo, Tprev, rprev = w_new, v_new, T_new, r_new
        H["T"][n + 1], H["wm"][n + 1], H["thm"][n + 1], H["tho"][n + 1] = T_new, wm, thm, tho
    return H


# ----------------------------------------------------------------------------------------------
# Sensors
# ----------------------------------------------------------------------------------------------


def _lowpass(x, fc, fine_rate):
    """First-order low-pass along axis 0 (matched pole, input averaged over the step), from rest."""
    if fc is None:
        return x
    a = math.exp(-TWO_PI * fc / fine_rate)
    return signal.lfilter([0.5 * (1.0 - a), 0.5 * (1.0 - a)], [1.0, -a], x, axis=0)


def _sample_times(seed, dev, K, B, sample_rate):
    """Jittered sample instants (K, B) in s: k/fs + U(±jitter)/fs, the first one ≥ 0."""
    j = _rng(seed, "jitter").uniform(-dev.jitter, dev.jitter, size=(K, B)) if dev.jitter else np.zeros((K, B))
    j[0] = np.abs(j[0])
    return (np.arange(K)[:, None] + j) / sample_rate


def _at(X, times, fine_rate):
    """Linear interpolation of fine-grid histories X (steps, B) at `times` (K, B)."""
    pos = times * fine_rate
    i0 = np.floor(pos).astype(int)
    fr = pos - i0
    c = np.arange(X.shape[1])[None, :]
    return (1.0 - fr) * X[i0, c] + fr * X[i0 + 1, c]


def _sense(bench, H, times, dev, fine_rate, mags, specs):
    """Noise-free recorded channels (K, B): what the sensors deliver before noise, offset and counts,
    plus the true signals at the sample instants."""
    sens, real = bench["sensors"], bench["realised"]
    T = H["T"]
    if np.any(mags["torque_sensor_ripple"] != 0):
        T = T + mags["torque_sensor_ripple"][None, :] * _periodic(specs["torque_sensor_ripple"], H["thm"].ravel())[
            0
        ].reshape(H["thm"].shape)
    tach = H["wm"]
    if dev.tacho_ripple:
        amp = dev.tacho_ripple * sens["tacho_noise"] * np.tanh(np.abs(tach))
        tach = tach + amp * np.sin(dev.tacho_ripple_order * H["thm"] + real["tacho_ripple_phase"])
    ia = _at(H["ia"], times, fine_rate)
    if dev.pwm_ripple:
        ph = (real["pwm_frequency_hz"] * times + real["pwm_phase"]) % 1.0
        ia = ia + dev.pwm_ripple * sens["current_noise"] * (4.0 * np.abs(ph - 0.5) - 1.0)
    mt = times
    return {
        "torque": _at(_lowpass(T, real["torque_filter_hz"], fine_rate), mt, fine_rate),
        "motor_velocity": _at(_lowpass(tach, real["tacho_filter_hz"], fine_rate), mt, fine_rate),
        "output_position": _at(H["tho"], mt, fine_rate),
        "current": ia,
        "true_torque": _at(H["T"], mt, fine_rate),
        "true_motor_velocity": _at(H["wm"], mt, fine_rate),
        "true_motor_position": _at(H["thm"], mt, fine_rate),
    }


def _noise_sigmas(bench, clean, noise):
    """Noise σ per channel and record, (B,) each."""
    sens = bench["sensors"]
    B = clean["torque"].shape[1]
    base = {"torque": sens["torque_noise"], "motor_velocity": sens["tacho_noise"], "current": sens["current_noise"]}
    out = {}
    for ch, s in base.items():
        if noise == "per_record":
            frac = {"torque": 0.0015, "motor_velocity": 0.001, "current": 0.001}[ch]
            out[ch] = np.maximum(frac * np.ptp(clean[ch], axis=0), 0.1 * s)
        elif noise == "none":
            out[ch] = np.zeros(B)
        else:
            out[ch] = np.full(B, s)
    return out


def _record(bench, clean, seed, dev, noise, free):
    """Recorded channels: clean + offset + white noise; output angle floored to encoder counts."""
    sig = _noise_sigmas(bench, clean, noise)
    rng = _rng(seed, "noise")
    rec = {}
    K, B = clean["torque"].shape
    for ch in ("current", "motor_velocity", "torque"):
        s_nom = np.full(B, bench["sensors"][{"torque": "torque_noise", "motor_velocity": "tacho_noise",
                                              "current": "current_noise"}[ch]])  # fmt: skip
        off = bench["realised"]["offset_factors"][ch] * s_nom if dev.offsets else 0.0
        rec[ch] = clean[ch] + off + sig[ch] * rng.standard_normal((K, B))
    q = bench["sensors"]["encoder_step"]
    th = clean["output_position"]
    rec["output_position"] = (np.floor(th / q) * q if dev.quantisation else th) + 0.0
    rec["output_position"][:, ~free] = 0.0
    return rec, sig


# ----------------------------------------------------------------------------------------------
# Effects: specification, magnitude and calibration
# ----------------------------------------------------------------------------------------------

_SNR_CHANNELS = ("torque", "motor_velocity", "output_position")
_EFFECT_KEYS = {"snr", "magnitude", "orders", "phases", "weights", "tau", "sigma", "channels"}


def _effect_specs(effects: dict, bench: dict, seed: int) -> tuple[dict, dict, dict]:
    """Parse `effects` → (specs for the integrator, snr targets, fixed magnitudes)."""
    st, p = bench["station"], bench["params"]
    specs: dict[str, Any] = {"thermal_tau": 450.0, "hysteresis_sigma": 0.02 * st.rated_torque / p["K1"], "channels": {}}
    targets, fixed = {}, {}
    for name, opt in (effects or {}).items():
        if name not in EFFECTS:
            raise ValueError(f"unknown effect {name!r}; known: {list(EFFECTS)}.")
        opt = dict(opt or {})
        bad = set(opt) - _EFFECT_KEYS
        if bad:
            raise ValueError(f"effect {name!r}: unknown option(s) {sorted(bad)}; allowed {sorted(_EFFECT_KEYS)}.")
        rng = _rng(seed, "effect-" + name)
        if name in PERIODIC:
            k = np.asarray(opt.get("orders", DEFAULT_ORDERS[name]), float)
            if k.ndim != 1 or k.size == 0 or np.any(k <= 0) or np.any(k != np.round(k)):
                raise ValueError(f"effect {name!r}: `orders` must be a list of positive integers, got {k.tolist()}.")
            phi = np.asarray(opt["phases"], float) if "phases" in opt else rng.uniform(0, TWO_PI, k.size)
            w = np.asarray(opt.get("weights", np.ones(k.size)), float)
            if phi.shape != k.shape or w.shape != k.shape:
                raise ValueError(f"effect {name!r}: `phases` and `weights` need one entry per order.")
            specs[name] = {"k": k, "phi": phi, "w": w}
        if name == "thermal_drift":
            specs["thermal_tau"] = float(opt.get("tau", rng.uniform(300.0, 600.0)))
        if name == "rate_independent_hysteresis" and "sigma" in opt:
            specs["hysteresis_sigma"] = float(opt["sigma"])
        chans = list(opt.get("channels", _SNR_CHANNELS))
        if not chans or set(chans) - set(_SNR_CHANNELS):
            raise ValueError(f"effect {name!r}: `channels` must be a non-empty subset of {list(_SNR_CHANNELS)}.")
        specs["channels"][name] = chans
        if "magnitude" in opt:
            fixed[name] = float(opt["magnitude"])
        else:
            targets[name] = float(opt.get("snr", 5.0))
            if not targets[name] > 0:
                raise ValueError(f"effect {name!r}: `snr` must be positive, got {targets[name]}.")
    return specs, targets, fixed


def _first_guess(name, bench) -> float:
    """A small plausible magnitude (unit: `EFFECT_UNITS[name]`) to start the snr calibration."""
    st, p, s = bench["station"], bench["params"], bench["sensors"]
    dr = st.rated_torque / p["K1"]
    return {
        "kinematic_error": 0.3 * s["torque_noise"] / p["K1"], "torque_sensor_ripple": s["torque_noise"],
        "cogging": 0.1 * p["Tsp"], "position_dependent_friction": 0.1, "nonlinear_stiffness": 0.05 * p["K1"] / dr**2,
        "lost_motion": 0.01 * dr, "load_dependent_friction": 0.02, "thermal_drift": 0.3, "input_delay": 5e-4,
        "rate_independent_hysteresis": 0.005 * st.rated_torque, "presliding_friction": 5e-4,
    }[name]  # fmt: skip


def _snr(bench, ca, cb, free, sig, channels=_SNR_CHANNELS):
    """snr of the change cb − ca: per channel, the RMS over the records where it acts (change above
    10 % of the largest record's) of RMS(change)/σ (output angle: σ = encoder step/√12); returns
    (max over `channels`, that channel, per-channel dict)."""
    per = {}
    for ch in _SNR_CHANNELS:
        d = cb[ch] - ca[ch]
        if ch == "output_position":
            d = d[:, free]
            s = np.full(d.shape[1], bench["sensors"]["encoder_step"] / math.sqrt(12.0))
        else:
            s = sig[ch]
        if d.shape[1] == 0:
            continue
        x = np.sqrt(np.mean(d * d, axis=0)) / s
        acts = x >= 0.1 * np.max(x)
        per[ch] = float(np.sqrt(np.mean(x[acts] ** 2))) if np.max(x) > 0 else 0.0
    ch = max((c for c in per if c in channels), key=per.get)
    return per[ch], ch, per


# ----------------------------------------------------------------------------------------------
# Public API
# ----------------------------------------------------------------------------------------------


def simulate_dataset(
    *,
    drive: str = "hd1",
    seed: int = 0,
    n_locked: int = 8,
    n_free: int = 8,
    duration: float = 2.5,
    sample_rate: float = 1000.0,
    effects: dict | None = None,
    deviations: Deviations | None = None,
    noise: str = "per_sensor",
    low_speed: str = "stick_slip",
    fine_rate: float = 20000.0,
) -> tuple[list[dict], dict]:
    """Simulate one bench session in memory. (Long through its options and the description of
    every recorded column below; the body draws the bench, integrates and samples.)

    **Arguments:** as `make_dataset` (without `out_dir`), plus `fine_rate` (Hz), the integrator's
    step rate, rounded to a multiple of `sample_rate`.

    **Returns:** `(records, truth)`. Each record is a dict with `file`, `mode`, `start_time` (s),
    `regime`, `kind`, `info`, the recorded columns `time` (s, jittered), `current` (A),
    `motor_velocity` (rad/s), `torque` (N·m), `output_position` (rad, free only), and `clean`: the
    same channels before noise/offsets/quantisation plus `true_torque`, `true_motor_velocity`,
    `true_motor_position` and `commanded_current` at the sample instants. `truth` is the
    `truth.yaml` mapping.
    """
    dev = Deviations() if deviations is None else deviations
    if low_speed not in ("stick_slip", "lugre"):
        raise ValueError(f"`low_speed` must be 'stick_slip' or 'lugre', got {low_speed!r}.")
    if n_locked < 0 or n_free < 0 or n_locked + n_free == 0:
        raise ValueError(f"need at least one record, got n_locked={n_locked}, n_free={n_free}.")
    if not 0.3 <= duration <= 60.0:
        raise ValueError(f"`duration` must be within 0.3–60 s, got {duration}.")
    if not 0 <= dev.jitter <= 0.004:
        raise ValueError(f"`Deviations.jitter` must be within 0–0.004 of the step, got {dev.jitter}.")
    bench = _draw_bench(drive, seed, dev, noise, sample_rate)
    sub = max(1, int(round(fine_rate / sample_rate)))
    fr = sub * sample_rate
    K = int(round(duration * sample_rate))
    ns = (K + 1) * sub
    tf = np.arange(ns) / fr
    profs = _profiles(bench, seed, n_locked, n_free, duration, tf)
    B = len(profs)
    free = np.array([pr["mode"] == "free" for pr in profs])
    icmd = np.stack([pr["current"] for pr in profs], axis=1)
    # session: records in random order, 30–150 s apart
    rng = _rng(seed, "session")
    order = rng.permutation(B)
    start = np.zeros(B)
    clock = rng.uniform(10.0, 60.0)
    for k in order:
        start[k] = round(clock, 3)
        clock += duration + rng.uniform(30.0, 150.0)
    specs, targets, fixed = _effect_specs(effects or {}, bench, seed)
    times = _sample_times(seed, dev, K, B, sample_rate)
    _pilot_locked(bench, profs, icmd, fr, dev, specs)

    def run(variants):
        """Simulate the records once per variant (dict name → magnitude); clean channels per variant."""
        V = len(variants)
        mags = {e: np.repeat([float(v.get(e, 0.0)) for v in variants], B) for e in EFFECTS}
        H = _integrate(bench, np.tile(icmd, (1, V)), np.tile(free, V), np.tile(start, V), mags, specs, dev, fr,
                       low_speed)  # fmt: skip
        C = _sense(bench, H, np.tile(times, (1, V)), dev, fr, mags, specs)
        return [{k: v[:, j * B : (j + 1) * B] for k, v in C.items()} for j in range(V)]

    calib: dict[str, dict] = {}
    final = dict(fixed)
    if targets:
        names = list(targets)
        tried = {e: [] for e in names}
        guess = {e: _first_guess(e, bench) for e in names}
        out = run([{}] + [{e: guess[e]} for e in names])
        base, outs = out[0], dict(zip(names, out[1:]))
        sig0 = _noise_sigmas(bench, base, "per_sensor" if noise == "none" else noise)
        todo = names
        for it in range(6):
            for e in todo:
                tried[e].append((guess[e], *_snr(bench, base, outs[e], free, sig0, specs["channels"][e]), outs[e]))
            todo = [e for e in names if abs(tried[e][-1][1] / targets[e] - 1.0) > 0.02 and len(tried[e]) < 5]
            if not todo:
                break
            for e in todo:
                (m1, s1, *_), tgt = tried[e][-1], targets[e]
                if len(tried[e]) == 1 or s1 == tried[e][-2][1]:
                    nxt = m1 * tgt / max(s1, 1e-12)
                else:
                    m0, s0 = tried[e][-2][:2]
                    nxt = m1 + (tgt - s1) * (m1 - m0) / (s1 - s0)
                    if not nxt > 0:
                        nxt = m1 * tgt / max(s1, 1e-12)
                guess[e] = nxt
            outs.update(zip(todo, run([{e: guess[e]} for e in todo])))
        for e in names:
            m, s, ch, per, c = min(tried[e], key=lambda x: abs(x[1] / targets[e] - 1.0))
            final[e] = m
            calib[e] = {"snr_target": targets[e], "snr": s, "channel": ch, "snr_per_channel": per,
                        "calibration_steps": len(tried[e])}  # fmt: skip
    clean = c if len(final) == 1 and targets else run([final])[0]  # one effect: its calibrated run is final
    rec, sig = _record(bench, clean, seed, dev, noise, free)
    icmd_s = _at(np.vstack([icmd, icmd[-1:]]), times, fr)

    records = []
    for j, pr in enumerate(profs):
        r = {"file": pr["name"] + ".csv", "mode": pr["mode"], "start_time": float(start[j]), "regime": pr["regime"],
             "kind": pr["kind"], "info": pr["info"], "time": times[:, j].copy()}  # fmt: skip
        for ch in ("current", "motor_velocity", "torque"):
            r[ch] = rec[ch][:, j].copy()
        if pr["mode"] == "free":
            r["output_position"] = rec["output_position"][:, j].copy()
        r["clean"] = {k: v[:, j].copy() for k, v in clean.items()}
        r["clean"]["commanded_current"] = icmd_s[:, j]
        r["noise"] = {k: float(v[j]) for k, v in sig.items()}
        records.append(r)
    truth = _truth(bench, dev, seed, drive, noise, low_speed, fr, final, calib, specs, records)
    return records, truth


def _pilot_locked(bench, profs, icmd, fine_rate, dev, specs):
    """The operator's trial runs: the large locked tests are simulated twice (2 kHz, ideal current)
    and their currents rescaled, in place, so that the peak torque meets `target_peak_torque`
    (T ≈ N·(Km·i − Ts), so the scale acts on the torque plus the friction's share)."""
    big = [j for j, pr in enumerate(profs) if pr["regime"] == "locked"]
    if not big:
        return
    st, p = bench["station"], bench["params"]
    step = max(1, int(round(fine_rate / 2000.0)))
    zero = {e: np.zeros(len(big)) for e in EFFECTS}
    for _ in range(2):
        H = _integrate(bench, icmd[::step, big], np.zeros(len(big), bool), np.zeros(len(big)), zero, specs,
                       dataclasses.replace(dev, current_loop=False), fine_rate / step, "stick_slip")  # fmt: skip
        fric = st.gear_ratio * 0.5 * (p["Tsp"] + p["Tsn"])
        for c, j in enumerate(big):
            peak = float(np.max(np.abs(H["T"][:, c])))
            target = profs[j]["info"]["target_peak_torque"]
            scale = min((target + fric) / (peak + fric), 3.0)
            icmd[:, j] *= scale
            profs[j]["current"] = icmd[:, j]
            profs[j]["info"]["pilot_scale"] = profs[j]["info"].get("pilot_scale", 1.0) * scale
            profs[j]["info"]["peak_current"] = float(np.max(np.abs(icmd[:, j])))


def _plain(x):
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, (np.bool_, bool)):
        return bool(x)
    if isinstance(x, (np.integer, int)):
        return int(x)
    if isinstance(x, (np.floating, float)):
        return float(x)
    return x


def _truth(bench, dev, seed, drive, noise, low_speed, fine_rate, final, calib, specs, records) -> dict:
    st, p = bench["station"], bench["params"]
    eff = {}
    for e, mag in final.items():
        d = {"magnitude": mag, "unit": EFFECT_UNITS[e], **calib.get(e, {"snr": None, "note": "magnitude given"})}
        if e in PERIODIC:
            d.update(orders=specs[e]["k"].astype(int), phases=specs[e]["phi"], weights=specs[e]["w"],
                     form="magnitude * weight_k * sin(k * theta_m + phi_k), theta_m: wave-generator angle")  # fmt: skip
        if e == "thermal_drift":
            d["tau"] = specs["thermal_tau"]
        if e == "rate_independent_hysteresis":
            d["sigma"] = specs["hysteresis_sigma"]
        if e == "presliding_friction":
            dl = mag + (LUGRE_DELTA if low_speed == "lugre" else 0.0)
            s0 = 0.5 * sum(bench["breakaway"].values()) / dl
            d.update(model="LuGre bristle widened" if low_speed == "lugre" else "elasto-plastic bristle while stuck",
                     sigma0=s0, sigma1=math.sqrt(s0 * p["Jeff"]))  # fmt: skip
        d["channels"] = specs["channels"][e]
        eff[e] = d
    truth = {
        "generator": "hdjax._bench: independent virtual test bench (numpy fixed-step integrator, stick-slip "
        "friction, current loop, sensor dynamics); it uses no hdjax plant, solver or model code",
        "seed": seed,
        "drive_name": st.name,
        "parameters": {k: p[k] for k in PARAMETER_KEYS},
        "nominal_parameters": dict(st.params),
        "drive": {
            "gear_ratio": st.gear_ratio,
            "torque_constant": st.torque_constant,
            "load_inertia": st.load_inertia,
        },  # fmt: skip
        "rated_torque": st.rated_torque,
        "low_speed": {
            "law": low_speed,
            "breakaway_torque": bench["breakaway"],
            "breakaway_factors": bench["breakaway_factors"],
            "sliding_zero_speed_friction": bench["zero_speed_friction"],
            "rule": "stick while the holding torque is within [-breakaway_n, breakaway_p]; breakaway = factor * "
            "max(Ts, Ts + Tss1) per direction; sliding friction = eq. 9 with its non-viscous part clipped at 0",
        },
        "motor": {"R": bench["R"], "L": bench["L"], "back_emf": st.torque_constant},
        "sensors": bench["sensors"],
        "deviations": {**dataclasses.asdict(dev), **bench["realised"]},
        "effects": eff,
        "integrator": {
            "fine_rate_hz": fine_rate,
            "current_loop_rate_hz": LOOP_RATE,
            "scheme": "fixed step, velocity level: trapezoidal flexspline torque (spring + power-law damping), "
            "viscous friction and positions, implicit half in closed form; Coulomb/Stribeck explicit; exact "
            "sticking with reversals and breakaways located inside the step",
        },
        "experiments": [
            {
                "file": r["file"],
                "mode": r["mode"],
                "start_time": r["start_time"],
                "regime": r["regime"],
                "kind": r["kind"],
                "noise": r["noise"],
                **r["info"],
            }
            for r in records
        ],  # fmt: skip
    }
    if low_speed == "lugre":
        s0 = 0.5 * sum(bench["breakaway"].values()) / LUGRE_DELTA
        truth["low_speed"].update(
            rule="LuGre: z' = w - sigma0 |w| z / g(w), F = sigma0 z + sigma1 exp(-(w/Tss2)^2) z' + viscous; g = eq. 9 "
            "non-viscous part plus a stiction bump (breakaway - g(0+)) exp(-(w / 0.1 Tss2)^2)",
            delta=LUGRE_DELTA, sigma0=s0, sigma1=math.sqrt(s0 * p["Jeff"]))  # fmt: skip
    if st.name == "HD2":
        truth["unit_reading"] = "HD2 Table I K1 = 104.2 and Tst = 7.96 read per degree: K1*(180/pi), Tst*(180/pi)^0.5"
    return _plain(truth)


def _atomic_write(path: pathlib.Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def make_dataset(
    out_dir: str | os.PathLike,
    *,
    drive: str = "hd1",
    seed: int = 0,
    n_locked: int = 8,
    n_free: int = 8,
    duration: float = 2.5,
    sample_rate: float = 1000.0,
    effects: dict | None = None,
    deviations: Deviations | None = None,
    noise: str = "per_sensor",
    low_speed: str = "stick_slip",
    fine_rate: float = 20000.0,
    name: str | None = None,
) -> dict:
    """Simulate a bench session and write it as a SPEC §2 dataset folder.

    **Arguments:**

    - `out_dir`: the folder (created if needed); gets `dataset.yaml`, one CSV per record and
      `truth.yaml`.
    - `drive`: "hd1" or "hd2" (Table I; parameters drawn around it from `seed`).
    - `seed`: fixes everything (drive, profiles, deviations, noise): same seed → same bytes.
    - `n_locked`, `n_free`: numbers of constrained and free-motion records; `duration` (s) each.
    - `sample_rate`: data-acquisition rate (Hz).
    - `effects`: hidden SPEC §4 effects, e.g. `{"kinematic_error": {"snr": 4.0, "orders": [2]}}`;
      options `snr` (default 5), `magnitude` (physical, skips the calibration; `EFFECT_UNITS`),
      `orders`, `phases`, `weights` (periodic), `tau` (thermal_drift, s), `sigma` (hysteresis, rad).
    - `deviations`: `Deviations` (default: all on).
    - `noise`: "per_sensor" (fixed σ per sensor), "per_record" (σ scaled with each record's range)
      or "none".
    - `low_speed`: "stick_slip" (exact sticking, breakaway) or "lugre".
    - `fine_rate`: integrator step rate (Hz).
    - `name`: the dataset's name in `dataset.yaml` (default `bench-<drive>-seed<seed>`).

    **Returns:** the truth mapping (also written to `truth.yaml`).
    """
    records, truth = simulate_dataset(drive=drive, seed=seed, n_locked=n_locked, n_free=n_free, duration=duration,
                                      sample_rate=sample_rate, effects=effects, deviations=deviations, noise=noise,
                                      low_speed=low_speed, fine_rate=fine_rate)  # fmt: skip
    folder = pathlib.Path(out_dir)
    folder.mkdir(parents=True, exist_ok=True)
    for r in records:
        cols = ["time", "current", "motor_velocity", "torque"] + (["output_position"] if r["mode"] == "free" else [])
        buf = io.StringIO()
        np.savetxt(buf, np.column_stack([r[c] for c in cols]), fmt="%.9g", delimiter=",", header=",".join(cols),
                   comments="")  # fmt: skip
        _atomic_write(folder / r["file"], buf.getvalue())
    st = STATIONS[drive]
    doc = {
        "name": name or f"bench-{drive}-seed{seed}",
        "drive": {"gear_ratio": st.gear_ratio, "torque_constant": st.torque_constant, "load_inertia": st.load_inertia},
        "experiments": [{"file": r["file"], "mode": r["mode"], "start_time": r["start_time"]} for r in records],
    }
    _atomic_write(folder / "truth.yaml", yaml.safe_dump(truth, sort_keys=False, allow_unicode=True))
    _atomic_write(folder / "dataset.yaml", yaml.safe_dump(doc, sort_keys=False, allow_unicode=True))
    return truth


# ----------------------------------------------------------------------------------------------
# Closed loop: a sampled controller on the bench's physics
# ----------------------------------------------------------------------------------------------


class Bench:
    """One drawn bench (drive, deviations, hidden effects), rebuilt from a seed or a `truth.yaml`,
    that a sampled controller can be run on (`closed_loop`).

    `Bench.from_truth(truth)` redraws the bench from the truth mapping's seed, drive, deviations,
    noise mode and sample rate, and checks that the drawn parameters are the recorded ones; hidden
    effects act with their recorded magnitudes (orders, phases, weights, τ, σ as recorded).
    Long only through `closed_loop`'s description of what the controller sees.
    """

    def __init__(self, *, drive="hd1", seed=0, deviations=None, effects=None, noise="per_sensor",
                 sample_rate=1000.0, low_speed="stick_slip", fine_rate=20000.0):  # fmt: skip
        self.dev = Deviations() if deviations is None else deviations
        self.bench = _draw_bench(drive, seed, self.dev, noise, sample_rate)
        self.seed, self.drive, self.low_speed = int(seed), drive, low_speed
        self.sample_rate = float(sample_rate)
        self.sub = max(1, int(round(fine_rate / sample_rate)))
        self.fine_rate = self.sub * self.sample_rate
        self.specs, targets, fixed = _effect_specs(effects or {}, self.bench, seed)
        if targets:
            raise ValueError(f"`Bench` needs physical magnitudes for its effects, got snr targets for {sorted(targets)}.")
        self.magnitudes = fixed

    @classmethod
    def from_truth(cls, truth: dict) -> Bench:
        """The bench that wrote `truth` (the mapping of a `truth.yaml` from `make_dataset`)."""
        if not str(truth.get("generator", "")).startswith("hdjax._bench"):
            raise ValueError("this truth.yaml was not written by hdjax._bench; no bench can be rebuilt from it.")
        fields = {f.name for f in dataclasses.fields(Deviations)}
        dev = Deviations(**{k: tuple(v) if isinstance(v, list) else v
                            for k, v in truth["deviations"].items() if k in fields})  # fmt: skip
        effects = {}
        for name, d in (truth.get("effects") or {}).items():
            e = {"magnitude": float(d["magnitude"])}
            for k_in, k_out in (("orders", "orders"), ("phases", "phases"), ("weights", "weights"), ("tau", "tau"),
                                ("sigma", "sigma")):  # fmt: skip
                if k_in in d:
                    e[k_out] = d[k_in]
            effects[name] = e
        b = cls(drive=str(truth["drive_name"]).lower(), seed=int(truth["seed"]), deviations=dev, effects=effects,
                noise=truth["sensors"]["noise"], sample_rate=float(truth["sensors"]["sample_rate"]),
                low_speed=truth["low_speed"]["law"], fine_rate=float(truth["integrator"]["fine_rate_hz"]))  # fmt: skip
        for k, v in truth["parameters"].items():
            if not math.isclose(b.bench["params"][k], float(v), rel_tol=1e-9, abs_tol=1e-15):
                raise ValueError(f"truth.yaml parameter {k} = {v} is not the one redrawn from its seed "
                                 f"({b.bench['params'][k]}); was it written by another version of hdjax._bench?")
        b.session_end = max((float(e["start_time"]) for e in truth.get("experiments", [])), default=0.0)
        return b

    @property
    def parameters(self) -> dict:
        """The drawn (true) parameters, SPEC keys."""
        return dict(self.bench["params"])

    @property
    def station(self) -> Station:
        return self.bench["station"]

    def closed_loop(self, law, reference, free, *, current_limit, seed=0, start_time=None, noise=True,
                    tare_samples=0) -> dict:  # fmt: skip
        """Run a sampled controller on the bench, B runs at once. (Long through this description
        of the sensed signals and the returned arrays; the body is the controller hook that
        `_integrate` calls at every sample.)

        At every sample instant t_k = k/sample_rate the controller sees the *sensed* signals:
        strain-gauge torque (true torque plus any torque-sensor ripple, through the drawn gauge
        low-pass, plus offset and white noise) and tachometer velocity (motor velocity plus tacho
        ripple, through its low-pass, plus offset and noise); time stamps are nominal (no jitter).
        It returns a current command, which is clipped to ±`current_limit` (the amplifier) and held
        (zero-order hold) as the set-point of the bench's current loop until t_{k+1}; the actual
        current drives the motor. Hidden effects act as in the recorded data.

        **Arguments:**

        - `law(k, r_k, y_k, w_k) -> u_k`: the controller, called once per sample with (B,) arrays of
          reference torque (N·m), measured torque (N·m) and measured motor velocity (rad/s); returns
          (B,) current commands (A). It keeps its own state.
        - `reference`: (K, B) reference torque at the sample instants (N·m), passed to `law`.
        - `free`: (B,) bool, True for a free output (load inertia), False for a locked one.
        - `current_limit`: amplifier limit (A).
        - `seed`: seed of the sensor noise of this run.
        - `start_time`: session time of the run (s; thermal drift), default the end of the session.
        - `noise`: False to switch the white sensor noise off (offsets and ripple stay).
        - `tare_samples`: if > 0, the strain gauge and the tachometer are zeroed at rest before the
          run, as an operator does: the mean of that many sensed samples with the drive at rest
          (offset, ripple at θm = 0, noise) is subtracted from what the controller sees.

        **Returns:** dict of (K, B) arrays at the sample instants: `time` (s), `reference`,
        `torque` (true transmitted torque), `measured_torque` (N·m), `motor_velocity` (true),
        `measured_velocity` (rad/s), `output_velocity` (rad/s), `command` (law output), `current_command`
        (after the limit), `current` (actual current at t_k, A).
        """
        reference = np.asarray(reference, float)
        if reference.ndim == 1:
            reference = reference[:, None]
        K, B = reference.shape
        free = np.broadcast_to(np.asarray(free, bool), (B,)).copy()
        sub, fr = self.sub, self.fine_rate
        ns = K * sub
        icmd = np.zeros((ns, B))
        sens, real = self.bench["sensors"], self.bench["realised"]
        mags = {e: np.full(B, float(self.magnitudes.get(e, 0.0))) for e in EFFECTS}
        t0 = getattr(self, "session_end", 0.0) if start_time is None else float(start_time)
        rng = _rng(seed, "closed-loop-noise")
        sT, sw = sens["torque_noise"], sens["tacho_noise"]
        offT = real["offset_factors"]["torque"] * sT if self.dev.offsets else 0.0
        offw = real["offset_factors"]["motor_velocity"] * sw if self.dev.offsets else 0.0
        nT = rng.standard_normal((K, B)) * sT if noise else np.zeros((K, B))
        nw = rng.standard_normal((K, B)) * sw if noise else np.zeros((K, B))
        tareT = tarew = 0.0
        if tare_samples > 0:
            rest = _rng(seed, "closed-loop-tare")
            rip = 0.0
            if self.magnitudes.get("torque_sensor_ripple"):
                rip = self.magnitudes["torque_sensor_ripple"] * _periodic(self.specs["torque_sensor_ripple"], np.zeros(1))[0][0]
            tareT = offT + rip + (rest.standard_normal((tare_samples, B)).mean(0) * sT if noise else 0.0)
            tarew = offw + (rest.standard_normal((tare_samples, B)).mean(0) * sw if noise else 0.0)
        filt = {}
        for key, fc in (("T", real["torque_filter_hz"]), ("w", real["tacho_filter_hz"])):
            if fc is None:
                filt[key] = None
            else:
                a = math.exp(-TWO_PI * fc / fr)
                filt[key] = ([0.5 * (1.0 - a), 0.5 * (1.0 - a)], [1.0, -a], np.zeros((1, B)))
        out = {k: np.zeros((K, B)) for k in ("torque", "measured_torque", "motor_velocity", "measured_velocity",
                                               "output_velocity", "command", "current_command", "current")}  # fmt: skip
        last = [-1]

        def sensed(key, x):
            f = filt[key]
            if f is None:
                return x[-1]
            y, zi = signal.lfilter(f[0], f[1], x, axis=0, zi=f[2])
            filt[key] = (f[0], f[1], zi)
            return y[-1]

        def hook(n, H):
            k = n // sub
            rows = slice(last[0] + 1, n + 1)
            last[0] = n
            T, wm, thm = H["T"][rows], H["wm"][rows], H["thm"][rows]
            if mags["torque_sensor_ripple"].any():
                T = T + mags["torque_sensor_ripple"][None, :] * _periodic(self.specs["torque_sensor_ripple"],
                                                                          thm.ravel())[0].reshape(thm.shape)  # fmt: skip
            tach = wm
            if self.dev.tacho_ripple:
                amp = self.dev.tacho_ripple * sT * np.tanh(np.abs(wm))
                tach = wm + amp * np.sin(self.dev.tacho_ripple_order * thm + real["tacho_ripple_phase"])
            y = sensed("T", T) + offT + nT[k]
            w = sensed("w", tach) + offw + nw[k]
            u = np.asarray(law(k, reference[k], y - tareT, w - tarew), float)
            i = np.clip(u, -current_limit, current_limit)
            icmd[n : n + sub] = i
            out["torque"][k], out["motor_velocity"][k] = H["T"][n], H["wm"][n]
            out["measured_torque"][k], out["measured_velocity"][k] = y - tareT, w - tarew
            out["command"][k], out["current_command"][k], out["current"][k] = u, i, H["ia"][n]
            out["output_velocity"][k] = (H["tho"][n] - H["tho"][max(n - sub, 0)]) * fr / sub

        _integrate(self.bench, icmd, free, np.full(B, t0), mags, self.specs, self.dev, fr, self.low_speed,
                   hook=hook, hook_every=sub)  # fmt: skip
        out["time"] = np.repeat((np.arange(K) / self.sample_rate)[:, None], B, axis=1)
        out["reference"] = reference.copy()
        return out


def pi_law(kp, ki, *, sample_period, feedforward=0.0):
    """A plain discrete PI torque law for `Bench.closed_loop`: u_k = ff·r_k + kp·e_k + I_k,
    I_{k+1} = I_k + ki·T_s·e_k, e_k = r_k − y_k (A, N·m); gains scalar or (B,)."""
    state = {"I": 0.0}

    def law(k, r, y, w):
        e = r - y
        u = feedforward * r + kp * e + state["I"]
        state["I"] = state["I"] + ki * sample_period * e
        return u

    return law
