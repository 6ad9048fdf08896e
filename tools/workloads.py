"""Run the real compute jobs through one emulated node of ``--cpus``; print their timings as JSON.
The code is in domain/workloads.py; ``--help`` lists the options."""

import sys

from domain.workloads import main

if __name__ == "__main__":
    sys.exit(main())
