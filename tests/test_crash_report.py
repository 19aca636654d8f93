"""A node's crash report cut out of a container's log (harness/crash_report.py):
its head, Python stack and native stack, whatever lies between them."""

from cloneguard.harness.crash_report import report_of

LOG = """\
[INFO] [1.0] [ComponentManager]: Loaded demo_robot::Planner as /planner (unique_id 2, pid 41)
cloneguard: pid 41 caught SIGSEGV at - (pc 7f00deadbeef)
cloneguard: si_code -6 (sent by pid 99)
[ERROR] [1.1] [ComponentManager]: /planner (pid 41) died: killed by SIGSEGV
cloneguard: pid 57 caught SIGABRT at - (pc 7f0000000001)
cloneguard: pid 41 Python stack (most recent call first):
  File "/x/nodes.py", line 36 in _plan
  File "/x/rclpy/executors.py", line 100 in spin_once
cloneguard: pid 41 native stack:
/lib/x86_64-linux-gnu/libc.so.6(+0x85f16)[0x7f00deadbeef]
/lib/x86_64-linux-gnu/libc.so.6(__poll+0x4f)[0x7f00deadbf00]
[INFO] [1.2] [ComponentManager]: unloaded
"""


def test_one_pids_report_is_its_three_parts_and_nothing_else():
    assert report_of(LOG, 41) == (
        "cloneguard: pid 41 caught SIGSEGV at - (pc 7f00deadbeef)\n"
        "cloneguard: si_code -6 (sent by pid 99)\n"
        "cloneguard: pid 41 Python stack (most recent call first):\n"
        '  File "/x/nodes.py", line 36 in _plan\n'
        '  File "/x/rclpy/executors.py", line 100 in spin_once\n'
        "cloneguard: pid 41 native stack:\n"
        "/lib/x86_64-linux-gnu/libc.so.6(+0x85f16)[0x7f00deadbeef]\n"
        "/lib/x86_64-linux-gnu/libc.so.6(__poll+0x4f)[0x7f00deadbf00]\n"
    )


def test_a_report_not_written_yet_is_what_there_is_or_none():
    assert report_of(LOG, 57) == "cloneguard: pid 57 caught SIGABRT at - (pc 7f0000000001)\n"
    assert report_of(LOG, 4) is None  # pid 4's "41" lines are not its own
