"""The Edge federate: decodes frames, estimates poses, tracks parts, runs the co-design policy."""
