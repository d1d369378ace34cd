"""The modules' own docking motion, sans-IO: readings in, joint targets and verdicts out.

``body`` is the module's body as data (boxes, hinges, connector faces, servo limits), which
the simulator's PyBullet model is built from as well; ``kinematics`` is a docking chain's
forward kinematics and its solver; ``readings`` is what a motion reads (the chain's joint
angles, a connector's infrared pair, the overhead tracker's poses); ``reach`` bends a chain's
face onto another; ``gaits`` are the joint schedules (the caterpillar's wave, a lone module's
back-off, creep and turn); ``crawl`` takes a released foot to a face (``Trip``) and creeps it
in (``Creep``); ``clearing`` crawls a robot clear of a body lying on the spot a foot must
come to; ``docking`` is the sequence around them all (reach_dock; reach_and_dock: crawl
clear, release, trip, creep dock, latch or bring again, give up), ``underway`` its records.
Nothing here opens a socket or a file, reads a clock or imports a simulator: the sequence is
stepped once a control cycle by its owner (``sim.runner.PhysicsRun`` in process, ``hil.reach_loop.LoopReaches`` in the
loop), which answers its reads and latches and writes the joint targets it returns.
"""
