"""Public datasets: the Indoor Location Competition 2.0 traces, replayed through the server's own path."""
