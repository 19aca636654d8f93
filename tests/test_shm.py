"""cloneguard.harness.shm: which Fast DDS files are orphans, on files made by the test.

Most cases build fake segments in a temporary directory (every function of
harness.shm takes the directory to look in). The cases about Fast DDS's port
mutex need glibc's semaphore directory, /dev/shm: they use port numbers no
Fast DDS port can have (above 65535) and remove only the files they made.
"""

import fcntl
import mmap
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from cloneguard.harness import shm

PARTICIPANT = "fastrtps_0123456789abcdef"


def make(d: Path, *names: str) -> None:
    for name in names:
        (d / name).write_bytes(b"\0" * mmap.PAGESIZE)


def verdicts(names, d) -> dict[str, bool]:
    return {seg.name: seg.orphan for seg in shm.classify(set(names), d)}


class Mapped:
    """A file mapped by this process (as a Fast DDS peer maps a port)."""

    def __init__(self, path: Path):
        self._fd = os.open(path, os.O_RDWR)
        self._map = mmap.mmap(self._fd, mmap.PAGESIZE)

    def close(self):
        self._map.close()
        os.close(self._fd)


class Peer:
    """Another live process that runs ``code``, says "ready", then waits
    for a line on stdin and exits."""

    def __init__(self, code: str):
        script = textwrap.dedent(code) + "\nimport sys\nprint('ready', flush=True)\nsys.stdin.readline()\n"
        self.proc = subprocess.Popen(
            [sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )
        assert self.proc.stdout is not None  # stdout=PIPE
        assert self.proc.stdout.readline().strip() == "ready"

    def stop(self):
        assert self.proc.stdin is not None  # stdin=PIPE
        self.proc.stdin.close()
        assert self.proc.wait(timeout=10) == 0


# -- segments with a lock file: Fast DDS's own rule -------------------------------------------


def test_a_segment_whose_lock_is_held_is_in_use_and_one_whose_lock_is_free_is_an_orphan(tmp_path):
    make(tmp_path, PARTICIPANT, PARTICIPANT + "_el")
    names = {PARTICIPANT, PARTICIPANT + "_el"}
    holder = os.open(tmp_path / (PARTICIPANT + "_el"), os.O_RDONLY)
    fcntl.flock(holder, fcntl.LOCK_EX)
    try:
        assert verdicts(names, tmp_path) == {PARTICIPANT: False}
        assert shm.remove_orphans(names, tmp_path) == []
        assert shm.segments(tmp_path) == names
    finally:
        os.close(holder)
    assert verdicts(names, tmp_path) == {PARTICIPANT: True}
    assert [s.name for s in shm.remove_orphans(names, tmp_path)] == [PARTICIPANT]
    assert shm.segments(tmp_path) == set()


def test_an_orphaned_port_goes_with_its_lock_file_and_semaphore(tmp_path):
    files = {"fastrtps_port7410", "fastrtps_port7410_el", "sem.fastrtps_port7410_mutex"}
    make(tmp_path, *files)
    (seg,) = shm.classify(files, tmp_path)
    assert (seg.name, seg.orphan, seg.lockless, set(seg.files)) == ("fastrtps_port7410", True, False, files)
    shm.remove_orphans(files, tmp_path)
    assert shm.segments(tmp_path) == set()


def test_a_lock_file_decides_even_when_a_live_process_maps_the_segment(tmp_path):
    # A live sender maps a dead listener's port: Fast DDS calls it a zombie.
    files = {"fastrtps_port7412", "fastrtps_port7412_el"}
    make(tmp_path, *files)
    sender = Mapped(tmp_path / "fastrtps_port7412")
    try:
        assert verdicts(files, tmp_path) == {"fastrtps_port7412": True}
    finally:
        sender.close()


# -- ports with no lock file ----------------------------------------------------------------------


def test_a_lockless_port_mapped_by_this_process_is_in_use_and_unmapped_an_orphan(tmp_path):
    files = {"fastrtps_port7414", "sem.fastrtps_port7414_mutex"}
    make(tmp_path, *files)
    user = Mapped(tmp_path / "fastrtps_port7414")
    try:
        (seg,) = shm.classify(files, tmp_path)
        assert (seg.lockless, seg.orphan) == (True, False)
        assert shm.remove_orphans(files, tmp_path) == []
        assert shm.segments(tmp_path) == files
    finally:
        user.close()
    (seg,) = shm.classify(files, tmp_path)
    assert (seg.lockless, seg.orphan) == (True, True)
    assert [s.name for s in shm.remove_orphans(files, tmp_path)] == ["fastrtps_port7414"]
    assert shm.segments(tmp_path) == set()


def test_a_lockless_port_whose_semaphore_is_mapped_is_being_opened(tmp_path):
    # Fast DDS maps the port's mutex before it opens or creates the port.
    files = {"fastrtps_port7416", "sem.fastrtps_port7416_mutex"}
    make(tmp_path, *files)
    opener = Mapped(tmp_path / "sem.fastrtps_port7416_mutex")
    try:
        assert verdicts(files, tmp_path) == {"fastrtps_port7416": False}
        assert shm.remove_orphans(files, tmp_path) == []
    finally:
        opener.close()
    assert verdicts(files, tmp_path) == {"fastrtps_port7416": True}


def test_a_lockless_port_mapped_by_another_live_process_is_in_use(tmp_path):
    port = tmp_path / "fastrtps_port7418"
    make(tmp_path, port.name)
    peer = Peer(f"""
        import mmap, os
        fd = os.open({str(port)!r}, os.O_RDWR)
        m = mmap.mmap(fd, mmap.PAGESIZE)
    """)
    try:
        assert verdicts({port.name}, tmp_path) == {port.name: False}
        assert shm.remove_orphans({port.name}, tmp_path) == []
    finally:
        peer.stop()
    assert verdicts({port.name}, tmp_path) == {port.name: True}


def test_a_mapping_of_an_unlinked_port_does_not_keep_a_new_one_of_that_name(tmp_path):
    port = tmp_path / "fastrtps_port7420"
    make(tmp_path, port.name)
    stale = Mapped(port)
    try:
        port.unlink()
        make(tmp_path, port.name)
        assert verdicts({port.name}, tmp_path) == {port.name: True}
    finally:
        stale.close()


def test_a_lock_file_makes_a_port_not_lockless(tmp_path):
    files = {"fastrtps_port7422", "fastrtps_port7422_sl"}
    make(tmp_path, *files)
    holder = os.open(tmp_path / "fastrtps_port7422_sl", os.O_RDONLY)
    fcntl.flock(holder, fcntl.LOCK_EX)
    try:
        (seg,) = shm.classify({"fastrtps_port7422"}, tmp_path)
        assert (seg.lockless, seg.orphan) == (False, False)
    finally:
        os.close(holder)


def test_only_orphans_of_our_owners_are_removed(tmp_path):
    make(
        tmp_path, "fastrtps_port7424", "sem.fastrtps_port7424_mutex", "fastrtps_port7426", "sem.fastrtps_port7426_mutex"
    )
    removed = shm.remove_orphans_of(shm.segments(tmp_path), {"fastrtps_port7424"}, tmp_path)
    assert [s.name for s in removed] == ["fastrtps_port7424"]
    assert shm.segments(tmp_path) == {"fastrtps_port7426", "sem.fastrtps_port7426_mutex"}


def test_mapped_by_names_the_segments_a_process_maps(tmp_path):
    make(tmp_path, "fastrtps_port7428", PARTICIPANT)
    maps = [Mapped(tmp_path / "fastrtps_port7428"), Mapped(tmp_path / PARTICIPANT)]
    try:
        assert shm.mapped_by(os.getpid(), tmp_path) == {"fastrtps_port7428", PARTICIPANT}
    finally:
        for m in maps:
            m.close()
    assert shm.mapped_by(os.getpid(), tmp_path) == set()


def test_locked_by_names_what_a_process_owns_not_what_it_shares(tmp_path):
    make(tmp_path, PARTICIPANT, PARTICIPANT + "_el", "fastrtps_port7430", "fastrtps_port7430_sl")
    owner = Peer(f"""
        import fcntl, os
        own = os.open({str(tmp_path / (PARTICIPANT + "_el"))!r}, os.O_RDONLY)
        fcntl.flock(own, fcntl.LOCK_EX)
        shared = os.open({str(tmp_path / "fastrtps_port7430_sl")!r}, os.O_RDONLY)
        fcntl.flock(shared, fcntl.LOCK_SH)
    """)
    try:
        assert shm.locked_by({owner.proc.pid}, tmp_path) == {PARTICIPANT}
        assert shm.locked_by({os.getpid()}, tmp_path) == set()
    finally:
        owner.stop()
    assert shm.locked_by({owner.proc.pid}, tmp_path) == set()


# -- Fast DDS's mutex of a port (a POSIX semaphore in /dev/shm) ----------------------------------

SEM_CODE = """
    import ctypes, os
    libc = ctypes.CDLL(None, use_errno=True)
    libc.sem_open.restype = ctypes.c_void_p
    libc.sem_open.argtypes = [ctypes.c_char_p, ctypes.c_int, ctypes.c_uint, ctypes.c_uint]
    libc.sem_wait.argtypes = [ctypes.c_void_p]
    libc.sem_close.argtypes = [ctypes.c_void_p]
    sem = libc.sem_open({name!r}, os.O_CREAT, 0o644, 1)
    assert sem, ctypes.get_errno()
    assert libc.sem_wait(sem) == 0
"""


@pytest.fixture
def dev_shm_port():
    """A lock-less port in /dev/shm under a number no Fast DDS port has;
    whatever the test leaves of it is removed afterwards."""
    for n in range(90000 + os.getpid() % 9000, 100000):
        base = f"fastrtps_port{n}"
        files = [shm.SHM_DIR / base, shm.SHM_DIR / f"{base}_el", shm.SHM_DIR / f"sem.{base}_mutex"]
        if not any(f.exists() for f in files):
            break
    make(shm.SHM_DIR, base)
    yield base
    for f in files:
        f.unlink(missing_ok=True)


def test_a_port_whose_mutex_a_live_process_holds_is_being_opened(dev_shm_port):
    holder = Peer(SEM_CODE.format(name=f"/{dev_shm_port}_mutex".encode()))
    try:
        assert shm.remove_orphans({dev_shm_port}) == []
        assert (shm.SHM_DIR / dev_shm_port).exists()
    finally:
        holder.stop()
    # It let go of it (it closed it by exiting, still taken): nobody is
    # opening the port any more, and it goes with its semaphore.
    assert [s.name for s in shm.remove_orphans({dev_shm_port})] == [dev_shm_port]
    assert not (shm.SHM_DIR / dev_shm_port).exists()
    assert not (shm.SHM_DIR / f"sem.{dev_shm_port}_mutex").exists()


def test_an_orphaned_port_with_a_free_mutex_goes_with_it(dev_shm_port):
    holder = Peer(
        SEM_CODE.format(name=f"/{dev_shm_port}_mutex".encode()).replace(
            "assert libc.sem_wait(sem) == 0", "assert libc.sem_close(sem) == 0"
        )
    )
    holder.stop()
    assert (shm.SHM_DIR / f"sem.{dev_shm_port}_mutex").exists()
    assert [s.name for s in shm.remove_orphans({dev_shm_port})] == [dev_shm_port]
    assert shm.segments() & {dev_shm_port, f"sem.{dev_shm_port}_mutex"} == set()


def test_an_orphaned_port_without_a_semaphore_leaves_none_behind(dev_shm_port):
    assert [s.name for s in shm.remove_orphans({dev_shm_port})] == [dev_shm_port]
    assert shm.segments() & {dev_shm_port, f"sem.{dev_shm_port}_mutex"} == set()


def test_the_check_made_under_the_mutex_still_sees_a_live_opener(dev_shm_port):
    # Someone who started opening the port after it was classified an orphan.
    holder = Peer(SEM_CODE.format(name=f"/{dev_shm_port}_mutex".encode()))
    try:
        assert not shm._remove_lockless(shm.SHM_DIR, dev_shm_port)
        assert (shm.SHM_DIR / dev_shm_port).exists()
    finally:
        holder.stop()
