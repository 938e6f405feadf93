"""The dashboard (a static page of ES modules over the public API) and the offline API docs."""
