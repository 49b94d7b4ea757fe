import sys

from usp_jax.cli import main

sys.exit(main())
