"""Camera calibration wizard: intrinsics and distortion (`camera`), marker colours (`markers`), checks."""
