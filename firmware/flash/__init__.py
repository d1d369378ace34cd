"""Flashing, the firmware's side: the A/B slots (``slots``), the host a module runs a rollout
in (``module_host``, opened through ``door`` only once an image concerns the module) and the
flasher on a cable or bus adapter (``cable``). The protocol itself is sans-IO in the core."""
