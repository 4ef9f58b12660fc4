"""Running a mission: the backend registry, one agent's tick, the lock-step runner, training the
experts, comparing modes."""
