"""``python -m marbler_jax_rl``: the ``marbler-jax`` command line."""
from marbler_jax_rl.cli import console

console()
