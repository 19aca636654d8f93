"""Where crash-resilience reports go: the repository root, the reports root
under it, a new run's directory name, and ``reports/latest``."""
from __future__ import annotations

import os
import secrets
from datetime import datetime, timezone
from pathlib import Path

from .model import write_atomic

ENV_REPORT_DIR = "CLONEGUARD_REPORT_DIR"
LATEST = "latest"


def repo_root() -> Path:
    """The directory holding pyproject.toml next to harness/ (for an
    installed, not editable, copy: the current directory)."""
    root = Path(__file__).resolve().parents[2]
    if (root / "pyproject.toml").is_file() and (root / "harness").is_dir():
        return root
    return Path.cwd()


def default_reports_root() -> Path:
    return repo_root() / "reports"


def new_run_id(now: datetime | None = None) -> str:
    now = now or datetime.now(timezone.utc)
    return now.strftime("%Y%m%dT%H%M%SZ") + "-" + secrets.token_hex(2)


def update_latest(root: Path, run_name: str) -> Path:
    """Point ``root/latest`` at ``run_name``: a relative symlink, replaced
    atomically, or a text file holding the name where symlinks fail."""
    link = root / LATEST
    tmp = root / f".{LATEST}.{os.getpid()}.{secrets.token_hex(2)}"
    try:
        os.symlink(run_name, tmp)
        os.replace(tmp, link)
    except OSError:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if link.is_symlink():
            link.unlink()
        write_atomic(link, run_name + "\n")
    return link
