import sys

from lazyq_jax.cli import main

sys.exit(main())
