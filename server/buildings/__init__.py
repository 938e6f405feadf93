"""A building being served: its host and the parts it is made of (the batch path, anchor edits, floor plans,
users, recording and retention), its recovery and snapshots, devices, anchor ids, the typed calls the API
makes of it, and its handle (a thread of this process or a process of its own)."""
