"""The scenario rig (harness/rig.py) on a real container."""
import signal

from cloneguard.harness.rig import Rig


def test_a_container_that_died_in_a_trial_is_crashed_with_its_last_log_lines(container_factory):
    rig = Rig(container_factory, "threads")
    rig.proc.signal(signal.SIGSEGV)
    assert rig.proc.wait(timeout=20) is not None
    out = rig.not_survived("the container is gone")
    assert out.outcome == "crashed" and out.details["exit_code"] == -signal.SIGSEGV
    # What it said last stays in the report after its log file is gone: the
    # lines before the fault, and faulthandler's dump of its threads.
    assert "Loaded cloneguard::Heartbeat as /survivor" in out.details["log_tail"]
    fatal = out.details["fatal_error"]
    assert fatal.startswith("Fatal Python error: Segmentation fault") and "most recent call first" in fatal
    log = rig.proc.log_text()
    assert log.index(out.details["log_tail"]) + len(out.details["log_tail"]) <= log.index(fatal)


def test_a_long_fault_dump_keeps_the_faulting_threads_stack():
    from cloneguard.harness.rig import fatal_excerpt
    others = "".join(f'Thread 0x{i:x} (most recent call first):\n  File "x.py", line {i} in f\n\n'
                     for i in range(400))
    current = 'Current thread 0xbeef (most recent call first):\n  Garbage-collecting\n  File "core.py", line 498 in _listen\n'
    dump = "Fatal Python error: Segmentation fault\n\n" + others + current + "\nExtension modules: yaml\n"
    cut = fatal_excerpt(dump, 4000)
    assert len(cut) <= 4000
    assert cut.startswith("Fatal Python error: Segmentation fault\nCurrent thread 0xbeef")
    assert current in cut and "more characters of the dump left out" in cut
    assert fatal_excerpt("Fatal Python error: x\n", 4000) == "Fatal Python error: x\n"
