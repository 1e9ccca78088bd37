"""Measured experiments as array PyTrees, one per record (`Experiment` for locked and free-motion
tests, `FrictionExperiment` for friction-only records); batches are padded and masked."""

import dataclasses
from collections.abc import Sequence
from typing import TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, Bool, Float

MODES = ("constrained", "free", "friction")
CONSTRAINED, FREE, FRICTION = 0, 1, 2
#: Units of the simulated and measured channels of a dynamic experiment.
CHANNEL_UNITS = {"torque": "N·m", "motor_velocity": "rad/s", "output_position": "rad"}


class Experiment(eqx.Module):
    """One constrained or free-motion record sampled on a uniform time grid (SI units).

    **Attributes:**

    - `time`: sample times (s), uniform step.
    - `current`: motor current (A), the input that drives the simulation.
    - `torque`: measured transmitted torque (N·m).
    - `motor_velocity`: measured wave-generator velocity (rad/s).
    - `output_position`: measured output angle (rad); zeros where not measured.
    - `motor_position`: measured wave-generator angle (rad); NaN-free, zeros where not measured.
    - `mask`: True on real samples, False on padding (batches of different lengths).
    - `free`: 1.0 for free motion, 0.0 for constrained (output locked).
    - `has_output_position`, `has_motor_position`: 1.0 where the channel was measured.
    - `start_time`: time since the session began (s), 0 when not given.
    - `mode`: 0 constrained, 1 free (see `MODES`).

    A stacked batch (`stack_experiments`) has a leading experiment axis on every field (`*exp`).
    """

    time: Float[Array, "*exp time"]
    current: Float[Array, "*exp time"]
    torque: Float[Array, "*exp time"]
    motor_velocity: Float[Array, "*exp time"]
    output_position: Float[Array, "*exp time"]
    motor_position: Float[Array, "*exp time"]
    mask: Bool[Array, "*exp time"]
    free: Float[Array, "*exp"]
    has_output_position: Float[Array, "*exp"]
    has_motor_position: Float[Array, "*exp"]
    start_time: Float[Array, "*exp"]

    @property
    def n_samples(self) -> int:
        return int(np.sum(np.asarray(self.mask)))

    def first(self, n: int) -> "Experiment":
        """The record cut to its first `n` samples (the per-sample arrays; scalars unchanged)."""
        return Experiment(**{k: (v[:n] if v.ndim == 1 else v) for k, v in
                             ((k, getattr(self, k)) for k in Experiment.__dataclass_fields__)})


def make_experiment(
    time,
    current,
    torque,
    motor_velocity,
    *,
    mode: str,
    output_position=None,
    motor_position=None,
    start_time: float = 0.0,
) -> Experiment:
    """Build an `Experiment` from arrays (SI units). `mode` is "constrained" or "free"; free motion
    needs `output_position`. Arrays must be 1-D, equally long and finite; time uniform."""
    if mode not in ("constrained", "free"):
        raise ValueError(f"`make_experiment`: mode must be 'constrained' or 'free', got {mode!r}.")
    arrays = {"time": time, "current": current, "torque": torque, "motor_velocity": motor_velocity}
    if output_position is not None:
        arrays["output_position"] = output_position
    if motor_position is not None:
        arrays["motor_position"] = motor_position
    arrays = {k: np.asarray(v, dtype=np.float64) for k, v in arrays.items()}
    n = len(arrays["time"])
    for k, v in arrays.items():
        if v.ndim != 1 or len(v) != n:
            raise ValueError(f"`make_experiment`: `{k}` must be 1-D with {n} samples like `time`, got shape {v.shape}.")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"`make_experiment`: `{k}` has NaN or inf at sample {int(np.argmin(np.isfinite(v)))}.")
    if n < 3:
        raise ValueError(f"`make_experiment`: need at least 3 samples, got {n}.")
    if mode == "free" and output_position is None:
        raise ValueError("`make_experiment`: free-motion experiments need `output_position` (rad).")
    zeros = np.zeros(n)
    return Experiment(
        time=jnp.asarray(arrays["time"]),
        current=jnp.asarray(arrays["current"]),
        torque=jnp.asarray(arrays["torque"]),
        motor_velocity=jnp.asarray(arrays["motor_velocity"]),
        output_position=jnp.asarray(arrays.get("output_position", zeros)),
        motor_position=jnp.asarray(arrays.get("motor_position", zeros)),
        mask=jnp.ones(n, dtype=bool),
        free=jnp.asarray(1.0 if mode == "free" else 0.0),
        has_output_position=jnp.asarray(1.0 if output_position is not None else 0.0),
        has_motor_position=jnp.asarray(1.0 if motor_position is not None else 0.0),
        start_time=jnp.asarray(float(start_time)),
    )


def _pad(x: np.ndarray, n: int, *, extend_time: bool = False) -> np.ndarray:
    if len(x) == n:
        return x
    if extend_time:
        dt = x[1] - x[0]
        return np.concatenate([x, x[-1] + dt * np.arange(1, n - len(x) + 1)])
    return np.concatenate([x, np.full(n - len(x), x[-1])])


R = TypeVar("R", bound=eqx.Module)


