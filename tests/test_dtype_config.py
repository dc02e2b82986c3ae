"""The suite runs in float32 (the users' setting); float64 is a per-test opt-in that does not leak."""

import jax.numpy as jnp
import pytest


def test_default_is_float32():
    assert jnp.asarray(1.0).dtype == jnp.float32
    assert jnp.zeros(3, float).dtype == jnp.float32


@pytest.mark.x64
def test_x64_marker_enables_float64():
    assert jnp.asarray(1.0).dtype == jnp.float64


def test_x64_does_not_leak_into_the_next_test():
    assert jnp.asarray(1.0).dtype == jnp.float32


def test_float64_request_without_the_marker_is_an_error():
    with pytest.raises(UserWarning, match="float64"):
        jnp.asarray(1.0, jnp.float64)
