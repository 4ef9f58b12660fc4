"""The Scamper (an ArduPilot Rover) over MAVLink: the driver (`driver.py`), its link and heartbeat
(`link.py`), the vehicle's pose fed to its EKF (`nav.py`, `vehicle.py`), its parameters and failsafe
(`params.py`, `failsafe.py`) and its telemetry log (`tlog.py`)."""
