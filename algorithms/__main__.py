"""``python -m marbler_jax_rl``: the ``marbler-jax`` command line."""
import sys

from marbler_jax_rl.cli import main

sys.exit(main())
