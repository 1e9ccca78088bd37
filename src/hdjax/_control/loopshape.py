r"""Linear design tools for the sampled torque loop: the linearised plant, the frequency response of
the sampled loop (differentiable in the gains), stability margins, a model-based PI design and
reference feasibility under the current limit. SI units throughout.

**Linearised plant.** About a moving operating point (no Coulomb/Stribeck kink), with state
$(\theta_m, \omega_m)$ locked or $(\theta_m, \omega_m, \theta_o, \omega_o)$ free:
$J_{eff}\dot\omega_m = K_m i - T/N - b\,\omega_m$, $T = K_1\Delta\theta + c\,\dot{\Delta\theta}$,
$J_L\dot\omega_o = T$, output $T$. $b$ is the mean viscous coefficient $(T_{vp}+T_{vn})/2$ and $c$
the describing-function equivalent of the power-law damping
$T_{st}|\dot{\Delta\theta}|^\alpha\mathrm{sign}$ at a torsion-rate amplitude $R$:
$c = T_{st}R^{\alpha-1}\,\frac{2}{\pi}\int_0^\pi \sin^{1+\alpha}x\,dx$ (1.113 for α = ½).
The zero-order-hold equivalent $P(z)$ at the sample period is exact (matrix exponential).

**Sampled loop.** The controller of `hdjax._control.closed_loop.closed_loop` seen from the measured torque,
linear part (feed-forward terms do not enter the loop):
$C(z) = k_p + k_i T_s/(z-1) + k_d (1-a)(1-z^{-1})/(T_s(1-az^{-1}))$, $a = e^{-T_s/\tau_d}$;
loop $L = CP$, sensitivity $S = 1/(1+L)$, its peak $M_s = \max_\omega|S(e^{j\omega T_s})|$ on a
fixed log grid up to Nyquist (`jax.grad` goes through the max: exact almost everywhere). Gain and
phase margins are read off the same grid (report only). Closed-loop stability is checked on the
eigenvalues of the closed-loop state matrix (plant, integrator, derivative filter).

**Model-based PI** (`model_pi`): the MIGO rule of Åström & Hägglund, i.e. the largest integral gain
with $M_s \le M_{s,max}$ (1.4) on every linearised plant given (locked and free), found on a
$(k_p, k_i)$ grid, then used with the model's feed-forward (reference, inertia, friction).
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from .._model.paper import Parameters, Smoothing, friction_torque
from .._plant.simulate import MAX_SENSOR_LEAD, sensor_lag_factor


def damping_equivalent(alpha: float, Tst: float, rate_amplitude: float) -> float:
    """Describing-function viscous equivalent (N·m·s/rad) of $T_{st}|x'|^\\alpha\\mathrm{sign}(x')$
    at torsion-rate amplitude `rate_amplitude` (rad/s)."""
    integral = math.sqrt(math.pi) * math.gamma((2.0 + alpha) / 2.0) / math.gamma((3.0 + alpha) / 2.0)
    return float(Tst * rate_amplitude ** (alpha - 1.0) * 2.0 / math.pi * integral)


def linear_plant(p: Parameters, drive, *, free: bool, rate_amplitude: float):
    """Continuous state space (A, B, C) of the linearised plant (see the module doc), numpy."""
    N, Km, JL = float(drive.gear_ratio), float(drive.torque_constant), float(drive.load_inertia)
    K1, J = float(p.K1), float(p.Jeff)
    b = 0.5 * (float(p.Tvp) + float(p.Tvn))
    c = damping_equivalent(float(p.alpha), float(p.Tst), rate_amplitude)
    if not free:
        # T = (K1 θm + c ωm)/N
        A = np.array([[0.0, 1.0], [-K1 / (N * N * J), -(b + c / (N * N)) / J]])
        B = np.array([[0.0], [Km / J]])
        C = np.array([[K1 / N, c / N]])
    else:
        # x = (Δθ, ωm, ωo) (the common angle is neither seen nor felt); T = K1 Δθ + c(ωm/N − ωo)
        C = np.array([[K1, c / N, -c]])
        A = np.array([[0.0, 1.0 / N, -1.0], -C[0] / (N * J), C[0] / JL])
        A[1, 1] -= b / J
        B = np.array([[0.0], [Km / J], [0.0]])
    return A, B, C


def zoh(A, B, ts: float):
    """Zero-order-hold discretisation (Ad, Bd) at period `ts` (s)."""
    n = A.shape[0]
    M = np.zeros((n + 1, n + 1))
    M[:n, :n], M[:n, n:] = A, B
    E = scipy.linalg.expm(M * ts)
    return E[:n, :n], E[:n, n:]


def frequency_grid(ts: float, n: int = 300, f_min: float = 0.1) -> np.ndarray:
    """Log grid of frequencies (Hz) from `f_min` to 0.999 of Nyquist."""
    return np.geomspace(f_min, 0.999 * 0.5 / ts, n)


def plant_response(p: Parameters, drive, *, free: bool, ts: float, rate_amplitude: float, freqs=None,
                   sensor_lag: float = 0.0):
    """(z on the grid, P(z), (Ad, Bd, C)) of the ZOH-sampled linearised plant from current to
    measured torque, numpy.

    `sensor_lag` (s): the torque sensor's lag as the fit identifies it (`sensor_bandwidth.torque_lag`).
    A lag τ > 0 is the strain-gauge amplifier's continuous first-order low-pass, ẏ = (T − y)/τ,
    appended to the continuous plant before it is sampled: the reading is filtered before it is
    sampled, so near the Nyquist frequency it loses phase as well as gain (HD1 locked at 0.6 of the
    Nyquist frequency, τ = 0.6 ms: −37° against −18° for the sample-level form the fit uses,
    $y_k = a\\,y_{k-1} + (1-a)\\,T_k$, which has the same low-frequency lag τ). On the ten drives of
    `benchmarks/tune_independent.py` (2026-12-06) the tuned controllers' bench cost was 2.1 %
    lower (geometric mean) than without the lag and 0.9 % lower than with the sample-level form
    here: both inside the benchmark's spread. A lead (τ < 0, down to −0.45 `ts`, which the fit
    allows) takes the sample-level form; 0 leaves the sensor out."""
    freqs = frequency_grid(ts) if freqs is None else freqs
    A, B, C = linear_plant(p, drive, free=free, rate_amplitude=rate_amplitude)
    tau = max(float(sensor_lag), -MAX_SENSOR_LEAD * ts)
    n0 = A.shape[0]
    if tau > 0.0:
        A = np.block([[A, np.zeros((n0, 1))], [C / tau, np.full((1, 1), -1.0 / tau)]])
        B = np.vstack([B, np.zeros((1, 1))])
        C = np.hstack([np.zeros((1, n0)), np.ones((1, 1))])
    Ad, Bd = zoh(A, B, ts)
    if tau < 0.0:
        a = float(sensor_lag_factor(tau, ts))
        Ad = np.block([[Ad, np.zeros((n0, 1))], [(1.0 - a) * C, np.full((1, 1), a)]])
        Bd = np.vstack([Bd, np.zeros((1, 1))])
        C = np.hstack([(1.0 - a) * C, np.full((1, 1), a)])
    z = np.exp(2j * np.pi * freqs * ts)
    n = Ad.shape[0]
    P = np.array([(C @ np.linalg.solve(zz * np.eye(n) - Ad, Bd))[0, 0] for zz in z])
    return z, P, (Ad, Bd, C)


def controller_response(gains, z, *, ts: float, derivative_filter: float):
    """C(z) of the feedback part of the torque law (jax, differentiable in `gains`)."""
    a = math.exp(-ts / derivative_filter)
    zi = 1.0 / z
    D = (1.0 - a) * (1.0 - zi) / (ts * (1.0 - a * zi))
    # real JAX gains cast to the complex dtype of z (what implicit promotion did; strict promotion
    # refuses it); Python or numpy gains stay as they are
    c = lambda k: k.astype(jnp.result_type(z)) if isinstance(k, jax.Array) else k  # noqa: E731
    return c(gains.kp) + c(gains.ki * ts) / (z - 1.0) + c(gains.kd) * D


def sensitivity_peak(gains, z, P, *, ts: float, derivative_filter: float):
    """$M_s$ (-) for each plant response in `P` (..., freq): max over the grid of |1/(1 + C P)|."""
    L = controller_response(gains, z, ts=ts, derivative_filter=derivative_filter) * P
    return jnp.max(jnp.abs(1.0 / (1.0 + L)), axis=-1)


def margins(kp, ki, kd, z, P, *, ts: float, derivative_filter: float) -> dict:
    """Gain margin (-, ∞ when no phase crossover), phase margin (deg, None without a gain crossover)
    and Ms of one loop, from the grid (numpy; report only)."""
    a = math.exp(-ts / derivative_filter)
    zi = 1.0 / z
    Cz = kp + ki * ts / (z - 1.0) + kd * (1.0 - a) * (1.0 - zi) / (ts * (1.0 - a * zi))
    L = Cz * P
    mag, ph = np.abs(L), np.unwrap(np.angle(L))
    gm = math.inf
    pm = None
    for j in range(len(z) - 1):
        # phase crossover: phase passes −180° (mod 360)
        k0, k1 = np.floor((ph[j] + np.pi) / (2 * np.pi)), np.floor((ph[j + 1] + np.pi) / (2 * np.pi))
        if k0 != k1:
            gm = min(gm, 1.0 / max(0.5 * (mag[j] + mag[j + 1]), 1e-300))
        if (mag[j] - 1.0) * (mag[j + 1] - 1.0) < 0 and pm is None:
            phc = ph[j] + (ph[j + 1] - ph[j]) * (1.0 - mag[j]) / (mag[j + 1] - mag[j])
            pm = float(np.degrees((phc + np.pi) % (2 * np.pi)))
            if pm > 180.0:
                pm -= 360.0
    return {"gain_margin": gm, "phase_margin_deg": pm, "Ms": float(np.max(np.abs(1.0 / (1.0 + L))))}


def closed_loop_radius(kp, ki, kd, plant_d, *, ts: float, derivative_filter: float):
    """Spectral radius of the sampled closed loop (plant, integrator, derivative filter, previous
    output), the cancelled integrator/zero pair at z = 1 of a free plant left out; < 1 is stable. `kp`, `ki`, `kd` may be arrays
    (broadcast); numpy."""
    Ad, Bd, C = plant_d
    n = Ad.shape[0]
    a = math.exp(-ts / derivative_filter)
    kp, ki, kd = (np.asarray(x, float) for x in (kp, ki, kd))
    shape = np.broadcast(kp, ki, kd).shape
    kp, ki, kd = (np.broadcast_to(x, shape).ravel() for x in (kp, ki, kd))
    m = len(kp)
    # states: x (n), I, d (filtered derivative), yprev; y = C x, e = −y (regulation)
    # u = −kp y + I − kd d_new, d_new = a d + (1−a)(y − yprev)/ts
    M = np.zeros((m, n + 3, n + 3))
    Cr = C[0]
    g = (1.0 - a) / ts
    # u as a row over the states
    u_row = np.zeros((m, n + 3))
    u_row[:, :n] = -kp[:, None] * Cr[None, :] - (kd * g)[:, None] * Cr[None, :]
    u_row[:, n] = 1.0
    u_row[:, n + 1] = -kd * a
    u_row[:, n + 2] = kd * g
    M[:, :n, :n] = Ad[None]
    M[:, :n, :] += Bd[None, :, 0, None] * u_row[:, None, :]
    M[:, n, :n] = -(ki * ts)[:, None] * Cr[None, :]
    M[:, n, n] = 1.0
    M[:, n + 1, :n] = g * Cr[None, :]
    M[:, n + 1, n + 1] = a
    M[:, n + 1, n + 2] = -g
    M[:, n + 2, :n] = Cr[None, :]
    lam = np.linalg.eigvals(M)
    # the free plant's torque has a zero at z = 1 (no torque at constant speed), which the PI's
    # integrator pole cancels: that pair leaves a marginal mode at exactly z = 1 (a constant speed
    # drift, held by friction on a real drive), not an instability
    lam = np.where(np.abs(lam - 1.0) < 1e-6, 0.0, lam)
    rho = np.max(np.abs(lam), axis=-1)
    return rho.reshape(shape)


def model_pi(responses, plants_d, *, static_gain: float, ts: float, derivative_filter: float, ms_max: float = 1.4,
             n_grid: int = 48) -> tuple[float, float, dict]:  # fmt: skip
    """MIGO PI: the (kp, ki) with the largest ki such that every loop (`responses`: list of (z, P);
    `plants_d`: their sampled state spaces) is stable with Ms ≤ `ms_max`. `static_gain` (N·m/A)
    sets the grid's range. Returns (kp, ki, info)."""
    kps = np.geomspace(0.003, 3.0, n_grid) / static_gain
    kis = np.geomspace(0.1, 3000.0, n_grid + 12) / static_gain
    KP, KI = np.meshgrid(kps, kis, indexing="ij")
    ok = np.ones(KP.shape, bool)
    ms_all = np.zeros(KP.shape)
    a = math.exp(-ts / derivative_filter)
    for (z, P), pd in zip(responses, plants_d):
        Cz = KP[..., None] + KI[..., None] * ts / (z - 1.0)
        ms = np.max(np.abs(1.0 / (1.0 + Cz * P)), axis=-1)
        ms_all = np.maximum(ms_all, ms)
        ok &= ms <= ms_max
        ok &= closed_loop_radius(KP, KI, 0.0, pd, ts=ts, derivative_filter=derivative_filter) < 1.0
    del a
    if not ok.any():
        j = np.unravel_index(np.argmin(ms_all), ms_all.shape)
        return float(KP[j]), float(KI[j]), {"rule": "min Ms (no grid point met the Ms bound)", "Ms": float(ms_all[j]),
                                            "ms_max": ms_max}  # fmt: skip
    ki_best = np.max(np.where(ok, KI, -np.inf))
    cand = ok & (KI == ki_best)
    # among the gains with that ki, the one with the smallest Ms
    j = np.unravel_index(np.argmin(np.where(cand, ms_all, np.inf)), ms_all.shape)
    return float(KP[j]), float(KI[j]), {"rule": f"MIGO: max ki with Ms <= {ms_max:g} on the locked and free plants",
                                        "Ms": float(ms_all[j]), "ms_max": ms_max}  # fmt: skip


