"""`python -m fpe_jax.runner WAYPOINTS`: the runner's step-time benchmark."""

from fpe_jax.runner._runner import _main

_main()
