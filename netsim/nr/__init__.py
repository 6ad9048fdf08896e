"""netsim NR: a 5G NR system-level cell model (TR 38.901 InF-SL channel, TS 38.214 PHY
abstraction, TDD self-contained slot MAC with HARQ, link adaptation and schedulers). ``NrCell``
is its entry; its modules, one concern each, are listed in docs/netsim.md."""

from fabric.native import use_native

# The compiled build of this package's modules, where a fresh one exists (fabric.native).
use_native(__name__, __path__)

from netsim.nr.radio_cell import NrCell  # noqa: E402
from scenario.nr import NrConfig  # noqa: E402

__all__ = ["NrCell", "NrConfig"]
