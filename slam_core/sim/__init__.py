"""The simulated world (the paper's testbed), range-model calibration on it, and evaluation statistics."""
