import sys

from marbler_jax.cli import main

sys.exit(main())
