"""The real lab as a rig (`rig.py`: real Tellos, motion capture and the Scamper, on the wall clock)."""
