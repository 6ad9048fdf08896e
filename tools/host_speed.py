"""Measure this host's speed score; ``--write-cache`` or ``--write-reference`` records it.
The code is in fabric/host_speed.py; ``--help`` lists the options."""

import sys

from fabric.host_speed import main

if __name__ == "__main__":
    sys.exit(main())
