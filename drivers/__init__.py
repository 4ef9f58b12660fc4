"""Hardware drivers (Tello, motion capture, Scamper) behind flightstack.hal. Filled by later issues."""
