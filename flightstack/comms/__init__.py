"""Messages and buses between agents (in-process now; Zenoh behind the same interface later)."""
