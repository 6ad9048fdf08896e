"""The fabric: simulated time, messages and keys, the bus (in-memory and zenoh), the federate base
class and its window protocol, compute emulation, record tables and seeding. It knows no federate;
every federate and the coordinator build on it (see docs/architecture.md sec. 11)."""
