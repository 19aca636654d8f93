"""Put the product's ament index entries (pyproject.toml's
[tool.setuptools.data-files], described in ament/README.md) under this
environment's prefix.

A wheel install of cloneguard installs them itself; setuptools' editable
installs (what scripts/setup.sh makes) leave data files out, so the set-up
links them here instead: links, like the rest of an editable install, so an
edit of ament/ shows at once. Run with the venv's python.
"""

from __future__ import annotations

import os
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def data_files() -> dict[str, list[str]]:
    with open(ROOT / "pyproject.toml", "rb") as f:
        return tomllib.load(f)["tool"]["setuptools"]["data-files"]


def main() -> int:
    prefix = Path(sys.prefix)
    for directory, files in data_files().items():
        target_dir = prefix / directory
        target_dir.mkdir(parents=True, exist_ok=True)
        for name in files:
            source = ROOT / name
            target = target_dir / source.name
            if target.is_symlink() or target.exists():
                target.unlink()
            os.symlink(source, target)
    print(f"ament index entries of cloneguard linked under {prefix}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
