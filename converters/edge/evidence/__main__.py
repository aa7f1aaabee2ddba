"""``python -m converters.edge.evidence [--check]``: regenerate (or check) docs/proposal.md."""

import sys

from converters.edge.evidence import main

sys.exit(main())
