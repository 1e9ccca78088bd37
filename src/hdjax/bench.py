"""The independent virtual test bench (public entry points of `hdjax._testbench.independent`): datasets that
hdjax's identification, diagnosis and tuning are judged on, made without hdjax's plant, solver or
model code (a fixed-step integrator in numpy, its loop compiled by numba; stick–slip friction with breakaway, a current loop,
sensor dynamics, drives drawn around HD1/HD2; see the `hdjax._testbench.independent` module docstring for what
differs from hdjax's plant).

- `make_dataset(out_dir, *, drive, seed, ..., effects, deviations)`: write a SPEC §2 dataset folder
  (with `truth.yaml`).
- `simulate_dataset(...)`: the same session in memory.
- `Deviations`: the real-bench deviations, each switchable (`Deviations.none()`: all off).
- `Bench`, `pi_law`: closed-loop runs of a controller on the bench a dataset came from.
"""

from ._testbench.independent import (
    Bench as Bench,
    Deviations as Deviations,
    Station as Station,
    make_dataset as make_dataset,
    pi_law as pi_law,
    simulate_dataset as simulate_dataset,
)

__all__ = ["Bench", "Deviations", "Station", "make_dataset", "pi_law", "simulate_dataset"]
