"""MCAP recordings of every accepted batch and estimate: written per building and hour, read back."""
