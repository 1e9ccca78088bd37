"""hdjax: a differentiable harmonic-drive model (Taghirad & Bélanger) identified from bench data.

Float64 is not switched on here: commands, tests and scripts call
`jax.config.update("jax_enable_x64", True)` themselves.
"""

import importlib.metadata

from ._control.closed_loop import (
    GainScaling as GainScaling,
    LoopTrajectory as LoopTrajectory,
    Plant as Plant,
    Reference as Reference,
    TorqueController as TorqueController,
    TorqueGains as TorqueGains,
    TuneResult as TuneResult,
    closed_loop as closed_loop,
    doublet_reference as doublet_reference,
    relay_test as relay_test,
    sine_reference as sine_reference,
    step_metrics as step_metrics,
    step_reference as step_reference,
    tracking_cost as tracking_cost,
    tune_gains as tune_gains,
    ziegler_nichols_pi as ziegler_nichols_pi,
)
from ._data.experiment import (
    Experiment as Experiment,
    FrictionExperiment as FrictionExperiment,
    make_experiment as make_experiment,
    make_friction_experiment as make_friction_experiment,
    select_experiments as select_experiments,
    stack_experiments as stack_experiments,
    take_experiments as take_experiments,
    unstack_experiments as unstack_experiments,
)
from ._data.load import Dataset as Dataset, DatasetError as DatasetError, load_config as load_config, load_dataset as load_dataset
from ._data.write import write_dataset as write_dataset
from ._discrepancy.evidence import covariate_drifts as covariate_drifts
from ._discrepancy.friction import diagnose_friction as diagnose_friction
from ._discrepancy.loop import Diagnosis as Diagnosis, diagnose as diagnose_effects  # noqa: F401 (public alias)
from ._discrepancy.significance import FRICTION_RULES as FRICTION_RULES, OUTPUT_ERROR_RULES as OUTPUT_ERROR_RULES, Significance as Significance
from ._fit.covariance import block_covariance as block_covariance, time_blocks as time_blocks
from ._fit.friction import (
    FrictionProblem as FrictionProblem,
    filtered_rms as filtered_rms,
    fit_coulomb_viscous as fit_coulomb_viscous,
    rms_stats as rms_stats,
)
from ._fit.least_squares import (
    BREAKAWAY_GRID as BREAKAWAY_GRID,
    DEFAULT_FREE as DEFAULT_FREE,
    POSITIVE as POSITIVE,
    CostStop as CostStop,
    experiment_residuals as experiment_residuals,
    fit_breakaway_friction as fit_breakaway_friction,
    fit_noise_levels as fit_noise_levels,
    fit_parameters as fit_parameters,
    fit_per_experiment as fit_per_experiment,
    make_effect_map as make_effect_map,
    make_parameter_map as make_parameter_map,
    noise_levels as noise_levels,
    profile_effect_parameters as profile_effect_parameters,
)
from ._fit.lm import MarquardtLM as MarquardtLM
from ._fit.paper import PAPER_HD2_SI as PAPER_HD2_SI, PaperIdentification as PaperIdentification, identify_paper as identify_paper
from ._fit.parameterisation import Entry as Entry, Parameterisation as Parameterisation, parameterisation as parameterisation
from ._model.effects import (
    EFFECT_NAMES as EFFECT_NAMES,
    MAX_ORDER as MAX_ORDER,
    TERMS as TERMS,
    AbstractPeriodicTerm as AbstractPeriodicTerm,
    AbstractTerm as AbstractTerm,
    BreakawayFriction as BreakawayFriction,
    Cogging as Cogging,
    Effects as Effects,
    InputBetweenSamples as InputBetweenSamples,
    InputDelay as InputDelay,
    KinematicError as KinematicError,
    LoadDependentFriction as LoadDependentFriction,
    LostMotion as LostMotion,
    LowSpeedFriction as LowSpeedFriction,
    NonlinearStiffness as NonlinearStiffness,
    PositionDependentFriction as PositionDependentFriction,
    PositionDependentTorque as PositionDependentTorque,
    PreslidingFriction as PreslidingFriction,
    RateIndependentHysteresis as RateIndependentHysteresis,
    SensorBandwidth as SensorBandwidth,
    SensorOffset as SensorOffset,
    ThermalDrift as ThermalDrift,
    TorqueSensorRipple as TorqueSensorRipple,
    ViscousFrictionLaw as ViscousFrictionLaw,
)
from ._model.friction_only import (
    FRICTION_NAMES as FRICTION_NAMES,
    FrictionParameters as FrictionParameters,
    FrictionStructure as FrictionStructure,
    friction_model_torque as friction_model_torque,
)
from ._model.paper import (
    PARAMETER_NAMES as PARAMETER_NAMES,
    PARAMETER_UNITS as PARAMETER_UNITS,
    Drive as Drive,
    Parameters as Parameters,
    Smoothing as Smoothing,
    compliance_torque as compliance_torque,
    friction_basis as friction_basis,
    friction_torque as friction_torque,
    motor_acceleration as motor_acceleration,
)
from ._model.smooth import smooth_sign as smooth_sign, smooth_signed_power as smooth_signed_power, smooth_step as smooth_step
from ._plant.rosenbrock import FirstStep as FirstStep, Rodas3 as Rodas3, Ros34PW2 as Ros34PW2, StepToSamples as StepToSamples
from ._plant.sharding import (
    COMPILATION_CACHE_ENV as COMPILATION_CACHE_ENV,
    CPU_COMPILE_FLAGS as CPU_COMPILE_FLAGS,
    HOST_DEVICES_ENV as HOST_DEVICES_ENV,
    available_cores as available_cores,
    compilation_cache_dir as compilation_cache_dir,
    experiment_batching as experiment_batching,
    for_each_experiment as for_each_experiment,
    use_compilation_cache as use_compilation_cache,
    use_host_devices as use_host_devices,
)
from ._plant.simulate import (
    PLANT_W_METHOD as PLANT_W_METHOD,
    Simulator as Simulator,
    Trajectory as Trajectory,
    initial_state as initial_state,
    plant_stiff_part as plant_stiff_part,
    simulate as simulate,
    simulate_batch as simulate_batch,
)
from ._plant.stepper import VelocityImplicit as VelocityImplicit
from ._workflows.artifacts import (
    effects_from_dict as effects_from_dict,
    effects_to_dict as effects_to_dict,
    read_extended_model as read_extended_model,
    read_fit_json as read_fit_json,
)
from ._workflows.config import ConfigError as ConfigError
from ._workflows.friction import friction_diagnosis_doc as friction_diagnosis_doc

try:
    __version__ = importlib.metadata.version("hdjax")
except importlib.metadata.PackageNotFoundError:  # run from a source tree (PYTHONPATH=src), not installed
    __version__ = "0+source"
