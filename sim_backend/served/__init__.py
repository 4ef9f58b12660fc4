"""The served world: the simulated world as a process (server), the agents' side of it (client) and
the wire messages between them."""
