"""The commands' workflows, one module each (`fit`, `diagnose`, `sensitivity`, `tune`, `friction`),
and what they share: the CLI, the config schema, fit.json / extended_model.json, atomic I/O,
reports, figures and progress.
"""
