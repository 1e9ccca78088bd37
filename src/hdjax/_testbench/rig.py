r"""A virtual test rig: the paper's two stations, their sensors and their experiment campaign.

Taghirad & Bélanger (section II) ran two harmonic-drive stations. Each has a DC motor driving the
wave generator, a strain-gauge bridge on the flexspline (transmitted torque), a tachometer (motor
velocity), an encoder on the load side (output angle, free motion only), the amplifier's current
monitor, and a positive lock for constrained (locked-output) tests. Per drive they ran 20
constrained and 30 free-motion experiments. This module reproduces that:

- `Station`: the truth (`Parameters`, Table I), the drive constants (`Drive`) and the sensor
  specifications; `station_hd1()` and `station_hd2()` are the paper's two setups.
- `campaign(station, seed=...)`: the current profiles (sine, chirp, square, multisine) of one
  campaign, each a `CurrentProfile` that unpacks as `(name, mode, current)`.
- `run_campaign(station, effects=..., seed=...)`: simulates the truth (`simulate_batch`, driven
  by the clean commanded current, tight tolerances, starting at rest) and adds the sensors:
  white strain-gauge noise on the torque, white tachometer noise on the motor velocity, encoder
  quantisation of the output angle, white noise on the recorded current. Each `Run` unpacks as
  `(file, mode, experiment, start_time)`.
- `write_campaign(folder, station, runs, name=..., effects=...)`: a dataset folder (SPEC §2) with
  a `truth.yaml` holding the true parameters, drive constants, sensor noise levels and the
  active effects in plain numbers.
- `hide_effect(name, magnitude, station=...)`: an `Effects` with one SPEC §4 effect at a given
  (or station-scaled default) magnitude, so that tests can hide it in the data.

The simulation is the package's own plant (`hdjax.simulate`), so the rig's truth *is* the model
plus any effects switched on; the sensors are the only thing added outside it.

Float64 is expected (call `jax.config.update("jax_enable_x64", True)`); this module does not switch
it on.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib
import typing
from typing import Any

import equinox as eqx
import numpy as np

from .._data.experiment import Experiment, make_experiment, stack_experiments
from .._data.write import write_dataset
from .._model.effects import EFFECT_NAMES, PERIODIC, PRESLIDING_DISTANCE, TERMS, THERMAL_TAU, Effects
from .._model.paper import PARAMETER_NAMES, PARAMETER_UNITS, Drive, Parameters
from .._plant.simulate import Simulator, simulate_batch

__all__ = [
    "CurrentProfile",
    "EFFECT_UNITS",
    "Run",
    "Station",
    "campaign",
    "describe_effects",
    "hide_effect",
    "reference_magnitude",
    "run_campaign",
    "station_hd1",
    "station_hd2",
    "truth_record",
    "write_campaign",
]

DEG = 180.0 / math.pi
RAMP_TIME = 0.05  # s, every profile ramps up from 0 A over this time (starts at rest)
EDGE_TIME = 0.005  # s, rise time of the smoothed square-wave edges
TWO_PI = 2.0 * math.pi


# ----------------------------------------------------------------------------------------------
# Stations
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class Station:
    """One test station: the true drive and its sensors (SI units).

    **Attributes:**

    - `name`: drive name ("HD1", "HD2").
    - `truth`: the true `Parameters` (Table I of the paper, SI units).
    - `drive`: the known `Drive` constants (gear ratio N, torque constant Km in N·m/A, load
      inertia Jload in kg·m²).
    - `rated_torque`: rated output torque of the harmonic drive (N·m); constrained experiments
      keep |T| below it.
    - `sample_rate`: data-acquisition rate (Hz), 1000 in the paper's setups.
    - `tacho_noise`: standard deviation of the white tachometer noise on the motor velocity
      (rad/s).
    - `torque_noise`: standard deviation of the white strain-gauge noise on the torque (N·m).
    - `encoder_counts`: load-encoder counts per output revolution; the recorded output angle is
      the true angle rounded to a multiple of `2π / encoder_counts` rad.
    - `current_noise`: standard deviation of the white noise on the *recorded* current (A); the
      truth simulation is driven by the clean commanded current.
    """

    name: str
    truth: Parameters
    drive: Drive
    rated_torque: float
    sample_rate: float = 1000.0
    tacho_noise: float = 0.03
    torque_noise: float = 0.12
    encoder_counts: int = 2**16
    current_noise: float = 0.01

    @property
    def encoder_step(self) -> float:
        """Output-angle resolution (rad): `2π / encoder_counts`."""
        return TWO_PI / self.encoder_counts

    @property
    def locked_gain(self) -> float:
        """Quasi-static locked-output torque per ampere, `N·Km` (N·m/A)."""
        return float(self.drive.gear_ratio) * float(self.drive.torque_constant)

    @property
    def rated_current(self) -> float:
        """Current (A) whose quasi-static locked torque `N·Km·i` equals the rated torque."""
        return self.rated_torque / self.locked_gain

    @property
    def locked_resonance(self) -> float:
        """Resonance of the locked drive, `sqrt(K1 / (N² Jeff)) / 2π` (Hz): 12.7 Hz for HD1, 7.7 Hz
        for HD2."""
        N = float(self.drive.gear_ratio)
        return math.sqrt(float(self.truth.K1) / (N**2 * float(self.truth.Jeff))) / TWO_PI

    @property
    def total_inertia(self) -> float:
        """Free-motion inertia seen by the motor, `Jeff + Jload/N²` (kg·m²)."""
        N = float(self.drive.gear_ratio)
        return float(self.truth.Jeff) + float(self.drive.load_inertia) / N**2

    def friction_levels(self, direction: int) -> tuple[float, float]:
        """Friction magnitude (N·m) just off zero velocity and at the end of the Stribeck range,
        `(|Ts + Tss1|·sign, Ts)`, in `direction` +1 or −1 (the Stribeck window of eq. 9)."""
        p = self.truth
        if direction > 0:
            return float(p.Tsp + p.Tssp1), float(p.Tsp)
        return float(p.Tsn + p.Tssn1), float(p.Tsn)

    def sensors(self) -> dict[str, float]:
        """The sensor specification as plain numbers (for `truth.yaml`)."""
        return {
            "sample_rate": float(self.sample_rate),
            "tacho_noise": float(self.tacho_noise),
            "torque_noise": float(self.torque_noise),
            "encoder_counts": int(self.encoder_counts),
            "encoder_step": float(self.encoder_step),
            "current_noise": float(self.current_noise),
        }


def station_hd1() -> Station:
    """The paper's first station: Electro-Craft 586-501-113 brushed DC motor (Km = 0.0543 N·m/A),
    HD Systems RHS-20-100 (N = 100, rated 40 N·m), load inertia 0.2 kg·m²; Table I, HD1.

    Sensors: strain-gauge noise 0.12 N·m (0.3 % of rated torque), tachometer noise 0.03 rad/s,
    2¹⁶-count load encoder (9.6e-5 rad), current-monitor noise 0.01 A (0.15 % of the 6 A peak).
    """
    truth = Parameters(
        alpha=0.5, K1=6340.0, Tst=57.2, Jeff=1.0e-4, Tvp=3.7e-4, Tvn=3.5e-4, Tsp=4.6e-2, Tsn=4.4e-2,
        Tssp1=-0.0076, Tssn1=-0.0203, Tss2=0.1,
    )  # fmt: skip
    drive = Drive(gear_ratio=100.0, torque_constant=0.0543, load_inertia=0.2)
    return Station(
        name="HD1", truth=truth, drive=drive, rated_torque=40.0, sample_rate=1000.0, tacho_noise=0.03,
        torque_noise=0.12, encoder_counts=2**16, current_noise=0.01,
    )  # fmt: skip


def station_hd2() -> Station:
    """The paper's second station: Kollmorgen RBE-01503 brushless motor (Km = 0.1815 N·m/A),
    HD Systems CFS (N = 160, rated peak 178 N·m), load inertia 0.5 kg·m²; Table I, HD2.

    Table I's K1 = 104.2 and Tst = 7.96 are read as per-degree values (SPEC §1):
    K1 = 104.2·(180/π) = 5970 N·m/rad, Tst = 7.96·(180/π)^½ = 60.2 N·m/(rad/s)^½.

    Sensors: strain-gauge noise 0.5 N·m (0.28 % of rated torque), tachometer noise 0.02 rad/s,
    2¹⁶-count load encoder (9.6e-5 rad), current-monitor noise 0.005 A (0.1 % of the 5 A peak).
    """
    truth = Parameters(
        alpha=0.5, K1=104.2 * DEG, Tst=7.96 * DEG**0.5, Jeff=1.0e-4, Tvp=1.8e-3, Tvn=2.1e-3, Tsp=7.5e-2,
        Tsn=3.3e-2, Tssp1=-0.0487, Tssn1=-0.0450, Tss2=0.1,
    )  # fmt: skip
    drive = Drive(gear_ratio=160.0, torque_constant=0.1815, load_inertia=0.5)
    return Station(
        name="HD2", truth=truth, drive=drive, rated_torque=178.0, sample_rate=1000.0, tacho_noise=0.02,
        torque_noise=0.5, encoder_counts=2**16, current_noise=0.005,
    )  # fmt: skip


# ----------------------------------------------------------------------------------------------
# Current profiles
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class CurrentProfile:
    """One commanded motor current of the campaign. Unpacks as `(name, mode, current)`.

    **Attributes:**

    - `name`: experiment name, also the CSV stem, e.g. `locked_03_chirp`, `free_21_slow_sine`.
    - `mode`: "constrained" or "free".
    - `current`: commanded current (A) at the sample instants `time`; it ramps up from 0 A over
      the first 50 ms, so every experiment starts at rest.
    - `time`: sample instants (s), from 0 at the station's sample rate.
    - `kind`: "sine", "chirp", "square" or "multisine".
    - `regime`: "locked", "low_velocity" (Stribeck range), "plateau" (slow square, viscous range) or
      "high_velocity" (two-directional, tens to hundreds of rad/s).
    - `info`: the shape's parameters in plain numbers (amplitude A, frequencies Hz, offset A, ...).
    """

    name: str
    mode: str
    current: np.ndarray
    time: np.ndarray
    kind: str
    regime: str
    info: dict

    def __iter__(self):
        return iter((self.name, self.mode, self.current))

    def scaled(self, factor: float) -> CurrentProfile:
        """A copy with the current (and the amplitude and offset in `info`) multiplied by `factor`."""
        info = dict(self.info)
        for key in ("amplitude", "offset"):
            if key in info:
                info[key] = float(info[key]) * factor
        info["scale"] = float(info.get("scale", 1.0)) * factor
        return dataclasses.replace(self, current=self.current * factor, info=info)


def _ramp(t: np.ndarray) -> np.ndarray:
    """Raised-cosine ramp from 0 to 1 over `RAMP_TIME`."""
    x = np.clip(t / RAMP_TIME, 0.0, 1.0)
    return 0.5 * (1.0 - np.cos(np.pi * x))


def _square(t: np.ndarray, f: float, phase: float) -> np.ndarray:
    """Unit square wave `sign(sin(2πft + φ))` with tanh edges rising over about `EDGE_TIME`."""
    w = EDGE_TIME * TWO_PI * f / 4.0
    return np.tanh(np.sin(TWO_PI * f * t + phase) / w) / np.tanh(1.0 / w)


def _chirp(t: np.ndarray, f0: float, f1: float, duration: float, phase: float) -> np.ndarray:
    """Unit linear chirp `cos(2π(f0 t + (f1 − f0) t² / 2T) + φ)`."""
    return np.cos(TWO_PI * (f0 * t + 0.5 * (f1 - f0) * t**2 / duration) + phase)


def _multisine(t: np.ndarray, freqs: np.ndarray, weights: np.ndarray, phases: np.ndarray) -> np.ndarray:
    """Sum of cosines normalised to unit peak."""
    s = np.sum(weights[:, None] * np.cos(TWO_PI * freqs[:, None] * t[None, :] + phases[:, None]), axis=0)
    return s / np.max(np.abs(s))


def _two_sided(u: np.ndarray, min_fraction: float = 0.25) -> bool:
    """True when `u` spends at least `min_fraction` of the time beyond ±20 % of its peak on each side."""
    peak = np.max(np.abs(u))
    return bool(np.mean(u > 0.2 * peak) >= min_fraction and np.mean(u < -0.2 * peak) >= min_fraction)


def _frictionless_velocity(shape: np.ndarray, dt: float) -> np.ndarray:
    """Integral of the ramped unit shape (A·s per A): the free velocity is `Km·A/J` times this."""
    return np.cumsum(shape) * dt


def _log_uniform(rng, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _spread(rng, lo: float, hi: float, n: int) -> np.ndarray:
    """`n` log-spaced values in [lo, hi], jittered within their stratum and shuffled."""
    if n <= 0:
        return np.zeros(0)
    edges = np.geomspace(lo, hi, n + 1)
    vals = np.exp(rng.uniform(np.log(edges[:-1]), np.log(edges[1:])))
    return rng.permutation(vals)


def _allocate(n: int, weights: dict[str, int]) -> dict[str, int]:
    """Split `n` experiments over groups in proportion to `weights` (largest remainders)."""
    total = sum(weights.values())
    raw = {k: n * w / total for k, w in weights.items()}
    out = {k: int(math.floor(v)) for k, v in raw.items()}
    for k in sorted(raw, key=lambda k: raw[k] - out[k], reverse=True)[: n - sum(out.values())]:
        out[k] += 1
    return out


def _kinds(n: int, kinds: tuple[str, ...]) -> list[str]:
    return [kinds[i % len(kinds)] for i in range(n)]


def campaign(
    station: Station,
    *,
    seed: int,
    n_constrained: int = 20,
    n_free: int = 30,
    duration: float = 1.5,
) -> list[CurrentProfile]:
    r"""The current profiles of one campaign on `station` (the paper: 20 constrained + 30 free).

    **Arguments:**

    - `station`: the `Station`; amplitudes are scaled to its drive and its friction levels.
    - `seed`: fixes the random spread of amplitudes, frequencies and phases.
    - `n_constrained`, `n_free`: numbers of constrained and free-motion experiments.
    - `duration`: length of every experiment (s); 1–2 s keeps a dataset at a few MB.

    **Returns:** a list of `CurrentProfile`, constrained first, each unpacking as
    `(name, mode, current)`.

    Every current ramps up from 0 A over the first 50 ms (raised cosine), so each experiment starts
    at rest; square waves have edges rising over about 5 ms.

    *Constrained* (output locked): sine, chirp, square and multisine currents; peak currents
    log-spread from 2× the Coulomb-friction current $i_c$ (the motor must overcome friction to
    wind the flexspline) up to a quasi-static locked torque $N(K_m i - T_s)$ of 85 % of the rated
    torque for sines (the largest at the lowest frequencies, and kept below the undamped
    resonance gain $1/(1 - (f/f_{res})^2)$), 55 % for chirps and squares (which pass or ring the
    locked resonance) and 60 % for multisines; half of them carry an offset. `run_campaign`
    rescales any test whose true torque still exceeds the rating. Motor velocities stay low
    (HD1: up to ~20 rad/s, mostly near zero), so these also probe the low-velocity friction.

    *Free motion*, three regimes (proportions 8 : 6 : 16 of 30):

    - `low_velocity`: a bias current inside the Stribeck window of eq. 9 (where Coulomb friction
      has not yet reached $T_s$, $K_m i$ between $T_s + T_{ss1}$ and $T_s$), plus a slow sine,
      square or multisine swing inside the window; the velocity follows the rising friction curve
      at 0.02–0.2 rad/s (median |ωm| well below 0.4 rad/s). Alternating directions; every fourth
      one reverses, using each direction's window in turn.
    - `plateau`: slow square waves (1–2 periods) at 1.3–2.6× the Coulomb current: velocity
      plateaus in both directions where viscous friction balances the drive (tens of rad/s).
    - `high_velocity`: zero-mean sine, square, chirp and multisine currents whose frictionless
      velocity peaks at 15–180 rad/s in both directions (rejection-sampled phases so that the
      velocity spends long stretches on each side), amplitudes at least 2× the Coulomb current.
    """
    if n_constrained < 0 or n_free < 0 or n_constrained + n_free == 0:
        raise ValueError(f"`campaign`: need at least one experiment, got {n_constrained=} and {n_free=}.")
    if not 0.3 <= duration <= 60.0:
        raise ValueError(f"`campaign`: duration must be between 0.3 and 60 s, got {duration}.")
    rng = np.random.default_rng([int(seed), 0x5EED])
    fs = float(station.sample_rate)
    dt = 1.0 / fs
    t = np.arange(int(round(duration * fs))) * dt
    ramp = _ramp(t)
    Km = float(station.drive.torque_constant)
    J = station.total_inertia
    i_coulomb = max(float(station.truth.Tsp), float(station.truth.Tsn)) / Km
    i_rated = station.rated_current
    profiles = _locked_profiles(rng, station, t, ramp, n_constrained, duration, i_coulomb, i_rated)

    # free motion: three regimes, drawn in this order, then interleaved through the session
    groups = _allocate(n_free, {"low_velocity": 8, "plateau": 6, "high_velocity": 16})
    if n_free >= 16:  # the minimum counts for a full campaign
        groups["low_velocity"] = max(groups["low_velocity"], 6)
        groups["high_velocity"] = max(groups["high_velocity"], 10)
        groups["plateau"] = n_free - groups["low_velocity"] - groups["high_velocity"]

    free: list[tuple[str, str, np.ndarray, dict]] = [
        *_low_velocity_currents(rng, station, t, ramp, groups["low_velocity"], Km),
        *_plateau_currents(rng, t, ramp, groups["plateau"], duration, i_coulomb),
        *_high_velocity_currents(rng, t, ramp, groups["high_velocity"], duration, dt, Km, J, i_coulomb),
    ]
    order = rng.permutation(len(free))  # interleave the regimes through the session
    for j, k in enumerate(order):
        kind, regime, i, info = free[k]
        profiles.append(CurrentProfile(f"free_{j + 1:02d}_{kind}", "free", i, t, kind.removeprefix("slow_"),
                                       regime, _plain(info)))  # fmt: skip
    return profiles


def _locked_profiles(rng, station: Station, t: np.ndarray, ramp: np.ndarray, n_constrained: int, duration: float,
                     i_coulomb: float, i_rated: float) -> list[CurrentProfile]:
    """`campaign`'s constrained (output-locked) profiles: sine, chirp, square and multisine currents
    (see `campaign`); draws from `rng` in a fixed order."""
    profiles: list[CurrentProfile] = []
    kinds = _kinds(n_constrained, ("sine", "chirp", "square", "multisine"))
    f_res = station.locked_resonance
    # peak currents per kind, log-spread from 2× the Coulomb current up to a quasi-static locked
    # torque N·(Km·i − Tc) of 85 % (sines) or 55–60 % (chirps, squares, multisines) of rated
    top = {"sine": 0.85, "chirp": 0.55, "square": 0.55, "multisine": 0.6}
    amps_by_kind = {
        k: list(_spread(rng, 2.0 * i_coulomb, top[k] * i_rated + i_coulomb, kinds.count(k))) for k in top
    }
    # sines: the largest amplitudes at the lowest frequencies (as on a real bench)
    f_sines = sorted(_log_uniform(rng, 0.5, min(8.0, 0.7 * f_res)) for _ in range(kinds.count("sine")))
    amps_by_kind["sine"] = sorted(amps_by_kind["sine"], reverse=True)
    if amps_by_kind["sine"]:  # one test always goes near the rating
        amps_by_kind["sine"][0] = top["sine"] * i_rated + i_coulomb
    for j, kind in enumerate(kinds):
        amp = float(amps_by_kind[kind].pop(0))
        info: dict[str, Any] = {}
        if kind == "sine":
            f = f_sines.pop(0)
            ph = rng.uniform(0, TWO_PI)
            shape = np.sin(TWO_PI * f * t + ph)
            # undamped resonance gain 1/(1 - (f/f_res)^2) kept below rated torque
            amp = min(amp, 0.9 * i_rated * (1.0 - (f / f_res) ** 2) + i_coulomb)
            info.update(frequency=f, phase=ph)
        elif kind == "chirp":  # passes the locked resonance
            f0, f1 = _log_uniform(rng, 0.3, 1.0), _log_uniform(rng, 5.0, 12.0)
            ph = rng.uniform(0, TWO_PI)
            shape = _chirp(t, f0, f1, duration, ph)
            info.update(f0=f0, f1=f1, phase=ph)
        elif kind == "square":  # the edges ring the locked resonance (up to ~45 % overshoot)
            f = _log_uniform(rng, 0.7, 4.0)
            ph = rng.uniform(0, TWO_PI)
            shape = _square(t, f, ph)
            info.update(frequency=f, phase=ph)
        else:
            freqs = np.geomspace(_log_uniform(rng, 0.5, 1.0), _log_uniform(rng, 6.0, 10.0), 5)
            weights = rng.uniform(0.5, 1.0, 5)
            phases = rng.uniform(0, TWO_PI, 5)
            shape = _multisine(t, freqs, weights, phases)
            info.update(frequencies=freqs.tolist(), weights=weights.tolist(), phases=phases.tolist())
        offset = 0.0
        if (j + j // 4) % 2 == 1:  # half of them (of every kind) with an offset, keeping the peak at `amp`
            offset = float(rng.uniform(-0.3, 0.3)) * amp
            amp = amp - abs(offset)
        i = ramp * (offset + amp * shape)
        info.update(amplitude=float(amp), offset=float(offset))
        profiles.append(
            CurrentProfile(f"locked_{j + 1:02d}_{kind}", "constrained", i, t, kind, "locked", _plain(info))
        )

    return profiles


def _low_velocity_currents(rng, station: Station, t: np.ndarray, ramp: np.ndarray, n: int, Km: float) -> list[tuple]:
    """`campaign`'s free-motion `low_velocity` currents (the Stribeck window, see `campaign`), as
    (kind, regime, current, info)."""
    free = []
    for j in range(n):
        kind = ("sine", "square", "multisine")[j % 3]
        direction = 1 if j % 2 == 0 else -1
        reverse = j % 4 == 3
        f = _log_uniform(rng, 0.7, 2.5)
        ph = rng.uniform(0, TWO_PI)
        if kind == "sine":
            swing = np.sin(TWO_PI * f * t + ph)
        elif kind == "square":
            swing = _square(t, f, ph)
        else:
            freqs = np.geomspace(f, 4.0 * f, 3)
            swing = _multisine(t, freqs, rng.uniform(0.5, 1.0, 3), rng.uniform(0, TWO_PI, 3))
        info = {"direction": 0 if reverse else direction, "reverses": reverse}
        if reverse:
            # slow zero-mean current that reaches deep into each direction's Stribeck window
            depth = rng.uniform(0.75, 0.9)
            f = _log_uniform(rng, 0.7, 1.5)
            s = np.tanh(3.0 * np.sin(TWO_PI * f * t)) / np.tanh(3.0)  # soft square: little time stuck at 0
            lo_p, hi_p = station.friction_levels(+1)
            lo_n, hi_n = station.friction_levels(-1)
            up = max(lo_p, 0.0) + depth * (hi_p - max(lo_p, 0.0))
            dn = max(lo_n, 0.0) + depth * (hi_n - max(lo_n, 0.0))
            i = ramp * np.where(s >= 0, s * up, s * dn) / Km
            kind = "sine"
            info.update(frequency=f, window_depth=depth)
        else:
            centre = rng.uniform(0.45, 0.6)
            half = rng.uniform(0.25, 0.35)
            x = centre + half * swing  # position inside the window, 0 (breakaway) .. 1 (Coulomb)
            x = np.clip(x, 0.05, 0.95)
            lo_d, hi_d = station.friction_levels(direction)
            i = ramp * direction * (lo_d + x * (hi_d - lo_d)) / Km
            info.update(frequency=f, window_centre=centre, window_swing=half)
        free.append(("slow_" + kind, "low_velocity", i, info))

    return free


def _plateau_currents(rng, t: np.ndarray, ramp: np.ndarray, n: int, duration: float, i_coulomb: float) -> list[tuple]:
    """`campaign`'s free-motion `plateau` currents: slow squares in the viscous range."""
    free = []
    for j in range(n):
        periods = 1 if j % 2 == 0 else 2
        f = periods / duration
        level = rng.uniform(1.3, 2.6)
        sign = 1 if j % 4 < 2 else -1
        shape = _square(t, f, 0.0 if sign > 0 else math.pi)
        i = ramp * level * i_coulomb * shape
        free.append(("square", "plateau", i, {"frequency": f, "amplitude": level * i_coulomb}))

    return free


