"""The scenario schema: every layer's settings, validated once by the coordinator and read by each
federate for its own section. It imports nothing else of the project, so no federate has to
import another to read its configuration (``schema``: the scenario; ``nr``: the NR cell)."""
