"""hdjax: a differentiable harmonic-drive model (Taghirad & Bélanger) identified from bench data.

Float64 is not switched on here: commands, tests and scripts call
`jax.config.update("jax_enable_x64", True)` themselves.
"""

import importlib.metadata

from ._experiment import (
    Experiment as Experiment,
    make_experiment as make_experiment,
    stack_experiments as stack_experiments,
    unstack_experiments as unstack_experiments,
)
from ._model import (
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
from ._effects import EFFECT_NAMES as EFFECT_NAMES, Effects as Effects
from ._plant import (
    Simulator as Simulator,
    Trajectory as Trajectory,
    initial_state as initial_state,
    simulate as simulate,
    simulate_batch as simulate_batch,
)
from ._solver import Rodas3 as Rodas3


__version__ = importlib.metadata.version("hdjax")
