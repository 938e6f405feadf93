"""Signal-map builds (SignalSLAM over a building's recordings), each in a process of its own."""