def _high_velocity_currents(rng, t: np.ndarray, ramp: np.ndarray, n: int, duration: float, dt: float, Km: float, J: float,
                            i_coulomb: float) -> list[tuple]:
    """`campaign`'s free-motion `high_velocity` currents: two-directional, with rejection-sampled
    phases (see `campaign`)."""
    free = []
    kinds = _kinds(n, ("sine", "square", "chirp", "multisine"))
    vpeaks = _spread(rng, 15.0, 180.0, len(kinds))
    for kind, vpk in zip(kinds, vpeaks):
        for _ in range(200):
            info = {}
            if kind == "sine":
                f = _log_uniform(rng, 0.8, 4.0)
                ph = rng.uniform(0, TWO_PI)
                shape = np.sin(TWO_PI * f * t + ph)
                info.update(frequency=f, phase=ph)
            elif kind == "square":
                f = _log_uniform(rng, 0.8, 3.0)
                ph = rng.uniform(0, TWO_PI)
                shape = _square(t, f, ph)
                info.update(frequency=f, phase=ph)
            elif kind == "chirp":
                f0, f1 = _log_uniform(rng, 0.8, 1.5), _log_uniform(rng, 3.0, 8.0)
                ph = rng.uniform(0, TWO_PI)
                shape = _chirp(t, f0, f1, duration, ph)
                info.update(f0=f0, f1=f1, phase=ph)
            else:
                freqs = np.geomspace(_log_uniform(rng, 0.8, 1.2), _log_uniform(rng, 5.0, 8.0), 4)
                weights = rng.uniform(0.5, 1.0, 4)
                phases = rng.uniform(0, TWO_PI, 4)
                shape = _multisine(t, freqs, weights, phases)
                info.update(frequencies=freqs.tolist(), weights=weights.tolist(), phases=phases.tolist())
            u = _frictionless_velocity(ramp * shape, dt)
            if _two_sided(u):
                break
        # friction margin; multisines spend more time at low current, so they get more
        margin = 2.0 if kind == "multisine" else 1.0
        # u, info and shape are bound: the 200-try loop above always runs
        amp = max(vpk * J / (Km * np.max(np.abs(u))) + margin * i_coulomb, (1.0 + margin) * i_coulomb)  # pyright: ignore[reportPossiblyUnboundVariable]
        info.update(amplitude=float(amp), target_peak_velocity=float(vpk))  # pyright: ignore[reportPossiblyUnboundVariable]
        free.append((kind, "high_velocity", ramp * amp * shape, info))  # pyright: ignore[reportPossiblyUnboundVariable]

    return free


