"""``python -m converters.evidence [--check]``: regenerate (or check) docs/proposal.md."""

import sys

from converters.evidence import main

sys.exit(main())
