r"""The discrepancy loop: what the fitted paper model gets wrong, which SPEC §4 effect explains it,
and how much an extended model gains on experiments held out of its fit.

Method (one JIT-compiled Jacobian per round, real simulations for every held-out figure):

1. Base model: the paper's identification, refined by a few trajectory-error LM steps (at the
   Jacobian tolerance). In the first round, before any effect, the base model's own assumptions
   (SPEC §4b `model_form`: low-speed friction scales, sensor offsets, sensor lags, the current's
   path between samples, and hdjax's fifth, the viscous law's exponent) are screened by the same
   held-out rules and every significant one is adopted (`Diagnosis.model_form`); the viscous
   law's held-out fits are damped (`DAMPED_SCREEN`), and once it is adopted the others are
   screened again against the adjusted model, each by a simulated held-out fit (the linearised
   prediction misjudged the sensor lags there by 42 points); each (experiment, channel) is weighted by its own noise
   level and, where the current model leaves more, by that misfit (a bench is never exactly the
   model). The effects are then screened with a fresh Jacobian: once adjustments are adopted,
   the noise model is re-estimated and base + adjustments are re-fitted from a new Jacobian
   (`readapt_after_form`, default on since 2026-11-27): a sensor lag fitted from zero moves the
   model far from where the first Jacobian was taken, and the base model's own correction to it dominated every candidate's fit (a hidden
   Dahl hysteresis and a second effect were missed). `readapt_after_form=False` screens the
   effects with round 1's Jacobian and noise model, as before; it is faster (one Jacobian and
   re-fit fewer) and names an input delay that the re-fitted sensor lags otherwise absorb (see
   `benchmarks/RESULTS.md`, seventeenth and eighteenth sessions, for both on the benchmark).
   With `form_competes` (off by default: see `diagnose`), the assumptions not adopted in round 1
   compete with the effects in every later round: one that wins is adopted, names nothing, and
   the round is screened again (a sensor lag hidden by a found ripple's misfit is otherwise taken
   up by a false `input_delay`). A strain-gauge ripple is screened together with the torque
   sensor's offset where `sensor_offset` was not adopted (`SCREENED_WITH`): over part of a cycle
   the one is the other, so neither was found alone; it is named only if it also passes the rules
   against that offset alone, and the offset then joins the model as a model_form item.
   Before that round, the tachometer's lag behind the output encoder is measured from the sensors
   alone (`evidence.tachometer_lag`: θo + Δθ − ∫ω dt/N = τ·ω/N + offsets in free motion, Δθ from
   the measured torque by eq. 5; the current does not enter); where it is determined,
   `sensor_bandwidth` holds its velocity lag there and fits only the torque lag
   (`measure_tachometer_lag`). A fitted velocity lag took up every hidden input delay of the
   independent bench (0 of 3 named, 2026-12-03); held at the measured lag, it cannot.
2. Evidence from residuals: order spectra against the wave-generator angle θm (cycles per turn;
   the measured angle, `Simulator.measured_angle`, the default here: the simulated one drifts by
   radians in free motion) for torque, velocity and output position, split locked/free, and correlations of the
   residuals with torsion, torsion³, |T|·sign(ω), di/dt and session time. The periodic
   candidates (kinematic error, strain-gauge ripple, cogging, position-dependent friction) are
   screened only at the orders whose spectral peak stands out (at most three), and not at all when
   none does. A second spectrum comes from the motor torque balance, eq. 8 evaluated on the
   *measured* current, torque and velocity of the fast free-motion tests: e = Km·i − T/N − Tf(ω) −
   Jeff·dω/dt against θm, and e·sign(ω). Cogging and strain-gauge ripple add a term periodic in θm
   to e, position-dependent friction one periodic in θm times sign(ω), a kinematic error none. An
   integer order counts where it stands out from the non-integer orders beside it (misfit that is
   not periodic in θm spreads over both); such an order is screened for cogging and ripple (e) or
   position-dependent friction (e·sign(ω)).
2b. Torque-balance route, before the output-error rounds: an e (cogging) or e·sign(ω)
   (position-dependent friction) peak that no strain-gauge ripple explains (a ripple b shows as b/N
   in e and as b in the torque residual; either term is skipped where the torque residual's
   amplitude at that order exceeds `TB_RIPPLE_RATIO` = 0.5 of N × its fitted amplitude) is fitted
   by weighted least squares on all fast free tests but one and must reduce the held-out test's
   torque-balance residual in `min_improved_fraction` of them (counted by
   `Significance.improved_fraction`, as in the rounds), and in total by more than `TB_MIN_GAIN` (1 %).
   The evidence functions are in `hdjax._discrepancy.evidence`.
   The output-error rounds do not resolve these terms on a bench the paper model misfits: a torque
   disturbance integrates into the velocity with opposite phase in the two directions of motion.
   The term keeps that fit; its simulated output-error change is reported.
3. Noise model: the recorded current drives the simulation, so its sensor noise makes the
   simulated velocity and output position wander beyond the sensor noise (in free motion a random
   walk whose variance changes ×40 between records and ×10 between realisations). That process
   noise is sampled by simulating the base model with white noise of the current's own level added
   to the current (two seeded realisations); an AR(16) model per experiment and channel of it plus
   the sensor noise whitens every residual and Jacobian (prediction-error weighting), so a correct
   model leaves unit-variance white residuals and chance fits gain their nominal Δχ². It is
   re-estimated at the start of every round, at the model with the effects accepted so far. Not the base
   model's residual RMS: that holds the misfit an effect leaves and so down-weights the very
   channel where it shows (thermal drift in free-motion velocity: ×61 instead of ×1.4).
4. Candidates: every effect of `hdjax._model.effects` as a term inside the plant, all switched on at
   zero magnitude (which leaves the simulation equal to the base model). One forward-mode Jacobian
   per round (through `Ros34PW2` with the plant's stiff part, `jacobian_solver`), of the whitened
   residuals of all experiments w.r.t. the base parameters, the accepted effects and every
   candidate's parameters, (a) refines base + accepted effects by
   Gauss–Newton steps with backtracking on the simulated error, (b) gives each candidate a
   Gauss–Newton fit of its parameters *with* the base parameters and the accepted effects on all
   experiments but one (an effect confounded with K1, Tst or the friction is judged after they
   re-adjust); the model is then *simulated* on the one left out, for every experiment in one
   batch simulation (leave-one-experiment-out cross-validation; `cross_validation="two_fold"`
   fits on one half and predicts the other). Held-out gains are also reported per half (the
   experiments alternate between halves within each mode). The reference is the same fit
   without the candidate. Candidates are ranked by the linearised held-out gain;
   the best `confirm_top` are simulated.
5. A finding needs, on held-out experiments: a reduction of the whitened squared error in both
   halves, above `min_relative_gain` in the locked or the free tests (the effect size where the
   effect acts, not diluted by the other mode; for a drift over the session, `DRIFT_EFFECTS`, its
   share of what a free value per record of the base parameters it changes would gain, at least
   `min_drift_share`, with its fitted sign physical in every held-out fit), far beyond the chance level of its parameter count
   (Δχ² > 10k + 50), also without the held-out experiment that gains most (a term that fits one
   odd experiment is no finding; without it, the mode where the effect acts must still gain half
   the effect size, `MIN_GAIN_WITHOUT_BEST`), and neither the locked nor the free tests may get worse beyond
   that chance level or a quarter of what the other gains (`MODE_TRADE`; a term that fits one kind
   of test at the other's expense explains no drive; these values are one `Significance`); an
   effect that acts on both kinds alike (`ACTS_ON_BOTH_MODES`: the input delay) may not make
   either worse beyond the chance level. An
   effect whose physics fixes the sign of its parameter (`PHYSICAL_SIGN`: β, μ, K3, Th, τd > 0)
   needs that sign in every held-out fold fit: with the other sign it absorbs some other misfit
   and is not that effect. The
   harm ratio (what the held-out experiments it makes worse lose over what
   those it improves gain) is reported, not used: a real effect periodic in θm hurts free-motion
   tests whose simulated θm has drifted from the true one (measured 0.47 for a true kinematic
   error, with the simulated angle), as much as a chance fit does. Greedy: the best finding is added to the model and the
   loop repeats (up to `max_findings`). It starts at its own columns' all-experiment fit, or, where
   that raises the simulated error, at the all-experiment counterpart of the fold fits that judged
   it (base parameters and accepted effects re-fitted with it; `_accept`).
6. What is left: residual order-spectrum peaks and channels far above their sensor noise under the
   final model are listed as `unexplained`, and so are the near misses (`near_misses`): effects of
   the last round whose held-out fits gain (simulated, or by the linearised prediction where not
   simulated) but that a rule refused, with the rule, its figures and the record that gains most.

A periodic term's Jacobian columns are zeroed in experiments where its order completes no cycle
of θm (locked tests): over a fraction of a cycle it is a smooth function of θm that absorbs other
misfit, so it is fitted and its fit judged only where it is resolved; its simulated effect still
enters every held-out figure. It still acts there, though (an order-1 kinematic error changes a
locked test's effective stiffness), so the fold fit has a second stage (`two_stage_periodic`,
default on since 2026-11-27): with the term fixed at its first-stage values, every other column is
re-fitted on the same training experiments to what the term does everywhere (unzeroed
Jacobian). Without it, a true order-1 kinematic error fitted on the free tests cost the locked
tests 29 % held out, because nothing re-fitted K1 (bench seed 5012).

Look-alikes (kinematic error, strain-gauge ripple, cogging, position-dependent friction are all
periodic in θm) are told apart by their held-out gains: each predicts a different pattern across
torque, velocity and output position and between locked and free tests, so the wrong one does not
transfer to held-out experiments as well as the right one.
"""

import dataclasses
import math
import time
import typing
from collections.abc import Sequence

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from jaxtyping import Bool, Float
from scipy import stats
from scipy.signal import lfilter

from .._data.experiment import Experiment, stack_experiments
from .._fit.least_squares import (
    DEFAULT_FREE,
    experiment_residuals,
    fit_parameters,
    make_parameter_map,
    noise_levels,
    process_noise as _process_noise,
    trajectory_residuals,
    white_noise_level,
)
from .._fit.parameterisation import Entry, Parameterisation, parameterisation
from .._model.effects import (
    DIAGNOSED_MODEL_FORM,
    EFFECT_NAMES,
    FIELD_UNITS,
    FIT_ONLY,
    MAX_ORDER,
    MODEL_FORM,
    MODEL_FORM_NAMES,
    PERIODIC,
    PERIODIC_UNITS,
    TERMS,
    AbstractPeriodicTerm,
    Effects,
    ThermalDrift,
)
from .._model.paper import Drive, Parameters
from .._plant.sharding import experiment_mesh, for_each_experiment, map_experiments, pad_experiments
from .._plant.simulate import PLANT_W_METHOD, Simulator, is_fixed_cost, simulate
from .._plant.stepper import VelocityImplicit
from .evidence import (
    TB_MIN_GAIN,
    TB_RIPPLE_RATIO,
    channel_nrmse,
    orders_per_candidate,
    residual_evidence,
    strain_gauge_ratio,
    tachometer_lag,
    torque_balance_cv,
    unexplained,
)
from .significance import OUTPUT_ERROR_RULES, Significance, drift_trend_test, drift_untestable, forward_selection

#: SPEC §4 effects of the plant that this loop does not screen (dropped from any candidate list):
#: `presliding_friction`, tried inside `low_speed_friction`, took the default bench from 17 to 15 of
#: 20 datasets (benchmarks/RESULTS.md, thirty-first session).
NOT_SCREENED = frozenset({"presliding_friction"}) | FIT_ONLY
#: The candidate effects a diagnosis screens by default.
SCREENED_EFFECTS = tuple(n for n in EFFECT_NAMES if n not in NOT_SCREENED)
JACOBIAN_BLOCK = 40
"""Tangents per Jacobian evaluation: the columns asked for go in blocks of this many, the last padded
with zero tangents, so one program serves every request on a dataset shape. A fresh Jacobian asks
for 19–39 columns on the bench datasets (the base θ and the candidates' columns); the compiled
Jacobian (≈ 9–10 s to trace and compile) was compiled once per distinct count, padded to a multiple
of 8, before 2026-12-08; an extra tangent costs 2–4 % of the primal simulation (measured: 0.40 s +
0.0085 s per tangent on 4 + 4 records × 1.5 s, 0.80 s + 0.029 s on 8 + 8 × 2.5 s)."""


@dataclasses.dataclass(frozen=True)
class _Column:
    effect: str
    field: str  # the term's field (`"K3"`; a periodic term's `"sin"` / `"cos"`)
    index: int | None  # the order − 1 of a periodic term's coefficient, None for a scalar field
    scale: float
    start: float

    @property
    def path(self) -> str:
        """The field's path in `Effects` (`"nonlinear_stiffness.K3"`)."""
        return f"{self.effect}.{self.field}"


def _all_columns(ctx: dict) -> list[_Column]:
    """Every effect parameter the plant can take, in `TERMS`' order (all orders of every periodic
    effect; `NOT_SCREENED` left out), each with the scale (the unit of the fitted coefficient) and
    start value its term gives (`AbstractTerm.fitted`). The simulation and the Jacobian are compiled
    once for this full vector; a round fits a subset."""
    cols = []
    for name, term in TERMS.items():
        if name in NOT_SCREENED:
            continue
        for f in term.fitted(ctx):
            if name in PERIODIC:
                cols += [_Column(name, f.field, k, f.scale, f.start) for k in range(MAX_ORDER)]
            else:
                cols.append(_Column(name, f.field, None, f.scale, f.start))
    return cols


def _candidate_columns(cols: list[_Column], name: str, orders, *, offset: int = 0) -> list[int]:
    """Indices of the parameters of candidate `name` (periodic: only `orders`): into `cols`, plus
    `offset` (the number of base parameters: indices into the loop's vector z)."""
    return [offset + j for j, c in enumerate(cols) if c.effect == name and (c.index is None or c.index + 1 in orders)]


def _effect_map(cols: list[_Column]) -> Parameterisation:
    """The effect columns as a `Parameterisation` of `Effects`: every column's value is
    `start + scale·z` (a periodic effect's orders are one array field)."""
    entries, j = [], 0
    while j < len(cols):
        c = cols[j]
        entries.append(Entry(c.path) if c.index is None else Entry(c.path, MAX_ORDER))
        j += 1 if c.index is None else MAX_ORDER
    return parameterisation(entries, np.array([c.scale for c in cols]), np.array([c.start for c in cols]))


def _apply(effects: Effects, cols: list[_Column], values) -> Effects:
    """`effects` with every column of `cols` set to `start + scale·value` (`_effect_map`)."""
    return _effect_map(cols).to_model(jnp.asarray(values), effects)


def _fixed_effect_settings(ctx: dict, active) -> Effects:
    """Effects with the shape parameters that are not fitted set from the data by each term
    (`AbstractTerm.from_data`: thermal τ, Dahl σ, the viscous law's reference speed), `active` on."""
    return Effects.from_data(ctx, active)


@dataclasses.dataclass
class Diagnosis:
    findings: list
    model_form: list
    unexplained: list
    baseline: dict
    evidence: dict
    params: Parameters
    effects: Effects
    rounds: list
    timing: dict = dataclasses.field(default_factory=dict)
    traces: dict = dataclasses.field(default_factory=dict)


