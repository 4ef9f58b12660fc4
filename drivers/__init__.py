"""Hardware drivers behind flightstack.hal: the Tello (`tello/`: UDP control, state, video), motion
capture (`mocap.py`), the Scamper over MAVLink (`scamper*.py`) and the guardian process that lands the
drones when a flight dies (`guardian*.py`); the real lab as a rig (`lab/rig.py`); beside them, for now,
the real lab's assembly (`hardware.py`) and its operator tools (`preflight.py`, `guard.py`,
`target_run.py`)."""
