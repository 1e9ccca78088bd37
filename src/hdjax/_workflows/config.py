"""Strict reading of config files: every section of a config YAML names its options, and a key
that is not one of them is an error that names the key and the nearest valid one.

A config YAML (SPEC §3) holds `dataset:` and one optional section per command:

```yaml
dataset: ../data/hd2
fit: {alpha: 0.5, Tss2: 0.1, trajectory: {max_experiments: 12}}
diagnose: {max_findings: 3}
sensitivity: {rtol: 1.0e-4}
tune: {plants: 6}
```

Each workflow module keeps its options and their defaults in a `DEFAULTS` dict
(`hdjax._workflows.fit.DEFAULTS` for `fit`, `hdjax._workflows.diagnose.DEFAULTS`,
`hdjax._workflows.sensitivity.DEFAULTS`, `hdjax._workflows.tune.DEFAULTS`) and reads its section with `section_options`.
The commands check the whole file first (`validate_config`), so a misspelt key fails before any
work, whichever command reads it.
"""

import difflib
from collections.abc import Iterable, Mapping

TOP_LEVEL_KEYS = ("dataset", "fit", "diagnose", "sensitivity", "tune")
"""The keys a config YAML may hold at its top level."""


class ConfigError(ValueError):
    """A config file or options mapping with a key no command knows, or a section that is not a
    mapping. A `ValueError`, so the commands report it as bad input (exit status 2)."""


def is_number(value) -> bool:
    """A YAML number: an int or float, not a bool (YAML's `true` is an int to Python)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def unit_share(value, where: str, note: str = "") -> float:
    """`value` of the config option `where` (e.g. `tune.friction_uncertainty`) as a float in
    [0, 1); anything else is refused, naming the option (`note` follows the range in the message)."""
    if not (is_number(value) and 0.0 <= float(value) < 1.0):
        raise ValueError(f"config `{where}` must be a number in [0, 1){note}, got {value!r}.")
    return float(value)


def nearest(word: str, candidates: Iterable[str]) -> str | None:
    """The candidate closest to `word` (difflib ratio ≥ 0.6), or None."""
    match = difflib.get_close_matches(str(word), [str(c) for c in candidates], n=1, cutoff=0.6)
    return match[0] if match else None


def check_keys(given: Mapping, known: Iterable[str], where: str) -> None:
    """Raise `ConfigError` when `given` has a key outside `known`.

    **Arguments:**

    - `given`: the mapping read from the file.
    - `known`: the valid keys.
    - `where`: how the message names the mapping, e.g. "config `tune:`".

    **Raises:** `ConfigError` naming every unknown key with the nearest valid one, e.g. ``config
    `tune:` has unknown option(s) ['plantz'] (`plantz`: did you mean `plants`?); known options:
    [...]``.
    """
    known = [str(k) for k in known]
    bad = sorted(str(k) for k in given if str(k) not in known)
    if not bad:
        return
    hints = []
    for k in bad:
        m = nearest(k, known)
        hints.append(f"`{k}`: did you mean `{m}`?" if m else f"`{k}`: no option is close")
    raise ConfigError(f"{where} has unknown option(s) {bad} ({'; '.join(hints)}); known options: {sorted(known)}.")


def section_options(config: Mapping | None, name: str, defaults: Mapping, *, nested: Iterable[str] = ()) -> dict:
    """The options of section `name` of `config`, checked against `defaults` and completed by them.

    Sub-sections listed in `nested` (for example `fit.trajectory`) are mappings checked and
    completed the same way against `defaults[sub]`.

    **Raises:** `ConfigError` for an unknown key or a section that is not a mapping.
    """
    raw = (config or {}).get(name) or {}
    if not isinstance(raw, Mapping):
        raise ConfigError(f"config `{name}:` must be a mapping of options, got {type(raw).__name__} {raw!r}.")
    check_keys(raw, defaults, f"config `{name}:`")
    out = {k: (dict(v) if isinstance(v, Mapping) else v) for k, v in defaults.items()}
    out.update({k: v for k, v in raw.items() if k not in nested})
    for sub in nested:
        given = raw.get(sub) or {}
        if not isinstance(given, Mapping):
            raise ConfigError(f"config `{name}.{sub}:` must be a mapping of options, got {type(given).__name__}.")
        check_keys(given, defaults[sub], f"config `{name}.{sub}:`")
        out[sub] = dict(defaults[sub]) | dict(given)
    return out


def all_defaults() -> dict[str, dict]:
    """Every config section's options and defaults, keyed by section (imports the workflows)."""
    from .diagnose import DEFAULTS as diagnose
    from .fit import DEFAULTS as fit
    from .sensitivity import DEFAULTS as sensitivity
    from .tune import DEFAULTS as tune

    return {"fit": fit, "diagnose": diagnose, "sensitivity": sensitivity, "tune": tune}


NESTED = {"fit": ("trajectory",)}


def validate_config(config: Mapping | None, *, source: str = "config") -> None:
    """Check a whole config (as `hdjax._data.load.load_config` returns it): top-level keys, then every
    section present. **Raises:** `ConfigError` for the first unknown key, named with the nearest
    valid one."""
    if not config:
        return
    check_keys(config, TOP_LEVEL_KEYS, source)
    defaults = all_defaults()
    for name in TOP_LEVEL_KEYS[1:]:
        if name in config:
            section_options(config, name, defaults[name], nested=NESTED.get(name, ()))
