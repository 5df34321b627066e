"""dmd_jax: DMD-Net mesh denoising in JAX and Flax, with sparse segment-sum graph ops."""

__version__ = "0.1.0"
