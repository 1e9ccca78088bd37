"""The `fit` workflow: the paper's identification, then the joint trajectory-error fit, then
fit.json, report.md and the paper-style figures. The command `python -m hdjax.fit` is a thin
wrapper around `run_fit`."""

import pathlib
import time

import jax.numpy as jnp
import numpy as np

from .._data.experiment import select_experiments, stack_experiments, take_experiments
from .._data.load import Dataset
from .._fit.covariance import UNDETERMINED_SE_RTOL, poorly_determined
from .._fit.least_squares import (
    BREAKAWAY_GRID,
    BREAKAWAY_PATHS,
    DEFAULT_FREE,
    PER_EXPERIMENT_REJECT_SE_TOL,
    fit_breakaway_friction,
    fit_parameters,
    fit_per_experiment,
    nrmse,
)
from .._fit.paper import identify_paper
from .._model.effects import BreakawayFriction, Effects, SensorBandwidth
from .._model.paper import PARAMETER_NAMES, PARAMETER_UNITS
from .._plant.rosenbrock import Rodas3
from .._plant.simulate import PLANT_W_METHOD, Simulator, simulate_batch
from .._plant.stepper import VelocityImplicit
from .config import section_options
from .io import write_results

FRICTION_NAMES = ("Jeff", "Tvp", "Tvn", "Tsp", "Tsn")
DEFAULTS = {
    "alpha": 0.5,
    "Tss2": 0.1,
    "cutoff_hz": 50.0,
    "trajectory": {
        "free": list(DEFAULT_FREE),
        "fit_alpha": False,
        "max_experiments": 12,
        "max_steps": 20,
        "rtol": 1e-5,
        "cost_rtol": 1e-5,
        "step_se_tol": 0.1,
        "se_block": 0.1,
        "per_experiment": True,
        "per_experiment_max_steps": 40,
        "per_experiment_rtol": 1e-4,
        "solver": "velocity_implicit",
        "substeps": 4,
        "per_experiment_substeps": 2,
        "reversal_quadrature": False,
        "sensor_bandwidth": True,
        "breakaway_friction": True,
    },
}


SOLVERS = ("rodas3", "ros34pw2", "velocity_implicit")


def trajectory_simulator(trajectory: dict) -> Simulator:
    """The simulator of the trajectory fit from the `fit.trajectory` options: `solver`
    "velocity_implicit" (the default: fixed-step TR-BDF2 on the exact model, set-valued sticking,
    `substeps` steps per sample; see `hdjax.VelocityImplicit`), "rodas3" (adaptive Rosenbrock on
    the smoothed model, tolerance `rtol`) or "ros34pw2" (the same model on the adaptive
    Rosenbrock-W method `hdjax.Ros34PW2` with the plant's stiff part: its LM Jacobians skip the
    second derivatives of the current and the smooth factors).

    Why the fixed-step stepper is the default (2026-12-04, shipped HD2 command, 2-core machine,
    reading the compilation cache): 19.1–19.4 s inside against 26.2 s with "ros34pw2" on the same
    code (34 s before that day's trace changes); the joint fit's program ran in 2.9 s at 4
    substeps against 8.5 s. Against the same fit at 16 substeps its
    estimates lie within 0.54 standard errors (the Stribeck amplitudes; K1 … Tsn within 0.16),
    the "ros34pw2" ones (the smoothed model) within 0.66 (K1 … Tsn within 0.11);
    at 4 substeps the simulation's RMS error is 0.003 σ in torque and 0.075 σ in velocity
    (`benchmarks/stepper.py`, against 128 substeps). `reversal_quadrature: true` takes friction's
    mean through the Stribeck dip and motor reversals (`hdjax.VelocityImplicit`): for records whose
    motor reverses fast in free motion (the shipped HD1 campaign: 0.065 σ in velocity at 4 substeps
    instead of 0.279 σ), at about 1.4× the fit's time."""
    name = trajectory["solver"]
    if name in ("rodas3", "ros34pw2"):
        rtol = _tolerance(trajectory, "rtol")
        solver = Rodas3() if name == "rodas3" else PLANT_W_METHOD
        return Simulator(solver=solver, rtol=rtol, atol=rtol * 1e-2)
    if name == "velocity_implicit":
        rq = trajectory["reversal_quadrature"]
        if not isinstance(rq, bool):
            raise ValueError(f"config `fit.trajectory.reversal_quadrature` must be true or false, got {rq!r}.")
        return Simulator(solver=VelocityImplicit(substeps=_whole_number(trajectory, "substeps"), reversal_quadrature=rq))
    raise ValueError(f"config `fit.trajectory.solver` must be one of {list(SOLVERS)}, got {name!r}.")


def _whole_number(options: dict, key: str, section: str = "fit.trajectory") -> int:
    """`<section>.<key>`, a whole number ≥ 1 (steps per sample interval of `velocity_implicit`, a
    step budget); anything else is refused, naming the key."""
    value = options[key]
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise ValueError(f"config `{section}.{key}` must be a whole number ≥ 1, got {value!r}.")
    return value


def _tolerance(trajectory: dict, key: str, section: str = "fit.trajectory") -> float:
    """`<section>.<key>`, a relative ODE tolerance: a number in (0, 0.1] (YAML reads `1e-5`
    without a decimal point as a string; one that reads as a number is taken)."""
    value = trajectory[key]
    try:
        x = float(value) if not isinstance(value, bool) else float("nan")
    except (TypeError, ValueError):
        x = float("nan")
    if not 0.0 < x <= 0.1:
        raise ValueError(f"config `{section}.{key}` must be a relative tolerance in (0, 0.1], such as 1e-5; "
                         f"got {value!r}.")
    return x


