"""`python -m dmd_jax.cli`: the `dmd-jax` command."""

from dmd_jax.cli import console

console()
