"""`AnyController`: every law in one controller type, so that one compiled program serves all.

Checks: each law's outputs (virtual input, state derivative, trimmed state, initial state) and
gradients through an `AnyController` equal the law's own (the same operations; to the last bit
but for the rounding XLA's code generation may change from one program to another, as a
multiply-add contracted or not), the other laws' gains get zero gradient; simulating FBL+PID,
AFBL and the printed AFBL compiles one program for the three, with each law's own results;
traced or batched gains keep the law's own class.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import afbl_jax as A
from afbl_jax.model import AnyController
from afbl_jax.model.controllers import LAWS, ReferenceSample
from afbl_jax.sim import ClosedLoop

RNG = np.random.default_rng(7)


def _gains(law):
    return {g: RNG.uniform(0.5, 20.0, 4) for g in law.gain_names}


@pytest.mark.parametrize("law", LAWS, ids=[c.name for c in LAWS])
def test_each_law_is_its_own_class(law):
    ctrl = law(**_gains(law))
    anyc = AnyController.of(ctrl)
    assert type(anyc.acting()) is law and int(anyc.law) == LAWS.index(law)
    # inputs as arguments (constants would be folded at compile time)
    x = tuple(jnp.asarray(RNG.normal(size=4)) for _ in range(7))

    def outputs(c, e, ed, r, rd, rdd, state, v):
        ref = ReferenceSample(r, rd, rdd)
        return (*c.virtual_input(e, ed, ref, state), c.state_for(v, ref), c.init_state())

    for ours, own in zip(jax.jit(outputs)(anyc, *x), jax.jit(outputs)(ctrl, *x), strict=True):
        np.testing.assert_allclose(ours, own, rtol=1e-15, atol=1e-13)

    def loss(c, *x):
        u, du, s, _ = outputs(c, *x)
        return jnp.sum(u**2) + jnp.sum(du**2) + jnp.sum(s**2)

    g_any, g_own = eqx.filter_grad(loss)(anyc, *x), eqx.filter_grad(loss)(ctrl, *x)
    for name in law.gain_names:
        np.testing.assert_allclose(
            getattr(g_any.laws[LAWS.index(law)], name), getattr(g_own, name), rtol=1e-14
        )
    for i, other in enumerate(g_any.laws):
        if i != LAWS.index(law):
            for name in other.gain_names:
                np.testing.assert_array_equal(getattr(other, name), 0.0)


def test_bad_controllers_are_refused():
    with pytest.raises(TypeError, match="controller must be one of FBLPID, AFBL, AFBLPaper"):
        AnyController.of(object())
    with pytest.raises(TypeError, match="laws must be instances of FBLPID, AFBL, AFBLPaper"):
        AnyController(jnp.int32(0), (A.AFBL(), A.FBLPID(), A.AFBLPaper()))


def test_the_laws_share_one_compiled_program_with_their_own_results():
    """FBL+PID, AFBL and the printed AFBL: the first simulation compiles, the other two
    compile nothing, and each result equals the law's own loop (its class, compiled inside an
    outer jit, where the gains are traced and the loop keeps them) to the rounding of another
    program."""
    sc = A.paper_scenario("uncertain", "step")
    compiles = []

    def listen(event, seconds, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(seconds)

    jax.monitoring.register_event_duration_secs_listener(listen)
    ctrls = [A.make_controller(c.name) for c in LAWS]
    counts, ise = [], []
    try:
        for ctrl in ctrls:
            before = len(compiles)
            r = A.simulate(ctrl, sc, n_save=0, rtol=1e-8, atol=1e-10)
            counts.append(len(compiles) - before)
            ise.append((float(r.ise_attitude), float(r.ise_altitude)))
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert counts[0] >= 1 and counts[1:] == [0, 0], counts
    assert len(set(ise)) == 3  # three different laws acted

    def own(ctrl):
        r = A.simulate(ctrl, sc, n_save=0, rtol=1e-8, atol=1e-10)
        return r.ise_attitude, r.ise_altitude

    for ctrl, shared in zip(ctrls, ise, strict=True):
        np.testing.assert_allclose(jax.jit(own)(ctrl), shared, rtol=1e-9)


def test_traced_or_batched_gains_keep_their_class():
    loop = ClosedLoop.make(A.AFBL())
    assert type(loop.shared_program().controller) is AnyController
    batched = ClosedLoop.make(A.AFBL(k=np.full((3, 4), 8.0)))
    assert type(batched.shared_program().controller) is A.AFBL
    kinds = []
    jax.jit(lambda c: kinds.append(type(ClosedLoop.make(c).shared_program().controller)))(
        A.FBLPID()
    )
    assert kinds == [A.FBLPID]
    # a controller closed over by an outer jit has concrete gains: converted there too
    paper = A.AFBLPaper()
    law = jax.jit(lambda: ClosedLoop.make(paper).shared_program().controller.law)()
    assert int(law) == LAWS.index(A.AFBLPaper)


def test_gains_of_another_dtype_are_kept():
    """Float32 gains of a float64 run (cast past the classes' converters): every law of the
    `AnyController` takes that dtype, and the run equals the law's own loop."""
    sc = A.paper_scenario("uncertain", "step")
    for name in ("fbl", "afbl"):
        ctrl = jax.tree.map(lambda x: x.astype(jnp.float32), A.make_controller(name))
        anyc = AnyController.of(ctrl)
        assert {x.dtype for x in jax.tree.leaves(anyc.laws)} == {jnp.dtype(jnp.float32)}
        r = A.simulate(ctrl, sc, n_save=0)
        own = jax.jit(lambda c: A.simulate(c, sc, n_save=0).ise_attitude)(ctrl)
        assert int(r.status) == 0
        np.testing.assert_allclose(r.ise_attitude, own, rtol=1e-9)
