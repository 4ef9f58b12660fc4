"""The shipped experiments, rigs and camera files (package data: found by name from any directory)."""
