"""The real lab: its rig (`rig.py`), the assembly of its devices behind flightstack.hal (`hardware.py`:
real Tellos, motion capture and the Scamper, on the wall clock) and its operator tools (`preflight.py`,
`guard.py`, `target_run.py`)."""
