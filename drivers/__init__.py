"""Hardware drivers behind flightstack.hal: the Tello (`tello/`: UDP control, state, video), motion
capture (`mocap.py`), the Scamper over MAVLink (`scamper/`) and the guardian process that lands the
drones when a flight dies (`guardian/`); the real lab (`lab/`: its rig, its assembly of these devices
and its operator tools)."""
