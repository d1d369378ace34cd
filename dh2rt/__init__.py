"""dh2rt: a runtime for DH2, the hormone-inspired distributed language for self-reconfigurable robots.

The core package holds the language (``dh2rt.lang``), the compiler, the sans-IO module engine,
topology profiles and the in-process robot. It does no I/O at import time and imports no
hardware or simulation library.
"""

__version__ = "0.1.0"
