"""The figures of the commands, for scripts that make them from their own results (matplotlib is
imported with this module, never by `import hdjax`). Every figure is written atomically as a PNG:
labelled axes with units, legends, measured against simulated."""

from ._workflows.plots import (
    diagnosis_figures as diagnosis_figures,
    fit_figures as fit_figures,
    friction_cv_figure as friction_cv_figure,
    friction_heldout_time_figure as friction_heldout_time_figure,
    friction_velocity_figure as friction_velocity_figure,
    sensitivity_figures as sensitivity_figures,
    tune_figures as tune_figures,
)
