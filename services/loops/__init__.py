"""The abstract loops federate: camera, Edge and robot of the loops not run in detail."""
