"""What the hang diagnosis reads off gdb's output (harness/diagnose.py).

The texts are trimmed copies of gdb output seen in real hangs of this
project: a node blocked on a Fast DDS mutex re-locked after a condvar wait,
a drain blocked inside jemalloc, a container thread on glibc's main arena.
The end-to-end checks (gdb on real hung containers) are the scenarios'
baselines, whose hangs must come out named.
"""

from cloneguard.harness.diagnose import BlockedOn, Diagnosis, _lock_wait, _state, parse_threads

HOLDER = """\
Thread 2 (Thread 0x7f01d2bff6c0 (LWP 3659) "dds.ev.2"):
#0  __futex_abstimed_wait_common64 (private=0, cancel=true, abstime=0x7f01d2bfe420, op=393, expected=0, futex_word=0x7f01d2c4663c) at ./nptl/futex-internal.c:57
#3  0x00007f01edea68bc in __pthread_cond_wait_common (abstime=0x7f01d2bfe420, clockid=0, mutex=0x7f01d2c02110, cond=0x7f01d2c46610) at ./nptl/pthread_cond_wait.c:503
#4  ___pthread_cond_timedwait64 (cond=0x7f01d2c46610, mutex=0x7f01d2c02110, abstime=0x7f01d2bfe420) at ./nptl/pthread_cond_wait.c:643
#5  0x00007f01ebafa1b4 in eprosima::fastrtps::rtps::ResourceEvent::event_service() () from /venv/lib/libfastrtps.so.2.14
Thread 1 (Thread 0x7f4a7e7fc6c0 (LWP 1798) "python"):
#0  futex_wait (private=0, expected=2, futex_word=0x7f4a58257c40) at ../sysdeps/nptl/futex-internal.h:146
#1  __GI___lll_lock_wait (futex=futex@entry=0x7f4a58257c40, private=0) at ./nptl/lowlevellock.c:49
#2  0x00007f4abfea9753 in __pthread_mutex_cond_lock (mutex=mutex@entry=0x7f4a58257c40) at ../nptl/pthread_mutex_lock.c:93
#3  0x00007f4abfea67ad in __pthread_cond_wait_common (abstime=<optimized out>, clockid=<optimized out>, mutex=0x7f4a58257c40, cond=0x7f4a58257c68) at ./nptl/pthread_cond_wait.c:607
#5  0x00007f4abe7ceb55 in eprosima::fastdds::dds::detail::WaitSetImpl::wait(std::vector<eprosima::fastdds::dds::Condition*> >&, eprosima::fastrtps::Time_t const&) () from /venv/lib/libfastrtps.so.2.14
Thread 2 (Thread 0x7f01d2bff6c0 (LWP 3659) "dds.ev.2"):
Traceback (most recent call first):
  <built-in method wait of pybind11_builtins object at remote 0x7f4abf6e24>
Thread 1 (Thread 0x7f4a7e7fc6c0 (LWP 1798) "python"):
Traceback (most recent call first):
  File "/venv/lib/python3.11/site-packages/rclpy/executors.py", line ?, in _wait_for_ready_callbacks
  File "/work/main/container/isolated/host.py", line 168, in _spin_until_stopped
"""

DRAIN = """\
Thread 1 (Thread 0x7f01e7472980 (LWP 3658) "python"):
#0  futex_wait (private=0, expected=2, futex_word=0x7f019a803a68) at ../sysdeps/nptl/futex-internal.h:146
#1  __GI___lll_lock_wait (futex=futex@entry=0x7f019a803a68, private=0) at ./nptl/lowlevellock.c:49
#2  0x00007f01edeaa482 in lll_mutex_lock_optimized (mutex=0x7f019a803a68) at ./nptl/pthread_mutex_lock.c:48
#3  ___pthread_mutex_lock (mutex=0x7f019a803a68) at ./nptl/pthread_mutex_lock.c:93
#4  0x00007f01ee6923a0 in ?? () from /usr/lib/x86_64-linux-gnu/libjemalloc.so.2
#5  0x00007f01ee688108 in ?? () from /usr/lib/x86_64-linux-gnu/libjemalloc.so.2
#9  0x00007f01ea42463b in drain_some (ring=ring@entry=0) at /work/main/faults/hammer.c:109
"""

