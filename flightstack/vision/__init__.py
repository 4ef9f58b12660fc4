"""Image side of the lab: marker extraction from camera frames and the camera calibration file."""
