"""``python -m tignn_jax.cli``: the same as the ``tignn`` command."""
import sys

from tignn_jax.cli import main

sys.exit(main())
