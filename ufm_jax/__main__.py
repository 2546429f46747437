"""`python -m ufm_jax infer|convert|to-official ...`: see ufm_jax/cli.py."""

import sys

from ufm_jax.cli import main

sys.exit(main())
