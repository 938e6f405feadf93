"""SignalSLAM (Mirowski et al.): PDR recalibration between landmarks, GraphSLAM on gtsam with landmark and
signal-similarity edges, and the signal maps built from the optimised trajectories."""