def stack_experiments(experiments: Sequence[R], length: int | None = None) -> R:
    """Stack records of one kind (`Experiment`, or `FrictionExperiment` for friction-only data)
    along a leading `experiment` axis, padding each to `length` samples (default: the longest).
    Padding repeats the last sample, extends the time grid and is masked out, so it never enters
    a residual (a friction record's presliding state runs on through it, after its real samples).
    The one stacking function of every workflow."""
    if not experiments:
        raise ValueError("`stack_experiments`: no experiments given.")
    kind = type(experiments[0])
    if any(type(e) is not kind for e in experiments):
        raise ValueError(f"`stack_experiments`: mixed record kinds {sorted({type(e).__name__ for e in experiments})}; "
                         "stack one kind at a time.")
    n = max(int(e.time.shape[0]) for e in experiments) if length is None else length  # pyright: ignore[reportAttributeAccessIssue]
    fields = {}
    for f in dataclasses.fields(kind):
        name = f.name
        vals = []
        for e in experiments:
            v = np.asarray(getattr(e, name))
            if v.ndim == 1:
                if name == "mask":
                    v = np.concatenate([v, np.zeros(n - len(v), dtype=bool)])
                else:
                    v = _pad(v, n, extend_time=(name == "time"))
            vals.append(v)
        fields[name] = jnp.asarray(np.stack(vals))
    return kind(**fields)


def select_experiments(modes: list[str], max_n: int) -> list[int]:
    """Positions of an evenly spread subset of at most `max_n` experiments (all when there are no
    more), half constrained and half free (the other mode fills the places one mode cannot),
    each mode's picks evenly spread over its records. The one selection rule of every workflow
    (the joint fit's `fit.trajectory.max_experiments`, `sensitivity.max_experiments`)."""
    if max_n < 1:
        raise ValueError(f"`select_experiments`: max_n must be at least 1, got {max_n}.")
    if len(modes) <= max_n:
        return list(range(len(modes)))
    cons = [j for j, m in enumerate(modes) if m == "constrained"]
    free = [j for j, m in enumerate(modes) if m != "constrained"]
    n_c = min(len(cons), max(max_n // 2, max_n - len(free)))

    def spread(lst: list[int], n: int) -> list[int]:
        return [lst[int(round(j))] for j in np.linspace(0, len(lst) - 1, n)] if n > 0 else []

    return sorted(spread(cons, n_c) + spread(free, max_n - n_c))


def take_experiments(batch: Experiment, positions) -> Experiment:
    """The experiments at `positions` (a list or integer array; repeats allowed) of a stacked
    batch, as a stacked batch with the same padding: its length stays that of `batch`, not that
    of the longest experiment taken."""
    return take_rows(batch, positions)


def take_rows(tree, positions):
    """Every array leaf of `tree` at the leading-axis `positions` (repeats allowed). Concrete arrays
    are indexed on the host with numpy: an eager `x[idx]` on a JAX array compiles a small gather
    program (and its index arithmetic) for every leaf shape, about 5 XLA compilations a leaf, which
    the commands paid once each in their start-up (2026-12-05). Inside a trace it is `x[idx]`."""
    idx = np.asarray(positions, dtype=int)

    def take(v):
        if isinstance(v, Tracer):
            return v[idx]
        return jnp.asarray(np.asarray(v)[idx])

    return jax.tree.map(take, tree)


def unstack_experiments(batch: Experiment) -> list[Experiment]:
    """Inverse of `stack_experiments`, trimming the padding."""
    out = []
    for i in range(batch.time.shape[0]):
        one = jax.tree.map(lambda v: v[i], batch)
        out.append(one.first(int(np.asarray(batch.mask)[i].sum())))
    return out


class FrictionExperiment(eqx.Module):
    """One friction record: friction torque against velocity (SI units), for fitting eq. 9 alone.

    **Attributes:**

    - `time`: sample times (s), uniform step.
    - `velocity`: velocity of the side the friction acts on (rad/s; wave generator for eq. 9).
    - `friction_torque`: measured friction torque (N·m).
    - `position`: angle (rad); zeros where not measured.
    - `has_position`: 1.0 when `position` was measured, else 0.0.
    - `start_time`: time since the session began (s), 0 when not given.
    - `mask`: True on real samples, False on padding.

    A stacked batch (`stack_experiments`) has a leading experiment axis on every field (`*exp`).
    """

    time: Float[Array, "*exp time"]
    velocity: Float[Array, "*exp time"]
    friction_torque: Float[Array, "*exp time"]
    position: Float[Array, "*exp time"]
    has_position: Float[Array, "*exp"]
    start_time: Float[Array, "*exp"]
    mask: Bool[Array, "*exp time"]

    @property
    def n_samples(self) -> int:
        return int(np.sum(np.asarray(self.mask)))


def make_friction_experiment(
    time, velocity, friction_torque, *, position=None, start_time: float = 0.0
) -> FrictionExperiment:
    """Build a `FrictionExperiment` from 1-D arrays: time (s), velocity (rad/s), friction torque
    (N·m) and optionally position (rad); `start_time` (s) since the session began."""
    arrays = {"time": time, "velocity": velocity, "friction_torque": friction_torque}
    if position is not None:
        arrays["position"] = position
    arrays = {k: np.asarray(v, dtype=np.float64) for k, v in arrays.items()}
    n = len(arrays["time"])
    for k, v in arrays.items():
        if v.ndim != 1 or len(v) != n:
            raise ValueError(
                f"`make_friction_experiment`: `{k}` must be 1-D with {n} samples like `time`, got shape {v.shape}."
            )
        if not np.all(np.isfinite(v)):
            raise ValueError(
                f"`make_friction_experiment`: `{k}` has NaN or inf at sample {int(np.argmin(np.isfinite(v)))}."
            )
    if n < 3:
        raise ValueError(f"`make_friction_experiment`: need at least 3 samples, got {n}.")
    return FrictionExperiment(
        time=jnp.asarray(arrays["time"]),
        velocity=jnp.asarray(arrays["velocity"]),
        friction_torque=jnp.asarray(arrays["friction_torque"]),
        position=jnp.asarray(arrays.get("position", np.zeros(n))),
        has_position=jnp.asarray(1.0 if position is not None else 0.0),
        start_time=jnp.asarray(float(start_time)),
        mask=jnp.ones(n, dtype=bool),
    )