def _plain(x: Any) -> Any:
    """Plain Python numbers, lists and dicts (for YAML)."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x)
    if hasattr(x, "shape"):
        a = np.asarray(x)
        return a.item() if a.ndim == 0 else a.tolist()
    return x


# ----------------------------------------------------------------------------------------------
# Running the campaign
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class Run:
    """One recorded experiment. Unpacks as `(file, mode, experiment, start_time)`.

    **Attributes:**

    - `file`: CSV name (`<profile name>.csv`).
    - `mode`: "constrained" or "free".
    - `experiment`: the *recorded* `Experiment` (noisy current, torque and motor velocity; quantised
      output angle for free motion; no output angle for constrained; no motor angle).
    - `start_time`: s since the session began.
    - `clean`: the noise-free truth at the sample instants, numpy arrays: `time`, `current`
      (commanded), `torque` (what a perfect strain gauge would read, ripple included),
      `motor_velocity`, `motor_position`, `output_position`, `output_velocity`, `torsion`.
    - `profile`: the `CurrentProfile` that drove it.
    """

    file: str
    mode: str
    experiment: Experiment
    start_time: float
    clean: dict[str, np.ndarray]
    profile: CurrentProfile

    def __iter__(self):
        return iter((self.file, self.mode, self.experiment, self.start_time))


def run_campaign(
    station: Station,
    *,
    effects: Effects = Effects(),
    seed: int = 0,
    profiles: list[CurrentProfile] | None = None,
    spacing: float = 30.0,
    simulator: Simulator | None = None,
    torque_limit: bool = True,
    **campaign_options,
) -> list[Run]:
    """Run a campaign on the virtual rig: simulate the truth, then record it through the sensors.

    **Arguments:**

    - `station`: the `Station` (truth and sensors).
    - `effects`: model extensions present in the "real" drive (`hdjax.Effects`, SPEC §4); default
      none, i.e. exactly the paper's model.
    - `seed`: seeds the sensor noise (`numpy.random.default_rng(seed)`) and, when `profiles` is
      not given, the campaign (`campaign(station, seed=seed, ...)`).
    - `profiles`: the current profiles to run (default: `campaign(...)`).
    - `spacing`: time between the starts of successive experiments (s); experiment `k` starts at
      `k·spacing` s into the session, which the `thermal_drift` effect sees.
    - `simulator`: numerical options; default `Simulator(rtol=1e-8, atol=1e-10)`.
    - `torque_limit`: if a constrained experiment's true torque exceeds the station's rated torque,
      scale its current down to reach 90 % of it and repeat the test (as an operator would); the
      `Run.profile` then holds the scaled current (`info["scale"]`). `campaign`'s amplitudes are
      chosen so that this is rare.
    - `**campaign_options`: `n_constrained`, `n_free`, `duration` for `campaign`.

    **Returns:** a list of `Run`, in campaign order.

    **Raises:** `RuntimeError` if a truth simulation fails (step budget or solver failure).

    The truth is simulated with `simulate_batch` (one call per mode), driven by the clean
    commanded current and starting at rest: zero torsion, velocity and output angle, with the
    wave generator at its home angle θm = 0 (the rig homes it before each test, so periodic
    effects keep their phase from one experiment to the next). The record
    then gets: torque + N(0, `torque_noise`²), motor velocity + N(0, `tacho_noise`²), output angle
    rounded to the encoder step (free motion only), current + N(0, `current_noise`²).
    """
    if profiles is None:
        profiles = campaign(station, seed=seed, **campaign_options)
    elif campaign_options:
        raise ValueError(f"`run_campaign`: {sorted(campaign_options)} are ignored when `profiles` is given.")
    if simulator is None:
        simulator = Simulator(rtol=1e-8, atol=1e-10)
    profiles = list(profiles)
    starts = [k * float(spacing) for k in range(len(profiles))]
    # every profile is constrained or free, so the loop below fills every slot
    clean: list[dict[str, np.ndarray]] = [None] * len(profiles)  # pyright: ignore[reportAssignmentType]
    for mode in ("constrained", "free"):
        idx = [k for k, pr in enumerate(profiles) if pr.mode == mode]
        if not idx:
            continue
        for attempt in range(5):
            traj = _simulate_profiles(station, [profiles[k] for k in idx], [starts[k] for k in idx], effects, simulator)
            peaks = [np.max(np.abs(traj["torque"][j])) for j in range(len(idx))]
            over = [j for j, pk in enumerate(peaks) if pk > station.rated_torque]
            if mode != "constrained" or not torque_limit or not over:
                break
            if attempt == 4:
                raise RuntimeError(
                    f"`run_campaign` ({station.name}): {[profiles[idx[j]].name for j in over]} still exceed the "
                    f"rated torque {station.rated_torque} N·m after rescaling; lower their currents."
                )
            for j in over:  # the experimenter turns the amplitude down and repeats the test
                profiles[idx[j]] = profiles[idx[j]].scaled(0.9 * station.rated_torque / peaks[j])
        for j, k in enumerate(idx):
            clean[k] = {f: v[j] for f, v in traj.items()}  # pyright: ignore[reportPossiblyUnboundVariable]  the 5-try loop always runs
            clean[k]["current"] = np.asarray(profiles[k].current)

    rng = np.random.default_rng(seed)
    q = station.encoder_step
    runs = []
    for k, pr in enumerate(profiles):
        c = clean[k]
        n = len(c["time"])
        current = c["current"] + station.current_noise * rng.standard_normal(n)
        velocity = c["motor_velocity"] + station.tacho_noise * rng.standard_normal(n)
        torque = c["torque"] + station.torque_noise * rng.standard_normal(n)
        output = np.round(c["output_position"] / q) * q + 0.0 if pr.mode == "free" else None  # + 0.0: no -0
        exp = make_experiment(
            c["time"], current, torque, velocity, mode=pr.mode, output_position=output, start_time=starts[k]
        )
        runs.append(Run(f"{pr.name}.csv", pr.mode, exp, starts[k], c, pr))
    return runs


@eqx.filter_jit
def _simulate_jit(p, drive, batch, effects, simulator):
    return simulate_batch(p, drive, batch, effects=effects, simulator=simulator)


def _simulate_profiles(station: Station, profiles, starts, effects: Effects, simulator: Simulator) -> dict:
    """Truth of one mode's profiles in one batched call, from rest; per-experiment numpy arrays."""
    mode = profiles[0].mode
    drivers = []
    for pr, start in zip(profiles, starts):
        z = np.zeros_like(pr.time)
        drivers.append(make_experiment(pr.time, pr.current, z, z, mode=mode, output_position=z, start_time=start))
    traj = _simulate_jit(station.truth, station.drive, stack_experiments(drivers), effects, simulator)
    ok = np.asarray(traj.success)
    if not np.all(ok):
        bad = [profiles[j].name for j in np.flatnonzero(~ok)]
        raise RuntimeError(
            f"`run_campaign` ({station.name}): the truth simulation failed for {bad} "
            f"(steps {np.asarray(traj.num_steps)[~ok].tolist()}); raise `simulator.max_steps` or loosen "
            "the tolerances."
        )
    out: dict[str, list] = {"time": [np.asarray(pr.time) for pr in profiles]}
    for f in ("torque", "motor_velocity", "motor_position", "output_position", "output_velocity", "torsion"):
        v = np.asarray(getattr(traj, f))
        out[f] = [v[j, : len(pr.time)] for j, pr in enumerate(profiles)]
    for j, pr in enumerate(profiles):
        if not all(np.all(np.isfinite(out[f][j])) for f in out):
            raise RuntimeError(f"`run_campaign` ({station.name}): non-finite truth in {pr.name}.")
    return out


