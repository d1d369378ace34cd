"""``dh2rt wireshark``: see :mod:`tools.wireshark.command`."""

import sys

from tools.wireshark.command import main

sys.exit(main())
