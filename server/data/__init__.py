"""Files shipped with the server: the simulated testbed and its encounter calibration."""
