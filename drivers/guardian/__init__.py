"""The guardian: a process beside each flight that lands its drones and stops its robot when the flight
dies or stalls (`launcher.py`: started and fed by the flight; `process.py`: the process itself, which
imports the launcher's protocol, never the reverse)."""