def per_experiment_simulator(trajectory: dict) -> Simulator:
    """The simulator of the per-experiment fits: `trajectory_simulator` at `per_experiment_rtol`
    (the adaptive solvers) or `per_experiment_substeps` (`velocity_implicit`; 2, against the joint
    fit's 4: on the shipped HD2 campaign every consistency figure within 2.2 % of itself, the
    stage 7.3 s against 11.0 s, 2026-12-04).

    The per-experiment estimates serve the consistency measure, their spread over the experiments,
    not the reported values, so their ODE tolerance can be a decade looser than the joint fit's.
    Measured on the shipped HD2 campaign (2026-12-01, 2-core machine, 50 experiments from the same
    joint estimate), against per-experiment fits at rtol 1e-6 (82.3 s): at 1e-4 (33.4 s) no estimate
    moved by more than 0.045 of its parameter's spread over the experiments and no consistency
    figure by more than 0.6 % of itself; at 1e-5, the tolerance used before (44.3 s), 0.11 and
    1.2 %. The estimates' differences are the LM paths', not the ODE error's. All 50 fits
    converged at each of the three; HD1: 50 of 50 at 1e-4 and 1e-5 (34.2 s against 48.7 s).
    Which fits converge matters more than the tolerance: at 3e-5 one fit ran out of
    `per_experiment_max_steps`, and leaving it out moved K1's consistency from 0.99 % to 0.65 %."""
    return trajectory_simulator({**trajectory, "rtol": _tolerance(trajectory, "per_experiment_rtol"),
                                 "substeps": _whole_number(trajectory, "per_experiment_substeps")})


def _options(config: dict) -> dict:
    """The `fit:` section of `config` completed by `DEFAULTS`; an unknown key is an error."""
    opts = section_options(config, "fit", DEFAULTS, nested=("trajectory",))
    per_experiment_simulator(opts["trajectory"])  # a bad solver, substeps or tolerance is refused before any work
    for key in ("sensor_bandwidth", "breakaway_friction"):
        if not isinstance(opts["trajectory"][key], bool):
            raise ValueError(f"config `fit.trajectory.{key}` must be true or false, got {opts['trajectory'][key]!r}.")
    if opts["trajectory"]["breakaway_friction"] and opts["trajectory"]["solver"] != "velocity_implicit":
        if _breakaway_given(config):
            raise ValueError("config `fit.trajectory.breakaway_friction: true` needs `fit.trajectory.solver: velocity_implicit` "
                             "(exact sticking); set `breakaway_friction: false` to use an adaptive solver.")
        opts["trajectory"]["breakaway_friction"] = False  # the default, with an adaptive solver: `run_fit` notes it
    return opts


def _breakaway_given(config: dict | None) -> bool:
    """Whether `config` sets `fit.trajectory.breakaway_friction` itself (not by the default)."""
    return "breakaway_friction" in ((((config or {}).get("fit") or {}).get("trajectory")) or {})


#: The sensor lags the joint fit frees with `fit.trajectory.sensor_bandwidth` (SPEC §4b
#: `sensor_bandwidth`): first-order time constants of the strain gauge and the tachometer, each
#: on the scale of the sample period, from 0.
SENSOR_LAGS = ("sensor_bandwidth.torque_lag", "sensor_bandwidth.velocity_lag")


def fit_model_form(trajectory: dict, dt: float) -> tuple[Effects, dict[str, float]]:
    """The model-form terms the joint fit applies and the parameters of them LM frees, from the
    `fit.trajectory` options (`dt` the sample period, s).

    With `breakaway_friction` (the default with the `velocity_implicit` solver): static friction
    above eq. 9's limit at zero speed (`hdjax.BreakawayFriction`, a breakaway torque per direction;
    exact sticking, so `velocity_implicit` only), switched on at 0 and set by
    `hdjax.fit_breakaway_friction` after the first LM fit: a grid search, LM again with the torques
    held, the search again. It acts through stick/slip events alone, so it has no derivative for LM.

    Why by default (measured 2026-12-06, shipped campaigns, whose independent bench breaks away at
    1.1–1.3× its friction level, as real drives stick): the breakaway torques came within 2.5 % (HD1)
    and 5 % (HD2) of the bench's; reduced χ² 2.63 → 1.34 (HD1) and 7.04 → 5.5 (HD2); HD1's K1
    consistency 11.9 → 1.8 % (its locked records where the motor sticks had given K1 of 6760–9870
    N·m against 6630–6930 on the others) and its Stribeck amplitudes −69 / −2 % → −22 / +17 % from the
    bench's. What it costs: about 10–14 s of the command (two grid searches of 32 simulations and
    the second LM fit), and on HD2 the per-experiment Stribeck estimates scatter more (Tssp1's
    consistency 61 → 374 %: with the motor held to a higher torque, a slow record has fewer sliding
    samples). As an excess over eq. 9's value at rest (the first design, 2026-12-06) the stick
    events moved with the Stribeck amplitudes and LM could not move them (HD2 Tssp1 consistency
    3400 %).

    With `sensor_bandwidth` (the default) a first-order lag of the
    simulated torque and motor velocity (the strain-gauge amplifier's and the tachometer's
    bandwidth, `hdjax.Effects.sensor_bandwidth`), both lags fitted from 0 on the scale of the
    sample period `dt` (s).

    Why by default (measured 2026-12-06 on the shipped campaigns, which the independent bench made
    with first-order sensor filters: HD1 strain gauge 473 Hz, tachometer 203 Hz; HD2 576 / 274 Hz):
    without the lags the fit reads the sensors' phase lag near the free-motion resonance as a
    softer flexspline. HD1: K1 −3.9 % from the truth at 4.9 of its standard errors, reduced χ²
    23.7; with the filters' true lags K1 +0.02 %, reduced χ² 2.6. HD2: K1 −1.1 % → +0.01 %, Jeff
    +1.3 % → +0.01 %, reduced χ² 30.5 → 7.1."""
    effects, free = Effects(), {}
    if trajectory["sensor_bandwidth"]:
        effects = effects.with_term(SensorBandwidth())
        free.update({path: dt for path in SENSOR_LAGS})
    if trajectory["breakaway_friction"]:
        effects = effects.with_term(BreakawayFriction())  # set by `profile_effect_parameters`, not by LM
    return effects, free


