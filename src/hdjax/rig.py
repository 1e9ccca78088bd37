"""The plant-based virtual rig (public entry points of `hdjax._testbench.rig`): the paper's two stations and
their 20 + 30 experiment campaigns, simulated with hdjax's **own plant** (`hdjax.simulate`) plus
sensor noise.

Because its truth *is* hdjax's model, data from this rig cannot judge an identification or a
diagnosis (the "inverse crime"): use `hdjax.bench` (an independent generator) for that. Use this
rig only where a check needs the model to be exact (numerics, AD, convergence, recovery of known
parameters by the fitter itself), and say so there.

- `station_hd1()`, `station_hd2()`: the paper's stations (`Station`: truth, drive, sensors).
- `campaign(station, *, seed, ...)`: the current profiles of one campaign.
- `run_campaign(station, *, effects, seed, profiles)`: simulated records (`Run`s).
- `write_campaign(folder, station, runs, ...)`: a SPEC §2 dataset folder with `truth.yaml`.
- `hide_effect(name, magnitude, *, station, ...)`: an `Effects` with one SPEC §4 effect.
"""

from ._testbench.rig import (
    CurrentProfile as CurrentProfile,
    Run as Run,
    Station as Station,
    campaign as campaign,
    hide_effect as hide_effect,
    run_campaign as run_campaign,
    station_hd1 as station_hd1,
    station_hd2 as station_hd2,
    write_campaign as write_campaign,
)

__all__ = ["CurrentProfile", "Run", "Station", "campaign", "hide_effect", "run_campaign", "station_hd1",
           "station_hd2", "write_campaign"]
