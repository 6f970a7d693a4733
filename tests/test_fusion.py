"""jaxrender.fusion.materialize: the value and gradient of fn, computed once as its own XLA computation."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxrender.fusion import materialize


def _fn(x, y):
    return jnp.sin(x) * y, jnp.exp(-x)


def test_value_and_gradient_are_those_of_fn():
    x = jnp.linspace(-2.0, 2.0, 11)
    y = jnp.linspace(0.5, 1.5, 11)
    for got, want in zip(jax.jit(lambda x, y: materialize(_fn, x, y))(x, y), _fn(x, y)):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(want))

    def loss(f, x, y):
        a, b = f(x, y)
        return jnp.sum(a * a + 3.0 * b)

    g_mat = jax.grad(lambda x, y: loss(lambda *a: materialize(_fn, *a), x, y), argnums=(0, 1))(x, y)
    g_ref = jax.grad(lambda x, y: loss(_fn, x, y), argnums=(0, 1))(x, y)
    for a, b in zip(g_mat, g_ref):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12)


def test_nan_input_takes_the_other_branch_with_the_same_function():
    x = jnp.array([jnp.nan, 1.0])
    got = jax.jit(lambda x: materialize(_fn, x, x))(x)
    for a, b in zip(got, _fn(x, x)):
        np.testing.assert_array_equal(np.isnan(np.asarray(a)), np.isnan(np.asarray(b)))
        np.testing.assert_array_equal(np.asarray(a)[1:], np.asarray(b)[1:])


def test_the_producer_is_a_separate_computation_in_the_optimized_program():
    """Two consumers of one elementwise producer: the optimized program keeps the conditional
    around the producer (the boundary fusion does not cross), and the values are unchanged."""
    def frame(x, wrap):
        a = wrap(lambda x: jnp.exp(jnp.sin(x) * 3.0), x)
        return jnp.sum(a * 2.0), jnp.max(a + 1.0)

    x = jnp.linspace(0.0, 1.0, 1 << 16)
    plain = jax.jit(lambda x: frame(x, lambda f, x: f(x))).lower(x).compile().as_text()
    stored = jax.jit(lambda x: frame(x, materialize)).lower(x).compile().as_text()
    assert "conditional" not in plain and "conditional" in stored
    np.testing.assert_allclose(np.asarray(jax.jit(lambda x: frame(x, materialize))(x)),
                               np.asarray(frame(x, lambda f, x: f(x))), rtol=1e-12)
