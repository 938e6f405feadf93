"""A building being served: its tracking and transaction, recovery and snapshots, devices, anchor ids, and its
worker (a thread of this process or a process of its own)."""
