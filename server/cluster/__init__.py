"""Cluster mode: buildings owned by worker processes through leases in NATS JetStream."""