def run_fit(dataset: Dataset, config: dict, out: pathlib.Path, *, log=print) -> dict:
    """Run the whole identification on `dataset` and write outputs into `out`. Returns fit.json."""
    t_start = time.time()
    opts = _options(config)
    out = pathlib.Path(out)
    drive, exps, files, modes = dataset.dynamic_part("fit")
    notes: list[str] = []

    log(f"[1/4] paper's identification (regressions, vmap over {len(exps)} experiments)")
    t0 = time.time()
    paper = identify_paper(exps, drive, alpha=opts["alpha"], Tss2=opts["Tss2"], cutoff_hz=opts["cutoff_hz"])
    t_paper = time.time() - t0
    notes += paper.notes
    p0 = paper.parameters()
    free_names, undetermined = _free_and_undetermined(opts, modes, paper)
    if opts["trajectory"]["solver"] != "velocity_implicit" and not _breakaway_given(config):
        notes.append(f"breakaway_friction (on by default) is off: the adaptive solver {opts['trajectory']['solver']!r} "
                     "smooths friction at rest and cannot stick exactly (`fit.trajectory.solver: velocity_implicit`).")

    log("[2/4] joint trajectory-error fit (optimistix Levenberg–Marquardt through the simulated plant)")
    sim_fit = trajectory_simulator(opts["trajectory"])
    full = stack_experiments(exps)  # once: the joint fit takes its subset from it
    res, sel_pos, t_traj, profile = _joint_fit(full, modes, drive, p0, free_names, sim_fit, opts, notes, log)
    per_fit, t_per = _per_experiment_fits(paper, res, drive, full, files, opts, notes, log)
    _lm_notes(res, undetermined, notes)
    _friction_sign_notes(res.params, res.effects, notes)

    log(f"[3/4] simulating all {len(exps)} experiments with the fitted parameters")
    t0 = time.time()
    # at the fit's own ODE tolerance (≤ 0.1 noise std from an rtol-1e-8 reference on HD2); called
    # unjitted on concrete arrays, so the experiments are spread over every device (`simulate_batch`)
    traj = simulate_batch(res.params, drive, full, simulator=sim_fit, effects=res.effects)
    t_sim = time.time() - t0
    per_exp, overall = _simulation_nrmse(traj, full, files, modes)
    truth = (dataset.truth or {}).get("parameters") if dataset.truth else None
    params_json = _parameters_json(res, paper, per_fit, undetermined, truth, files)

    log("[4/4] report and figures")
    from .plots import fit_figures  # matplotlib loads only when figures are drawn
    figs = fit_figures(out, res.params, paper, full, traj, modes, files, drive, exps)
    total = time.time() - t_start
    result = {
        "schema": "hdjax.fit/1",
        "dataset": dataset.name,
        "parameters": params_json,
        "model_form": _model_form_json(res, profile),
        "fit": _fit_section(res, overall, per_exp, [files[j] for j in sel_pos]),
        "paper_identification": paper.to_dict(),
        "consistency_note": (
            "`consistency` is the paper's measure, std/|mean| of per-experiment estimates. For fitted parameters it "
            "comes from one trajectory-error LM fit per experiment (`per_experiment`, aligned with "
            "`fit.per_experiment`; null where the experiment does not inform the parameter, LM did not converge, or "
            "the estimate is undetermined: its own standard error (`per_experiment_std_error`, block sandwich of its "
            "record) infinite or over 30 % of it; these are "
            "listed with their reasons in `per_experiment_undetermined` and left out of `consistency`, whose count is "
            "`consistency_n`); `spread_over_std_error` is how far the counted estimates scatter beyond their own "
            "standard errors (about 1 when the experiments agree within them); `paper_method` holds the paper's "
            "regressions and their consistency."
        ),
        "per_experiment_fit": None if per_fit is None else {
            "parameters": list(per_fit.free),
            "converged": [bool(c) if per_fit.mask[j].any() else None for j, c in enumerate(per_fit.converged)],
            "lm_steps": [int(x) for x in per_fit.steps],
            "chi2_reduced": [float(x) for x in per_fit.chi2_reduced],
            "lm_stop_reason": [str(x) if per_fit.mask[j].any() else None for j, x in enumerate(per_fit.stop_reason)],
        },
        "notes": notes,
        "figures": figs,
        "timing_s": {"total": total, "paper_identification": t_paper, "trajectory_fit": t_traj,
                     "per_experiment_fits": t_per, "simulate_all": t_sim},
    }
    write_results(out, "fit.json", result, _report(result, truth), log=log)
    return result