class _Problem(eqx.Module):
    """The residual of every experiment as a function of one flat vector z = [base θ, effect values]:
    `simulate(zs)` with one z per experiment (fold fits are held out experiment by experiment),
    `jacobian(z, tangents)` for one shared z. Data enter as arguments, so each compiles once.

    With several devices (`jax.device_count() > 1`, e.g. `XLA_FLAGS=--xla_force_host_platform_device_count=2`
    on a 2-core CPU) the experiments are spread over them (`mesh`, `hdjax._plant.sharding`): the batch is
    padded with dummy experiments to a multiple of the device count and each device simulates its
    share; the dummies are dropped from every output."""

    pmap: Parameterisation  # the base parameters
    emap: Parameterisation  # the effect columns (`_effect_map`)
    effects: Effects
    drive: Drive
    simulator: Simulator
    mesh: Mesh | None = eqx.field(static=True, default=None)

    def _one(self, z, p_ref, exp, sigma):
        n = self.pmap.size
        p = self.pmap.to_model(z[:n], p_ref)
        e = self.emap.to_model(z[n:], self.effects)
        return experiment_residuals(p, self.drive, exp, sigma, self.simulator, e)

    def _one_with_trajectory(self, z, p_ref, exp, sigma):
        tr = self._traj(z, p_ref, exp)
        return trajectory_residuals(tr, exp, sigma), tr

    def _traj(self, z, p_ref, exp):
        n = self.pmap.size
        p = self.pmap.to_model(z[:n], p_ref)
        e = self.emap.to_model(z[n:], self.effects)
        return simulate(p, self.drive, exp, effects=e, simulator=self.simulator)

    def _each(self, fn, shared, batched):
        """`fn(shared, *slices)` for every experiment of the tuple `batched`, on every device."""
        fixed = is_fixed_cost(self.simulator)
        per_device = lambda sh, b: for_each_experiment(lambda *xs: fn(sh, *xs), *b, fixed_cost=fixed)
        return map_experiments(per_device, self.mesh)(shared, batched)

    def _pad(self, zs, batch, sigma=None):
        """Pad the experiment axis to a multiple of the device count (dummy experiments: masked,
        at rest, with the first experiment's z; `zs` None where z is shared). Returns (zs, batch,
        sigma, number of real ones)."""
        if self.mesh is None:
            return zs, batch, sigma, None
        padded, n = pad_experiments(batch, self.mesh.size)
        extra = padded.time.shape[0] - n
        if extra:
            if zs is not None:
                zs = jnp.concatenate([zs, jnp.broadcast_to(zs[:1], (extra,) + zs.shape[1:])])
            if sigma is not None:
                sigma = jnp.concatenate([sigma, jnp.ones((extra,) + sigma.shape[1:], sigma.dtype)])
        return zs, padded, sigma, n

    def simulate(self, zs, p_ref, batch, sigma):
        zs, batch, sigma, n = self._pad(zs, batch, sigma)
        return self._simulate(zs, p_ref, batch, sigma)[0][:n]

    def trajectories(self, zs, p_ref, batch):
        sigma = jnp.ones((batch.time.shape[0], 3), batch.time.dtype)  # the residuals are not used here
        zs, batch, sigma, n = self._pad(zs, batch, sigma)
        return jax.tree.map(lambda x: x[:n], self._simulate(zs, p_ref, batch, sigma)[1])

    def jacobian(self, z, tangents, p_ref, batch, sigma):
        _, batch, sigma, n = self._pad(None, batch, sigma)
        r, J = self._jacobian(z, tangents, p_ref, batch, sigma)
        return r[:n], J[:n]

    @eqx.filter_jit
    def _simulate(self, zs, p_ref, batch, sigma):
        """Residuals and trajectories of every experiment: one program for both (as two, the
        trajectories' copy compiled for ~2 s more per dataset shape, 2026-12-05)."""
        return self._each(lambda p, z, e, s: self._one_with_trajectory(z, p, e, s), p_ref, (zs, batch, sigma))

    @eqx.filter_jit
    def _jacobian(self, z, tangents, p_ref, batch, sigma):
        f = lambda z_: self._each(lambda sh, e, s: self._one(sh[0], sh[1], e, s), (z_, p_ref), (batch, sigma))
        r, J = jax.vmap(lambda v: jax.jvp(f, (z,), (v,)), out_axes=(None, -1))(tangents)
        return r, J


def _jacobian_columns(jvps, n_z: int, need: Sequence[int], *, block: int | None = None) -> np.ndarray:
    """Jacobian columns `need` (indices into z, in that order) from `jvps(E)`, which returns the
    directional derivatives along the rows of the tangent matrix E (block, n_z) on a last axis. The
    tangents go in blocks of `block` (default `JACOBIAN_BLOCK`) rows, the last padded with zero rows,
    so that every call has one shape."""
    block = JACOBIAN_BLOCK if block is None else block
    out = []
    for b0 in range(0, len(need), block):
        cols = list(need[b0 : b0 + block])
        E = np.zeros((block, n_z))
        E[np.arange(len(cols)), cols] = 1.0
        out.append(np.asarray(jvps(E))[..., : len(cols)])
    return np.concatenate(out, axis=-1)


def _solve_normal(JtJ: Float[np.ndarray, "z z"], Jtr: Float[np.ndarray, " z"]) -> Float[np.ndarray, " z"]:
    """Gauss–Newton step −(JᵀJ + εI)⁻¹Jᵀr, ε = 1e-9 × the mean diagonal (guards rank loss). Columns
    without information (a zero diagonal: the residual does not depend on them, e.g. where every
    simulation failed and the residual is the constant failure value) get a zero step."""
    if not len(Jtr):
        return np.zeros(0)
    live = np.diag(JtJ) > 0
    out = np.zeros(len(Jtr))
    if not live.any():
        return out
    A = JtJ[np.ix_(live, live)]
    n = A.shape[0]
    out[live] = -np.linalg.solve(A + 1e-9 * np.trace(A) / n * np.eye(n), Jtr[live])
    return out


@dataclasses.dataclass(frozen=True)
class _NoiseModel:
    """Per (experiment, channel) autoregressive noise model of the sensor-weighted residual: white
    sensor noise (unit variance) plus the process noise of the current. `whiten` applies the
    prediction-error filter A(q) = 1 − Σ aᵢq⁻ⁱ and divides by the innovation std, so residuals of
    a correct model become white with unit variance (and Jacobian columns transform alike)."""

    a: Float[np.ndarray, "exp channel lag"]  # AR coefficients
    s: Float[np.ndarray, "exp channel"]  # innovation std
    mask: Bool[np.ndarray, "exp time"]

    def whiten(self, x: Float[np.ndarray, "exp channel time *column"]) -> Float[np.ndarray, "exp channel time *column"]:
        """x: (exp, channel, time, ...) → whitened, zero on padding."""
        out = np.zeros_like(x)
        for e in range(x.shape[0]):
            n = int(self.mask[e].sum())
            for c in range(x.shape[1]):
                out[e, c, :n] = lfilter(np.r_[1.0, -self.a[e, c]], [1.0], x[e, c, :n], axis=0) / self.s[e, c]
        return out


def _noise_model(process: np.ndarray, mask: np.ndarray, *, order: int = 16, seed: int = 0) -> _NoiseModel:
    """AR(`order`) fit (least squares) per experiment and channel to samples of its noise: the process
    noise realisations `process` (realisations, exp, channel, time; sensor-weighted units) plus
    seeded white noise of unit variance (the sensor noise). The random walk that the current's
    noise drives in free-motion position has a level that varies by ×10 between realisations but
    increments that thousands of samples pin down: whitening by its AR model weighs each experiment
    by what it can tell, and makes Δχ² of chance fits follow their nominal distribution."""
    rng = np.random.default_rng(seed)
    R, n_exp, n_ch, _ = process.shape
    a = np.zeros((n_exp, n_ch, order))
    s = np.ones((n_exp, n_ch))
    for e in range(n_exp):
        n = int(mask[e].sum())
        if n <= 10 * order:
            continue
        for c in range(n_ch):
            x = process[:, e, c, :n] + rng.standard_normal((R, n))
            X = np.concatenate([np.stack([xr[order - i - 1 : n - i - 1] for i in range(order)], 1) for xr in x])
            y = np.concatenate([xr[order:] for xr in x])
            coef, *_ = np.linalg.lstsq(X, y, rcond=None)
            a[e, c] = coef
            s[e, c] = float(np.sqrt(np.mean((y - X @ coef) ** 2)))
    return _NoiseModel(a=a, s=s, mask=np.asarray(mask))


def _gn_step(r: np.ndarray, J: np.ndarray, rows, cols_idx) -> np.ndarray:
    """Gauss–Newton step on the experiments `rows` (bool) for the columns `cols_idx` of `J`."""
    if not len(cols_idx):
        return np.zeros(0)
    rr = r[rows].reshape(-1)
    JJ = J[rows][..., cols_idx].reshape(-1, len(cols_idx))
    return _solve_normal(JJ.T @ JJ, JJ.T @ rr)


@dataclasses.dataclass
class _Loop:
    """The state of one diagnosis: the data, the compiled problem, the current model z (base θ and
    every effect column) with its residuals, the round's noise model and the Jacobian cache.
    Stages read and update it; `diagnose` runs them in order."""

    prob: _Problem
    jac_prob: _Problem  # the same at the Jacobian tolerance
    p_base: Parameters
    batch: Experiment
    sig_exp: np.ndarray  # (exp, channel) sensor-noise levels
    m: np.ndarray  # (exp, time) mask
    modes: np.ndarray  # (exp,) "constrained" / "free"
    cols: list[_Column]
    n_base: int
    unresolved: dict  # column → (exp,) bool: periodic term completes no cycle there
    timing: dict
    z: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))  # current model
    r: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))  # its whitened residuals
    r_raw: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))  # and sensor-weighted ones
    noise_model: _NoiseModel | None = None  # set in each round: every residual and Jacobian is whitened by it
    jac_cache: dict = dataclasses.field(default_factory=dict)  # column → unwhitened Jacobian column (exp, channel, time)
    jac_full: dict = dataclasses.field(default_factory=dict)  # the same before the unresolved experiments are zeroed

    @property
    def n_exp(self) -> int:
        return self.sig_exp.shape[0]

    def tile(self, z: np.ndarray) -> np.ndarray:
        """One copy of z per experiment."""
        return np.tile(z, (self.n_exp, 1))

    def jacobian(self, z, sel, *, reuse=False):
        """Whitened Jacobian columns `sel` at z. With `reuse`, columns computed in an earlier round
        are taken from the cache (a chord Jacobian: it sets Gauss–Newton directions and screening
        predictions only; every accepted step and held-out figure is simulated) and only missing
        ones are computed; a refinement that keeps gaining asks for a fresh one."""
        need = [j for j in sel if not (reuse and j in self.jac_cache)]
        if need:
            t1 = time.perf_counter()
            z_dev, sig_dev = jnp.asarray(z), jnp.asarray(self.sig_exp)  # once for every block

            def jvps(E):
                return self.jac_prob.jacobian(z_dev, jnp.asarray(E), self.p_base, self.batch, sig_dev)[1]

            Jn = _jacobian_columns(jvps, len(z), need)
            for k, j in enumerate(need):
                self.jac_cache[j] = Jn[..., k]
                if j in self.unresolved:
                    self.jac_full[j] = Jn[..., k].copy()
                    # a periodic term over less than one of its cycles is a smooth function of θm that
                    # absorbs other misfit (a locked test turns the wave generator by a fraction of a
                    # turn): it is fitted, and its fit judged, only where it completes a cycle (its
                    # simulated effect everywhere still enters every held-out figure)
                    self.jac_cache[j][self.unresolved[j]] = 0.0
            self.timing["jacobians"] += time.perf_counter() - t1
        J = np.stack([self.jac_cache[j] for j in sel], axis=-1)
        if self.noise_model is not None:
            J = self.noise_model.whiten(J)
        return J

    def full_jacobian(self, J: np.ndarray, sel) -> np.ndarray:
        """`J` (whitened columns `sel`, from `jacobian(z, sel)` under the current noise model) with
        the unresolved experiments not zeroed: what each column does everywhere. Only the columns
        that were zeroed are whitened again (the whitening acts on each column alone)."""
        k = [i for i, j in enumerate(sel) if j in self.jac_full]
        if not k:
            return J
        raw = np.stack([self.jac_full[sel[i]] for i in k], axis=-1)
        out = J.copy()
        out[..., k] = self.noise_model.whiten(raw) if self.noise_model is not None else raw
        return out

    def simulate_each(self, zs, data=None):
        """Residuals (exp, 3, time) with experiment j of `data` (default: the diagnosed batch)
        simulated at zs[j]: (whitened by the noise model, weighted by the sensor noise)."""
        t1 = time.perf_counter()
        data = self.batch if data is None else data
        r = np.array(self.prob.simulate(jnp.asarray(zs), self.p_base, data, jnp.asarray(self.sig_exp)))
        w = self.noise_model.whiten(r) if self.noise_model is not None else r
        self.timing["simulations"] += time.perf_counter() - t1
        return w, r

    def nrmse(self, raw) -> dict:
        """Pooled NRMSE per channel of sensor-weighted residuals (exp, 3, time)."""
        return channel_nrmse(raw, self.sig_exp, self.batch, self.m)


def _per_exp(res):
    """Squared error per experiment of residuals (exp, channel, time)."""
    return np.sum(res**2, axis=(1, 2))


def _check_names(candidates, model_form, cross_validation) -> tuple[list[str], list[str]]:
    """The candidate effects (without `NOT_SCREENED`) and model_form assumptions, checked against the
    known names."""
    candidates = [c for c in candidates if c not in NOT_SCREENED]
    unknown = sorted(set(candidates) - set(EFFECT_NAMES))
    if unknown:
        raise ValueError(f"`diagnose`: unknown candidate effect(s) {unknown}; known: {list(EFFECT_NAMES)}.")
    model_form = list(model_form)
    unknown = sorted(set(model_form) - set(MODEL_FORM_NAMES))
    if unknown:
        raise ValueError(f"`diagnose`: unknown model_form assumption(s) {unknown}; known: {list(MODEL_FORM_NAMES)}.")
    fit_only = sorted(set(model_form) & FIT_ONLY)
    if fit_only:
        raise ValueError(f"`diagnose`: {fit_only} is fitted by `hdjax fit`, not screened by the diagnosis; "
                         f"choose model_form from {list(DIAGNOSED_MODEL_FORM)}.")
    if cross_validation not in ("leave_one_out", "two_fold"):
        raise ValueError(f"`diagnose`: cross_validation must be 'leave_one_out' or 'two_fold', got {cross_validation!r}.")
    return candidates, model_form


def untestable(candidates, experiments: list[Experiment]) -> dict[str, str]:
    """The candidates these data cannot test, each with why and what to record or give instead.

    `thermal_drift` needs the records spread over the session (`start_time`, SPEC §2): when every
    record starts at the same session time (a dataset.yaml without `start_time` gives 0 to all),
    the term is the same function of the time within each record in every one of them, a transient
    that every record shares, which no held-out gain can tell from a drift (`drift_untestable`, which
    the friction-only diagnosis asks too). Measured on default-bench seed 5009 (thermal drift
    hidden, named with its start times) with every `start_time` taken out of dataset.yaml: nothing
    named, the drift's predicted held-out gain −0.000 (between-record share −0.01), and no word of
    why before this check (2026-12-03). (The periodic effects' orders that the tests cannot resolve
    are found later, from the residual spectra: `unresolved_orders`.)

    `lost_motion` (a dead band of the torsion around zero) acts only where the transmitted torque
    passes through zero: where no test's measured torque changes sign, it is left out too."""
    out = {}
    why = drift_untestable([e.start_time for e in experiments]) if "thermal_drift" in candidates else None
    if why is not None:
        out["thermal_drift"] = why
    why = torque_reversal_missing(experiments) if "lost_motion" in candidates else None
    if why is not None:
        out["lost_motion"] = why
    return out


def torque_reversal_missing(experiments: list[Experiment]) -> str | None:
    """Why `lost_motion` cannot be tested on `experiments`, or None where it can: some test's
    measured torque takes both signs."""
    ranges = [(float(np.min(t)), float(np.max(t))) for t in
              (np.asarray(e.torque)[np.asarray(e.mask, dtype=bool)] for e in experiments) if t.size]
    if not ranges or any(lo < 0.0 < hi for lo, hi in ranges):
        return None
    lo, hi = min(r[0] for r in ranges), max(r[1] for r in ranges)
    return (f"no test's measured torque changes sign (each stays on one side of zero; all together {lo:.3g} to {hi:.3g} N·m): "
            "lost motion, a dead band of the torsion around zero, never acts in them. To test it, record a test whose "
            "torque swings through zero (a locked-output sine or triangle about zero, or free motion that reverses)")


def unresolved_orders(evidence: dict, candidates) -> list[dict]:
    """`unexplained` entries for the periodic candidates' orders that no residual spectrum resolves.

    An order k counts in an order spectrum only where the tests of its kind turn the wave generator
    through one of its cycles (2π/k rad, median over the tests, `spectral_peaks`); locked tests turn
    it by N times the torsion, rarely a turn. So on a locked-only dataset the low orders, often all
    of them, cannot be tested, and nothing said so before (bench seed 8101, 8 locked records with a
    kinematic error [2] at 5× the noise, 2026-12-03: the median test turned it 2.2 rad, orders 1 and
    2 unresolved, nothing named, the log's "no order-spectrum peak … not screened" the only trace).
    The torque-balance route, where it has records (free tests turning ≥ 2 turns), resolves every
    order of cogging, strain-gauge ripple and position-dependent friction; not of the kinematic error."""
    periodic = [c for c in candidates if c in PERIODIC]
    det = list(evidence.get("order_spectra_detection", {}).values())
    resolved = np.array([any(d["resolved"][k] for d in det) for k in range(MAX_ORDER)], dtype=bool)
    span = max((d.get("median_turn", 0.0) for d in det), default=0.0)
    torque_balance = bool(evidence.get("torque_balance_spectra"))
    groups: dict[tuple, list[str]] = {}
    for c in periodic:
        missing = () if (torque_balance and c != "kinematic_error") else tuple(int(k) + 1 for k in np.flatnonzero(~resolved))
        if missing:
            groups.setdefault(missing, []).append(c)
    out = []
    for missing, names in groups.items():
        which = "any order" if len(missing) == MAX_ORDER else (
            f"order {missing[0]}" if len(missing) == 1 else f"orders {missing[0]}–{missing[-1]}")
        out.append({"description": f"{', '.join(names)} not testable at {which}",
                    "evidence": f"the tests turn the wave generator by at most {span:.2f} rad (median over the tests of one kind); "
                                f"a cycle of order k takes 2π/k rad, and an order is tested only over whole cycles, or a smooth "
                                f"function of the torsion over part of a cycle would pass for it. To test {which}, record "
                                "free-motion runs that turn the wave generator through several turns in each direction"})
    return out


