"""The phone page: a browser on a phone becomes a tracked client of the batch API, with nothing to install."""
