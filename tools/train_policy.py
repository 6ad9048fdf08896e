"""Train one learned co-design policy with PPO and export it to ONNX (``--quick``: a 1-min check).
The code is in training/policy/train.py; ``--help`` lists the options."""

import sys

from training.policy.train import main

if __name__ == "__main__":
    sys.exit(main())
