"""The isolated mode's participant profiles (see host.py for what each means).

Kept apart so the command line can list them without loading the C core."""

PER_NODE = "per-node"
SHARED = "shared"
PROFILES = (PER_NODE, SHARED)
DEFAULT = PER_NODE
