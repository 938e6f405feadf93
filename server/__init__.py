"""crowdslam server: the only package with I/O (HTTP, WebSocket, SQL, MCAP, files, CLI)."""
