"""The test suite's runtime type checker (installed by `tests/conftest.py`) covers hdjax: every
module but `UNCHECKED` is imported through jaxtyping's hook, so an annotated function refuses
arrays whose shapes disagree with its physical axis names; the independent bench is left out on
purpose (numpy only, no array annotations, 5.3× slower when wrapped)."""

import importlib
import os
import sys

import jaxtyping
import numpy as np
import pytest

from conftest import UNCHECKED, checked_modules

pytestmark = pytest.mark.skipif(os.environ.get("HDJAX_RUNTIME_TYPECHECK", "1") == "0", reason="checker switched off")


def test_every_module_but_the_bench_is_imported_through_the_checker():
    names = checked_modules()
    assert "hdjax._model.paper" in names and "hdjax._discrepancy.loop" in names and not set(UNCHECKED) & set(names)
    for name in [*names, *UNCHECKED]:
        importlib.import_module(name)
        loader = type(sys.modules[name].__spec__.loader).__name__
        assert (loader == "_JaxtypingLoader") == (name not in UNCHECKED), (name, loader)


def test_an_annotated_function_refuses_mismatched_axes():
    from hdjax._discrepancy.evidence import order_spectrum  # (res: " sample", theta: " sample")

    order_spectrum(np.zeros(64), np.linspace(0.0, 10.0, 64))
    with pytest.raises(jaxtyping.TypeCheckError):
        order_spectrum(np.zeros(64), np.linspace(0.0, 10.0, 65))
