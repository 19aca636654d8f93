"""The container under test, as a real process the harness owns.

It runs in a session (and so a process group) of its own, with
PR_SET_PDEATHSIG=SIGKILL so it cannot outlive the harness, its own
ROS_DOMAIN_ID, Fast DDS on UDP only by default, and its output in a log file.
Stopping it is SIGTERM to its process group, 2 s of grace, then SIGKILL.
Only process groups this module started are ever signalled.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from . import procfs, shm, stops
from .errors import HarnessTimeout
from .memory_cgroup import MemoryCgroup

REPO_ROOT = Path(__file__).resolve().parent.parent
NO_SHM_PROFILE = REPO_ROOT / "fixtures" / "fastdds_no_shm.xml"
SHM_PROFILE = REPO_ROOT / "fixtures" / "fastdds_shm.xml"
STOP_GRACE_S = 2.0


def default_container_exe() -> str:
    """The ``component_container`` next to this interpreter, else on PATH."""
    beside = Path(sys.prefix) / "bin" / "component_container"
    if beside.exists():
        return str(beside)
    found = shutil.which("component_container")
    if found is None:
        raise FileNotFoundError("component_container is not installed (pip install -e .)")
    return found


def ros_environment(domain_id: int, *, fastdds_profile: Path = NO_SHM_PROFILE) -> dict[str, str]:
    """The ROS variables a harness-launched process (and the harness) runs with.

    Both profiles keep every packet on the loopback interface.
    """
    return {
        "ROS_DOMAIN_ID": str(domain_id),
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "FASTRTPS_DEFAULT_PROFILES_FILE": str(fastdds_profile),
    }


def process_environment(
    domain_id: int, *, fastdds_profile: Path = NO_SHM_PROFILE, base: dict[str, str] | None = None
) -> dict[str, str]:
    """``base`` (default: this process's environment) with the ROS variables
    of ros_environment(), and the signal a container's node processes take
    stop requests on (stops.py); a discovery-range setting would replace
    the profile's transports, so it goes."""
    env = dict(os.environ if base is None else base)
    for key in DISCOVERY_RANGE_VARIABLES:
        env.pop(key, None)
    env.update(ros_environment(domain_id, fastdds_profile=fastdds_profile))
    env[stops.STOP_SIGNAL_ENV] = str(stops.STOP_SIGNAL)
    return env


#: variables a discovery range setting would use to replace the profile's transports
DISCOVERY_RANGE_VARIABLES = ("ROS_AUTOMATIC_DISCOVERY_RANGE",)


def loopback_variables() -> dict[str, str]:
    """What this process's own participants (the harness's clients) run
    with to follow the rules the containers get, UDP on loopback only (the
    domain is chosen per context). rmw_implementation and Fast DDS read them
    at the process's first rclpy import and first participant."""
    return {k: v for k, v in ros_environment(0).items() if k != "ROS_DOMAIN_ID"}


def use_loopback_ros() -> None:
    """Set loopback_variables() in this process, for good: call before any
    rclpy import (the command-line tools and benchmarks do)."""
    for key in DISCOVERY_RANGE_VARIABLES:
        os.environ.pop(key, None)
    os.environ.update(loopback_variables())


def stop_group(popen: subprocess.Popen, pgid: int, grace: float) -> tuple[int, bool]:
    """Stop a process we started as the leader of group ``pgid``: SIGTERM
    the group, SIGKILL it after ``grace`` s; then whatever is still in the
    group (a child that outlived its leader: ours too) is killed.
    (its return code, whether SIGKILL was needed)."""
    forced = False
    if popen.poll() is None:
        _killpg(pgid, signal.SIGTERM)
        try:
            popen.wait(grace)
        except subprocess.TimeoutExpired:
            forced = True
            _killpg(pgid, signal.SIGKILL)
    code = popen.wait()
    if procfs.pids_in_group(pgid):
        forced = True
        _killpg(pgid, signal.SIGKILL)
        procfs.wait_group_empty(pgid, timeout=grace)
    return code, forced


def _killpg(pgid: int, sig: int) -> None:
    try:
        os.killpg(pgid, sig)
    except ProcessLookupError:
        pass


@dataclass(frozen=True)
class ExitStatus:
    returncode: int  # as subprocess reports it: -N for signal N
    forced: bool  # True when SIGKILL was needed
    stop_seconds: float


class ContainerProcess:
    """One started container. Use :meth:`stop` (or the context manager)."""

    def __init__(
        self,
        args: list[str],
        *,
        domain_id: int,
        log_path: Path,
        exe: str | None = None,
        node_name: str = "ComponentManager",
        fastdds_profile: Path = NO_SHM_PROFILE,
        extra_env: dict[str, str] | None = None,
        memory_cgroup: MemoryCgroup | None = None,
    ):
        self.exe = exe or default_container_exe()
        # Born in it, when given (memory_cgroup.py); removed after its stop.
        self.memory_cgroup = memory_cgroup
        self.node_name = node_name
        self.domain_id = domain_id
        self.log_path = Path(log_path)
        ros_args = [] if node_name == "ComponentManager" else ["--ros-args", "-r", f"__node:={node_name}"]
        self.argv = [self.exe, *args, *ros_args]
        env = process_environment(domain_id, fastdds_profile=fastdds_profile)
        env["PYTHONUNBUFFERED"] = "1"
        env.update(extra_env or {})
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log = open(self.log_path, "ab", buffering=0)
        # Wall time before the process exists: whatever is named for its pid
        # (a cgroup) but older than this belongs to an earlier owner of the pid.
        self.started_at = time.time()
        # setpriv sets PR_SET_PDEATHSIG in the child and execs the container,
        # so the pid below is the container's own.
        born_in = [] if memory_cgroup is None else ["sh", "-c", 'echo $$ > "$0" && exec "$@"', str(memory_cgroup.procs)]
        self._popen = subprocess.Popen(
            [*born_in, "setpriv", "--pdeathsig", "KILL", "--", *self.argv],
            stdin=subprocess.DEVNULL,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,
        )
        self.pid = self._popen.pid
        self.pgid = self.pid  # start_new_session: the leader of its own group
        self.exit_status: ExitStatus | None = None
        self.shm_seen: set[str] = set()  # Fast DDS segments it was seen to map

    @property
    def fqn(self) -> str:
        return "/" + self.node_name.lstrip("/")

    def alive(self) -> bool:
        return self._popen.poll() is None

    def log_text(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def wait_for_log(self, pattern: str, timeout: float) -> re.Match:
        """The first match of the regular expression ``pattern`` in the
        container's log, waited for up to ``timeout`` s; HarnessTimeout, with
        the log's tail, if it does not come."""
        deadline = time.monotonic() + timeout
        while True:
            log = self.log_text()
            found = re.search(pattern, log)
            if found:
                return found
            if time.monotonic() > deadline:
                raise HarnessTimeout(f"the log did not say /{pattern}/ within {timeout:g} s; its end:\n{log[-2000:]}")
            time.sleep(0.05)

    def group_members(self) -> list[int]:
        """Live or zombie processes still in the container's process group."""
        return procfs.pids_in_group(self.pgid)

    def signal(self, sig: int) -> None:
        """Signal the container process itself (not its group)."""
        if self.alive():
            os.kill(self.pid, sig)

    def wait(self, timeout: float) -> int | None:
        try:
            return self._popen.wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def record_shm(self) -> set[str]:
        """Note the Fast DDS segments the container maps now (its node
        processes share its memory map, so theirs are included). Only these
        can later be called the container's orphans."""
        self.shm_seen |= shm.mapped_by(self.pid)
        return self.shm_seen

    def stop(self, grace: float = STOP_GRACE_S) -> ExitStatus:
        """SIGTERM the group, wait ``grace`` s, then SIGKILL what is left."""
        if self.exit_status is not None:
            return self.exit_status
        if self.alive():
            self.record_shm()
        t0 = time.monotonic()
        code, forced = stop_group(self._popen, self.pgid, grace)
        self._log.close()
        self.exit_status = ExitStatus(code, forced, time.monotonic() - t0)
        if self.memory_cgroup is not None:
            self.memory_cgroup.close()
        return self.exit_status

    def __enter__(self) -> ContainerProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
