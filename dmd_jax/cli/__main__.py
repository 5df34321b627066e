"""`python -m dmd_jax.cli`: the `dmd-jax` command."""

import sys

from dmd_jax.cli import main

sys.exit(main())
