"""A phone's sensors to steps and anchor detections: pedestrian dead reckoning and the building-anchor
detectors."""
