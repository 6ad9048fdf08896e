"""The robot federate: the pick controller on the robot node's emulated CPU."""
