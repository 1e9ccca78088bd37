"""Shared test fixtures: the paper's drives (Table I, SI reading) and short synthetic records."""

import numpy as np

import hdjax

DEG = 180.0 / np.pi


def hd1():
    p = hdjax.Parameters(alpha=0.5, K1=6340.0, Tst=57.2, Jeff=1.0e-4, Tvp=3.7e-4, Tvn=3.5e-4, Tsp=4.6e-2,
                         Tsn=4.4e-2, Tssp1=-0.0076, Tssn1=-0.0203, Tss2=0.1)
    return p, hdjax.Drive(gear_ratio=100.0, torque_constant=0.0543, load_inertia=0.2)


def hd2():
    p = hdjax.Parameters(alpha=0.5, K1=104.2 * DEG, Tst=7.96 * DEG**0.5, Jeff=1.0e-4, Tvp=1.8e-3, Tvn=2.1e-3,
                         Tsp=7.5e-2, Tsn=3.3e-2, Tssp1=-0.0487, Tssn1=-0.0450, Tss2=0.1)
    return p, hdjax.Drive(gear_ratio=160.0, torque_constant=0.1815, load_inertia=0.5)


def sine_experiment(mode, *, amplitude=1.0, freq=2.0, duration=0.5, dt=1e-3, offset=0.0):
    t = np.arange(0.0, duration, dt)
    i = offset + amplitude * np.sin(2 * np.pi * freq * t) * np.minimum(1.0, t / 0.05)
    z = np.zeros_like(t)
    return hdjax.make_experiment(t, i, z, z, mode=mode, output_position=z)


def host_callbacks(jaxpr) -> int:
    """How many host-callback equations a jaxpr holds, nested jaxprs included (JAX writes no
    program with one to its persistent compilation cache)."""
    import jax.extend.core as jc

    return sum(("callback" in eqn.primitive.name) + sum(host_callbacks(sub) for sub in jc.jaxprs_in_params(eqn.params))
               for eqn in jaxpr.eqns)
