"""Where crash-resilience reports go: ``reports/`` under the pytest run's
root directory (the project under test: this repository for its own
scenarios, a team's own for theirs), a new run's directory name, and
``reports/latest``."""

from __future__ import annotations

import os
import secrets
from datetime import UTC, datetime
from pathlib import Path

from .model import write_atomic

ENV_REPORT_DIR = "CLONEGUARD_REPORT_DIR"
LATEST = "latest"


def default_reports_root(rootdir: Path) -> Path:
    """``rootdir``: pytest's root directory of the run (config.rootpath)."""
    return Path(rootdir) / "reports"


def new_run_id(now: datetime | None = None) -> str:
    now = now or datetime.now(UTC)
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
