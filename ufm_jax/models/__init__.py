"""Flax (linen) modules of UFM; parameter names mirror the official PyTorch modules."""
