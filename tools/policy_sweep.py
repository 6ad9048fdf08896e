"""The learned policy's lambda sweep: a policy per lambda, the Pareto table, ``--ship`` the choice.
The code is in training/policy/sweep.py; ``--help`` lists the options."""

import sys

from training.policy.sweep import main

if __name__ == "__main__":
    sys.exit(main())