def _data_context(p_base: Parameters, batch: Experiment, sigma, tachometer_lag_s: float | None = None) -> dict:
    """Scales of the effect columns, from the data and the base parameters where possible (they
    would otherwise need a simulation): K1 (N·m/rad), Coulomb level and noise levels (N·m, rad/s,
    A), largest torsion (rad) and torque (N·m), sample interval and session span (s), the RMS
    measured wave-generator speed of the free-motion tests (rad/s; of all tests if none is free)
    and, where given, the measured `tachometer_lag` (s; `sensor_bandwidth` then holds its velocity
    lag there instead of fitting it)."""
    m = np.asarray(batch.mask)
    n_exp = m.shape[0]
    free = np.asarray(batch.free) > 0
    speed_rows = m & free[:, None] if free.any() else m
    speed = float(np.sqrt(np.mean(np.square(np.asarray(batch.motor_velocity)[speed_rows]))))
    return {
        "K1": float(p_base.K1),
        "coulomb": 0.5 * (abs(float(p_base.Tsp)) + abs(float(p_base.Tsn))),
        "torque_noise": float(sigma[0]),
        "velocity_noise": float(sigma[1]),
        "current_noise": max(float(np.median([white_noise_level(np.asarray(batch.current)[e][m[e]]) for e in range(n_exp)])),
                             1e-3 * float(np.max(np.abs(np.asarray(batch.current)[m])))),
        "torsion": float(np.max(np.abs(np.asarray(batch.torque)[m]))) / float(p_base.K1) or 1e-3,
        "torque_max": float(np.max(np.abs(np.asarray(batch.torque)[m]))),
        "dt": float(np.median(np.diff(np.asarray(batch.time[0])[m[0]]))),
        "session_span": float(np.max(np.asarray(batch.start_time)) + np.max(np.asarray(batch.time))),
        "wave_generator_speed": speed if speed > 0.0 else 1.0,
    } | ({} if tachometer_lag_s is None else {"tachometer_lag": float(tachometer_lag_s)})


def _record_noise(experiments: list[Experiment], modes: np.ndarray, sigma, per_record: bool) -> np.ndarray:
    """Sensor-noise level per (experiment, channel): every record at its own (a bench may scale the
    noise with the range), or one level per channel."""
    sig_exp = np.tile(np.asarray(sigma), (len(experiments), 1))
    if per_record:
        sig_exp = np.stack([np.asarray(noise_levels(stack_experiments([e]))) for e in experiments])
        sig_exp[:, 2] = np.where(modes == "free", sig_exp[:, 2], float(sigma[2]))
    return sig_exp


def _folds(modes: np.ndarray, cross_validation: str) -> tuple[np.ndarray, np.ndarray]:
    """(`folds`, `fit_folds`): the two halves (experiments alternate within each mode, so each half
    holds both modes when possible), and the fits that predict each held-out experiment: leave
    one experiment out (every fit sees all but one record, so its effect estimate is nearly the
    full-data one; one batch simulation evaluates all of them, one z per experiment), or the two
    halves. Held-out gains are reported, and must be positive, per half either way."""
    n_exp = len(modes)
    folds = np.arange(n_exp) % 2
    for md in ("constrained", "free"):
        idx = np.where(modes == md)[0]
        folds[idx] = np.arange(len(idx)) % 2
    fit_folds = np.arange(n_exp) if cross_validation == "leave_one_out" else folds
    return folds, fit_folds


def _screened_orders(evidence: dict, orders, candidates: list[str], log) -> tuple[dict, list[str]]:
    """The orders at which each periodic candidate is screened, and the candidates left.

    A periodic effect is screened only at the orders its evidence proposes, and not at all when no
    order stands out. (Over the fraction of a turn that a locked test covers, sin/cos of a low order
    are smooth functions of the torque that absorb other misfit: with orders 1 and 2 screened by
    default, a spurious torque_sensor_ripple [1, 2] was named on independent-bench datasets that hid
    load-dependent friction or hysteresis.)"""
    orders_of = orders_per_candidate(orders, evidence)
    dropped = [c for c in candidates if c in PERIODIC and not orders_of.get(c)]
    candidates = [c for c in candidates if c not in dropped]
    if dropped:
        log(f"diagnose: no order-spectrum peak for {', '.join(dropped)}: not screened")
    log("diagnose: periodic candidates screened at orders " + ", ".join(f"{c} {orders_of[c]}" for c in candidates if c in PERIODIC))
    evidence["periodic_candidates_screened"] = bool(any(orders_of.values()))
    evidence["candidate_orders_per_effect"] = {c: orders_of[c] for c in candidates if c in PERIODIC}
    return orders_of, candidates


def _torque_balance_route(loop: _Loop, traj, evidence: dict, drive: Drive, *, requested: set, max_findings: int,
                          rule: Significance, cand_idx: dict, orders_of: dict, log) -> list[dict]:
    """Cogging and position-dependent friction from the motor torque balance (module docstring,
    step 2b), before the output-error rounds: an order that stands out in the torque-balance
    spectrum (measured signals, eq. 8) is judged by its held-out gain in that residual, record by
    record. The output-error screening cannot resolve these: a torque disturbance integrates into
    the velocity with opposite phase in the two directions of motion, and the paper model's
    free-motion misfit hides what is left. A term found here keeps its torque-balance fit (its
    columns are not re-fitted by the output-error rounds; `loop.z` is set) and counts towards
    `max_findings`. Returns the findings (updates `cand_idx`, `orders_of`)."""
    # both spectra were taken by `residual_evidence` at this model (p_base, traj)
    batch, m, modes, cols, n_base = loop.batch, loop.m, loop.modes, loop.cols, loop.n_base
    torque_amp = {}
    for pk in evidence["spectral_peaks"]:
        if pk["where"].endswith("/torque"):
            torque_amp[pk["order"]] = max(torque_amp.get(pk["order"], 0.0), pk["amplitude"])
    found: list[dict] = []
    for pk in sorted(evidence["torque_balance_peaks"], key=lambda x: -x["over_median"]):
        where, k, over_med, over_max = pk["where"], pk["order"], pk["over_median"], pk["over_max"]
        name = "position_dependent_friction" if where.endswith("sign(w)") else "cogging"
        if name in [f["effect"] for f in found] or name not in requested or len(found) >= max_findings:
            continue
        cv = torque_balance_cv(batch, traj, m, modes, loop.p_base, drive, name, k, rule=rule)
        if cv is None:
            continue
        ratio = strain_gauge_ratio(torque_amp.get(k, 0.0), loop.p_base, drive, name, cv["coef"])
        log(f"diagnose: torque balance: {name} [{k}] torque-residual amplitude / (N × its amplitude) = {ratio:.3f}")
        if ratio > TB_RIPPLE_RATIO:
            continue  # a strain-gauge ripple, not a motor-side torque (see TB_RIPPLE_RATIO)
        log(f"diagnose: torque balance: {name} [{k}] peak {over_med:.1f}× median, held-out gain {100 * cv['gain']:+.2f} % "
            f"(improved in {cv['n_improved']} of {cv['n_records']} records, {cv['n_counted']} counted; record changes "
            f"{', '.join(f'{100 * x:+.0f}' for x in cv['record_changes'])} %)")
        if not (cv["gain"] > TB_MIN_GAIN and rule.consistent(cv["improved_fraction"])):
            continue
        jcols = _candidate_columns(cols, name, [k], offset=n_base)  # sin, cos of order k
        scale = np.array([cols[j - n_base].scale for j in jcols])
        zs = loop.tile(loop.z)
        for e in range(loop.n_exp):
            zs[e, jcols] = cv["coef_without"].get(e, cv["coef"]) / scale
        _, raw_a = loop.simulate_each(zs)
        d = _per_exp(loop.r_raw) - _per_exp(raw_a)
        # reported, not a veto: on the independent bench a true order-1 cogging (fitted at 80 % of
        # its amplitude, phase right) made the simulated output error worse, most of it in a slow
        # free test that turns the wave generator by 1 rad
        log(f"  simulated held-out SSE (sensor-noise units) change {-float(np.sum(d)):+.1f}")
        loop.z[jcols] = cv["coef"] / scale
        cand_idx[name] = jcols
        orders_of[name] = sorted(set(orders_of.get(name, [])) | {k})
        found.append({
            "effect": name,
            "confidence": round(float(1.0 - 2.0 ** -cv["n_improved"]), 4),
            "gain": {"heldout_nrmse_before": loop.nrmse(loop.r_raw),
                     "heldout_nrmse_after": loop.nrmse(raw_a),
                     "relative_reduction": cv["gain"], "fold_reductions": cv["fold_gains"],
                     "heldout_torque_balance_reduction": cv["gain"],
                     "heldout_output_error_sse_reduction": float(np.sum(d))},
            "_round": None, "_tb": {"order": k, "over_median": over_med, "over_max": over_max, **cv},
        })
    if found:
        loop.r, loop.r_raw = loop.simulate_each(loop.tile(loop.z))
    return found


def _drop_torque_balance_lookalikes(tb_findings: list[dict], orders_of: dict, cand_idx: dict, remaining: list[str],
                                    cols: list[_Column], n_base: int, log) -> None:
    """After the torque-balance route names cogging or position-dependent friction at order k, the
    other of the two is not screened at k by the output-error rounds (updates `orders_of`,
    `cand_idx`, `remaining`). The torque balance tells them apart directly (a term periodic in θm
    in e, or in e·sign(ω)); the output error cannot (a torque disturbance integrates with opposite
    phase in the two directions of motion), and with the found term held at its torque-balance
    fit, the other one at the same order takes up the correction to it: independent-bench seed
    5016 (cogging [3] hidden) named a false position_dependent_friction [3] at +3.4 % held out
    (free tests +5.3 %, 6 of 8 improved) after the route's cogging [3] (2026-11-27)."""
    other = {"cogging": "position_dependent_friction", "position_dependent_friction": "cogging"}
    for f in tb_findings:
        twin, k = other[f["effect"]], f["_tb"]["order"]
        if twin not in remaining or k not in orders_of.get(twin, []):
            continue
        orders_of[twin] = [o for o in orders_of[twin] if o != k]
        cand_idx[twin] = _candidate_columns(cols, twin, orders_of[twin], offset=n_base)
        log(f"diagnose: {twin} [{k}] not screened: the torque balance named {f['effect']} [{k}]")
        if not orders_of[twin]:
            remaining.remove(twin)


def _round_noise_model(loop: _Loop, *, misfit_scaling: bool) -> tuple[np.ndarray, np.ndarray]:
    """Noise model of the model as it now stands (module docstring, step 3), used by every SSE
    compared within this round; sets `loop.noise_model` and re-whitens `loop.r`.

    The recorded current drives the simulation, so its sensor noise makes the simulated velocity and
    output position wander (a random walk in free motion, ×1 to ×40 the sensor noise's variance from
    one record to the next) beyond the sensor noise. That process noise is sampled by simulating the
    current model with white noise of the current's own level added to the current; an AR model per
    experiment and channel of it plus the sensor noise whitens residuals and Jacobian (a linear
    filter along time: Gauss–Newton fits stay exact). Re-estimated every round: an accepted effect
    changes how the current's noise propagates (e.g. friction that varies with θm). Not the base
    model's residual RMS: that holds the very misfit an effect leaves, and down-weighted the channel
    where e.g. thermal drift shows. With `misfit_scaling`, what the current model leaves in an
    (experiment, channel) beyond its noise model counts as that record's noise (a bench is never
    exactly the model). Returns the process-noise samples and the residual whitened before that
    scaling."""
    z, m = loop.z, loop.m
    proc = _process_noise(lambda b: loop.simulate_each(loop.tile(z), b)[1], loop.batch, loop.r_raw)
    noise_model = _noise_model(proc, m)
    r_white0 = noise_model.whiten(loop.r_raw)
    if misfit_scaling:
        rho = np.ones(noise_model.s.shape)
        for e in range(loop.n_exp):
            for c in range(3):
                v = r_white0[e, c, : int(m[e].sum())]
                if np.any(v != 0):
                    rho[e, c] = max(1.0, float(np.sqrt(np.mean(v**2))))
        noise_model = dataclasses.replace(noise_model, s=noise_model.s * rho)
    loop.noise_model = noise_model
    loop.r = noise_model.whiten(loop.r_raw)
    return proc, r_white0


def _noise_evidence(loop: _Loop, proc: np.ndarray, r_white0: np.ndarray, evidence: dict, log) -> None:
    """Per mode and channel (first round): noise (sensor + process) over sensor noise, and the base
    model's residual RMS before and after whitening (1 = noise only), into `evidence`."""
    modes, m = loop.modes, loop.m
    ratio, raw_rms, white_rms = {}, {}, {}
    for md in ("constrained", "free"):
        selm = modes == md
        for c, ch in enumerate(("torque", "motor_velocity", "output_position")):
            rr = loop.r_raw[selm, c][m[selm]]
            if not selm.any() or not np.any(rr != 0):
                continue
            ratio[f"{md}/{ch}"] = float(np.sqrt(1.0 + np.mean(proc[:, selm, c][:, m[selm]] ** 2)))
            raw_rms[f"{md}/{ch}"] = float(np.sqrt(np.mean(rr**2)))
            white_rms[f"{md}/{ch}"] = float(np.sqrt(np.mean(r_white0[selm, c][m[selm]] ** 2)))
    evidence["noise_over_sensor_noise"] = ratio
    evidence["base_residual_rms"] = raw_rms
    evidence["base_whitened_residual_rms"] = white_rms
    log("  noise (sensor + process) / sensor noise: " + ", ".join(f"{k} {v:.2f}" for k, v in ratio.items()))
    log("  base model residual RMS / sensor noise: " + ", ".join(f"{k} {v:.2f}" for k, v in raw_rms.items()))
    log("  base model whitened residual RMS (1 = noise only): " + ", ".join(f"{k} {v:.2f}" for k, v in white_rms.items()))


def _refine(loop: _Loop, J: np.ndarray, sel: list[int], active: list[int], *, steps: int, jacobians: int, log,
            relinearise_on_stall: bool = False) -> np.ndarray:
    """Refit base + accepted effects (`active` columns) by chord Gauss–Newton steps with
    backtracking on the *simulated* error, re-linearised (at most `jacobians` Jacobians) while those
    steps keep gaining; updates `loop.z` and its residuals. Returns the Jacobian (columns `sel`)
    the round screens with: a slightly stale one still gives descent directions, and every figure
    is simulated. `relinearise_on_stall`: a chord step that gains nothing after earlier ones of the
    same Jacobian did also calls for a new Jacobian (else the refit ends there), for a strongly
    nonlinear adjustment (`DAMPED_SCREEN`)."""
    col_of = {j: k for k, j in enumerate(sel)}
    all_rows = np.ones(loop.n_exp, bool)
    sse_cur = float(np.sum(loop.r**2))
    for jac_round in range(jacobians):
        if jac_round:
            # the chord steps were still gaining: the model moved far from where J was taken (a
            # nonlinear effect parameter such as the thermal time constant); re-linearise, or the
            # misfit left over would be offered to the next candidate as a finding
            log("  refinement still gaining: new Jacobian")
            J = loop.jacobian(loop.z, sel)
        converged = False
        for it in range(steps):
            delta = _gn_step(loop.r, J, all_rows, [col_of[j] for j in active])
            improved = False
            for frac in (1.0, 0.5, 0.25):
                z = loop.z.copy()
                z[active] += frac * delta
                r, r_z = loop.simulate_each(loop.tile(z))
                sse = float(np.sum(r**2))
                if sse < sse_cur:
                    improved = True
                    break
            if not improved:
                converged = not (relinearise_on_stall and it > 0)
                break
            gain_it = 1.0 - sse / sse_cur
            loop.z, loop.r, loop.r_raw, sse_cur = z, r, r_z, sse
            log(f"  refit: whitened SSE {sse_cur:.5g} (step fraction {frac}, −{100 * gain_it:.2f} %)")
            if gain_it < 1e-3:
                converged = True
                break
        if converged:
            break
    return J


