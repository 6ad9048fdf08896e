"""The camera federate: captures, compresses and packetises frames, drops them by the loop's PDP."""
