"""``python -m redman_jax``: see :mod:`redman_jax._cli`."""

import sys

from ._cli import main

if __name__ == "__main__":
    sys.exit(main())
