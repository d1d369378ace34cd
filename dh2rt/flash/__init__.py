"""Flashing: delivering a signed program image over the robot's own links, with no addresses
(sans-IO).

A *rollout* is one image's flash across the robot: one :class:`~dh2rt.flash.rollout.Rollout`
per module, one :class:`~dh2rt.flash.flasher.Flasher` at the entry point. The firmware's side
(the A/B slots, the hosts with their I/O) is :mod:`firmware.flash`; the command is
``dh2rt flash`` (:mod:`tools.flash`); the frames' codec is :mod:`dh2rt.wire.transfer`.

The files, by what a reader looks for:

* ``values.py``: what an image and a program are (``ImageInfo``, ``Program``, ``Partial``),
  the ``Timing``, the actions a host carries out (``Send``, ``Persist``, ``Stage``,
  ``Switch``, ...) and the counters.
* ``pacing.py``: how much of a module's links a rollout may take each cycle (``Pacing``,
  ``link_pacing``); a module checks its lines with it at boot, loading nothing else here.
* ``store.py``: the bytes of one image held so far (``Store``).
* ``sender.py``: the per-hop retransmission, one image's transfer out through one connector
  (``Sender``, its own small state machine).
* ``reports.py``: the outcomes' ranks, what the entry point keeps of a module
  (``ModuleReport``) and the reports waiting to cross a hop (``Outbox``).
* ``node.py``: what a module and the entry point share (``Node``): ports, pacing, the commit
  flood, and the steps every received frame takes first.
* ``rollout.py``: the module's state machine (``Rollout``).
* ``flasher.py``: the entry point's state machine (``Flasher``, ``Progress``).

This ``__init__`` imports none of them: a module that boots with nothing to flash loads only
``pacing`` (``firmware.flash.door`` opens the rest when an image concerns it).

How a rollout goes (``docs/flashing.md``, "Delivery over the links", has the message tables,
the sequence and the rules):

* **Transfer, per hop.** A holder OFFERs the image (version, id, length, segment size, how
  many segments it holds, its path from the entry point) and pushes the first window of
  SEGMENTs; the receiver REQUESTs from the first segment it lacks ("you are my source") and
  ACKs every segment (cumulative, plus a 16-bit selective bitmap). Unacknowledged segments
  go again after ``rto_ticks`` cycles, or at once when a later one was acknowledged. A peer
  silent for ``stall_ticks`` is given up. A module that lost its source (a link drop, a
  restart with the bytes it persisted) *probes* its neighbours (a REQUEST flagged probe);
  they OFFER what they hold, and it takes the rest from the one it is named after (its
  parent), else from the one holding most (nearest the entry point on a tie).
* **Pipelined, checked.** A module offers the image to its other neighbours as soon as it is
  offered it, and forwards each segment as soon as it holds every segment before it, but the
  *last* segment only once its own flash accepted the image: an image a module refuses is
  never complete beyond it (and the module CANCELs what it forwarded).
* **Paced.** Every frame costs link units (``Pacing.cost``: serial bytes, CAN bits); a
  connector (or, on a shared bus, the module) spends at most ``Pacing.budget`` units per
  cycle, so hormone frames keep their cycle. Control frames go before segments.
* **Staged by the host.** When every byte is in and the image id (blake2b of the bytes)
  matches, the Rollout asks the host to :class:`~dh2rt.flash.values.Stage` it (``Flash.stage``) and is told the
  verdict (:meth:`~dh2rt.flash.rollout.Rollout.staged`). Received bytes are persisted as they come
  (:class:`~dh2rt.flash.values.Persist`) so that a restarted module resumes (``partial=``).
* **Reports, back along the path.** Each module learns its *name*, the path from the entry
  point, from the OFFER it took; its reports (staged, committed, refused with the verdict,
  reverted, ...) travel back hop by hop along that path reversed, each hop acknowledged, as a
  DH2 reply travels along ``path-1``. A module reports *staged* only once every neighbour it
  offered the image to has reported (or declined, or fell silent: then it reports that
  neighbour *silent* by its name) and every attached connector has been heard from (or
  stayed silent for ``stall_ticks``), so the entry point knows the whole robot is staged
  when its own neighbour reports staged. A module that refuses the image reports the
  neighbours it does not pass it on to as *withheld*.
* **The switch.** The entry point then sends COMMIT, unless a module refused the image:
  "switch ``remaining_us`` from when this frame left", with a margin of ``depth + 4``
  cycles. Each module turns that into an instant on its own clock (arrival time + remaining
  - the frame's transit time), floods the commit on at once (each copy stating the time
  remaining when it leaves; re-sent after 1, 2, 4 cycles until acknowledged), and starts the
  new program at its first cycle that begins at or after that instant. Clocks are never
  compared, only their rates; cycle counters are never used. The first module moves the
  instant to the middle of its own cycle, so modules whose cycles are in step switch at the
  same cycle despite per-hop timing errors below half a period. While staged, a neighbour
  on the staged program is tolerated (:meth:`~dh2rt.flash.rollout.Rollout.tolerated`), and after the switch one
  on the old program, for ``tolerate_ticks`` cycles.
* **Late modules.** The Hello carries the program version; a module offers its running image
  to a neighbour on a lower version, flagged *running*: a module that stages an image a
  neighbour runs (or hears a neighbour's Hello with the staged program's digest) switches at
  once.

Sans-IO: no I/O, no threads, no clock. Time comes from the ``now`` arguments (seconds, any
origin: only differences on one module's clock are used), cycles from calls to ``tick``.
Every input returns the actions it causes, in order; carry them out before the next input.
Garbage is counted (``counters.garbage``) and ignored, never raised.
"""
