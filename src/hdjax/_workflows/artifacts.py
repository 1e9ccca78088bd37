"""The commands' JSON artifacts, read and described in one place (SPEC §3).

- `read_fit_json`: the identified parameters (and their consistency, per-experiment estimates and
  the fit's noise levels) from a `fit.json` written by `hdjax fit`, for `sensitivity` and `tune`.
- `read_extended_model`: parameters and effects from `hdjax diagnose`'s `extended_model.json`.
- `effects_to_dict` / `effects_from_dict`: the plain-number form of `Effects` that
  `extended_model.json` and the benches' `truth.yaml` use (periodic effects as
  orders/amplitudes/phases of $a_k \\sin(k\\theta_m + \\phi_k)$, scalar effects by their parameter
  names).

Writing goes through `hdjax._workflows.io` (atomic). Errors name the file, the field and the fix.
"""

import dataclasses
import json
import math
import pathlib

from .._model.effects import Effects
from .._model.paper import PARAMETER_NAMES, Parameters


@dataclasses.dataclass(frozen=True)
class FitFile:
    """What `sensitivity` and `tune` use from a `fit.json`: `parameters` (SI), and per parameter
    name its `consistency` (std/|mean| of the per-experiment estimates, or None) and
    `per_experiment` estimates (list, or None); `noise_levels` (channel → σ) of the fit, possibly
    empty; the `dataset` name it was fitted on; `std_error` per parameter name (its unit; None
    where not fitted), empty when the file has none; `effects`, the terms the fit fitted with the
    parameters (`model_form`: the sensor lags, the breakaway torques), `Effects()` when it has
    none."""

    path: pathlib.Path
    dataset: str | None
    parameters: Parameters
    consistency: dict
    per_experiment: dict
    noise_levels: dict
    std_error: dict = dataclasses.field(default_factory=dict)
    effects: Effects = dataclasses.field(default_factory=Effects)


def fit_json_dataset(path) -> str | None:
    """The `dataset` a fit.json names, or None when the file cannot be read as one."""
    try:
        return json.loads(pathlib.Path(path).read_text(encoding="utf-8")).get("dataset")
    except (OSError, ValueError, AttributeError):
        return None


def read_fit_json(path, *, setting: str) -> FitFile:
    """Read a `fit.json`; `setting` names the config key or option that chose this file (for the
    error message's fix)."""
    path = pathlib.Path(path)
    fix = f"Re-run `python -m hdjax.fit` to rewrite it, or name another file in {setting}."
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
        entries = {k: d["parameters"][k] for k in PARAMETER_NAMES}
        values = {k: float(e["value"]) for k, e in entries.items()}
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: not a usable fit.json ({type(e).__name__}: {e}); it needs "
                         f"`parameters.<name>.value` for all of {list(PARAMETER_NAMES)}. {fix}") from None
    bad = [k for k, v in values.items() if not math.isfinite(v)]
    if bad:
        raise ValueError(f"{path}: `parameters.<name>.value` is not finite for {bad}. {fix}")
    noise = (d.get("fit") or {}).get("noise_levels") or {}
    return FitFile(path, d.get("dataset"), Parameters.from_dict(values),
                   {k: e.get("consistency") for k, e in entries.items()},
                   {k: e.get("per_experiment") for k, e in entries.items()}, dict(noise),
                   {k: e.get("std_error") for k, e in entries.items()}, _model_form_effects(d, path, fix))


def _model_form_effects(d: dict, path: pathlib.Path, fix: str) -> Effects:
    """The `Effects` of a fit.json's `model_form` (`{term: {"note": ..., field: {"value": ...}}}`)."""
    effects = Effects()
    for name, entry in (d.get("model_form") or {}).items():
        try:
            values = {f: float(e["value"]) for f, e in entry.items() if f != "note"}
            bad = [f for f, v in values.items() if not math.isfinite(v)]
            if bad:
                raise ValueError(f"not finite: {bad}")
            effects = effects.with_values(name, **values)
        except (ValueError, KeyError, TypeError, AttributeError) as e:
            raise ValueError(f"{path}: `model_form.{name}` is not usable ({type(e).__name__}: {e}); it needs "
                             f"`model_form.{name}.<field>.value` for the term's fields. {fix}") from None
    return effects


def read_extended_model(path) -> tuple[Parameters, Effects]:
    """Parameters and effects from `hdjax diagnose`'s `extended_model.json`."""
    path = pathlib.Path(path)
    try:
        em = json.loads(path.read_text(encoding="utf-8"))
        params = Parameters.from_dict({k: float(em["parameters"][k]) for k in PARAMETER_NAMES})
        effects = effects_from_dict(em.get("effects"))
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: not a usable extended_model.json ({type(e).__name__}: {e}); it needs "
                         f"`parameters.<name>` for all of {list(PARAMETER_NAMES)} and `effects` as `hdjax diagnose` "
                         "writes them. Re-run `python -m hdjax.diagnose`, or remove the file.") from None
    return params, effects


def effects_to_dict(effects: Effects) -> dict:
    """Plain-number description of the active effects (periodic: orders, amplitudes, phases);
    `Effects.to_dict`, each term serialising itself."""
    return effects.to_dict()


def effects_from_dict(d: dict | None) -> Effects:
    """`Effects` from the plain-number description (`effects_to_dict`, or a bench's `truth.yaml`);
    `Effects.from_dict`."""
    return Effects.from_dict(d)
