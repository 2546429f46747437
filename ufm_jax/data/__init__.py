"""Datasets: one source per dataset (registered by name), file formats, the grain pipeline."""

from ufm_jax.data.registry import SAMPLE_KEYS, available, get_source, register

__all__ = ["SAMPLE_KEYS", "available", "get_source", "register"]
