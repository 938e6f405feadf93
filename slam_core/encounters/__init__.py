"""Human anchors before the filter: encounter models, detection across users, which detections are chosen."""