def _free_and_undetermined(opts: dict, modes: list[str], paper) -> tuple[list[str], dict[str, str]]:
    """Structural identifiability: the parameters the joint fit frees, and why each parameter the
    experiment types cannot determine is left out (name → reason)."""
    free_names = [k for k in opts["trajectory"]["free"] if k in PARAMETER_NAMES]
    if opts["trajectory"]["fit_alpha"] and "alpha" not in free_names:
        free_names.append("alpha")
    undetermined = {}
    if "free" not in modes:
        for k in FRICTION_NAMES:
            undetermined[k] = (
                "no free-motion experiments: the locked tests barely move the wave generator fast enough to separate "
                "inertia, viscous and Coulomb friction; record free-motion runs above 0.3 rad/s in both directions"
            )
    for k in paper.undetermined():
        if k in ("Tssp1", "Tssn1"):
            undetermined.setdefault(
                k, "no low-velocity experiments in this direction (median |ω| below 5·Tss2); record slow runs"
            )
    return [k for k in free_names if k not in undetermined], undetermined


def _joint_fit(full, modes, drive, p0, free_names, sim_fit, opts, notes, log):
    """The joint trajectory-error LM fit on an evenly spread subset (`select_experiments`) of the
    stacked experiments `full`, from the paper's estimates `p0`. Returns the fit, the positions of
    the experiments used, and its time (s)."""
    sel_pos = select_experiments(modes, int(opts["trajectory"]["max_experiments"]))
    if len(sel_pos) < len(modes):
        notes.append(
            f"The trajectory-error fit used {len(sel_pos)} of {len(modes)} experiments (evenly spread over constrained and "
            f"free; `fit.trajectory.max_experiments`) to bound the run time on a CPU; all experiments are simulated "
            f"for the NRMSE figures."
        )
    batch = take_experiments(full, sel_pos)
    effects, free_effects = fit_model_form(opts["trajectory"], _sample_period(full))
    t0 = time.time()
    res = fit_parameters(
        p0, drive, batch, free=free_names, simulator=sim_fit, max_steps=int(opts["trajectory"]["max_steps"]),
        cost_rtol=float(opts["trajectory"]["cost_rtol"]), step_se_tol=float(opts["trajectory"]["step_se_tol"]),
        se_block=float(opts["trajectory"]["se_block"]), throw=False,  # a fit that stops short is reported (`_lm_notes`), not an error
        effects=effects, free_effects=free_effects,
    )
    log(f"      {res.steps} LM steps, stopped on {res.stop_reason}, reduced chi-square {res.chi2_reduced:.3g} ({time.time() - t0:.1f} s)")
    profile = None
    if opts["trajectory"]["breakaway_friction"]:
        # stick/slip events give LM no derivative: grid search, LM with the torques held, search again
        res, profile = fit_breakaway_friction(
            res, drive, batch, simulator=sim_fit, free_effects=free_effects, max_steps=int(opts["trajectory"]["max_steps"]),
            cost_rtol=float(opts["trajectory"]["cost_rtol"]), step_se_tol=float(opts["trajectory"]["step_se_tol"]))
        edge = [p.split(".")[1] for p in BREAKAWAY_PATHS if profile["paths"][p]["value"] >= profile["paths"][p]["grid"][-1]]
        if edge:
            notes.append(f"breakaway_friction: {', '.join(edge)} at the top of its search grid "
                         f"({BREAKAWAY_GRID[-1]:g}× the direction's Coulomb friction): the drive may break "
                         "away higher still; the value is a lower bound.")
        sticks = [max(float(getattr(res.effects.breakaway_friction, f"breakaway_{d}")),
                      float(getattr(res.params, f"Ts{d}")) + float(getattr(res.params, f"Tss{d}1"))) for d in "pn"]
        log(f"      breakaway torques {sticks[0]:.3g} / {sticks[1]:.3g} N·m (grid search, then {profile['lm_steps']} LM "
            f"steps with them held; at least eq. 9's friction at rest), reduced chi-square {res.chi2_reduced:.3g} "
            f"({time.time() - t0:.1f} s)")
    t_traj = time.time() - t0
    return res, sel_pos, t_traj, profile


def _per_experiment_fits(paper, res, drive, full, files, opts, notes, log):
    """The trajectory method's consistency: one LM fit per experiment (one compiled program), each experiment
    fitting what the paper's regressions take from it (locked: K1, Tst; fast free motion: Jeff and
    the viscous/Coulomb terms of the directions it covers; slow free motion: Stribeck), the rest
    fixed at the joint estimate. Returns the fits (None when off or no experiment informs a
    parameter) and their time (s)."""
    per_fit, t_per = None, 0.0
    if not opts["trajectory"]["per_experiment"]:
        return per_fit, t_per
    n_exp = len(files)
    mask = np.array([[np.isfinite(paper.per_experiment[k][j]) for k in res.free] for j in range(n_exp)], dtype=bool)
    informed = np.any(mask, axis=1)
    if not informed.any():
        return per_fit, t_per
    log(f"[2b/4] per-experiment trajectory-error fits ({int(informed.sum())} experiments, one compiled program)")
    t0 = time.time()
    per_fit = fit_per_experiment(
        res.params, drive, full, mask, free=res.free, simulator=per_experiment_simulator(opts["trajectory"]), sigma=res.sigma,
        max_steps=int(opts["trajectory"]["per_experiment_max_steps"]),
        cost_rtol=float(opts["trajectory"]["cost_rtol"]), step_se_tol=float(opts["trajectory"]["step_se_tol"]),
        effects=res.effects,  # the sensor lags held at the joint estimate
        se_block=res.se_block,
    )
    t_per = time.time() - t0
    bad = [files[j] for j in range(n_exp) if informed[j] and not per_fit.converged[j]]
    if bad:
        notes.append(
            f"per-experiment trajectory fit: Levenberg–Marquardt did not converge within "
            f"{opts['trajectory']['per_experiment_max_steps']} steps for {', '.join(bad)} "
            "(`fit.trajectory.per_experiment_max_steps`); these are left out of the consistency measure."
        )
    und = {k: int(np.sum(per_fit.undetermined[:, i] != "")) for i, k in enumerate(per_fit.free)}
    und_text = ", ".join(f"{k} {n}" for k, n in und.items() if n)
    jumps = int(np.sum(per_fit.stop_reason[informed] == "cost_jump"))
    log(f"      {int(per_fit.converged[informed].sum())}/{int(informed.sum())} converged ({t_per:.1f} s)"
        + (f"; {jumps} stopped where a step under {PER_EXPERIMENT_REJECT_SE_TOL:g} standard errors raised the cost (a "
           "jump: a stick or slip event appears or vanishes)" if jumps else "")
        + (f"; undetermined by their own record, left out of the consistency: {und_text}" if und_text else ""))
    return per_fit, t_per


