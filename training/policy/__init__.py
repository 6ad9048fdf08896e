"""The learned co-design policy: a Gymnasium environment of one control loop
(env.py, ``cosim5g/PickLoop-v0``) over a randomised family of cells (cells.py) with a network
model measured on the NR cell (network.py, data/network_table.json), PPO training with
stable-baselines3 and ONNX export (train.py), and the lambda sweep that chooses the shipped
trade-off (sweep.py). Nothing here runs in a federate: the Edge runs the exported network with
ONNX Runtime (domain/policy.py, ``learned``).
"""
