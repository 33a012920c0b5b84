"""``python -m knitfem.cli``: the ``knitfem`` command."""

import sys

from knitfem.cli.main import main

sys.exit(main())
