"""Fitting: the trajectory-error least squares (`least_squares`) with its LM (`lm`),
parameterisation and covariance, the paper's regressions (`paper`), sensitivities
(`sensitivity`), and the friction-only fits (`friction`, `friction_low_speed`).
"""
