"""How the files written during a flight survive a crash of the computer: each writer (the run directory's,
the devices' raw traffic) fsyncs a file it wrote to at most every FSYNC_PERIOD_S and at close, so that
an OS crash or a power loss costs at most that much of it."""

FSYNC_PERIOD_S = 1.0
"""The longest a written file goes without an fsync while it is written to (s)."""
