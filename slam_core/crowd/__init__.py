"""What the crowd learns together: the shared anchor map, its joint solve, and the WiFi fingerprint map."""
