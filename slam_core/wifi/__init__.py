"""How alike two WiFi scans are: DynamicSLAM's Eq. 3 and the union-fingerprint distance, and pair features."""
