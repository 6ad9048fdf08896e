"""The learned co-design policy: the environment (env.py), the work cell family (work_cells.py), the
network model (network.py), PPO training and export (train.py) and the lambda sweep (sweep.py).
Nothing here runs in a federate: the Edge runs the exported network (docs/policy.md, "learned").
"""