def _friction_sign_notes(params, effects, notes: list[str]) -> None:
    """A note per direction where the fitted eq. 9 puts the friction of a sliding motor below zero
    near rest (Ts + Tss1 < 0: the Stribeck term larger than the Coulomb term), with the slip speed
    under which it pushes with the motion (Ts + Tss1·exp(−(ω/Tss2)²) = 0) and the torque that holds
    the motor at rest. Measured on the shipped HD2 campaign (bench: stick–slip with breakaway):
    Tsn + Tssn1 = −0.022 N·m, below zero under 0.068 rad/s, with the breakaway torque 0.045 N·m; the
    paper's Table I itself gives HD2 Tsn + Tssn1 = −0.012 N·m (under 0.056 rad/s)."""
    breakaway = effects.term("breakaway_friction") if "breakaway_friction" in effects.active else None
    for d, word in (("p", "positive"), ("n", "negative")):
        ts, tss1, tss2 = (float(getattr(params, k)) for k in (f"Ts{d}", f"Tss{d}1", "Tss2"))
        if ts > 0 and ts + tss1 < 0:
            w0 = tss2 * float(np.sqrt(np.log(-tss1 / ts)))
            hold = (f"the breakaway torque {float(getattr(breakaway, f'breakaway_{d}')):.3g} N·m holds the motor at rest"
                    if breakaway is not None else "nothing holds the motor at rest")
            notes.append(
                f"Ts{d} + Tss{d}1 = {ts + tss1:.3g} N·m: in the {word} direction eq. 9's friction of a sliding motor is "
                f"below zero (it pushes with the motion) at slip speeds under {w0:.3g} rad/s; {hold}. A negative "
                "Stribeck amplitude (friction rising from rest, as the paper found) is physical; one larger than the "
                "Coulomb friction is not: the fit is taking up a low-speed friction that eq. 9 cannot express (for "
                "example a sharp drop from breakaway to sliding), so read it as a shape, not a physical friction "
                "(`hdjax diagnose` screens `low_speed_friction`). The paper's own Table I gives HD2 "
                "Tsn + Tssn1 = 0.033 − 0.045 N·m < 0.")


def _lm_notes(res, undetermined: dict[str, str], notes: list[str]) -> None:
    """A note when the joint fit stopped short of its tolerance; a parameter whose standard error
    is not finite or over 30 % of its estimate is marked undetermined."""
    if not res.converged:
        notes.append(
            f"Levenberg–Marquardt did not reach its tolerance within {res.steps} steps (`fit.trajectory.max_steps`); "
            "the estimates are the last iterate."
        )
    for k in res.free:
        se, v = res.std_error[k], float(getattr(res.params, k))
        if poorly_determined(v, se):
            undetermined.setdefault(k, f"standard error {se:.3g} is over {100 * UNDETERMINED_SE_RTOL:.0f} % of the estimate {v:.3g}: "
                                       "the data do not pin it down")


def _simulation_nrmse(traj, full, files, modes) -> tuple[list[dict], dict[str, float]]:
    """NRMSE of the simulated torque (N·m), motor velocity (rad/s) and, for free experiments,
    output position (rad) against the measurements: one row per experiment, and pooled over all."""
    m = np.asarray(full.mask)
    # on the host once (indexing the JAX arrays per experiment compiles small gather programs)
    channels = ("torque", "motor_velocity", "output_position")
    sim = {ch: np.asarray(getattr(traj, ch)) for ch in channels}
    meas = {ch: np.asarray(getattr(full, ch)) for ch in channels}
    success = np.asarray(traj.success)
    per_exp = []
    pooled = {"torque": ([], []), "motor_velocity": ([], [])}
    for j in range(len(files)):
        row = {"file": files[j], "mode": modes[j], "nrmse": {}, "simulation_ok": bool(success[j])}
        for ch in ("torque", "motor_velocity"):
            s = sim[ch][j][m[j]]
            y = meas[ch][j][m[j]]
            row["nrmse"][ch] = nrmse(s, y)
            pooled[ch][0].append(s)
            pooled[ch][1].append(y)
        if modes[j] == "free":
            s = sim["output_position"][j][m[j]]
            y = meas["output_position"][j][m[j]]
            row["nrmse"]["output_position"] = nrmse(s, y)
        per_exp.append(row)
    overall = {ch: nrmse(np.concatenate(a), np.concatenate(b)) for ch, (a, b) in pooled.items()}
    return per_exp, overall


