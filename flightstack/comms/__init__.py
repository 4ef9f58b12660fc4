"""Messages and buses between agents: the in-process lock-step bus and the Zenoh bus (same interface)."""