ARENA = """\
Thread 15 (Thread 0x7f320d1fe6c0 (LWP 12816) "python"):
#0  futex_wait (private=0, expected=2, futex_word=0x7f32301f1c60 <main_arena>) at ../sysdeps/nptl/futex-internal.h:146
#1  __GI___lll_lock_wait_private (futex=futex@entry=0x7f32301f1c60 <main_arena>) at ./nptl/lowlevellock.c:34
#2  0x00007f32300b497d in _int_free (av=0x7f32301f1c60 <main_arena>, p=0x55da7d965850, have_lock=have_lock@entry=0) at ./malloc/malloc.c:4572
#3  0x00007f32300b6f5f in __GI___libc_free (mem=<optimized out>) at ./malloc/malloc.c:3385
Thread 14 (Thread 0x7f320d9ff6c0 (LWP 12815) "python"):
#0  0x00007f3230126f36 in epoll_wait (epfd=18, events=events@entry=0x7f320d9fe820, maxevents=maxevents@entry=32, timeout=timeout@entry=-1) at ../sysdeps/unix/sysv/linux/epoll_wait.c:30
#1  0x00007f322fc7b2f5 in monitor_main (unused=<optimized out>) at /work/main/container/isolated/clonecore.c:938
Thread 13 (Thread 0x7f320d9ff6c1 (LWP 12817) "python"):
#0  0x00007f3230126f37 in spin_forever (n=3) at spin.c:10
#1  0x00007f3230126f38 in main_loop () at spin.c:20
"""


def test_a_mutex_relocked_after_a_condvar_wait_is_a_mutex_wait():
    threads = parse_threads(HOLDER, pid=1798)
    main = next(t for t in threads if t.tid == 1798)
    assert _lock_wait(main) == ("pthread mutex", "0x7f4a58257c40", "eprosima::fastdds::dds::detail::WaitSetImpl::wait")
    assert main.python[0].startswith("_wait_for_ready_callbacks (executors.py")
    events = next(t for t in threads if t.tid == 3659)
    assert _lock_wait(events) is None and _state(events)[0] == "idle"


POOL = """\
Thread 3 (Thread 0x7f5729ffb6c0 (LWP 24196) "python"):
#0  futex_wait (private=0, expected=2, futex_word=0x55d08e863088) at ../sysdeps/nptl/futex-internal.h:146
#1  __GI___lll_lock_wait (futex=futex@entry=0x55d08e863088, private=0) at ./nptl/lowlevellock.c:49
#2  0x00007f57450aa482 in lll_mutex_lock_optimized (mutex=0x55d08e863088) at ./nptl/pthread_mutex_lock.c:48
#3  ___pthread_mutex_lock (mutex=0x55d08e863088) at ./nptl/pthread_mutex_lock.c:93
#4  0x00007f5743745b4b in eprosima::fastrtps::rtps::TopicPayloadPool::release_payload(eprosima::fastrtps::rtps::CacheChange_t&) () from /venv/lib/libfastrtps.so.2.14
#5  0x00007f5743771278 in eprosima::fastrtps::rtps::RTPSReader::releaseCache(eprosima::fastrtps::rtps::CacheChange_t*) () from /venv/lib/libfastrtps.so.2.14
"""


def test_a_mutex_is_described_by_the_function_that_takes_it_and_a_shared_one_says_so():
    [t] = parse_threads(POOL, pid=24190)
    wait = _lock_wait(t)
    assert wait == (
        "pthread mutex",
        "0x55d08e863088",
        "eprosima::fastrtps::rtps::TopicPayloadPool::release_payload",
    )
    kind, addr, taker = wait
    b = BlockedOn(
        tid=24196,
        kind=kind,
        address=addr,
        owner_tid=31910,
        owner_node=None,
        owner_dead=True,
        where="container",
        taker=taker,
    )
    assert b.describe() == (
        "tid 24196 (container) waits on the pthread mutex at 0x55d08e863088 (taken in "
        "eprosima::fastrtps::rtps::TopicPayloadPool::release_payload: Fast DDS's payload pool of one "
        "topic, shared by every participant in the process (TopicPayloadPoolRegistry)), "
        "owned by tid 31910 (a dead process)"
    )