@dataclasses.dataclass(frozen=True)
class _FoldFits:
    """Linearised fold fits at the current model z (residuals r, Jacobian J with columns `col_of`)
    from the per-experiment normal equations `A_exp`, `b_exp` (a fold's fit sums those of its
    training experiments)."""

    z: np.ndarray
    r: np.ndarray
    J: np.ndarray
    col_of: dict
    n_base: int
    fit_folds: np.ndarray
    A_exp: np.ndarray
    b_exp: np.ndarray
    J_full: np.ndarray | None = None  # J with the unresolved experiments not zeroed (`two_stage`)
    unresolved: frozenset = frozenset()  # columns zeroed somewhere

    @classmethod
    def at(cls, loop: _Loop, J: np.ndarray, sel: list[int], fit_folds: np.ndarray, *, two_stage: bool = False) -> "_FoldFits":
        """The fold fits at `loop`'s current model, with `J` (columns `sel`)."""
        n_exp = loop.n_exp
        Jf = J.reshape(n_exp, -1, J.shape[-1])
        return cls(z=loop.z, r=loop.r, J=J, col_of={j: k for k, j in enumerate(sel)}, n_base=loop.n_base, fit_folds=fit_folds,
                   A_exp=np.einsum("eti,etj->eij", Jf, Jf), b_exp=np.einsum("eti,et->ei", Jf, loop.r.reshape(n_exp, -1)),
                   J_full=loop.full_jacobian(J, sel) if two_stage else None,
                   unresolved=frozenset(j for j in sel if j in loop.unresolved))

    def steps(self, idx):
        """Per-experiment parameter vectors: experiment j gets the Gauss–Newton fit of the base
        parameters and the columns `idx` on the fold that does not contain j (so an effect
        confounded with K1, Tst or the friction is judged after they re-adjust, as in a full re-fit);
        plus the linearised prediction of its residual."""
        zs = np.tile(self.z, (self.r.shape[0], 1))
        pred = self.r.copy()
        cols_ = list(range(self.n_base)) + list(idx)
        k = [self.col_of[j] for j in cols_]
        A = self.A_exp[:, k][:, :, k]
        b = self.b_exp[:, k]
        part = [j for j in idx if j in self.unresolved]
        for f in np.unique(self.fit_folds):
            test = self.fit_folds == f
            delta = _solve_normal(A[~test].sum(0), b[~test].sum(0))
            if part and self.J_full is not None:
                delta = self._second_stage(cols_, delta, part, test)
                pred[test] = self.r[test] + self.J_full[test][..., k] @ delta
            else:
                pred[test] = self.r[test] + self.J[test][..., k] @ delta
            zs[np.ix_(test, cols_)] += delta
        return zs, pred

    def all_records_step(self, idx, *, two_stage: bool = False) -> np.ndarray:
        """The Gauss–Newton fit of the base parameters and the columns `idx` on every experiment
        (one z, the in-sample counterpart of `steps`)."""
        z = self.z.copy()
        cols_ = list(range(self.n_base)) + list(idx)
        k = [self.col_of[j] for j in cols_]
        delta = _solve_normal(self.A_exp[:, k][:, :, k].sum(0), self.b_exp[:, k].sum(0))
        part = [j for j in idx if j in self.unresolved]
        if two_stage and part and self.J_full is not None:
            delta = self._second_stage(cols_, delta, part, np.zeros(self.r.shape[0], bool))
        z[cols_] += delta
        return z

    def between_record_share(self, pred_before: np.ndarray, pred: np.ndarray, modulated: list[int], records: np.ndarray) -> float:
        """Of what a free value per record of the base columns `modulated` (each record's own fit,
        on top of its held-out prediction `pred_before`) would gain on `records`, the share that the
        held-out prediction `pred` gains (linearised; 1 = a drift term predicts every record's own
        value from the others, ≤ 0 = none of it; `DRIFT_EFFECTS`)."""
        n_exp = self.r.shape[0]
        Jf = self.J.reshape(n_exp, -1, self.J.shape[-1])[..., [self.col_of[j] for j in modulated]]
        gain = own = 0.0
        for e in np.where(records)[0]:
            rb = pred_before[e].reshape(-1)
            x, *_ = np.linalg.lstsq(Jf[e], -rb, rcond=None)
            sse_b = float(rb @ rb)
            gain += sse_b - float(np.sum(pred[e] ** 2))
            own += sse_b - float(np.sum((rb + Jf[e] @ x) ** 2))
        return gain / own if own > 0 else 0.0

    def _second_stage(self, cols_: list[int], delta: np.ndarray, part: list[int], test: np.ndarray) -> np.ndarray:
        """`two_stage`: the periodic columns `part` keep their fit from the experiments where they
        complete a cycle (`delta`); every other column is re-fitted on the training experiments to
        what those terms do everywhere (the unzeroed Jacobian `J_full`). Without this, a term fitted
        on free tests changes the locked tests' effective stiffness, which no other column was
        fitted to take up (measured 2026-11-27 on bench seed 5012: locked tests −29 % held out)."""
        assert self.J_full is not None
        n_exp = self.r.shape[0]
        pos = {j: i for i, j in enumerate(cols_)}
        rest = [j for j in cols_ if j not in part]
        Jt = self.J_full.reshape(n_exp, -1, self.J_full.shape[-1])[~test]
        Jr, Jp = Jt[..., [self.col_of[j] for j in rest]], Jt[..., [self.col_of[j] for j in part]]
        dp = delta[[pos[j] for j in part]]
        rr = self.r.reshape(n_exp, -1)[~test] + Jp @ dp
        d_rest = _solve_normal(np.einsum("eti,etj->ij", Jr, Jr), np.einsum("eti,et->i", Jr, rr))
        out = delta.copy()
        out[[pos[j] for j in rest]] = d_rest
        return out


def _judge(res_before: np.ndarray, res_after: np.ndarray, folds: np.ndarray, modes: np.ndarray, k: int,
           rule: Significance, *, drift_share: float | None = None) -> dict:
    """The simulated held-out figures of a candidate with `k` parameters from the whitened held-out
    residuals without and with it, and whether `rule` names it. A drift term (`DRIFT_EFFECTS`)
    passes the effect-size rule also with a `drift_share` ≥ `rule.min_drift_share` (its fit's
    signs consistent and physical; see `_screen`)."""
    sse_before, sse_after = _fold_sse(res_before, folds), _fold_sse(res_after, folds)
    e_before = _per_exp(res_before)
    gain = 1.0 - sse_after.sum() / sse_before.sum()
    dchi = float(sse_before.sum() - sse_after.sum())
    d = e_before - _per_exp(res_after)
    # reported, not decisive (see the module docstring): how much the held-out experiments it makes
    # worse lose, over what those it improves gain
    harm = float(np.sum(np.maximum(-d, 0.0)) / max(np.sum(np.maximum(d, 0.0)), 1e-300))
    # and not resting on one experiment: without the held-out experiment that gains most, the rest
    # must still gain beyond the chance level
    chance = rule.chance(k)
    dchi_rest = float(np.sum(d) - np.max(d))
    # effect size where the effect acts: an effect of the locked tests only (stiffness) is not
    # diluted by the free-motion channels, and vice versa
    mode_gains = {md: float(np.sum(d[modes == md]) / np.sum(e_before[modes == md]))
                  for md in ("constrained", "free") if np.any(modes == md)}
    # and a term that makes one kind of test worse beyond chance, by more than a `mode_trade` share of
    # what it gains on the other, explains no drive: a spurious order-1 kinematic error fitted to
    # locked tests loses on the free ones
    mode_dchi = {md: float(np.sum(d[modes == md])) for md in mode_gains}
    # consistency over records: most held-out experiments of the mode where it acts must improve
    # (misfit that one term absorbs in a few records is no finding)
    moved = _per_exp(res_after - res_before)  # how far the candidate moves each held-out record
    counts = {md: rule.improved_fraction(d[modes == md], e_before[modes == md], moved[modes == md]) for md in mode_gains}
    improved_in = {md: c[0] for md, c in counts.items()}
    acting = max(mode_gains, key=mode_gains.__getitem__)
    if rule.consistency_in == "any_acting":  # a mode where it gains beyond the effect size, consistent first
        large_modes = [md for md in mode_gains if mode_gains[md] > rule.min_relative_gain] or [acting]
        acting = max(large_modes, key=lambda md: (rule.consistent(improved_in[md]), mode_gains[md]))
    improved = improved_in[acting]
    # and the effect size, too, not resting on one record: the acting mode without its experiment
    # that gains most (`MIN_GAIN_WITHOUT_BEST`; not judged with a single experiment in that mode)
    in_mode = modes == acting
    d_m, e_m = d[in_mode], e_before[in_mode]
    best = int(np.argmax(d_m))
    gain_rest = float((np.sum(d_m) - d_m[best]) / (np.sum(e_m) - e_m[best])) if d_m.size > 1 else None
    drift_large = rule.drift_is_large(drift_share)
    sized = max(mode_gains.values()) > rule.min_relative_gain
    sized_without_best = gain_rest is None or gain_rest > rule.min_gain_without_best
    # and no record contradicts it (`MAX_RECORD_LOSS`)
    rel = d / e_before
    worst = int(np.argmin(rel))
    contradicted = rule.contradicted(float(-d[worst]), float(-rel[worst]), k)
    refused_by = [name for name, ok in (
        ("folds", bool(np.all(sse_after < sse_before))),
        ("effect_size", sized or drift_large),
        ("effect_size_without_best", not sized or sized_without_best or drift_large),
        ("chance", dchi > chance),
        ("chance_without_best", dchi_rest > chance),
        ("mode_trade", min(mode_dchi.values()) > -max(chance, rule.mode_trade * max(mode_dchi.values()))),
        ("consistency", rule.consistent(improved)),
        ("record_loss", not contradicted),
    ) if not ok]
    significant = not refused_by
    return dict(simulated=True, gain=float(gain), fold_gains=(1 - sse_after / sse_before).tolist(), delta_chi2=dchi,
                refused_by=refused_by, best_experiment=int(np.flatnonzero(in_mode)[best]),
                improved_count=counts[acting][1], counted_count=counts[acting][2], mode_count=int(d_m.size), chance=chance,
                delta_chi2_without_best_experiment=dchi_rest, mode_gains=mode_gains,
                harm_ratio=harm, per_experiment_gain=rel.tolist(),
                moved_count={md: rule.records_moved(moved[modes == md], e_before[modes == md]) for md in mode_gains},
                mode_delta_chi2=mode_dchi, improved_fraction=improved, acting_mode=acting,
                acting_mode_gain_without_best=gain_rest, contradicted_by=int(worst) if contradicted else None,
                significant=significant)


#: Effects that change a base parameter from record to record (a drift over the session), with the
#: base parameters they change and the test mode where they act. Such a term's size is not its share of the whole residual: thermal drift on the
#: independent bench (β = 0.47 % of the viscous friction, 4.5× the velocity noise before the base fit
#: takes up its mean) gained 1.1 % of the held-out whitened error, but 80 % of what a free viscous
#: friction per record would gain (bench seed 5009; 2026-11-27); so it is judged by that share
#: (`Significance.min_drift_share`). Its fit's sign must be physical (`PHYSICAL_SIGN`: β > 0).
DRIFT_EFFECTS = {"thermal_drift": (("Tvp", "Tvn"), "free")}


#: The sign SPEC §4's physics gives an effect's fitted parameter: friction falls as the lubricant
#: warms (β > 0), meshing friction grows with the transmitted torque (μ > 0), the stiffness rises
#: with torsion (K3 > 0), the flexspline's rate-independent loop dissipates (Th > 0), the amplifier
#: lags (τd > 0). A term fitted with the other sign absorbs some other misfit and is not that
#: effect: on clean independent-bench data whose viscous friction grows as |ω|^0.7 instead of
#: linearly (a drive's no-load running torque often does), the loop named a `thermal_drift` with
#: β = −0.13, friction *rising* over the session by 13 % (2026-11-29, seed 5010). A candidate is
#: named only when every held-out fold fit has this sign (`Significance.physical_sign`).
#: Lost motion (|backlash|) and the periodic terms (a phase) have no sign.
PHYSICAL_SIGN = {"thermal_drift": ("beta", 1.0), "load_dependent_friction": ("mu", 1.0), "nonlinear_stiffness": ("K3", 1.0),
                 "rate_independent_hysteresis": ("Th", 1.0), "input_delay": ("delay", 1.0)}


def _physical_sign(cols: list[_Column], n_base: int, c: str, zs: np.ndarray, cols_c: list[int]) -> bool:
    """True when candidate `c`'s parameter has the sign of `PHYSICAL_SIGN` in every held-out fold fit
    `zs` (one row per experiment: `n_base` base values, then the effect columns `cols`; `cols_c` are
    `c`'s indices into a row), or `c` has no such sign."""
    if c not in PHYSICAL_SIGN:
        return True
    field, sign = PHYSICAL_SIGN[c]
    for j in cols_c:
        col = cols[j - n_base]
        if col.field == field:
            return bool(np.all(sign * (col.start + col.scale * zs[:, j]) > 0))
    return True


def _drift_share(ff: _FoldFits, pred_before: np.ndarray, steps: tuple[np.ndarray, np.ndarray], cols_c: list[int],
                 modulated: list[int], records: np.ndarray, sign: float) -> float:
    """The between-record share (`_FoldFits.between_record_share`) of a drift term with columns
    `cols_c`, whose held-out fold fits are `steps` (`_FoldFits.steps`), over the base columns
    `modulated` on `records`; 0 where a held-out fit of its parameter has not the sign `sign`."""
    zs, pred = steps
    if not np.all(sign * zs[:, cols_c] > 0):
        return 0.0
    return ff.between_record_share(pred_before, pred, modulated, records)


def _share_of(loop: _Loop, ff: _FoldFits, c: str, pred_before: np.ndarray, steps: tuple[np.ndarray, np.ndarray],
              cols_c: list[int]) -> float:
    """`_drift_share` of candidate `c` (`DRIFT_EFFECTS` or `AMPLITUDE_EFFECTS`: the base parameters
    it changes from record to record) on the tests of the mode where it acts; 0 where a base
    parameter it changes is not fitted."""
    names, mode = DRIFT_EFFECTS[c] if c in DRIFT_EFFECTS else AMPLITUDE_EFFECTS[c]
    sign = PHYSICAL_SIGN[c][1]
    fields = loop.prob.pmap.fields  # the base parameters, in the order of z[:n_base]
    if not all(n in fields for n in names):
        return 0.0
    return _drift_share(ff, pred_before, steps, cols_c, [fields.index(n) for n in names], loop.modes == mode, sign)


def _drift_course(loop: _Loop, c: str) -> np.ndarray:
    """The time course of drift `c` at each record (`DRIFT_EFFECTS`; the mean over its samples):
    `thermal_drift`'s e^(−t_session/τ) at the τ the loop holds (`AbstractTerm.from_data`)."""
    term = loop.prob.effects.term(c)
    assert isinstance(term, ThermalDrift), c
    tau = abs(float(term.tau))
    b = loop.batch
    t = np.asarray(b.start_time)[:, None] + np.asarray(b.time)
    m = np.asarray(b.mask, dtype=bool)
    return np.sum(np.exp(-t / tau), axis=1, where=m) / np.sum(m, axis=1)


def _drift_trend_of(loop: _Loop, ff: _FoldFits, c: str, cols_c: list[int]) -> tuple[float, float]:
    """The between-record trend test (`hdjax._discrepancy.significance.drift_trend_test`) of drift
    candidate `c` with its one amplitude column `cols_c` (β) on the records of the mode where it
    acts: each record's own level of what the drift scales (its whitened residual projected on the
    amplitude column, divided by the course: for the thermal drift, the record's viscous friction
    relative to the common fit) against the course `_drift_course`, weighted by each record's
    information about that level. Returns (p-value, amplitude in the column's units)."""
    _, mode = DRIFT_EFFECTS[c]
    rec = np.flatnonzero(loop.modes == mode)
    if len(cols_c) != 1 or rec.size < 3:
        return 1.0, 0.0
    k = ff.col_of[cols_c[0]]
    g = _drift_course(loop, c)[rec]
    a, b = ff.A_exp[rec, k, k], ff.b_exp[rec, k]
    if not (np.all(a > 0) and np.all(g > 0)):
        return 1.0, 0.0
    p, slope = drift_trend_test(g, -g * b / a, a / g**2)
    col = loop.cols[cols_c[0] - loop.n_base]
    return p, col.scale * slope


#: Effects that change a base parameter with the size of the motion of each record, with that base
#: parameter and the test mode where they act: a cubic stiffness (K1Δθ + K3Δθ³) is, record by record,
#: mostly a stiffer K1 in the records twisted further, which the base fit's one K1 takes up; what is
#: left in the residual is small (HD2-like bench seeds 5019, 5065, 5077: the cubic predicted +0.3 to
#: +1.6 % held out, under the effect size). `_stiffness_trend_of` tests it between records.
AMPLITUDE_EFFECTS = {"nonlinear_stiffness": (("K1",), "constrained")}


def _stiffness_trend_of(loop: _Loop, ff: _FoldFits, c: str, cols_c: list[int]) -> tuple[float, float]:
    """The between-record trend test (`drift_trend_test`) of `c` (`AMPLITUDE_EFFECTS`, one amplitude
    column `cols_c`) on the records of the mode where it acts: each record's own level of the base
    parameter it changes (its linearised one-parameter fit on top of the common model, −b/a of that
    record's normal equations) against how much of the candidate's column that parameter takes up in
    the record (the projection of the candidate's column on the base column, A_ck/A_kk: for K3, about
    the record's mean squared torsion times 3), weighted by each record's information about its level.
    Returns (p-value, amplitude in physical units)."""
    (name,), mode = AMPLITUDE_EFFECTS[c]
    rec = np.flatnonzero(loop.modes == mode)
    fields = loop.prob.pmap.fields
    if len(cols_c) != 1 or rec.size < 3 or name not in fields or fields.index(name) not in ff.col_of:
        return 1.0, 0.0
    k, j = ff.col_of[fields.index(name)], ff.col_of[cols_c[0]]
    col = loop.cols[cols_c[0] - loop.n_base]
    return amplitude_trend(ff.A_exp[rec, k, k], ff.A_exp[rec, k, j], ff.b_exp[rec, k], col.scale)


