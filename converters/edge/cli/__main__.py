"""``python -m converters.edge.cli``: the ``lidarscan`` command line."""

import sys

from converters.edge.cli import main

sys.exit(main())
