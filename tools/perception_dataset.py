"""Render one split (train, val or test) of the pose network's labelled RGB-D data set.
The code is in training/perception/dataset.py; ``--help`` lists the options."""

import sys

from training.perception.dataset import main

if __name__ == "__main__":
    sys.exit(main())