def amplitude_trend(a_kk: np.ndarray, a_kj: np.ndarray, b_k: np.ndarray, scale: float) -> tuple[float, float]:
    """`_stiffness_trend_of` from each record's normal equations (column k: the base parameter; j:
    the candidate's, `scale` its physical units per column unit): level −b_k/a_kk against course
    a_kj/a_kk, weights a_kk, one-sided towards a positive parameter. Returns (p-value, amplitude
    in physical units)."""
    a, g, b = (np.asarray(x, dtype=float) for x in (a_kk, a_kj, b_k))
    if not np.all(a > 0) or scale == 0:
        return 1.0, 0.0
    sign = 1.0 if scale > 0 else -1.0  # one-sided in the parameter, not in the column
    p, slope = drift_trend_test(sign * g / a, -b / a, a)
    return p, sign * scale * slope


def _fold_sse(res: np.ndarray, folds: np.ndarray) -> np.ndarray:
    """Squared error of each half."""
    return np.array([np.sum(res[folds == f] ** 2) for f in (0, 1)])


#: Effects that act on every test alike, so that neither kind of test (locked or free) may get worse
#: held out beyond the chance level (`Significance.mode_trade` = 0 for them). The amplifier's delay
#: between the recorded current and the motor torque drives the locked tests' torque as it drives the
#: free tests' motion. All six true input delays logged on the default bench (2026-12-06/07, seeds
#: 5011–5070) gained in both modes (locked +3.7 … +16.6 %, free +2.4 … +13.6 %); a false one on clean
#: data of the LuGre/per-record variant (seed 5024, sixty-seventh session) gained +5.2 % on the free
#: tests and cost the locked ones 1.1 % (7× the chance level), within `MODE_TRADE`. An effect of one
#: kind of test (stiffness, or a periodic term that mostly shows in free motion) keeps `MODE_TRADE`.
ACTS_ON_BOTH_MODES = frozenset({"input_delay"})


#: A candidate screened together with one parameter of a model_form term when that term was not
#: adopted in round 1 (candidate → the parameter's path). A strain-gauge ripple b·sin(kθm + φ) is, over
#: the part of a cycle that a locked or slow record turns the wave generator through, an offset of
#: that record's torque, and every record starts its angle at the same place: the ripple and the
#: torque sensor's offset explain each other's misfit, and neither is found alone. Variant-bench
#: seed 5039 (LuGre law, per-record noise, a ripple [4] at 4.7× the noise, a torque offset of
#: 0.30 N·m; sixty-seventh session): alone, the offset lost 421 % held out on a slow window record
#: (fitted at its noise before) and the ripple 279 % on the same record, so sensor_offset was refused in
#: round 1 and the ripple contradicted by that record; fitted together they gain +36.6 % held out. The
#: ripple is then judged also against the offset alone (`companion` rule), so that it is not named for
#: what the offset explains; where it is named, the offset joins the model as a `sensor_offset`
#: model_form item (its torque offset only) with the finding's held-out figures.
SCREENED_WITH = {"torque_sensor_ripple": "sensor_offset.torque_offset"}


def _companion_columns(loop: _Loop, cand_idx: dict, c: str) -> list[int]:
    """The columns among candidate `c`'s that belong to another term: those `SCREENED_WITH` gave it."""
    return [j for j in cand_idx[c] if loop.cols[j - loop.n_base].effect != c]


def _rule_for(c: str, rule: Significance) -> Significance:
    """The rules candidate `c` is judged by. A model_form adjustment (an offset, a lag) fitted on
    the other records may miss one record's own: the per-record rule (`MAX_RECORD_LOSS`) judges
    effects only. An effect of `ACTS_ON_BOTH_MODES` may not make either kind of test worse beyond
    the chance level (`mode_trade` 0)."""
    if c in MODEL_FORM:
        rule = dataclasses.replace(rule, max_record_loss=None)
    if c in ACTS_ON_BOTH_MODES:
        rule = dataclasses.replace(rule, mode_trade=0.0)
    return rule


#: Candidates whose held-out fold fits are damped before they are simulated: the linearised step
#: of `viscous_friction_law`'s exponent overshoots. On clean independent-bench data with a
#: |ω|^0.7 viscous law, its full held-out steps gained 68–80 % in the fastest free record and lost
#: 34–242 % in three to four others (seeds 5000, 5010 of the `viscous_exponent` variant, 2026-11-29).
DAMPED_SCREEN = frozenset({"viscous_friction_law"})
#: Adopted model_form adjustments (a term's name: all its parameters; a column path
#: `"term.field"`: that parameter alone) that keep their all-records value in the held-out fold fits
#: of later screenings (the base parameters and the effects are re-fitted per fold as before).
#: Log-scale shape parameters (the viscous law's exponent, the low-speed friction's scales), whose
#: linearised per-fold steps overshoot: on viscous-variant seed 5004 (viscous law and low-speed
#: friction adopted) 12 of 16 held-out fits went to ~10^9 × their whitened SSE when they were
#: re-fitted per fold (holding the exponent alone left that unchanged), and every candidate was
#: judged against that (2026-11-29, thirty-fourth session). And the current's DC offset (the
#: suspect, not measured fold by fold: in free motion a constant motor torque integrates into a
#: ramp of velocity, so a small per-fold step moves a held-out record far). Re-fitted per fold, the
#: offsets sent every held-out fit with fresh default-bench seed 5027's strain-gauge ripple [4] to
#: 5–100× its whitened SSE (gain −6 300 %, nothing named); with the current offset held it is named
#: alone (+37.5 % held out; 2026-12-04, forty-ninth session). Holding all three offsets named it too (+33 %), but the suite's small lost-motion
#: dataset then named a false input_delay beside the lost motion (+14.2 % held out; forty-seventh
#: session); with the current offset alone held, that dataset names the lost motion alone. The leak
#: is a few bench-wide constants, adopted on held-out evidence before; candidates with and without
#: are judged with the same values.
FIXED_IN_FOLDS = frozenset({"viscous_friction_law", "low_speed_friction", "sensor_offset.current_offset"})


def held_in_folds(adopted, cand_idx: dict, cols: list[_Column], n_base: int, held=FIXED_IN_FOLDS) -> set[int]:
    """The columns of the adopted model_form terms `adopted` (`cand_idx`: a term's columns, from
    `n_base` on into `cols`) that keep their all-records value in the held-out fold fits: every
    column of a term named in `held`, and a column whose path (`"term.field"`) is in `held`."""
    return {j for c in adopted for j in cand_idx[c] if c in held or cols[j - n_base].path in held}


#: The step fractions `_in_sample_step_fraction` tries, largest first.
STEP_FRACTIONS = (1.0, 0.5, 0.25)


def _in_sample_step_fraction(loop: _Loop, ff: _FoldFits, chosen_idx: list[int], idx: list[int]) -> float:
    """The fraction of the all-experiment Gauss–Newton step of the columns `idx` (from the fit
    without them) with the smallest simulated in-sample whitened SSE, among `STEP_FRACTIONS`; that
    fraction then scales every held-out fold step. The search sees every record, the held-out ones
    included: a choice among three step lengths, not a fit, so the leak is small (three batch
    simulations instead of one per fold for a search on each fold's training records)."""
    z0, z1 = ff.all_records_step(chosen_idx), ff.all_records_step(chosen_idx + idx)
    sse = [float(np.sum(loop.simulate_each(loop.tile(z0 + f * (z1 - z0)))[0] ** 2)) for f in STEP_FRACTIONS]
    return STEP_FRACTIONS[int(np.argmin(sse))]


def _screen(loop: _Loop, ff: _FoldFits, pool: list[str], chosen_idx: list[int], cand_idx: dict, folds: np.ndarray, *,
            n_simulated: int, rule: Significance, log, simulate_all: bool = False):
    """Screen the candidates `pool`: rank them by the linearised held-out error, simulate the held-out
    fits of the best `n_simulated` predicted above half the threshold (`simulate_all`: of every
    candidate, whatever its prediction), and judge those. A candidate with companion columns (among
    `cand_idx[c]`, of a model_form term: `SCREENED_WITH`) that passes is judged again against the
    held-out fits with those columns alone, and must pass there too. Returns the
    scores per candidate, the held-out residuals without any candidate (raw), and those with each
    simulated one (raw)."""
    zs_before, pred_before = ff.steps(chosen_idx)
    res_before, raw_before = loop.simulate_each(zs_before)
    e_before = _per_exp(res_before)
    steps = {c: ff.steps(chosen_idx + cand_idx[c]) for c in pool}  # held-out fold fits with each candidate
    predicted = {c: 1.0 - _fold_sse(steps[c][1], folds).sum() / _fold_sse(pred_before, folds).sum() for c in pool}
    share = {c: _share_of(loop, ff, c, pred_before, steps[c], cand_idx[c]) for c in pool if c in DRIFT_EFFECTS}
    trend = ({c: _drift_trend_of(loop, ff, c, cand_idx[c]) for c in pool if c in DRIFT_EFFECTS}
             if rule.drift_trend_p > 0 else {})
    amp_trend = {c: _stiffness_trend_of(loop, ff, c, cand_idx[c]) for c in pool if c in AMPLITUDE_EFFECTS}
    amp_share = {c: _share_of(loop, ff, c, pred_before, steps[c], cand_idx[c]) for c in amp_trend}
    scores, raw_after_of = {}, {}
    for c in sorted(pool, key=lambda c: -predicted[c]):
        s = {"predicted_gain": float(predicted[c]), "k": len(cand_idx[c]), "simulated": False}
        drift = share.get(c)
        if drift is not None:
            s["between_record_share"] = drift
        amp_named = c in amp_trend and rule.names_by_amplitude_trend(amp_trend[c][0], amp_share[c])
        trend_named = (c in trend and rule.names_by_trend(trend[c][0], drift)) or amp_named
        if c in amp_trend:
            s["trend_p_value"], s["trend_amplitude"] = amp_trend[c]
            s["between_record_share"] = amp_share[c]
        if c in trend:
            s["trend_p_value"], s["trend_amplitude"] = trend[c]
            if rule.names_by_trend(trend[c][0], None) and not trend_named:
                s["trend_contradicted"] = True  # by a negative between-record share of its held-out fits
        if simulate_all or trend_named or (len(raw_after_of) < n_simulated
                                           and (predicted[c] > SIMULATED_FROM * rule.min_relative_gain
                                                or rule.drift_is_large(drift))):
            zs_c = steps[c][0]
            if c in DAMPED_SCREEN:
                s["step_fraction"] = frac = _in_sample_step_fraction(loop, ff, chosen_idx, cand_idx[c])
                zs_c = zs_before + frac * (zs_c - zs_before)
            res_after, raw_after_of[c] = loop.simulate_each(zs_c)
            s.update(_judge(res_before, res_after, folds, loop.modes, s["k"], _rule_for(c, rule), drift_share=drift))
            if c in PHYSICAL_SIGN:
                s["physical_sign"] = _physical_sign(loop.cols, loop.n_base, c, steps[c][0], cand_idx[c])
                if rule.physical_sign and not s["physical_sign"]:
                    s["significant"] = False
                    s["refused_by"] = s["refused_by"] + ["physical_sign"]
            comp = _companion_columns(loop, cand_idx, c)
            if comp and s["significant"]:
                # and what it adds to its companion columns fitted alone must pass the same rules
                res_comp, _ = loop.simulate_each(ff.steps(chosen_idx + comp)[0])
                over = _judge(res_comp, res_after, folds, loop.modes, s["k"] - len(comp), _rule_for(c, rule))
                s["over_companion"] = {"gain": over["gain"], "mode_gains": over["mode_gains"], "refused_by": over["refused_by"]}
                if not over["significant"]:
                    s["significant"] = False
                    s["refused_by"] = s["refused_by"] + ["companion"]
            if amp_named and not s["significant"]:
                # and a term that the trend would name must move the held-out records it acts on:
                # at least two by more than `untouched_record_change` of their error (the consistency
                # rule's floor). Default-bench seed 5014 (a kinematic error [2]; sixty-sixth session):
                # a cubic at p 0.0020 moved no locked record by over 2 %; the hidden 5019 and 5077 pass
                s["trend_moved_count"] = n_moved = s["moved_count"].get(AMPLITUDE_EFFECTS[c][1], 0)
                if n_moved < 2:
                    trend_named = False
                    s["trend_too_small"] = True
            if trend_named and not s["significant"]:
                # the drift's own test: the records' levels follow its time course beyond what
                # shuffled start times give (`drift_trend_test`); the held-out rules' verdict is kept
                s["held_out_refused_by"], s["refused_by"], s["significant"] = s["refused_by"], [], True
                s["named_by"] = "between_record_trend"
        else:
            s.update(gain=float(predicted[c]), significant=False)
        scores[c] = s
        log(f"  {c:30s} held-out gain {'simulated' if s['simulated'] else 'predicted'} {s['gain']:+.3f}"
            + (f" (folds {np.round(s['fold_gains'], 3).tolist()}, modes "
               + ", ".join(f"{k} {v:+.3f}" for k, v in s["mode_gains"].items())
               + f", harm ratio {s['harm_ratio']:.2f}"
               + (f", {s['acting_mode']} without its best {s['acting_mode_gain_without_best']:+.3f}"
                  if s["acting_mode_gain_without_best"] is not None else "") + ")" if s["simulated"] else "")
            + (f" (between-record share {s['between_record_share']:.2f})" if "between_record_share" in s else "")
            + (f" (trend p {s['trend_p_value']:.4f}, amplitude {s['trend_amplitude']:+.4f})" if "trend_p_value" in s else "")
            + (" trend contradicted by the held-out fits (negative share)" if s.get("trend_contradicted") else "")
            + (" named by its between-record trend" if s.get("named_by") == "between_record_trend" else "")
            + (f" (over its companion {', '.join(loop.cols[j - loop.n_base].path for j in _companion_columns(loop, cand_idx, c))} alone: "
               f"{s['over_companion']['gain']:+.3f}" + (f", refused by {', '.join(s['over_companion']['refused_by'])}"
                                                       if s["over_companion"]["refused_by"] else "") + ")"
               if "over_companion" in s else "")
            + (f" (its trend not named: it moves {s['trend_moved_count']} held-out records by over "
               f"{100 * rule.untouched_record_change:g} %)" if s.get("trend_too_small") else "")
            + (f" contradicted by held-out experiment {s['contradicted_by']}" if s.get("contradicted_by") is not None else "")
            + (f" fitted with the unphysical sign of {PHYSICAL_SIGN[c][0]}" if s.get("physical_sign") is False else "")
            + (f" (step fraction {s['step_fraction']:g})" if "step_fraction" in s else "")
            + (" significant" if s["significant"] else ""))
        if s["simulated"]:
            log("    per held-out experiment: " + " ".join(f"{100 * g:+.0f}" for g in s["per_experiment_gain"])
                + " % of whitened SSE " + " ".join(f"{v:.0f}" for v in e_before))
    return scores, raw_before, raw_after_of


def _refusal(c: str, s: dict, rule: Significance, labels: list[str]) -> str:
    """Why the simulated candidate `c` with scores `s` (`_judge`) was not named, rule by rule, with
    its figures and the thresholds of `rule`; `labels` name the experiments."""
    md = s["acting_mode"]
    kind = {"constrained": "locked", "free": "free"}[md]
    best = s["best_experiment"]
    gain_best = 100 * s["per_experiment_gain"][best]
    drift = (f"; as a drift, its between-record share is {s['between_record_share']:.2f} (rule {rule.min_drift_share:g})"
             if "between_record_share" in s else "")
    why = {
        "folds": lambda: "one half of the held-out experiments does not improve (halves "
                         + " / ".join(f"{100 * g:+.1f} %" for g in s["fold_gains"]) + ")",
        "effect_size": lambda: (f"its largest gain on one kind of test, {100 * max(s['mode_gains'].values()):+.1f} %, "
                                f"is below the effect size of {100 * rule.min_relative_gain:g} %" + drift),
        "effect_size_without_best": lambda: (
            f"its gain on the {kind} tests, {100 * s['mode_gains'][md]:+.1f} %, falls to "
            f"{100 * (s['acting_mode_gain_without_best'] or 0.0):+.1f} % without {labels[best]} ({gain_best:+.0f} % there; "
            f"rule {100 * rule.min_gain_without_best:g} %)" + drift),
        "chance": lambda: f"its held-out Δχ² {s['delta_chi2']:.0f} is within the chance level {s['chance']:.0f}",
        "chance_without_best": lambda: (f"without {labels[best]} ({gain_best:+.0f} % there) its held-out Δχ² "
                                        f"{s['delta_chi2_without_best_experiment']:.0f} is within the chance level "
                                        f"{s['chance']:.0f}"),
        "mode_trade": lambda: "it makes one kind of test worse by more than it may for what it gains on the other ("
                              + ", ".join(f"{k} {100 * v:+.1f} %" for k, v in s["mode_gains"].items()) + ")",
        "consistency": lambda: (f"only {s['improved_count']} of the {s['counted_count']} {kind} tests "
                                + (f"counted (those made worse by at most {100 * rule.negligible_record_loss:g} % are left out, down to "
                                   f"those it moves, at least two, and at most half of the {s['mode_count']}) "
                                   if s["counted_count"] != s["mode_count"] else "")
                                + "improve held out "
                                f"(rule: {100 * rule.min_improved_fraction:g} %); the most, {labels[best]}, by "
                                f"{gain_best:+.0f} %"),
        "record_loss": lambda: (f"{labels[s['contradicted_by']]} gets {-100 * s['per_experiment_gain'][s['contradicted_by']]:.0f} % "
                                f"worse held out (rule: at most {100 * (rule.max_record_loss or 0.0):g} %)"),
        "physical_sign": lambda: f"its fitted {PHYSICAL_SIGN[c][0]} has the sign its physics excludes in some held-out fit",
        "companion": lambda: (f"fitted with {SCREENED_WITH.get(c, 'its companion')}, it does not pass the rules against that "
                              f"adjustment alone ({', '.join(s.get('over_companion', {}).get('refused_by', []))})"),
    }
    return "; ".join(why[r]() for r in s["refused_by"])