def _parameters_json(res, paper, per_fit, undetermined: dict[str, str], truth, files: list[str]) -> dict[str, dict]:
    """fit.json's `parameters`: per parameter the joint estimate (SI, with its unit) and standard
    error, the consistency (the trajectory method's where per-experiment fits ran, over their
    determined estimates, else the paper's), the paper method's numbers, why it is undetermined,
    and the truth where known."""
    params_json = {}
    for k in PARAMETER_NAMES:
        traj_per = per_fit.per_experiment(k, determined_only=True) if per_fit is not None and k in per_fit.free else None
        traj_cons = per_fit.consistency(k) if per_fit is not None and traj_per is not None else None
        entry = {
            "value": float(getattr(res.params, k)),
            "unit": PARAMETER_UNITS[k],
            "std_error": res.std_error.get(k),
            "std_error_white": res.std_error_white.get(k),
            # the trajectory method's own consistency where per-experiment fits ran, else the paper's
            "consistency": _finite_or_none(traj_cons) if traj_per is not None else _finite_or_none(paper.consistency.get(k)),
            "consistency_method": "trajectory" if traj_per is not None else "paper",
            "per_experiment": [_finite_or_none(v) for v in (traj_per if traj_per is not None else paper.per_experiment[k])],
            "fitted": k in res.free,
            "paper_method": {
                "value": _finite_or_none(paper.estimates.get(k)),
                "consistency": _finite_or_none(paper.consistency.get(k)),
                "per_experiment": [_finite_or_none(v) for v in paper.per_experiment[k]],
            },
        }
        if per_fit is not None and traj_per is not None:
            col = per_fit.free.index(k)
            entry["consistency_n"] = int(np.sum(np.isfinite(traj_per)))
            entry["spread_over_std_error"] = _finite_or_none(per_fit.spread_over_std_error(k))
            entry["per_experiment_std_error"] = [
                _finite_or_none(se) if per_fit.undetermined[j, col] == "" else None for j, se in enumerate(per_fit.std_error[:, col])]
            entry["per_experiment_undetermined"] = [
                {"file": files[j], "value": _finite_or_none(per_fit.values[j, col]),
                 "std_error": _finite_or_none(per_fit.std_error[j, col]), "reason": str(per_fit.undetermined[j, col])}
                for j in range(len(files)) if per_fit.undetermined[j, col]]
        if k in undetermined:
            entry["undetermined"] = undetermined[k]
        if truth and k in truth:
            entry["truth"] = float(truth[k])
        params_json[k] = entry
    return params_json


def _fit_section(res, overall: dict, per_exp: list[dict], experiments_in_fit: list[str]) -> dict:
    """fit.json's `fit`: pooled and per-experiment NRMSE, the LM outcome, the noise levels (N·m,
    rad/s, rad), the correlation matrix of the freed parameters and how their standard errors
    were computed (`TrajectoryFit.std_error_method`)."""
    return {
        "nrmse": overall,
        "per_experiment": per_exp,
        "chi2_reduced": res.chi2_reduced,
        "converged": res.converged,
        "lm_steps": res.steps,
        "lm_stop_reason": res.stop_reason,
        "experiments_in_fit": experiments_in_fit,
        "noise_levels": dict(zip(("torque", "motor_velocity", "output_position"), res.sigma.tolist())),
        "correlation": {"parameters": list(res.free) + list(res.free_effects), "matrix": res.correlation.tolist()},
        "std_error_method": res.std_error_method,
        "std_error_block_s": res.se_block,
    }


def _sample_period(full) -> float:
    """The sample period (s) of the stacked experiments: the median step of the first record's time
    stamps (the loader holds every record to one rate within the SPEC's jitter)."""
    t = np.asarray(full.time)[0][np.asarray(full.mask)[0]]
    return float(np.median(np.diff(t)))


_FORM_NOTES = {
    "sensor_bandwidth": "first-order time constants of the strain gauge (torque_lag) and the tachometer "
                        "(velocity_lag): the simulated torque and motor velocity pass through them before they are "
                        "compared with the records (`fit.trajectory.sensor_bandwidth`)",
    "breakaway_friction": "static friction above eq. 9's limit at zero speed, per direction (breakaway_p, breakaway_n; "
                          "magnitudes, N·m): a motor at rest sticks until the torque holding it exceeds "
                          "max(Tsp + Tssp1, breakaway_p) or max(Tsn + Tssn1, breakaway_n) (`fit.trajectory.breakaway_friction`)",
}


def _model_form_json(res, profile: dict | None) -> dict:
    """fit.json's `model_form`: per term fitted with the parameters (hdjax's base-model adjustments,
    SPEC §4b's `sensor_bandwidth` and hdjax's `breakaway_friction`) each field's value, unit and
    standard errors, with a note; empty when the fit used none. A field set by a grid search
    (`profile`) has no standard error (its derivative is zero) and carries its grid and whitened
    squared errors instead."""
    out: dict[str, dict] = {}
    searched = profile["paths"] if profile else {}
    for path in list(res.free_effects) + list(searched):
        name, field = path.split(".", 1)
        term = res.effects.term(name)
        entry = out.setdefault(name, {"note": _FORM_NOTES.get(name, "")})
        if path in searched:
            entry[field] = {"value": float(getattr(term, field)), "unit": term.units[field], "std_error": None,
                            "method": "grid search of the whitened squared error (stick/slip events: no derivative)",
                            "grid": searched[path]["grid"], "sse": searched[path]["sse"]}
            if name == "breakaway_friction":
                entry[field].update(breakaway_summary(res.params, field, float(getattr(term, field)),
                                                      searched[path]["grid"], searched[path]["sse"],
                                                      float(res.chi2_reduced)))
        else:
            entry[field] = {"value": float(getattr(term, field)), "unit": term.units[field],
                            "std_error": res.std_error[path], "std_error_white": res.std_error_white[path]}
    return out