def test_a_wait_on_the_gils_own_mutex_is_named_so():
    b = BlockedOn(
        tid=7,
        kind="pthread mutex",
        address="0x7f00",
        owner_tid=9,
        owner_node=None,
        owner_dead=True,
        where="container",
        taker="take_gil",
    )
    assert b.describe() == (
        "tid 7 (container) waits on the pthread mutex at 0x7f00 (taken in take_gil: the GIL's own mutex "
        "(CPython's gil->mutex), taken by every thread that takes the GIL), owned by tid 9 (a dead process)"
    )


def test_a_lock_taken_inside_jemalloc_is_named_so():
    [t] = parse_threads(DRAIN, pid=3658)
    assert _lock_wait(t) == ("jemalloc lock", "0x7f019a803a68", "")


def test_a_glibc_arena_lock_is_named_by_its_arena_and_idle_and_running_threads_are_told_apart():
    threads = parse_threads(ARENA, pid=12787)
    by_tid = {t.tid: t for t in threads}
    assert _lock_wait(by_tid[12816]) == ("malloc arena lock", "0x7f32301f1c60", "main_arena")
    assert _state(by_tid[12815])[0] == "idle"
    state, where = _state(by_tid[12817])
    assert state == "running" and where.startswith("spin_forever")


def test_without_a_lock_the_summary_says_what_the_main_threads_do():
    from cloneguard.harness.diagnose import ThreadState

    d = Diagnosis(
        pid=10,
        stacks_text="",
        threads=[],
        blocked=[],
        names={10: "container", 11: "/drain"},
        states=[
            ThreadState(10, 10, "idle", "epoll_wait"),
            ThreadState(11, 11, "running", "drain_some [Python: _drain (components.py:225)]"),
        ],
    )
    assert d.summary() == (
        "no thread waits on a lock; /drain (pid 11) main thread running: "
        "drain_some [Python: _drain (components.py:225)]"
    )


def test_a_thread_that_burns_cpu_while_nothing_progresses_is_called_spinning():
    from cloneguard.harness.diagnose import ThreadState

    d = Diagnosis(
        pid=10,
        stacks_text="",
        threads=[],
        blocked=[],
        names={10: "container"},
        states=[
            ThreadState(10, 10, "idle", "epoll_wait"),
            ThreadState(12, 10, "running", "process_data_message", cpu_percent=97),
        ],
    )
    assert d.summary() == (
        "no thread waits on a lock; container tid 12 spinning (97% of a CPU while "
        "nothing progressed): process_data_message"
    )


