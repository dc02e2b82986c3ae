"""jaxmpm: a differentiable Material Point Method in pure JAX."""