# ----------------------------------------------------------------------------------------------
# Reference feasibility under the current limit
# ----------------------------------------------------------------------------------------------


def feedforward_current(torque, *, free: bool, p: Parameters, drive, ts: float) -> np.ndarray:
    """Current (A) the identified model needs to follow the output-torque trajectory `torque`
    (N·m, samples at `ts`) exactly: locked, $r/(NK_m) + T_f(\\omega_m)/K_m$ with the motor
    velocity $\\omega_m = N\\dot r/K_1$ of the spring, plus the motor inertia $J_{eff}\\dot\\omega_m$;
    free, $[(1/N + NJ_{eff}/J_L)r + T_f(\\omega_m)]/K_m$
    with $\\omega_m = N\\int r\\,dt/J_L$ (rigid body)."""
    r = np.asarray(torque, float)
    N, Km, JL = float(drive.gear_ratio), float(drive.torque_constant), float(drive.load_inertia)
    if free:
        wm = N * np.cumsum(r) * ts / JL
        drive_part = (1.0 / N + N * float(p.Jeff) / JL) * r
    else:
        wm = N * np.gradient(r, ts) / float(p.K1)
        drive_part = r / N + float(p.Jeff) * np.gradient(wm, ts)
    Tf = np.asarray(friction_torque(p, wm, Smoothing(velocity_scale=1e-3)))
    return (drive_part + Tf) / Km


def feasible_scale(torque, *, free: bool, p: Parameters, drive, ts: float, current_limit: float,
                   headroom: float = 0.7) -> tuple[float, float]:  # fmt: skip
    """Largest s ≤ 1 such that the model's feed-forward current for s·`torque` stays within
    `headroom`·`current_limit` (bisection; friction makes it nonlinear in s). Returns (s, peak
    feed-forward current of the unscaled reference / limit)."""
    lim = headroom * current_limit

    def peak(s):
        return float(np.max(np.abs(feedforward_current(s * np.asarray(torque), free=free, p=p, drive=drive, ts=ts))))

    need = peak(1.0)
    if need <= lim:
        return 1.0, need / current_limit
    lo, hi = 0.0, 1.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if peak(mid) <= lim:
            lo = mid
        else:
            hi = mid
    return lo, need / current_limit
