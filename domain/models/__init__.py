"""Model files: the arm (arm6.xml)."""