def breakaway_summary(params, field: str, value: float, grid, sse, chi2_reduced: float) -> dict:
    """What a searched breakaway torque means for the model (fit.json's `model_form.breakaway_friction`).

    A motor at rest sticks until the holding torque exceeds max(Ts + Tss1, breakaway) in that
    direction, so a torque at or below eq. 9's friction at rest (`at_rest_eq9`, N·m) changes
    nothing: `effective` is the limit the model sticks to. `consistent_range` brackets the torques
    the data do not tell apart from the best: the grid values next to the run of values whose
    whitened squared error is within `chi2_reduced` of the minimum (Δχ² = 1 scaled by the fit's
    reduced χ², as the standard errors are for misfit), or the grid's ends, as effective torques.
    A wide range says the records hold few stick events in that direction."""
    ts, tss = ("Tsp", "Tssp1") if field.endswith("_p") else ("Tsn", "Tssn1")
    rest = float(getattr(params, ts)) + float(getattr(params, tss))
    g, e = np.asarray(grid, dtype=float), np.asarray(sse, dtype=float)
    k = int(np.argmin(e))
    near = e - e[k] <= max(float(chi2_reduced), 1.0)
    lo, hi = k, k
    while lo > 0 and near[lo - 1]:
        lo -= 1
    while hi < len(g) - 1 and near[hi + 1]:
        hi += 1
    lo, hi = max(lo - 1, 0), min(hi + 1, len(g) - 1)
    return {"at_rest_eq9": rest, "effective": max(value, rest),
            "consistent_range": [max(float(g[lo]), rest), max(float(g[hi]), rest)]}


def _finite_or_none(v):
    if v is None:
        return None
    v = float(v)
    return v if np.isfinite(v) else None


def _ms(v) -> str:
    """A time's standard error (s) for the report in ms to 3 digits, "—" when not finite."""
    return "—" if v is None or not np.isfinite(v) else f"{1e3 * v:.3g}"


def _fmt(v):
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "—"
    return f"{v:.4g}"


def _breakaway_text(field: str, e: dict) -> str:
    """One breakaway torque for the report: the torque the model sticks to, its consistent range,
    and whether it is eq. 9's own friction at rest (no breakaway above it)."""
    name = field.replace("_", " ")
    if "effective" not in e:  # a fit.json written before `breakaway_summary`
        return f"{name} {e['value']:.4g} N·m"
    lo, hi = e["consistent_range"]
    text = f"{name} {e['effective']:.4g} N·m [{lo:.4g}, {hi:.4g}]"
    if e["value"] <= e["at_rest_eq9"]:
        text += " (eq. 9's friction at rest: no breakaway above it found)"
    return text


