"""The independent virtual test bench (numpy only, written apart from hdjax's plant, solver and
effect code; see `hdjax._bench` for what differs from the plant): datasets to judge an
identification or a diagnosis on without the inverse crime, and closed-loop runs to validate
controllers on."""

from ._bench import (
    EFFECTS as EFFECTS,
    STATIONS as STATIONS,
    Bench as Bench,
    Deviations as Deviations,
    make_dataset as make_dataset,
    pi_law as pi_law,
    simulate_dataset as simulate_dataset,
)