# ----------------------------------------------------------------------------------------------
# Effects to hide
# ----------------------------------------------------------------------------------------------

#: Unit of `hide_effect`'s `magnitude` for each effect (SPEC §4).
EFFECT_UNITS: dict[str, str] = {
    "kinematic_error": "rad (output-side transmission error amplitude a_k)",
    "torque_sensor_ripple": "N·m (strain-gauge ripple amplitude b_k)",
    "cogging": "N·m (motor-side torque ripple amplitude c_k)",
    "position_dependent_friction": "- (relative Coulomb modulation ε_k)",
    "nonlinear_stiffness": "N·m/rad³ (cubic stiffness K3)",
    "lost_motion": "rad (dead-band half-width of the torsion)",
    "load_dependent_friction": "- (mu: Coulomb += mu·|T|/N)",
    "thermal_drift": "- (beta: viscous × (1 + beta·exp(−t/tau)))",
    "input_delay": "s (current-loop delay)",
    "rate_independent_hysteresis": "N·m (Dahl hysteresis torque Th)",
    "presliding_friction": f"- (fraction of Coulomb and Stribeck friction on a Dahl state, δ = {PRESLIDING_DISTANCE:g} rad)",
}


def reference_magnitude(name: str, station: Station) -> float:
    """A physically plausible magnitude of effect `name` on `station`, in `EFFECT_UNITS[name]`,
    large enough to stand out of the sensor noise of a campaign:

    | effect | reference magnitude | HD1 | HD2 |
    |---|---|---|---|
    | `kinematic_error` | 3·torque_noise / K1 (≈ 3σ of torque in a locked test) | 5.7e-5 rad | 2.5e-4 rad |
    | `torque_sensor_ripple` | 3·torque_noise | 0.36 N·m | 1.5 N·m |
    | `cogging` | 0.25·max(Tsp, Tsn) | 0.0115 N·m | 0.019 N·m |
    | `position_dependent_friction` | 0.2 | 0.2 | 0.2 |
    | `nonlinear_stiffness` | 0.2·K1/δr², δr = rated torque / K1 (+20 % torque at rated torsion) | 3.2e7 | 2.2e5 |
    | `lost_motion` | 0.05·δr | 3.2e-4 rad | 1.5e-3 rad |
    | `load_dependent_friction` | mu = 0.05 | 0.05 | 0.05 |
    | `thermal_drift` | beta = 0.5 (τ = 600 s) | 0.5 | 0.5 |
    | `input_delay` | 2 ms | 2e-3 s | 2e-3 s |
    | `rate_independent_hysteresis` | Th = 0.03·rated torque (σ = 0.02·δr) | 1.2 N·m | 5.3 N·m |
    """
    p = station.truth
    K1 = float(p.K1)
    dr = station.rated_torque / K1
    table = {
        "kinematic_error": 3.0 * station.torque_noise / K1,
        "torque_sensor_ripple": 3.0 * station.torque_noise,
        "cogging": 0.25 * max(float(p.Tsp), float(p.Tsn)),
        "position_dependent_friction": 0.2,
        "nonlinear_stiffness": 0.2 * K1 / dr**2,
        "lost_motion": 0.05 * dr,
        "load_dependent_friction": 0.05,
        "thermal_drift": 0.5,
        "input_delay": 2e-3,
        "rate_independent_hysteresis": 0.03 * station.rated_torque,
        "presliding_friction": 1.0,
    }
    if name not in table:
        raise ValueError(
            f"`reference_magnitude`: unknown or unsupported effect {name!r}; supported: {sorted(table)} "
            f"(SPEC §4 names implemented by `hdjax.Effects`: {list(EFFECT_NAMES)})."
        )
    return float(table[name])


