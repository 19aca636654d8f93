"""Fast DDS shared-memory segments in /dev/shm."""
from __future__ import annotations

from pathlib import Path

SHM_DIR = Path("/dev/shm")
PREFIX = "fastrtps_"


def segments() -> set[str]:
    """Names of the Fast DDS segments (and their lock files) present now."""
    try:
        return {p.name for p in SHM_DIR.iterdir() if p.name.startswith(PREFIX)}
    except FileNotFoundError:
        return set()
