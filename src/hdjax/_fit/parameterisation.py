r"""One map between a model's fields and the flat vector an optimiser works on.

Every fit, sensitivity and tuning loop of hdjax moves a flat vector $x$ and evaluates a model
`eqx.Module` (`Parameters`, `Effects`, `FrictionParameters`, `TorqueGains`). A `Parameterisation`
says, field by field (the *path* is the field's name, or a dotted path into a field that is
itself a Module, e.g. `"law.Tvp"` of `FrictionParameters`; an array field takes as many vector
slots as it has elements), how a slot of $x$ becomes a value:

| transform | value | for |
|---|---|---|
| `"scaled"` | `offset + scale·x` | signed values, O(1) in x (torques over their RMS, effect amplitudes from a start) |
| `"log"` | `scale·exp(x)` | positive values (K1, Jeff, Tss2, time constants); relative changes |
| `"logit"` | `lo + (hi − lo)·sigmoid(x)` | values inside bounds (α) |

With `scale` = a reference value, a `"log"` slot is the relative change ln(value/reference)
(sensitivities, controller gains). The entries are static (one compiled program per layout);
`scale` and `offset` are array leaves (one program serves every start and every dataset).
`to_model(x, base)` returns `base` with the listed fields replaced (every other field as in
`base`); `to_vector(model)` is its inverse.
"""

from collections.abc import Sequence
from typing import Literal, NamedTuple, TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

Transform = Literal["scaled", "log", "logit"]
M = TypeVar("M", bound=eqx.Module)


class Entry(NamedTuple):
    """One field of the model in the vector: its name, its number of slots (None: a scalar
    field), its transform, and the bounds of a `"logit"` field."""

    field: str
    size: int | None = None
    transform: Transform = "scaled"
    bounds: tuple[float, float] = (0.0, 1.0)


class Parameterisation(eqx.Module):
    """Map between model fields and a flat vector (see the module docstring)."""

    entries: tuple[Entry, ...] = eqx.field(static=True)
    scale: Float[Array, " vector"]
    offset: Float[Array, " vector"]

    def __check_init__(self):
        _check(self.entries, self.scale.shape, self.offset.shape)

    @property
    def fields(self) -> tuple[str, ...]:
        """The fields in vector order."""
        return tuple(e.field for e in self.entries)

    @property
    def size(self) -> int:
        """Length of the vector."""
        return self.scale.shape[0]

    def slot(self, field: str) -> int | slice:
        """The vector index (scalar field) or slice (array field) of `field`."""
        where = slots(self.entries)
        if field not in where:
            raise KeyError(f"`Parameterisation`: no field {field!r}; fields: {list(self.fields)}.")
        return where[field]

    def _slots(self) -> list[tuple[Entry, int | slice]]:
        """Each entry with its vector index (scalar field) or slice (array field)."""
        where = slots(self.entries)
        return [(e, where[e.field]) for e in self.entries]

    def values(self, x: Float[Array, " vector"]) -> dict[str, Array]:
        """The model values of the vector, by field."""
        out = {}
        for e, at in self._slots():
            xi, s, o = x[at], self.scale[at], self.offset[at]
            if e.transform == "log":
                out[e.field] = s * jnp.exp(xi)
            elif e.transform == "logit":
                lo, hi = e.bounds
                out[e.field] = lo + (hi - lo) * jax.nn.sigmoid(xi)
            else:
                out[e.field] = o + s * xi
        return out

    def to_model(self, x: Float[Array, " vector"], base: M) -> M:
        """`base` with every field of the entries set from `x`."""
        vals = self.values(x)
        return eqx.tree_at(lambda m: tuple(_get(m, k) for k in self.fields), base, tuple(vals[k] for k in self.fields))

    def to_vector(self, model: eqx.Module) -> Float[Array, " vector"]:
        """The vector of `model`'s fields (inverse of `to_model`)."""
        out = []
        for e, at in self._slots():
            v, s, o = jnp.asarray(_get(model, e.field), dtype=float), self.scale[at], self.offset[at]
            if e.transform == "log":
                out.append(jnp.log(v / s))
            elif e.transform == "logit":
                lo, hi = e.bounds
                u = (v - lo) / (hi - lo)
                out.append(jnp.log(u) - jnp.log1p(-u))
            else:
                out.append((v - o) / s)
        return jnp.concatenate([jnp.reshape(a, (-1,)) for a in out])


def _get(model, path: str):
    """The value at a field path (`"K1"`, or dotted into a sub-Module: `"law.Tvp"`)."""
    for name in path.split("."):
        model = getattr(model, name)
    return model


def _check(entries: tuple[Entry, ...], scale_shape, offset_shape) -> None:
    n = vector_size(entries)
    if tuple(scale_shape) != (n,) or tuple(offset_shape) != (n,):
        raise ValueError(f"`Parameterisation`: the entries take {n} slots, but scale has shape "
                         f"{tuple(scale_shape)} and offset {tuple(offset_shape)}; give one value per slot.")
    for e in entries:
        if e.transform not in ("scaled", "log", "logit"):
            raise ValueError(f"`Parameterisation`: field {e.field}: unknown transform {e.transform!r}; "
                             "use 'scaled', 'log' or 'logit'.")


def slots(entries: tuple[Entry, ...]) -> dict[str, int | slice]:
    """Vector index (scalar field) or slice (array field) of every entry, by field; needs no
    arrays (usable at import, before JAX starts)."""
    out, j = {}, 0
    for e in entries:
        out[e.field] = j if e.size is None else slice(j, j + e.size)
        j += 1 if e.size is None else e.size
    return out


def vector_size(entries: tuple[Entry, ...]) -> int:
    """Length of the vector of `entries`."""
    return sum(1 if e.size is None else e.size for e in entries)


def parameterisation(
    entries, scale: ArrayLike | Sequence[float] | None = None, offset: ArrayLike | Sequence[float] | None = None
) -> Parameterisation:
    """A `Parameterisation` of `entries` (`Entry` or field names); `scale` (default 1) and `offset`
    (default 0) per vector slot."""
    entries = tuple(e if isinstance(e, Entry) else Entry(e) for e in entries)
    n = vector_size(entries)
    scale = np.ones(n) if scale is None else np.asarray(scale, dtype=float)
    offset = np.zeros(n) if offset is None else np.asarray(offset, dtype=float)
    _check(entries, scale.shape, offset.shape)
    return Parameterisation(entries=entries, scale=jnp.asarray(scale, dtype=float), offset=jnp.asarray(offset, dtype=float))
