"""One module per dataset; each registers its source(s) with `ufm_jax.data.register`."""
