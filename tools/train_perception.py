"""Train the Edge pose network on rendered frames and export domain/models/pose.onnx.
The code is in training/perception/train.py; ``--help`` lists the options."""

import sys

from training.perception.train import main

if __name__ == "__main__":
    sys.exit(main())