#: A candidate is simulated (among the best `confirm_top` of its round) from this share of
#: `Significance.min_relative_gain` of predicted held-out gain.
SIMULATED_FROM = 0.5


#: A near miss (reported in `unexplained`, never a finding): a candidate of the last round whose
#: held-out fits gain (simulated, or linearised where it was not simulated) at least this share of
#: the held-out error, named by no rule.
NEAR_MISS_GAIN = 0.01


def near_misses(scores: dict[str, dict], rule: Significance, labels: list[str], orders_of: dict) -> list[dict]:
    """`unexplained` entries for the effects of the last screening round (`scores`, which named
    nothing) whose held-out fits gain at least `NEAR_MISS_GAIN` but that a rule refused, largest
    gain first: what each would explain, and why it is not named (`_refusal`; a candidate that
    was not simulated, by its linearised prediction), so that a user sees what the data leave open
    and what record would settle it."""
    out = []
    for c, s in sorted(scores.items(), key=lambda x: -x[1]["gain"]):
        if c in MODEL_FORM or s["significant"] or s["gain"] < NEAR_MISS_GAIN:
            continue
        orders = f" {orders_of[c]}" if c in PERIODIC and c in orders_of else ""
        if not s.get("simulated"):
            # predicted only: its linearised held-out gain stayed under what is simulated
            out.append({"description": f"{c}{orders} is predicted to gain {100 * s['gain']:+.1f} % held out but is not named",
                        "evidence": "a linearised prediction of its held-out fits, not simulated (a round simulates the "
                                    f"best few candidates predicted above {100 * SIMULATED_FROM * rule.min_relative_gain:g} %); an effect "
                                    "this small, if real, needs more or longer records where it acts"})
            continue
        # resting on too few records (not a sign or a trade between the kinds of test): more would settle it
        few = bool({"consistency", "chance_without_best", "effect_size_without_best"} & set(s["refused_by"]))
        out.append({"description": f"{c}{orders} gains {100 * s['gain']:+.1f} % held out but is not named",
                    "evidence": "simulated held-out fits (halves " + " / ".join(f"{100 * g:+.1f} %" for g in s["fold_gains"])
                                + f"); not named because {_refusal(c, s, rule, labels)}"
                                + ((". More records where it acts would settle it" + (
                                    " (for a drift over the session: tests recorded early, while it lasts)"
                                    if c in DRIFT_EFFECTS else "")) if few else "")})
    return out


def _accept(loop: _Loop, J: np.ndarray, sel: list[int], new_cols: list[int], refit_cols: Sequence[int] = (), *,
            two_stage: bool = True, log=lambda *_: None) -> None:
    """Start accepted terms (`new_cols`) at their all-experiment Gauss–Newton fit (their columns
    only), where that lowers the simulated error; else at the all-experiment counterpart of the
    fold fits that judged them (`_screen`: the base parameters, the accepted columns `refit_cols`
    that the folds re-fit, and `new_cols`, two-stage), at the first of `STEP_FRACTIONS` that lowers
    it. The next round's refinement re-fits base and effects jointly."""
    col_of = {j: k for k, j in enumerate(sel)}
    z_try = loop.z.copy()
    z_try[new_cols] += _gn_step(loop.r, J, np.ones(loop.n_exp, bool), [col_of[j] for j in new_cols])
    r_try, raw_try = loop.simulate_each(loop.tile(z_try))
    sse_now, sse_own = float(np.sum(loop.r**2)), float(np.sum(r_try**2))
    if sse_own < sse_now:
        loop.z, loop.r, loop.r_raw = z_try, r_try, raw_try
        return
    # its own columns alone, with the base parameters and the accepted terms held, can raise the
    # error where the judgement re-fitted those too. On variant seeds 5001 and 5050 (a strain-gauge
    # ripple, +26.9 % and +18.8 % held out, with the torque offset accepted before it or screened
    # with it) the term stayed at its start, the next round's refinement found no descent either,
    # and the finding was named with its amplitudes at 0
    ff = _FoldFits.at(loop, J, sel, np.zeros(loop.n_exp, int), two_stage=two_stage)
    cols_ = list(dict.fromkeys(list(refit_cols) + list(new_cols)))
    z_full = ff.all_records_step(cols_, two_stage=two_stage)
    for frac in STEP_FRACTIONS:
        z_two = loop.z + frac * (z_full - loop.z)
        r_two, raw_two = loop.simulate_each(loop.tile(z_two))
        sse_two = float(np.sum(r_two**2))
        if sse_two < sse_now:
            log(f"  started at the all-records fit with the base parameters and the accepted terms (step fraction {frac}; "
                f"whitened SSE {sse_now:.5g} → {sse_two:.5g}; its own columns alone: {sse_own:.5g})")
            loop.z, loop.r, loop.r_raw = z_two, r_two, raw_two
            return
    log(f"  no all-records fit with it lowers the whitened SSE ({sse_now:.5g}; its own columns alone: {sse_own:.5g}): "
        "it starts at its screening start, and the next round's refinement fits it")


def _form_item(loop: _Loop, c: str, s: dict, raw_before, raw_after_of: dict, rnd: int) -> dict:
    """A `model_form` entry (SPEC §4b) from its screening scores; its adjustment and evidence are
    added by `_finish`."""
    return {
        "assumption": c,
        "gain": {"heldout_nrmse_before": loop.nrmse(raw_before),
                 "heldout_nrmse_after": loop.nrmse(raw_after_of[c]) if c in raw_after_of else None,
                 "relative_reduction": s["gain"], "fold_reductions": s["fold_gains"],
                 "mode_reductions": s["mode_gains"], "improved_fraction": s["improved_fraction"]},
        "_round": rnd,
    }


def _finding(loop: _Loop, c: str, s: dict, raw_before, raw_after, rnd: int) -> dict:
    """A finding (SPEC §4) from its screening scores; parameters, orders and evidence are added by
    `_finish`. Confidence: the χ² probability of its held-out Δχ² with k degrees of freedom; for a
    drift or a cubic stiffness named by its between-record trend alone (`held_out_refused_by`), 1 − the
    trend's p-value."""
    conf = float(1.0 - stats.chi2.sf(max(s["delta_chi2"], 0.0), s["k"])) if s["delta_chi2"] > 0 else 0.0
    if "held_out_refused_by" in s:
        conf = 1.0 - float(s["trend_p_value"])
    gain = {"heldout_nrmse_before": loop.nrmse(raw_before), "heldout_nrmse_after": loop.nrmse(raw_after),
            "relative_reduction": s["gain"], "fold_reductions": s["fold_gains"],
            "mode_reductions": s["mode_gains"],
            "heldout_weighted_sse_reduction": s["delta_chi2"],
            "mode_weighted_sse_reductions": s["mode_delta_chi2"], "harm_ratio": s["harm_ratio"]}
    if "between_record_share" in s:  # a drift over the session or a cubic (`DRIFT_EFFECTS`, `AMPLITUDE_EFFECTS`)
        gain["between_record_share"] = s["between_record_share"]
    if "trend_p_value" in s:  # and its between-record trend test (`_drift_trend_of`, `_stiffness_trend_of`)
        gain["between_record_trend_p"] = s["trend_p_value"]
        gain["between_record_trend_amplitude"] = s["trend_amplitude"]
    if "held_out_refused_by" in s:
        gain["held_out_rules_refused"] = s["held_out_refused_by"]
    if "over_companion" in s:  # fitted with a model_form parameter (`SCREENED_WITH`): its gain over that alone
        gain["over_companion"] = {"gain": s["over_companion"]["gain"], "mode_gains": s["over_companion"]["mode_gains"]}
    return {"effect": c, "confidence": round(conf, 4), "gain": gain, "_round": rnd}


def _next_round(rounds: list, rnd: int) -> dict | None:
    """The scores of the round after `rnd` (None: `rnd` was the last)."""
    return rounds[rnd + 1] if rnd + 1 < len(rounds) else None


def _describe_items(findings: list[dict], form_items: list[dict], final_effects: Effects, evidence: dict, rounds: list,
                    orders_of: dict) -> None:
    """Complete the findings and model_form items with their fitted values, orders and evidence text."""
    for f in form_items:
        f["adjustment"] = final_effects.term(f["assumption"]).to_dict()
        f["adjustment_units"] = {k: FIELD_UNITS[k] for k in f["adjustment"]}
        measured = f.pop("_measured", False)
        rnd = f.pop("_round", None)
        with_ = f.pop("_with", None)
        if with_ is not None:
            f["evidence"] = (f"fitted together with {with_} ({SCREENED_WITH[with_]}; this assumption was not adopted alone in "
                             f"round 1): over the part of a cycle that a locked or slow record turns the wave generator "
                             f"through, a term periodic in θm is an offset of that record, so the two explain each other's "
                             f"misfit; the held-out figures are those of the two together, and {with_} also had to pass "
                             f"the rules against this adjustment alone")
        else:
            f["evidence"] = "" if measured else _evidence_text(f["assumption"], evidence, rounds[rnd], f, _next_round(rounds, rnd))
        tacho = evidence.get("tachometer_lag") or {}
        if f["assumption"] == "sensor_bandwidth" and tacho.get("lag") is not None:
            f["evidence"] += ("; " if f["evidence"] else "") + (
                f"the velocity lag {tacho['lag'] * 1e3:.4f} ± {tacho['std_error'] * 1e3:.4f} ms is measured, not fitted: "
                f"the tachometer against the output encoder in {tacho['records']} free-motion records "
                "(θo + Δθ − ∫ω dt/N = τ·ω/N + per-record offset and ramp, Δθ from the measured torque by eq. 5), "
                "a relation the current does not enter, so an input delay cannot hide in it")
    for f in findings:
        f["parameters"], f["orders"] = _describe(final_effects, f["effect"], orders_of.get(f["effect"], ()))
        f["parameter_units"] = parameter_units(f["effect"], f["parameters"])
        rnd = f.pop("_round")
        tb = f.pop("_tb", None)
        if tb is None:
            f["evidence"] = _evidence_text(f["effect"], evidence, rounds[rnd], f, _next_round(rounds, rnd))
        else:
            f["evidence"] = (f"the motor torque-balance residual (eq. 8 from measured current, torque and velocity) of the "
                             f"free-motion tests is periodic at order {tb['order']} per wave-generator turn"
                             f"{' times the direction of motion' if f['effect'] == 'position_dependent_friction' else ''} "
                             f"({tb['over_median']:.1f}× the median and {tb['over_max']:.1f}× the largest amplitude at "
                             f"neighbouring non-integer orders); fitted without each record, it reduces that record's "
                             f"residual by {100 * tb['gain']:.1f} % in total, in {tb['n_improved']} of {tb['n_records']} "
                             f"records; the output-error screening did not resolve it (a torque disturbance integrates "
                             f"into the velocity with opposite phase in the two directions of motion)")
        comp = f.pop("_companion", None)
        if comp is not None:
            f["evidence"] += (f"; fitted together with {comp} (model_form {comp.split('.')[0]}, refused alone in round 1): in the "
                              f"records that turn the wave generator through only part of a cycle the two explain each other's "
                              f"misfit; against that offset alone it gains {100 * f['gain']['over_companion']['gain']:.1f} % "
                              f"held out")
        if f["orders"] is None:
            f.pop("orders")


def _setup(p_base: Parameters, drive: Drive, experiments: list[Experiment], batch: Experiment, sigma, *, base_free,
           effects: list[str], simulator: Simulator, jacobian_rtol: float, jacobian_solver, jacobian_substeps: int | None,
           per_record_noise: bool, timing: dict, log, tachometer_lag_s: float | None = None):
    """Every effect column (scaled from the data), the compiled problem (simulations at `simulator`'s
    tolerance, Jacobians at `jacobian_rtol`, with `jacobian_solver` where given and the simulator is
    not the fixed-step `VelocityImplicit`, at `jacobian_substeps` where it is: they only set
    Gauss–Newton directions and predicted gains, every accepted
    step and held-out figure is simulated) and the base model's simulation. Returns the `_Loop` at
    the base model (`effects` switched on at zero), the base trajectories, the parameter map and
    the data context."""
    pmap = make_parameter_map(p_base, base_free)
    n_base = len(base_free)
    n_exp = len(experiments)
    m = np.asarray(batch.mask)
    modes = np.where(np.asarray(batch.free) > 0, "free", "constrained")
    ctx = _data_context(p_base, batch, sigma, tachometer_lag_s)
    cols = _all_columns(ctx)
    prob = _Problem(pmap=pmap, emap=_effect_map(cols), effects=_fixed_effect_settings(ctx, effects), drive=drive,
                    simulator=simulator, mesh=experiment_mesh() if jax.device_count() > 1 else None)
    loose = dataclasses.replace(simulator, rtol=jacobian_rtol, atol=jacobian_rtol * 1e-2)
    if is_fixed_cost(simulator):
        if jacobian_substeps is not None:
            loose = dataclasses.replace(loose, solver=dataclasses.replace(simulator.solver, substeps=jacobian_substeps))
    elif jacobian_solver is not None:
        loose = dataclasses.replace(loose, solver=jacobian_solver)
    z0 = np.concatenate([np.asarray(pmap.to_vector(p_base)), np.zeros(len(cols))])
    t1 = time.perf_counter()
    traj = prob.trajectories(jnp.asarray(np.tile(z0, (n_exp, 1))), p_base, batch)
    timing["compile_and_base_simulation"] = time.perf_counter() - t1
    timing["jacobians"] = timing["simulations"] = 0.0
    failed = np.where(~np.asarray(traj.success))[0]
    if failed.size:
        # their residuals are the constant failure value of `experiment_residuals`: no information
        log(f"diagnose: WARNING: the base-model simulation failed on experiment(s) {failed.tolist()} "
            f"({type(simulator.solver).__name__}); they carry no information in this diagnosis")
    th_span = np.array([np.ptp(np.asarray(traj.motor_position)[e][m[e]]) if m[e].any() else 0.0 for e in range(n_exp)])
    unresolved = {n_base + j: (c.index + 1) * th_span < 2.0 * math.pi for j, c in enumerate(cols) if c.index is not None}
    loop = _Loop(prob=prob, jac_prob=eqx.tree_at(lambda q: q.simulator, prob, loose), p_base=p_base, batch=batch,
                 sig_exp=_record_noise(experiments, modes, sigma, per_record_noise), m=m, modes=modes, cols=cols,
                 n_base=n_base, unresolved={j: u for j, u in unresolved.items() if u.any()}, timing=timing, z=z0)
    return loop, traj, pmap, ctx


@dataclasses.dataclass
class _Outcome:
    """What the greedy rounds decided: effects found (SPEC §4, in order), base-model assumptions
    adopted (SPEC §4b), their entries, every stage's scores, and the held-out residuals of the
    base model (the first screening's reference)."""

    chosen: list = dataclasses.field(default_factory=list)
    adopted: list = dataclasses.field(default_factory=list)
    findings: list = dataclasses.field(default_factory=list)
    form_items: list = dataclasses.field(default_factory=list)
    rounds: list = dataclasses.field(default_factory=list)
    base_res: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class _RoundOptions:
    """How the greedy rounds run (the arguments of `diagnose` of the same names)."""

    model_form: list[str]
    folds: np.ndarray
    fit_folds: np.ndarray
    n_found_before: int
    max_findings: int
    misfit_scaling: bool
    reuse_jacobian: bool
    refine_steps: int
    refine_jacobians: int
    confirm_top: int
    rule: Significance
    readapt_after_form: bool = True
    two_stage_periodic: bool = True
    form_competes: bool = False


