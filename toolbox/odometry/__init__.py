"""Visual odometry: how a sensor moved between two overlapping looks (stereo and depth), and the
heading a sun sensor gives. Pure functions on images and points; no devices, no files."""
