"""`hdjax.Parameterisation`: the one map between model fields and an optimiser's vector."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hdjax import Effects, Entry, FrictionParameters, Parameterisation, Parameters, make_parameter_map, parameterisation

jax.config.update("jax_enable_x64", True)

P = Parameters(alpha=0.5, K1=5000.0, Tst=10.0, Jeff=1e-4, Tvp=1e-3, Tvn=1.1e-3, Tsp=0.03, Tsn=0.033,
               Tssp1=-0.01, Tssn1=-0.02, Tss2=0.1)  # fmt: skip


def test_transforms_and_round_trip():
    pm = parameterisation(
        (Entry("K1", transform="log"), Entry("alpha", transform="logit", bounds=(0.05, 1.5)), Entry("Tssp1")),
        scale=[2.0, 1.0, 0.5], offset=[0.0, 0.0, -0.01])
    x = jnp.asarray([0.3, -0.7, 0.2])
    q = pm.to_model(x, P)
    assert float(q.K1) == pytest.approx(2.0 * np.exp(0.3), rel=1e-15)
    assert float(q.alpha) == pytest.approx(0.05 + 1.45 / (1 + np.exp(0.7)), rel=1e-15)
    assert float(q.Tssp1) == pytest.approx(-0.01 + 0.5 * 0.2, rel=1e-15)
    # the fields not listed stay as in the base
    assert float(q.Tst) == float(P.Tst) and float(q.Tss2) == float(P.Tss2)
    np.testing.assert_allclose(pm.to_vector(q), x, rtol=1e-13, atol=1e-15)
    # the derivative of a log slot is the value itself, of a scaled one its scale
    d = jax.jacfwd(lambda x: jnp.stack([pm.to_model(x, P).K1, pm.to_model(x, P).Tssp1]))(x)
    np.testing.assert_allclose(np.asarray(d), [[float(q.K1), 0, 0], [0, 0, 0.5]], rtol=1e-13)


def test_array_fields_take_one_slot_per_element():
    """Also a dotted path into a sub-Module: the eq. 9 law of a friction-only model."""
    pm = parameterisation((Entry("law.Tss2", transform="log"), Entry("position_dependent_friction.sin", 3), Entry("thermal_drift.beta")))
    assert pm.size == 5 and pm.slot("position_dependent_friction.sin") == slice(1, 4) and pm.slot("thermal_drift.beta") == 4
    base = FrictionParameters(Tvp=1.0, Tvn=1.0, Tsp=0.5, Tsn=0.5, Tssp1=0.1, Tssn1=0.1, Tss2=0.05)
    q = pm.to_model(jnp.asarray([np.log(0.2), 0.1, 0.2, 0.3, 0.4]), base)
    np.testing.assert_allclose(np.asarray(q.position_dependent_friction.sin), [0.1, 0.2, 0.3])
    assert float(q.law.Tss2) == pytest.approx(0.2) and float(q.thermal_drift.beta) == pytest.approx(0.4)
    assert float(q.law.Tvp) == 1.0 and np.isnan(float(q.law.K1))  # the rest as in `base`
    np.testing.assert_allclose(np.asarray(pm.to_vector(q)), [np.log(0.2), 0.1, 0.2, 0.3, 0.4], rtol=1e-14)
    with pytest.raises(KeyError, match="no field 'K1'"):
        pm.slot("K1")


def test_one_compiled_program_serves_every_scale():
    """Entries are static, scale and offset are leaves: a new scale is an argument, not a retrace."""
    traces = []

    @jax.jit
    def k1(pm, x):
        traces.append(1)
        return pm.to_model(x, P).K1

    a = k1(parameterisation((Entry("K1"),), scale=[1.0]), jnp.ones(1))
    b = k1(parameterisation((Entry("K1"),), scale=[3.0]), jnp.ones(1))
    assert (float(a), float(b), len(traces)) == (1.0, 3.0, 1)


def test_effects_and_the_paper_parameters_use_it():
    e = parameterisation((Entry("cogging.sin", 8), Entry("nonlinear_stiffness.K3")), scale=np.full(9, 2.0), offset=np.r_[np.zeros(8), 1.0])
    q = e.to_model(jnp.arange(9.0), Effects(active=frozenset({"cogging", "nonlinear_stiffness"})))
    np.testing.assert_allclose(np.asarray(q.cogging.sin), 2.0 * np.arange(8.0))
    assert float(q.nonlinear_stiffness.K3) == 17.0 and q.active == frozenset({"cogging", "nonlinear_stiffness"})
    pm = make_parameter_map(P, ("alpha", "K1", "Tssp1"))
    assert isinstance(pm, Parameterisation) and pm.fields == ("alpha", "K1", "Tssp1")
    np.testing.assert_allclose(pm.to_vector(P), [np.log((0.5 - 0.05) / (1.5 - 0.5)), np.log(5000.0), -1.0], rtol=1e-14)


def test_bad_layouts_are_refused():
    with pytest.raises(ValueError, match="unknown transform"):
        parameterisation((Entry("K1", transform="exp"),))  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="take 2 slots"):
        parameterisation((Entry("K1"), Entry("Tst")), scale=[1.0])
