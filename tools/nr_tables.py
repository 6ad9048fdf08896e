"""Write the NR PHY lookup tables into netsim/nr/tables/, or ``--check`` the shipped ones.
The code is in netsim/nr/make_tables.py; ``--help`` lists the options."""

import sys

from netsim.nr.make_tables import main

if __name__ == "__main__":
    sys.exit(main())