class _GreedyRounds:
    """The greedy rounds (module docstring, steps 3–5), recorded in `out`, as stages a reader can
    follow (`run`):

    1. `prepare`: each round re-estimates the noise model, takes one Jacobian (w.r.t. the base, the
       accepted effects and every candidate) at the current model and refines base + accepted
       effects;
    2. `model_form_stage`: round 1 first screens the base model's own assumptions (model_form) and
       adopts every significant one (`adopt_form`), then (with `readapt_after_form`) re-estimates the
       noise model, takes a fresh Jacobian and re-fits base + adjustments; after a `DAMPED_SCREEN`
       adjustment the other assumptions are screened again, each simulated, and the periodic
       candidates take their orders from the adjusted model's residual evidence;
    3. `screen` and `accept_effect`, one effect per round, in `hdjax._discrepancy.significance.forward_selection`
       (the friction-only diagnosis's loop too): the best significant candidate is accepted.

    Stops when nothing is significant, no candidate is left, or `max_findings` (with the
    `n_found_before` torque-balance findings) are reached. With `form_competes`, the model_form
    assumptions not adopted in round 1 are screened beside the effects in every effect round: where
    one wins a round, every significant one is adopted (they name no effect and count towards no
    limit) and the round is screened again against the adjusted model. An assumption that a found
    effect's misfit hid (a sensor lag under a strain-gauge ripple) is then not taken up by the effect
    that looks most like it (a false `input_delay`, thirty-third session's viscous-variant dataset
    5001)."""

    def __init__(self, loop: _Loop, out: _Outcome, evidence: dict, cand_idx: dict, opts: _RoundOptions, log,
                 evidence_after_form=None):
        self.loop, self.out, self.evidence, self.cand_idx, self.opts, self.log = loop, out, evidence, cand_idx, opts, log
        self.evidence_after_form = evidence_after_form
        # the round's Jacobian, its columns and the held-out residuals of its screening
        self.J: np.ndarray = np.zeros((0, 0))  # set by `prepare`, which `run` calls first
        self.sel: list[int] = []
        self.raw_before = None
        self.raw_after_of: dict = {}
        self.stale = False  # an assumption won an effect round: the round is screened again
        self.noise_evidence_taken = False

    def accepted_idx(self) -> list[int]:
        """Columns of the adopted adjustments and the effects found so far."""
        return list(dict.fromkeys(j for c in self.out.adopted + self.out.chosen for j in self.cand_idx[c]))

    def refitted_in_folds(self) -> list[int]:
        """The accepted columns that the held-out fold fits re-fit with each candidate: all but an
        adopted adjustment held in the folds (`FIXED_IN_FOLDS`: a whole term or one parameter of
        it), which keeps its all-records value in every fold."""
        fixed = held_in_folds(self.out.adopted, self.cand_idx, self.loop.cols, self.loop.n_base)
        return [j for j in self.accepted_idx() if j not in fixed]

    def form_left(self) -> list[str]:
        """The model_form assumptions that compete with the effects (`form_competes`)."""
        return [c for c in self.opts.model_form if c not in self.out.adopted] if self.opts.form_competes else []

    def columns(self, pool: list[str]) -> tuple[list[int], list[int]]:
        """(active, sel): the base and accepted columns, and those plus the columns of `pool`."""
        active = list(range(self.loop.n_base)) + self.accepted_idx()
        return active, list(dict.fromkeys(active + [j for c in pool for j in self.cand_idx[c]]))

    def prepare(self, form_pool: list[str], pool: list[str], relinearise_on_stall: bool = False) -> None:
        loop, o = self.loop, self.opts
        n_base = loop.n_base
        rnd = len(self.out.chosen)  # one effect found per round
        active, sel = self.columns(form_pool + pool)
        self.log(f"diagnose: round {rnd + 1}: Jacobian w.r.t. {n_base} base + {len(sel) - n_base} effect parameters")
        proc, r_white0 = _round_noise_model(loop, misfit_scaling=o.misfit_scaling)
        J = loop.jacobian(loop.z, sel, reuse=o.reuse_jacobian and rnd > 0)
        if not self.noise_evidence_taken:
            _noise_evidence(loop, proc, r_white0, self.evidence, self.log)
            self.noise_evidence_taken = True
        self.J = _refine(loop, J, sel, active, steps=o.refine_steps, jacobians=o.refine_jacobians, log=self.log,
                         relinearise_on_stall=relinearise_on_stall)
        self.sel, self.stale = sel, False

    def screen_stage(self, pool: list[str], n_simulated: int, simulate_all: bool = False) -> dict[str, dict]:
        loop, o, out = self.loop, self.opts, self.out
        ff = _FoldFits.at(loop, self.J, self.sel, o.fit_folds, two_stage=o.two_stage_periodic)
        scores, raw_before, raw_after_of = _screen(loop, ff, pool, self.refitted_in_folds(),
                                                   self.cand_idx, o.folds, n_simulated=n_simulated, rule=o.rule,
                                                   log=self.log, simulate_all=simulate_all)
        if out.base_res is None:
            out.base_res = raw_before
        out.rounds.append(scores)
        self.raw_before, self.raw_after_of = raw_before, raw_after_of
        return scores

    def adopt(self, names: list[str], scores: dict[str, dict], note: str = "") -> list[str]:
        """Adopt every significant model_form assumption among `names` (largest gain first) at this
        screening's figures; returns them."""
        out = self.out
        accept = sorted([c for c in names if scores[c]["significant"]], key=lambda c: -scores[c]["gain"])
        if accept:
            out.form_items += [_form_item(self.loop, c, scores[c], self.raw_before, self.raw_after_of, len(out.rounds) - 1)
                               for c in accept]
            _accept(self.loop, self.J, self.sel, [j for c in accept for j in self.cand_idx[c]], self.refitted_in_folds(),
                    two_stage=self.opts.two_stage_periodic, log=self.log)
            self.log(f"  accepted {', '.join(accept)}{note}")
            out.adopted.extend(accept)
            for c in self.cand_idx:  # a companion adopted itself (`form_competes`) is no longer one
                own = [j for j in self.cand_idx[c] if j not in _companion_columns(self.loop, self.cand_idx, c)
                       or self.loop.cols[j - self.loop.n_base].effect not in accept]
                self.cand_idx[c] = own
        return accept

    def adopt_form(self, form_pool: list[str], simulate_all: bool = False) -> list[str]:
        loop, o = self.loop, self.opts
        scores = self.screen_stage(form_pool, len(form_pool), simulate_all)
        accept = self.adopt(list(scores), scores)
        if accept and o.readapt_after_form:
            # the effects are screened against the adjusted base model: its noise model
            # (misfit scaling) re-estimated and base + adjustments re-fitted first, or the
            # base model's own correction to the adjustment dominates every candidate's fit
            _round_noise_model(loop, misfit_scaling=o.misfit_scaling)
            self.J = _refine(loop, loop.jacobian(loop.z, self.sel), self.sel, list(range(loop.n_base)) + self.accepted_idx(),
                             steps=o.refine_steps, jacobians=o.refine_jacobians, log=self.log,
                             relinearise_on_stall=bool(DAMPED_SCREEN & set(accept)))
        return accept

    def model_form_stage(self, remaining: list[str]) -> None:
        """Round 1's screening of the base model's own assumptions (stage 2 of the class docstring)."""
        loop, out = self.loop, self.out
        accept = self.adopt_form(self.opts.model_form)
        rest = [c for c in self.opts.model_form if c not in out.adopted]
        if DAMPED_SCREEN & set(accept) and rest:
            # the other assumptions were judged against a base model whose misfit that adjustment
            # dominated (a linear viscous law on a |ω|^0.7 bench: free velocity 38x its noise);
            # judge them again against the adjusted model before any effect is screened, each by a
            # simulated held-out fit: on the small viscous-law test dataset (seed 821) the linearised
            # prediction put the sensor lags at −15 % where their simulated held-out gain was +27 %,
            # and a false input_delay took them up (2026-11-29, thirty-fourth session)
            self.log("  model_form: the other assumptions screened again against the adjusted base model (all simulated)")
            self.adopt_form(rest, simulate_all=True)
        if DAMPED_SCREEN & set(out.adopted) and self.evidence_after_form is not None and self.evidence_after_form():
            # and the periodic candidates' orders come from the adjusted model's residual spectra
            # (the base model's misfit hid every peak on the |ω|^0.7 bench): a Jacobian with their columns
            n_base = loop.n_base
            _, sel = self.columns(self.form_left() + remaining)
            self.log(f"diagnose: round 1: Jacobian w.r.t. {n_base} base + {len(sel) - n_base} effect parameters (new orders)")
            self.J, self.sel = loop.jacobian(loop.z, sel), sel

    def screen(self, pool: list[str]) -> dict[str, dict]:
        """One effect round's screening; round 1 screens with the Jacobian it already has."""
        left = self.form_left()
        if self.out.chosen or self.stale:
            self.prepare(left, pool, relinearise_on_stall=bool(self.stale and DAMPED_SCREEN & set(self.out.adopted)))
        return self.screen_stage(pool + left, self.opts.confirm_top + len(left))

    def accept_effect(self, best: str, scores: dict[str, dict]) -> None:
        if best in MODEL_FORM:
            # an assumption won the round: every significant one adopted (round 1's rule, and one
            # re-fit instead of one per assumption), and the round screened again
            self.adopt([c for c in scores if c in MODEL_FORM], scores, " (model_form, in an effect round)")
            self.stale = True
            return
        out = self.out
        _accept(self.loop, self.J, self.sel, self.cand_idx[best], self.refitted_in_folds(),
                two_stage=self.opts.two_stage_periodic, log=self.log)
        self.log(f"  accepted {best}")
        out.chosen.append(best)
        out.findings.append(_finding(self.loop, best, scores[best], self.raw_before, self.raw_after_of[best],
                                     len(out.rounds) - 1))
        comp = _companion_columns(self.loop, self.cand_idx, best)
        if comp:
            # its companion columns are in the model now: their term is adopted with those columns
            # only, reported as a model_form item with the finding's held-out figures
            form = self.loop.cols[comp[0] - self.loop.n_base].effect
            self.cand_idx[form] = list(comp)
            out.adopted.append(form)
            item = _form_item(self.loop, form, scores[best], self.raw_before, {form: self.raw_after_of[best]}, len(out.rounds) - 1)
            out.form_items.append(item | {"_with": best})
            out.findings[-1]["_companion"] = SCREENED_WITH[best]
            self.log(f"  adopted {', '.join(self.loop.cols[j - self.loop.n_base].path for j in comp)} with {best}")

    def attach_companions(self, remaining: list[str]) -> None:
        """`SCREENED_WITH`: after round 1's model_form stage, a candidate whose companion term was
        not adopted (but screened: in `model_form`) takes the companion's parameter among its columns."""
        loop, out = self.loop, self.out
        for c, path in SCREENED_WITH.items():
            form = path.split(".")[0]
            if c not in remaining or not self.cand_idx.get(c) or form not in self.opts.model_form or form in out.adopted:
                continue
            comp = [loop.n_base + j for j, col in enumerate(loop.cols) if col.path == path]
            if comp and all(j in self.sel for j in comp):
                self.cand_idx[c] = self.cand_idx[c] + comp
                self.log(f"diagnose: {c} screened with {path} ({form} was not adopted; the two explain each other)")

    def run(self, remaining: list[str]) -> None:
        if not remaining:
            return
        # round 1: the base model's own assumptions first, every significant one adopted
        self.prepare(self.opts.model_form, remaining)
        if self.opts.model_form:
            self.model_form_stage(remaining)
            self.attach_companions(remaining)
        # then the effects, one per round
        forward_selection(remaining, self.screen, self.accept_effect,
                          max_findings=self.opts.max_findings - self.opts.n_found_before,
                          counts=lambda name: name not in MODEL_FORM)


