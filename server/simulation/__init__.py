"""Simulated phones: their batches, a crowd posting them over HTTP, and the scenario evaluation through the
server's tracker."""
