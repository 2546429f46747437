"""`python -m ufm_jax infer|convert|to-official ...`: see ufm_jax/tools/cli.py."""

import sys

from ufm_jax.tools.cli import main

sys.exit(main())
