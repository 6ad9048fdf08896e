"""Compile the NR cell and physics stepper into build/native (``build``) or report it (``status``).
The code is in fabric/native.py; ``--help`` lists the options."""

import sys

from fabric.native import main

if __name__ == "__main__":
    sys.exit(main())
