"""The physics federate: the MuJoCo factory hall stepped on the simulated clock."""
