"""Test configuration: strict dtype promotion, float64 available on request."""

import jax
import pytest

jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_enable_x64", True)  # tests choose their dtype explicitly


@pytest.fixture(params=[2, 3], ids=["2d", "3d"])
def dim(request):
    return request.param
