"""netsim NR: a 5G NR system-level cell model (TR 38.901 InF-SL channel, TS 38.214 PHY
abstraction, TDD self-contained slot MAC with HARQ, link adaptation and schedulers).

Modules, one concern each: ``config`` (NrConfig), ``channel`` (path loss, shadowing, fading),
``phy`` (MCS/TBS/LDPC/EESM/BLER, tables in ``tables/`` written by ``make_tables``),
``buffers`` (sender queues), ``harq``, ``link_adaptation``, ``scheduler`` and ``cell`` (NrCell,
the slot loop tying them together).
"""

from netsim.nr.cell import NrCell
from scenario.nr import NrConfig

__all__ = ["NrCell", "NrConfig"]
