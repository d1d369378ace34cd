"""``python -m dh2rt``: the same as the ``dh2rt`` command."""

import sys

from dh2rt.entry import main

sys.exit(main())