def hide_effect(
    name: str,
    magnitude: float | None,
    *,
    order: int = 2,
    phase: float = 0.3,
    station: Station,
    tau: float | None = None,
    sigma: float | None = None,
    base: Effects = Effects(),
) -> Effects:
    """`Effects` with one SPEC §4 effect switched on at `magnitude`, to hide in a campaign.

    **Arguments:**

    - `name`: an effect of `hdjax.EFFECT_NAMES`.
    - `magnitude`: in the effect's own unit (`EFFECT_UNITS[name]`): periodic effects take the
      amplitude of `a·sin(k·θm + φ)` (θm the wave-generator angle); `nonlinear_stiffness` K3
      (N·m/rad³), `lost_motion` the dead-band half-width (rad), `load_dependent_friction` mu,
      `thermal_drift` beta, `input_delay` the delay (s), `rate_independent_hysteresis` Th (N·m),
      `presliding_friction` the fraction of Coulomb and Stribeck friction on its Dahl state (-).
      `None` takes `reference_magnitude(name, station)`, scaled to the station.
    - `order`, `phase`: order k (cycles per wave-generator turn) and phase φ (rad) of a periodic
      effect.
    - `station`: the `Station` (for the default magnitude and the secondary parameters).
    - `tau`: `thermal_drift` time constant (s); default 600 s.
    - `sigma`: `rate_independent_hysteresis` Dahl length (rad of torsion); default 2 % of the
      torsion at rated torque.
    - `base`: effects to add to (default none).

    **Returns:** an `Effects`.
    """
    if name not in EFFECT_NAMES:
        raise ValueError(f"`hide_effect`: unknown effect {name!r}; known: {list(EFFECT_NAMES)}.")
    a = reference_magnitude(name, station) if magnitude is None else float(magnitude)
    if name in PERIODIC:
        return base.with_periodic(name, int(order), a, float(phase))
    values = {typing.cast(str, TERMS[name].magnitude_field): a}
    if name == "thermal_drift":
        values["tau"] = THERMAL_TAU if tau is None else float(tau)
    if name == "rate_independent_hysteresis":
        values["sigma"] = 0.02 * station.rated_torque / float(station.truth.K1) if sigma is None else float(sigma)
    return base.with_values(name, **values)


