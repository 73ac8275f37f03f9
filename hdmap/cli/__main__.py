"""``python -m hdmap.cli``: the same as the ``hdmap`` command."""

import sys

from hdmap.cli import main

sys.exit(main())
