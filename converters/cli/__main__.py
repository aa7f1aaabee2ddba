"""``python -m converters.cli``: the ``lidarscan`` command line."""

import sys

from converters.cli import main

sys.exit(main())