def _report(r: dict, truth) -> str:
    lines = [f"# Identification of `{r['dataset']}`", ""]
    lines.append("Two methods: the paper's regressions (section III, per experiment, with its consistency measure) and "
                 "the joint trajectory-error fit (Levenberg–Marquardt through the simulated plant, standard errors from "
                 + ("a block sandwich covariance that allows a misfit correlated in time)."
                    if r["fit"].get("std_error_method") == "block_sandwich" else "the Gauss–Newton covariance)."))
    lines += ["", "## Table I", ""]
    lines.append("Consistency is the paper's measure, std/|mean| of the per-experiment estimates (trajectory: one LM fit "
                 "per experiment; paper: its regressions per experiment).")
    lines.append("")
    head = ("| parameter | unit | trajectory fit | std error | consistency (trajectory) | paper method | "
            "consistency (paper) |" + (" truth |" if truth else ""))
    lines += [head, "|" + "---|" * (8 if truth else 7)]

    def pct(v):
        return "—" if v is None else f"{v * 100:.3g} %"

    for k, e in r["parameters"].items():
        traj_c = e["consistency"] if e.get("consistency_method") == "trajectory" else None
        n_c = f" (n = {e['consistency_n']})" if traj_c is not None and "consistency_n" in e else ""
        row = (f"| {k} | {e['unit']} | {_fmt(e['value'])}{'' if e['fitted'] else ' (fixed)'} | {_fmt(e['std_error'])} | "
               f"{pct(traj_c)}{n_c} | {_fmt(e['paper_method']['value'])} | {pct(e['paper_method']['consistency'])} |")
        if truth:
            row += f" {_fmt(e.get('truth'))} |"
        lines.append(row)
    lines += ["", "## Fit quality (NRMSE = RMS(sim − meas) / RMS(meas − mean))", ""]
    for ch, v in r["fit"]["nrmse"].items():
        lines.append(f"- {ch}: {v:.4f}")
    lines.append(f"- reduced chi-square (noise-weighted): {r['fit']['chi2_reduced']:.3g}; LM steps {r['fit']['lm_steps']}, "
                 f"converged: {r['fit']['converged']}")
    form = r.get("model_form") or {}
    if form.get("sensor_bandwidth"):
        lags = ", ".join(f"{k.replace('_', ' ')} {1e3 * e['value']:.3f} ± {_ms(e['std_error'])} ms"
                         for k, e in form["sensor_bandwidth"].items() if k != "note")
        lines.append(f"- sensor bandwidth fitted with the parameters (first-order lags of the simulated outputs): {lags}")
    if form.get("breakaway_friction"):
        ex = ", ".join(_breakaway_text(k, e) for k, e in form["breakaway_friction"].items() if k != "note")
        lines.append(f"- breakaway torques, static friction above eq. 9's at rest (a grid search, then LM again with them "
                     f"held; stick/slip events give no derivative, so no standard error; in brackets the torques the "
                     f"data do not tell apart from it): {ex}")
    if r["fit"].get("std_error_method") == "block_sandwich":
        lines.append(f"- std errors: robust to a misfit correlated over {r['fit']['std_error_block_s']:g} s (block sandwich); the white-noise "
                     "Gauss–Newton ones are in fit.json (`std_error_white`) and are smaller where the model is not exact")
    left = {k: e["per_experiment_undetermined"] for k, e in r["parameters"].items() if e.get("per_experiment_undetermined")}
    if left:
        lines += ["", "## Per-experiment estimates left out of the consistency", "",
                  "An estimate counts only where its own record determines it (standard error, block sandwich of the "
                  "record, finite and at most 30 % of it); the others "
                  "are in fit.json (`per_experiment_undetermined`).", ""]
        for k, rows in left.items():
            ex = "; ".join(f"{u['file']}: {_fmt(u['value'])} ({u['reason']})" for u in rows[:3])
            lines.append(f"- **{k}**: {len(rows)} left out, {r['parameters'][k].get('consistency_n', 0)} counted. {ex}"
                         + ("; …" if len(rows) > 3 else ""))
    und = {k: e["undetermined"] for k, e in r["parameters"].items() if "undetermined" in e}
    if und:
        lines += ["", "## Parameters the data do not determine", ""]
        lines += [f"- **{k}**: {why}" for k, why in und.items()]
    if r["notes"]:
        lines += ["", "## Notes", ""] + [f"- {n}" for n in r["notes"]]
    lines += ["", "## Figures", ""] + [f"![{f}]({f})" for f in r["figures"]]
    lines += ["", f"Total time {r['timing_s']['total']:.1f} s.", ""]
    return "\n".join(lines)


def hysteresis_curves(paper, experiment, drive, j: int) -> dict:
    """Fig. 3's data for constrained experiment `j` (its index in the list given to
    `identify_paper`): the measured torsion θm/N and torque, and eq. 5 with the paper's two
    compliance regressions of this record, evaluated on the same filtered signals they were fitted
    to: the linear one at the fixed α (`paper.estimates["alpha"]`, K1, Tst and torsion offset of
    this record) and the nonlinear one at this record's optimal α (its own K1, Tst and offset).

    Each curve is its own parameter set's least-squares fit of this loop, and the nonlinear
    regression starts from the linear one's solution at α = ½ (`_compliance_nonlinear_one`), so the
    optimal-α curve fits at least as well as the α = ½ one when the fixed α is ½. (Swapping the
    optimal α into the joint fit's K1 and Tst, which were fitted at α = ½, does not.)

    **Returns:** a dict with `torsion` (rad), `torque` (N·m, measured), and `curves`: a list of
    `{"label", "alpha", "K1", "Tst", "offset", "torque", "rms"}` (`rms` against the filtered torque
    the regressions fit), the fixed-α curve first; a regression that did not determine this record
    is left out.
    """
    from .._fit.paper import _TORSION_RATE_SCALE, _prepare
    from .._model.smooth import smooth_signed_power

    opts = paper.details.get("options", {})
    q, _, _ = _prepare([experiment], drive, opts.get("cutoff_hz", 50.0), opts.get("filter_order", 5), [])
    n = int(np.asarray(q.mask[0]).sum())
    tors, rate, T_filt = (np.asarray(x[0])[:n] for x in (q.torsion, q.torsion_rate, q.torque))
    n_meas = int(np.asarray(experiment.mask).sum())
    sets = []
    a_fixed = float(paper.estimates.get("alpha", 0.5))
    K1, Tst = paper.per_experiment["K1"][j], paper.per_experiment["Tst"][j]
    c = paper.details.get("torsion_offset", [np.nan] * (j + 1))[j]
    if all(np.isfinite(v) for v in (K1, Tst, c)):
        sets.append((f"regression at fixed α = {a_fixed:.3g}", a_fixed, K1, Tst, c))
    nl = paper.alpha_nonlinear or {}
    if j in nl.get("indices", []):
        k = nl["indices"].index(j)
        if nl["converged"][k] and np.isfinite(nl["alpha"][k]):
            sets.append((f"regression at optimal α = {nl['alpha'][k]:.3f}", nl["alpha"][k], nl["K1"][k], nl["Tst"][k],
                         nl["offset"][k]))
    curves = []
    for label, a, K1, Tst, c in sets:
        model = K1 * (tors + c) + Tst * np.asarray(smooth_signed_power(jnp.asarray(rate), a, _TORSION_RATE_SCALE))
        curves.append({"label": label, "alpha": float(a), "K1": float(K1), "Tst": float(Tst), "offset": float(c),
                       "torque": model, "rms": float(np.sqrt(np.mean((model - T_filt) ** 2)))})
    return {"torsion": tors, "torque": np.asarray(experiment.torque)[:n_meas][:n], "curves": curves}
