"""netsim: the 5G NR network simulator federate and its cell models (``radio_cell``: the interface,
``simple``: shared-capacity queues, ``nr``: the NR system-level model, ``standalone``: the cell
alone under camera load, ``federate``: the cell on the simulated clock)."""

from fabric.native import use_native

# The compiled build of this package's modules, where a fresh one exists (fabric.native).
use_native(__name__, __path__)