def describe_effects(effects: Effects) -> dict[str, dict]:
    """The active effects in plain numbers (for `truth.yaml`).

    Periodic effects: `orders`, `amplitudes`, `phases` in the SPEC's `a_k·sin(k·θm + φ_k)` form (θm
    the wave-generator angle, rad) plus the `unit` of the amplitudes; scalar effects: their
    parameters (`hdjax._model.effects.SCALAR`) plus `unit`."""
    out: dict[str, dict] = {}
    for name, d in effects.to_dict().items():
        if name in PERIODIC:
            keep = [a > 0 for a in d["amplitudes"]]
            out[name] = {"form": "a_k*sin(k*theta_m + phi_k)",
                         **{k: [v for v, on in zip(d[k], keep) if on] for k in ("orders", "amplitudes", "phases")},
                         "unit": EFFECT_UNITS[name].split(" (")[0]}
        else:
            out[name] = {**d, "unit": EFFECT_UNITS[name]}
    return out


def truth_record(station: Station, effects: Effects = Effects(), runs: list[Run] | None = None) -> dict:
    """The `truth.yaml` mapping: true parameters (SPEC names, SI), their units, drive constants,
    rated torque, sensor specification, active effects, and (with `runs`) the campaign."""
    d = station.drive
    rec: dict[str, Any] = {
        "source": "hdjax virtual test rig (hdjax._testbench.rig); truth = Taghirad & Bélanger Table I",
        "drive_name": station.name,
        "parameters": station.truth.to_dict(),
        "parameter_units": dict(PARAMETER_UNITS),
        "drive": {
            "gear_ratio": float(d.gear_ratio),
            "torque_constant": float(d.torque_constant),
            "load_inertia": float(d.load_inertia),
        },
        "rated_torque": float(station.rated_torque),
        "sensors": station.sensors(),
        "effects": describe_effects(effects),
    }
    if station.name == "HD2":
        rec["unit_reading"] = (
            "Table I lists HD2 K1 = 104.2 and Tst = 7.96; read as per-degree values: "
            "K1 = 104.2*(180/pi) N*m/rad, Tst = 7.96*(180/pi)^0.5 N*m/(rad/s)^0.5"
        )
    if runs is not None:
        rec["experiments"] = [
            {"file": r.file, "kind": r.profile.kind, "regime": r.profile.regime, **r.profile.info} for r in runs
        ]
    assert set(rec["parameters"]) == set(PARAMETER_NAMES)
    return rec


