"""Camera calibration wizard (intrinsics, distortion, marker colours). Filled by a later issue."""