def diagnose(
    p0: Parameters,
    drive: Drive,
    experiments: list[Experiment],
    *,
    candidates=SCREENED_EFFECTS,
    model_form=DIAGNOSED_MODEL_FORM,
    base_free=DEFAULT_FREE,
    base_steps: int = 5,
    max_findings: int = 3,
    min_relative_gain: float = OUTPUT_ERROR_RULES.min_relative_gain,
    refine_steps: int = 4,
    refine_jacobians: int = 3,
    confirm_top: int = 2,
    per_record_noise: bool = True,
    misfit_scaling: bool = True,
    min_improved_fraction: float = OUTPUT_ERROR_RULES.min_improved_fraction,
    reuse_jacobian: bool = True,
    simulator: Simulator = Simulator(solver=VelocityImplicit(substeps=4), measured_angle=True),
    jacobian_rtol: float = 1e-5,
    jacobian_solver: dfx.AbstractSolver | None = PLANT_W_METHOD,
    jacobian_substeps: int | None = None,
    cross_validation: str = "leave_one_out",
    tb_route: bool = True,
    readapt_after_form: bool = True,
    two_stage_periodic: bool = True,
    form_competes: bool = False,
    measure_tachometer_lag: bool = True,
    consistency_in: str = OUTPUT_ERROR_RULES.consistency_in,
    physical_sign: bool = OUTPUT_ERROR_RULES.physical_sign,
    negligible_record_loss: float = OUTPUT_ERROR_RULES.negligible_record_loss,
    untouched_record_change: float = OUTPUT_ERROR_RULES.untouched_record_change,
    drift_trend_p: float = OUTPUT_ERROR_RULES.drift_trend_p,
    stiffness_trend_p: float = OUTPUT_ERROR_RULES.stiffness_trend_p,
    labels: list[str] | None = None,
    log=lambda *_: None,
) -> Diagnosis:
    """Find the SPEC §4 effects that the data show beyond the paper's model (see module docstring).

    **Arguments:** `p0` start parameters (paper identification), `drive`, `experiments`
    (constrained/free), `candidates` effect names to consider, `base_free` base parameters re-fitted
    with every candidate, `base_steps` LM steps refining the base model, `max_findings`,
    `min_relative_gain` held-out threshold, `refine_steps` Gauss–Newton iterations re-fitting base
    and accepted effects after each finding per Jacobian, `refine_jacobians` most Jacobians per round
    for that refit (a new one when the chord steps are still gaining), `confirm_top` candidates (best linearised held-out
    gain first) whose held-out gain is confirmed by simulation each round, `simulator` the
    numerics of every simulation (default the fixed-step `VelocityImplicit` at 4 substeps, with the
    periodic terms at the measured angle: on the independent-bench benchmark 33 of 40 datasets
    named right against 34–35 with adaptive Rodas3 at rtol 1e-6, in about half the time, 2026-12-04; `Simulator(rtol=1e-6,
    atol=1e-8, measured_angle=True)` is that former default); with an adaptive simulator
    `jacobian_rtol` is the tolerance of the Jacobians (directions only) and
    `jacobian_solver` their ODE solver (default `PLANT_W_METHOD`, `Ros34PW2(stiff_part=plant_stiff_part)`:
    frozen-J W-method tangents that keep the plant's stiff second derivatives, 1.3–1.4× faster
    diagnoses than exact tangents through `Rodas3` with the same findings on every benchmark and
    test dataset, see `hdjax._plant.rosenbrock`; None uses the simulator's own solver; the fixed-step
    plant takes exact tangents at its own steps), `jacobian_substeps` the fixed-step plant's
    substeps in the Jacobians (default None: the simulator's own; measured 2026-12-05 at 2 against
    the simulations' 4: the Jacobians took about half the time and 34 of 40 benchmark datasets were
    named right against 33, but the hidden input delay of `tests/test_diagnose_bench.py` (seed 908)
    fell out of the screened candidates and was not named, so it is not the default),
    `cross_validation` "leave_one_out" (each held-out experiment predicted by the fit on all the
    others) or "two_fold" (by the fit on the other half). `readapt_after_form`: after model_form
    adjustments are adopted, re-estimate the noise model and re-fit base + adjustments from a fresh
    Jacobian before effects are screened (default True; False screens the effects with round 1's
    Jacobian and noise model, see the module docstring).
    `two_stage_periodic`: a periodic term that completes no cycle in some experiments is fitted where
    it does, and then every other fitted column is re-fitted, on the same training experiments, to
    what the term does everywhere (default True; False keeps the term's Jacobian columns zeroed in
    those experiments for the whole fold fit, so nothing takes up what it does there).
    `model_form` the SPEC §4b base-model assumptions screened (and all significant ones adopted)
    in a first round, before any effect; `form_competes`: those not adopted there are screened
    beside the effects in every later round, and one that wins is adopted instead of naming an
    effect (default False: round 1 only. True removed viscous-variant 5001's false input_delay and
    kept the default bench at 17/20, but on the small kinematic-error test dataset the sensor
    offsets, adopted after the kinematic error [2], let a false cogging [2] be named beside it).
    `measure_tachometer_lag`: measure the tachometer's lag behind the output encoder from the
    free-motion records (`hdjax._discrepancy.evidence.tachometer_lag`, no plant involved) and, where
    it is determined, hold `sensor_bandwidth`'s velocity lag there instead of fitting it (default
    True; the fitted lags otherwise take up an input delay); `per_record_noise` weighs every experiment by its own
    sensor-noise level (else one level per channel); `misfit_scaling` divides the whitened residual
    of every (experiment, channel) by its RMS under the current model where that exceeds 1 (misfit
    the model cannot explain counts as noise of that record, so no record's misfit dominates the
    screening); `min_improved_fraction` of the held-out experiments of the mode where a candidate
    acts must improve (`consistency_in`: that mode is the one where it gains most, "largest_gain", or
    any mode where it gains beyond `min_relative_gain`, "any_acting"; see `Significance`).
    `physical_sign`: an effect whose physics fixes the sign of its parameter (`PHYSICAL_SIGN`) is
    named only with that sign in every held-out fold fit (default True). `negligible_record_loss`: a held-out
    experiment a candidate makes worse by no more than this share of its error does not count
    against it in the consistency rule, down to half of the mode's (`Significance.improved_fraction`).
    `untouched_record_change`: down to the held-out experiments the candidate moves by more than this
    share of their error instead, when fewer, at least two (default 0.02; 0: half the mode's).
    `drift_trend_p`: a drift over the session (`thermal_drift`) is named also when its
    between-record trend test gives at most this p-value (`Significance.drift_trend_p`,
    `_drift_trend_of`; default 0.01; 0: the held-out rules alone, the loop before 2026-12-05) and
    its held-out fits do not contradict the trend (`Significance.names_by_trend`).
    `stiffness_trend_p`: a cubic stiffness (`nonlinear_stiffness`) is named also when the locked
    records' own K1 rises with their torsion (`amplitude_trend`, the records' torsions shuffled
    among them) at most at this p-value and its held-out fits do not contradict it
    (`Significance.names_by_amplitude_trend`; 0: the held-out rules alone).
    `reuse_jacobian`: later rounds reuse the first round's Jacobian columns
    (re-whitened by their own noise model), computing only columns not seen yet.
    `labels`: a name per experiment (its file) for the texts of `unexplained` (default
    "experiment i"); a candidate of the last round that gains held out but that a rule refused is
    listed there with the rule and its figures (`near_misses`).

    **Returns:** a `Diagnosis` with findings (most important first), evidence, the extended model,
    stage timings (s) and simulated torque and motor-velocity traces for the figures.

    The stages, in order: base fit, setup (columns, compiled problem, base simulation), evidence
    and screened orders, torque-balance route, then per round: noise model, Jacobian, refinement,
    screening of model_form assumptions (round 1) and effects, acceptance; last the extended
    model's description, traces and what is left unexplained. (Over 100 lines only through its
    options and this docstring; the body is those stages, about 70 lines.)
    """
    timing = {}
    t0 = time.perf_counter()
    candidates, model_form = _check_names(candidates, model_form, cross_validation)
    if jacobian_substeps is not None and (not isinstance(jacobian_substeps, int) or isinstance(jacobian_substeps, bool)
                                          or jacobian_substeps < 1):
        raise ValueError(f"`diagnose`: jacobian_substeps must be a whole number ≥ 1 or None (the simulator's own), "
                         f"got {jacobian_substeps!r}.")
    if labels is not None and len(labels) != len(experiments):
        raise ValueError(f"`diagnose`: `labels` names {len(labels)} experiments, but {len(experiments)} were given; "
                         "pass one name per experiment (its file), or none.")
    not_testable = untestable(candidates, experiments)
    for name, why in not_testable.items():
        log(f"diagnose: {name} not testable: {why}")
    candidates = [c for c in candidates if c not in not_testable]
    requested = set(candidates)
    rule = dataclasses.replace(OUTPUT_ERROR_RULES, min_relative_gain=min_relative_gain,
                               min_improved_fraction=min_improved_fraction, consistency_in=consistency_in,
                               physical_sign=physical_sign, negligible_record_loss=negligible_record_loss,
                               untouched_record_change=untouched_record_change, drift_trend_p=drift_trend_p,
                               stiffness_trend_p=stiffness_trend_p)
    batch = stack_experiments(experiments)
    n_exp = len(experiments)
    sigma = noise_levels(batch)

    # stage 1: base model. The base fit weighs each channel by its sensor noise only, not by
    # `fit_noise_levels` (sensor + process noise, the default of `fit_parameters`): on the
    # independent bench that default moved the base model so that a free record's misfit dominated
    # the held-out SSE and a hidden lost_motion was no longer named (tests/test_diagnose_bench.py,
    # 2026-11-25). The loop's own noise model (step 3) whitens everything after the base fit.
    log(f"diagnose: refining the base model ({base_steps} LM steps on {n_exp} experiments)")
    base_sim = dataclasses.replace(simulator, rtol=max(simulator.rtol, 1e-5), atol=max(simulator.atol, 1e-7))
    p_base = fit_parameters(p0, drive, batch, free=base_free, simulator=base_sim, max_steps=base_steps, sigma=sigma,
                            throw=False).params
    timing["base_fit"] = time.perf_counter() - t0

    # stage 1b: the tachometer's lag behind the output encoder, measured from the sensors alone
    # (`tachometer_lag`); where it is determined, `sensor_bandwidth` holds its velocity lag there
    # instead of fitting it, so that an input delay is not taken up by the fitted sensor lags
    tacho = tachometer_lag(batch, p_base, drive) if measure_tachometer_lag and "sensor_bandwidth" in model_form else None
    if tacho is not None:
        log("diagnose: tachometer lag behind the output encoder: " + (
            f"{tacho['lag'] * 1e3:.4f} ± {tacho['std_error'] * 1e3:.4f} ms ({tacho['records']} free records); "
            "the velocity lag of sensor_bandwidth is held there" if tacho["lag"] is not None else
            f"not used ({tacho['reason']}); sensor_bandwidth fits the velocity lag"))

    # stage 2: every effect column, the compiled problem, the base simulation
    loop, traj, pmap, ctx = _setup(p_base, drive, experiments, batch, sigma, base_free=base_free,
                                   effects=list(candidates) + model_form, simulator=simulator, jacobian_rtol=jacobian_rtol,
                                   jacobian_solver=jacobian_solver, jacobian_substeps=jacobian_substeps,
                                   per_record_noise=per_record_noise, timing=timing, log=log,
                                   tachometer_lag_s=None if tacho is None else tacho["lag"])
    n_base, m, modes, cols = loop.n_base, loop.m, loop.modes, loop.cols

    # stage 3: evidence (residual spectra and covariate correlations of the base model), the orders
    # screened, the halves
    evidence, orders = residual_evidence(batch, traj, m, modes, sigma, p_base, drive)
    if tacho is not None:
        evidence["tachometer_lag"] = tacho
    requested_order = list(candidates)
    orders_of, candidates = _screened_orders(evidence, orders, candidates, log)
    folds, fit_folds = _folds(modes, cross_validation)
    cand_idx = {c: _candidate_columns(cols, c, orders_of.get(c, ()), offset=n_base) for c in list(candidates) + model_form}

    remaining = list(candidates)
    loop.r, loop.r_raw = loop.simulate_each(loop.tile(loop.z))
    # stage 4: the torque-balance route (cogging, position-dependent friction)
    tb_findings = []
    if tb_route:
        tb_findings = _torque_balance_route(loop, traj, evidence, drive, requested=requested, max_findings=max_findings,
                                            rule=rule, cand_idx=cand_idx,
                                            orders_of=orders_of, log=log)
    tb_found = [f["effect"] for f in tb_findings]
    for name in tb_found:
        if name in remaining:
            remaining.remove(name)
    _drop_torque_balance_lookalikes(tb_findings, orders_of, cand_idx, remaining, cols, n_base, log)

    def evidence_after_form() -> bool:
        """The residual evidence again, at the base model adjusted by `DAMPED_SCREEN` items: the
        periodic candidates' orders from its spectra (`remaining`, `cand_idx`, `orders_of`,
        `candidates` and `evidence` updated in place). True if the periodic candidates changed."""
        traj_f = loop.prob.trajectories(jnp.asarray(loop.tile(loop.z)), p_base, batch)
        p_f = pmap.to_model(jnp.asarray(loop.z[:n_base]), p_base)
        ev_f, orders_f = residual_evidence(batch, traj_f, m, modes, sigma, p_f, drive)
        log("diagnose: residual evidence taken again at the adjusted base model")
        periodic = [c for c in requested_order if c in PERIODIC and c not in tb_found]
        new_of, new_cands = _screened_orders(ev_f, orders_f, periodic, log)
        before = {c: tuple(orders_of.get(c, ())) for c in periodic if c in remaining}
        evidence.update(ev_f)
        for c in periodic:
            if c in remaining:
                remaining.remove(c)
            if c in candidates:
                candidates.remove(c)
        for c in new_cands:
            orders_of[c] = new_of[c]
            cand_idx[c] = _candidate_columns(cols, c, new_of[c], offset=n_base)
            remaining.append(c)
            candidates.append(c)
        # the torque-balance route's look-alike rule holds for the new orders too
        _drop_torque_balance_lookalikes(tb_findings, orders_of, cand_idx, remaining, cols, n_base, log)
        after = {c: tuple(orders_of[c]) for c in periodic if c in remaining}
        return before != after

    # stage 5: greedy rounds
    out = _Outcome(findings=tb_findings)
    opts = _RoundOptions(model_form=model_form, folds=folds, fit_folds=fit_folds, n_found_before=len(tb_found),
                         max_findings=max_findings, misfit_scaling=misfit_scaling, reuse_jacobian=reuse_jacobian,
                         refine_steps=refine_steps, refine_jacobians=refine_jacobians, confirm_top=confirm_top, rule=rule,
                         readapt_after_form=readapt_after_form, two_stage_periodic=two_stage_periodic,
                         form_competes=form_competes)
    _GreedyRounds(loop, out, evidence, cand_idx, opts, log, evidence_after_form=evidence_after_form).run(remaining)
    chosen, adopted, findings, form_items, rounds, base_res = out.chosen, out.adopted, out.findings, out.form_items, out.rounds, out.base_res

    # stage 6: the extended model, its description, traces for the figures, what is left
    z_cur = loop.z
    current_p = pmap.to_model(jnp.asarray(z_cur[:n_base]), p_base)
    # a measured tachometer lag was in every simulation of the diagnosis: it stays in the extended
    # model, and is reported as a model_form item (measured, no held-out figure) where the torque
    # lag was not adopted
    held = ["sensor_bandwidth"] if "tachometer_lag" in ctx and "sensor_bandwidth" not in adopted else []
    form_items += [{"assumption": c, "gain": {"relative_reduction": None}, "_measured": True} for c in held]
    final_effects = _apply(_fixed_effect_settings(ctx, adopted + chosen + tb_found + held), cols, z_cur[n_base:])
    _describe_items(findings, form_items, final_effects, evidence, rounds, orders_of)
    # torque of the final base parameters without / with the effects (figures), and what is left
    z_plain = z_cur.copy()
    in_form = {j for c in adopted for j in cand_idx[c]}  # a companion column (`SCREENED_WITH`) stays: it is model_form
    z_plain[[j for c in chosen + tb_found for j in cand_idx[c] if j not in in_form]] = 0.0
    tr0 = loop.prob.trajectories(jnp.asarray(loop.tile(z_plain)), p_base, batch)
    tr1 = loop.prob.trajectories(jnp.asarray(loop.tile(z_cur)), p_base, batch) if findings else tr0
    traces = {"torque_base": np.asarray(tr0.torque), "torque_extended": np.asarray(tr1.torque),
              "motor_velocity_base": np.asarray(tr0.motor_velocity), "motor_velocity_extended": np.asarray(tr1.motor_velocity),
              "torsion_extended": np.asarray(tr1.torsion), "motor_position": np.asarray(tr1.motor_position)}
    named_at = {}
    for f in findings:
        for k in f.get("orders") or []:
            named_at.setdefault(int(k), []).append(f["effect"])
    left = unexplained(batch, tr1, m, modes, sigma, loop.r_raw, loop.r, named_at)
    if rounds and not any(sc["significant"] for sc in rounds[-1].values()):
        names = list(labels) if labels is not None else [f"experiment {i}" for i in range(len(experiments))]
        left += near_misses(rounds[-1], rule, names, orders_of)
    left += [{"description": f"{name} not testable", "evidence": why} for name, why in not_testable.items()]
    left += unresolved_orders(evidence, requested_order)
    timing["total"] = time.perf_counter() - t0
    base_n = loop.nrmse(base_res) if base_res is not None else {}
    return Diagnosis(findings=findings, model_form=form_items, unexplained=left, baseline={"heldout_nrmse": base_n},
                     evidence=evidence, params=current_p, effects=final_effects, rounds=rounds,
                     timing=timing, traces=traces)


def _describe(effects: Effects, name: str, orders):
    if name in PERIODIC:
        k, amp, ph = effects.amplitudes(name)
        letter = typing.cast(AbstractPeriodicTerm, effects.term(name)).letter
        params = {}
        for o in orders:
            params[f"{letter}{o}"] = float(amp[o - 1])
            params[f"phi{o}"] = float(ph[o - 1])
        # report the orders that carry the effect (amplitude above 20 % of the largest)
        top = max(params[f"{letter}{o}"] for o in orders)
        orders = [o for o in orders if params[f"{letter}{o}"] >= 0.2 * top]
        return params, orders
    params = effects.term(name).to_dict()
    return params, None


def parameter_units(name: str, parameters: dict) -> dict[str, str]:
    """The unit of each reported parameter of effect `name` (`_describe`'s keys): a periodic
    effect's amplitudes in `PERIODIC_UNITS`, its phases `phi<k>` in rad; scalars in `FIELD_UNITS`."""
    if name in PERIODIC:
        return {k: "rad" if k.startswith("phi") else PERIODIC_UNITS[name] for k in parameters}
    return {k: FIELD_UNITS[k] for k in parameters}


def _evidence_text(name, evidence, round_scores, finding, next_round_scores=None) -> str:
    """The finding's (or model_form item's) evidence in words. Every other candidate of its round that
    passed every rule too (however it ranked) is said to be so, with what it gains (or loses) in the next round, once `name` is
    in the model: where that is no longer significant, the two explained the same residual and the
    data chose between them by held-out gain alone (bench seed 5012 of the variant bench, 2026-12-03:
    a strain-gauge ripple [1] at +6.2 % named over the hidden kinematic error [1] at +5.7 %, which then
    lost 7.1 %)."""
    g = finding["gain"]
    verb = "reduces" if g["relative_reduction"] >= 0 else "raises"
    txt = (f"adding {name} to the plant, re-fitted without the experiment it predicts, {verb} the whitened "
           f"squared error of the held-out experiments by {100 * abs(g['relative_reduction']):.1f} % (halves: "
           f"{', '.join(f'{100 * x:.1f} %' for x in g['fold_reductions'])}; "
           f"{', '.join(f'{k} tests {100 * x:.1f} %' for k, x in g['mode_reductions'].items())})")
    if "between_record_trend_p" in g:
        if name in AMPLITUDE_EFFECTS:
            txt += (f"; between records, the trend of the locked tests' own K1 with how far each is twisted has weighted "
                    f"p = {g['between_record_trend_p']:.4f} over every assignment of their torsions to the records "
                    f"(K3 {g['between_record_trend_amplitude']:.4g} N·m/rad³ from that trend alone)")
            why_small = ("the base fit's one K1 takes up most of a cubic stiffness record by record, so what it leaves in "
                         "each record's residual is small")
        else:
            txt += (f"; between records, the free tests' own viscous friction follows the drift's course over the session "
                    f"(weighted trend p = {g['between_record_trend_p']:.4f} over every ordering of their start times, "
                    f"amplitude {100 * g['between_record_trend_amplitude']:+.2f} % of the viscous friction)")
            why_small = ("a drift of a few tenths of a percent changes every record's fit little, so its held-out gain is "
                         "small and one record's misfit can outweigh it")
        if g.get("held_out_rules_refused"):
            txt += (" and names it; the held-out rules alone would not have ("
                    + ", ".join(g["held_out_rules_refused"]) + "): " + why_small)
    if name in PERIODIC:
        txt += (f"; residual order spectra peak at orders {evidence['candidate_orders']} per wave-generator turn"
                f" (orders screened for {name}: {evidence['candidate_orders_per_effect'].get(name)})")
    ranked = sorted(((c, s["gain"]) for c, s in round_scores.items() if c != name), key=lambda x: -x[1])
    if ranked:
        txt += "; next best candidates: " + ", ".join(f"{c} ({100 * v:.1f} %)" for c, v in ranked[:2])
    # every candidate of the round that passed the rules, not only the two listed: one ranked below
    # a refused candidate of larger gain is a look-alike all the same
    for c, v in ranked:
        if not round_scores[c].get("significant"):
            continue
        passed = (f"; {c} passed every significance rule in the same round too ({100 * v:.1f} % against "
                  f"{100 * g['relative_reduction']:.1f} %)")
        later = (next_round_scores or {}).get(c)
        if later is None:
            txt += passed + ", and the larger held-out gain decided"
        elif not later.get("significant"):
            txt += (passed + f", but with {name} in the model its held-out gain is {100 * later['gain']:+.1f} % "
                    f"({'simulated' if later.get('simulated') else 'predicted'}): the two explain the same residual, "
                    f"and these data chose {name} by the larger held-out gain alone")
    return txt


