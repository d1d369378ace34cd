"""The firmware: the program a module runs on its own processor, from power-up to power-off.

``main_loop`` boots it (``dh2rt module --config module.toml``), ``config`` and ``module_toml``
read its configuration, ``sensors`` feeds the program's ``S.*``, ``channels`` and
``negotiated_links`` agree on its links with its neighbours, ``control`` is the typed channel a
HIL world or an operator drives it through, and ``flash`` holds its A/B flash slots, the host
that takes part in rollouts and the cable-side flasher. It builds on ``drivers`` and ``dh2rt``
and never imports ``sim`` or ``hil`` (an import-linter contract): the HIL world starts this very
program for each of its modules.
"""
