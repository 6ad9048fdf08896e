"""Measure the abstract loops' frame model: compressed frame sizes and estimator error.
The code is in training/measure_frames.py; ``--help`` lists the options."""

import sys

from training.measure_frames import main

if __name__ == "__main__":
    sys.exit(main())
