"""Webhooks: zone events POSTed to the receivers operators name, signed, in order, retried, never into the
server's own network."""