def write_campaign(
    folder: str | os.PathLike,
    station: Station,
    runs: list[Run],
    *,
    name: str,
    effects: Effects = Effects(),
    truth_extra: dict | None = None,
    digits: int | None = 7,
) -> pathlib.Path:
    """Write `runs` as a dataset folder (SPEC §2) with `truth.yaml` beside `dataset.yaml`.

    **Arguments:**

    - `folder`: the dataset folder (created if needed).
    - `station`: the `Station` that recorded `runs` (drive constants, truth, sensors).
    - `runs`: from `run_campaign`.
    - `name`: free text for `dataset.yaml`.
    - `effects`: the effects the runs were simulated with, recorded in `truth.yaml`.
    - `truth_extra`: more entries for `truth.yaml` (e.g. the seed, a note).
    - `digits`: significant digits of the CSV values (default 7, far below the sensor noise;
      `None` writes exact `repr` floats).

    **Returns:** the folder path.
    """
    truth = truth_record(station, effects, runs)
    if truth_extra:
        truth.update(_plain(truth_extra))
    return write_dataset(
        folder,
        name,
        station.drive,
        [r.experiment for r in runs],
        [r.mode for r in runs],
        [r.file for r in runs],
        start_times=[r.start_time for r in runs],
        truth=truth,
        digits=digits,
    )