def test_a_live_busy_loop_is_told_from_a_sleeper():
    """gdb on a real process: one thread spins, the main thread sleeps."""
    import subprocess
    import sys

    import pytest

    from cloneguard.harness.diagnose import diagnose, gdb_available

    if not gdb_available():
        pytest.skip("no gdb here")
    code = (
        "import threading, time\nthreading.Thread(target=lambda: [None for _ in iter(int, 1)], daemon=True).start()\n"
        "print('ready', flush=True)\ntime.sleep(60)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None  # stdout=PIPE
    try:
        assert proc.stdout.readline().strip() == "ready"
        d = diagnose(proc.pid)
        by_cpu = sorted(d.states, key=lambda s: -s.cpu_percent)
        # The loop's thread used the CPU (how much depends on the machine's
        # load); the sleeping main thread none.
        assert by_cpu[0].tid != proc.pid and by_cpu[0].cpu_percent > 0, d.states
        assert next(s for s in d.states if s.tid == proc.pid).cpu_percent == 0, d.states
    finally:
        proc.kill()
        proc.wait()


def test_an_owner_in_no_process_looked_into_is_described_from_proc():
    from cloneguard.harness.diagnose import BlockedOn

    b = BlockedOn(
        tid=5,
        kind="GIL",
        address="",
        owner_tid=77,
        owner_node=None,
        owner_dead=False,
        where="container",
        note="tid 77: state D (disk sleep), thread group 70",
    )
    assert b.describe() == (
        "tid 5 (container) waits on the GIL, owned by tid 77 (tid 77: state D (disk sleep), thread group 70)"
    )


def test_proc_facts_of_a_live_task_name_its_state_and_group():
    import os

    from cloneguard.harness import procfs

    facts = procfs.task_facts(os.getpid())
    assert facts.startswith("state R") or facts.startswith("state S"), facts
    assert f"thread group {os.getpid()}" in facts


SET_LISTENER = """\
Thread 1 (Thread 0x7f7a4d7f26c0 (LWP 3976) "python"):
#0  0x00007f7ad962ab30 in clock_gettime ()
#1  0x00007f7ad8eed439 in __GI___clock_gettime (clock_id=<optimized out>, tp=<optimized out>) at ../sysdeps/unix/sysv/linux/clock_gettime.c:42
#2  0x00007f7ad60cb1c5 in std::chrono::_V2::steady_clock::now() () from /lib/x86_64-linux-gnu/libstdc++.so.6
#3  0x00007f7ad7688e4e in eprosima::fastdds::dds::DomainParticipant::set_listener(eprosima::fastdds::dds::DomainParticipantListener*, eprosima::fastdds::dds::StatusMask const&, std::chrono::duration<long, std::ratio<1l, 1l> >) () from /venv/lib/libfastrtps.so.2.14
#5  0x00007f7ad7fd4c84 in rmw_fastrtps_shared_cpp::destroy_participant(CustomParticipantInfo*) () from /venv/lib/librmw_fastrtps_shared_cpp.so
"""


def test_a_known_busy_wait_in_another_project_is_named_with_its_reference():
    [t] = parse_threads(SET_LISTENER, pid=3976)
    assert _lock_wait(t) is None
    state, where = _state(t)
    assert state == "running"
    assert where.startswith("clock_gettime in eprosima::fastdds::dds::DomainParticipant::set_listener (")
    assert "eProsima/Fast-DDS#6513" in where


def test_a_child_no_event_named_is_looked_into_too(container_factory):
    """A per-node container's warm spare is a child of it that no LOADED
    event names: it can hold what the rest wait for (the GIL, say), so its
    stacks are taken and it is named as what it is."""
    import pytest

    from cloneguard.harness import rest
    from cloneguard.harness.diagnose import UNNAMED_CHILD, diagnose, gdb_available

    if not gdb_available():
        pytest.skip("no gdb here")
    proc = container_factory.start(["--isolated", "--profile", "per-node"])  # it keeps a spare
    client = container_factory.connect(proc)
    (spare,) = rest.wait_at_rest(client.node, proc.pid, spare=True)
    d = diagnose(proc.pid)
    assert d.names[spare] == UNNAMED_CHILD
    assert f"===== {UNNAMED_CHILD} (pid {spare}) =====" in d.stacks_text
    assert any(t.pid == spare for t in d.threads)


def test_what_the_container_said_of_a_lock_it_left_comes_first():
    from cloneguard.container import repairs
    from cloneguard.harness.diagnose import CONTAINER_NOT_REPAIRED, not_repaired_lines

    assert CONTAINER_NOT_REPAIRED == repairs.NOT_REPAIRED  # the container's own words
    log = (
        "[INFO] [1.0] [ComponentManager]: Loaded faults::X as /x\n"
        "[WARN] [2.0] [ComponentManager]: lock not repaired: /w (pid 7) thread 7 is blocked on native NORMAL "
        "mutex 0x10 in libm.so's data (m+0), whose owner thread 9 is gone but was not seen in a dead node "
        "process: not released\n"
        "[WARN] [2.5] [ComponentManager]: lock not repaired: /w (pid 7) thread 7 is blocked on native NORMAL "
        "mutex 0x10 in libm.so's data (m+0), whose owner thread 9 is gone but was not seen in a dead node "
        "process: not released\n"
    )
    said = not_repaired_lines(log)
    assert len(said) == 1 and said[0].startswith("/w (pid 7) thread 7 is blocked on native NORMAL mutex 0x10")
    d = Diagnosis(pid=10, stacks_text="", threads=[], blocked=[], names={10: "container"}, container_said=said)
    assert d.summary().startswith("the container said: /w (pid 7) thread 7 is blocked on native NORMAL mutex")
    assert d.summary().endswith("no thread waits on a lock; every thread is idle (waiting for work that never comes)")


HELD_MUTEX = """\
import ctypes, threading, time
libc = ctypes.CDLL(None)
mutex = ctypes.create_string_buffer(40)  # a pthread_mutex_t, zeroed: PTHREAD_MUTEX_INITIALIZER
libc.pthread_mutex_lock(mutex)
tids = {}
def run(name, wait):
    tids[name] = threading.get_native_id()
    wait()
threads = [threading.Thread(target=run, args=a, daemon=True) for a in [
    ("mutex", lambda: libc.pthread_mutex_lock(mutex)),  # the main thread holds it for good
    ("event", threading.Event().wait),  # a futex too, on another word
    ("sleep", lambda: time.sleep(60)),
]]
for t in threads:
    t.start()
while len(tids) < 3:
    time.sleep(0.01)
print(ctypes.addressof(mutex), tids["mutex"], tids["event"], tids["sleep"], flush=True)
time.sleep(60)
"""


def _held_mutex_process():
    """A process whose thread waits for good on a mutex its main thread
    holds, another in a futex wait on a word of its own, a third asleep;
    (proc, mutex address, their tids), once each sleeps where it should."""
    import subprocess
    import sys
    import time

    from cloneguard.harness import procfs

    proc = subprocess.Popen([sys.executable, "-c", HELD_MUTEX], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None  # stdout=PIPE
    addr, *tids = (int(x) for x in proc.stdout.readline().split())
    deadline = time.monotonic() + 10
    while not all(procfs.syscall_now(t) for t in tids):  # each in its call, not on the way to it
        assert time.monotonic() < deadline, [procfs.syscall_now(t) for t in tids]
        time.sleep(0.01)
    return proc, addr, tids


def test_a_lock_wait_the_stacks_caught_for_a_moment_is_not_called_blocked():
    """The stacks show a moment: a thread caught in a lock wait that it
    left (now asleep elsewhere) is not reported blocked (a silent-topic
    hang once named a passing wait of an idle container's thread);
    one still asleep on the lock's futex word is."""
    from cloneguard.harness import procfs
    from cloneguard.harness.diagnose import ThreadStack, _passing

    proc, addr, (on_mutex, on_event, asleep) = _held_mutex_process()
    try:
        assert procfs.syscall_now(on_mutex) == (procfs.SYS_FUTEX, addr)
        said = ("pthread mutex", hex(addr), "")  # what the stacks said of each of them
        waits = [(ThreadStack(tid, "", proc.pid), said) for tid in (on_mutex, on_event, asleep)]
        assert _passing(waits, None) == {on_event, asleep}
        # A GIL wait sleeps on any futex word of CPython's GIL state.
        now = procfs.syscall_now(on_event)
        assert now is not None and now[0] == procfs.SYS_FUTEX
        word = now[1]
        gil_wait = (ThreadStack(on_event, "", proc.pid, frames=["take_gil"]), ("GIL", "", ""))
        assert _passing([gil_wait], (word - 8, word + 40)) == set()
        assert _passing([gil_wait], (word + 4, word + 52)) == {on_event}
        assert _passing([gil_wait], None) == set()  # where the GIL lies is not known: any futex word
    finally:
        proc.kill()
        proc.wait()


def test_a_real_wait_on_a_held_mutex_is_named_with_its_owner():
    """gdb on a real process: the wait that lasts is blocked, on the mutex
    at its address, owned by the main thread; the others are not."""
    import pytest

    from cloneguard.harness.diagnose import diagnose, gdb_available

    if not gdb_available():
        pytest.skip("no gdb here")
    proc, addr, (on_mutex, _, _) = _held_mutex_process()
    try:
        d = diagnose(proc.pid)
        assert [(b.tid, b.kind, b.address, b.owner_tid) for b in d.blocked] == [
            (on_mutex, "pthread mutex", hex(addr), proc.pid)
        ]
    finally:
        proc.kill()
        proc.wait()
