"""The benchmarks (bench/) run end to end with tiny counts and write their
tables. Structure only: no figure here is compared with anything."""

import json
import subprocess
import sys

import pytest

from cloneguard.bench import __main__ as bench_all
from cloneguard.bench import pkeys_cost
from cloneguard.bench.results import SUMMARY_COLUMNS
from cloneguard.harness.process import REPO_ROOT

# The tables each benchmark writes, with the "tiny" preset's parameters.
EXPECTED_TABLES = {
    "child_start": [
        ["measure", "n", "median", "p90", "max", "÷ clone child (medians)"],
        ["measure", "n", "median", "p90", "cold (round 0)", "process-per-node ÷ this (medians)"],
    ],
    "memory": [
        [
            "mode",
            "processes @2",
            "address spaces @2",
            "PSS @1 (MiB)",
            "PSS @2 (MiB)",
            "marginal PSS / node (MiB)",
            "marginal USS / node (MiB)",
            "marginal page tables / node (KiB)",
            "process-per-node ÷ this (marginal PSS)",
        ],
        ["mode", "@1", "@2"],
    ],
    "crash_latency": [
        [
            "profile",
            "signal",
            "n",
            "lost (no CRASHED in 10 s)",
            "container stuck afterwards (next LoadNode unanswered)",
            "→ CRASHED stamp: median",
            "stamp: p90",
            "stamp: max",
            "→ CRASHED at client: median",
            "at client: p90",
            "median vs goal 0.8 ms",
        ],
        [
            "profile",
            "signal",
            "n",
            "CRASHED stamped (published)",
            "'died' error logged (manager)",
            "'left in memory' warning logged (host)",
        ],
        [
            "signal",
            "n",
            "monitor detected: median",
            "detected: p90",
            "detected: max",
            "on_event called: median",
            "on_event: p90",
        ],
    ],
    "load_latency": [
        [
            "mode",
            "n",
            "→ LOADED at client: median",
            "→ LOADED: p90",
            "LoadNode round trip: median",
            "round trip: p90",
            "→ LOADED published (container clock): median",
            "cold first load → LOADED",
            "UnloadNode round trip: median",
            "LOADED median vs goal 20 ms",
        ],
    ],
    "shutdown": [
        [
            "mode",
            "nodes",
            "processes before",
            "n",
            "→ container exited: median",
            "exited: p90",
            "exited: max",
            "→ process group empty: median",
            "exit codes",
            "timed out / forced",
            "children SIGKILLed after 500 ms",
            "vs goal (≤ 1 s with 20 isolated nodes)",
        ],
    ],
    "intra": [
        [
            "size",
            "transport",
            "n",
            "latency: median",
            "latency: p90",
            "latency: max",
            "period (ms)",
            "latency > period",
            "burst: received / sent",
            "burst: msgs/s",
            "burst: MiB/s",
            "burst: source's publish rate (msgs/s)",
            "lost",
            "KEEP_LAST dropped",
            "publish() call: median",
            "build (not in latency): median",
            "sent over DDS (source)",
        ],
        ["ratio", "numerator", "denominator", "measured", "goal", "verdict"],
    ],
    "python_locks": [["case", "CPython", "ours", "ours ÷ CPython", "ours p90"]],
    "lock_doctor": [
        ["node processes", "tasks looked at", "before any death", "after a death", "after a death, per task"],
        ["resident memory made", "container RSS", "monitor CPU", "more than with none, per MiB"],
    ],
    "message_faults_cost": [
        ["transport", "pairs", "engine loaded (A)", "no engine (B)", "A ÷ B: median [95% interval]"],
        ["transport", "hooks a message meets", "added (ns)", "of B's median latency"],
    ],
    "scale": [
        [
            "mode",
            "nodes",
            "load all (s)",
            "idle CPU (% of a core)",
            "of it, Fast DDS threads",
            "PSS (MiB)",
            "SIGTERM → exit (s)",
            "processes",
        ],
        ["mode", "load all", "idle CPU", "PSS"],
    ],
}
# Rows of the first table: one per mode (or profile × signal, or measure; intra:
# 2 sizes × 3 transports and the floor).
EXPECTED_ROWS = {
    "child_start": 8,
    "memory": 3,
    "crash_latency": 4,
    "load_latency": 2,
    "shutdown": 5,
    "intra": 7,
    "python_locks": 6,  # 3 uncontended, contended at 2, 4, 8 threads
    "lock_doctor": 2,  # one per node count
    "scale": 6,  # 3 modes × 2 counts
    "message_faults_cost": 2,  # intra-process, DDS
}


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    results, failures, summary = bench_all.run_all(preset="tiny", out=out, quiet=True)
    return out, results, failures, summary


def test_every_benchmark_ran_and_cleaned_up(tiny_run):
    _, results, failures, _ = tiny_run
    assert failures == {}
    assert sorted(results) == sorted(bench_all.BENCHMARKS)
    assert {name: r.cleanup for name, r in results.items()} == {name: [] for name in results}


@pytest.mark.parametrize("name", sorted(EXPECTED_TABLES))
def test_report_files_hold_the_expected_tables(tiny_run, name):
    out, _, _, _ = tiny_run
    data = json.loads((out / f"{name}.json").read_text())
    md = (out / f"{name}.md").read_text()
    assert data["name"] == name
    assert data["command"].startswith(f"python -m cloneguard.bench.{name} ")
    for key in ("kernel", "cpu_model", "glibc", "date"):
        assert data["host"][key], key
    assert f"`{data['command']}`" in md and "Host: kernel " in md
    assert [t["columns"] for t in data["tables"]] == EXPECTED_TABLES[name]
    assert len(data["tables"][0]["rows"]) == EXPECTED_ROWS[name]
    for table in data["tables"]:
        assert table["rows"], table["title"]
        assert "| " + " | ".join(table["columns"]) + " |" in md
        for row in table["rows"]:
            assert list(row) == table["columns"]
    for goal in data["goals"]:
        assert goal["verdict"] and goal["goal"]
    assert data["summary"] and all(list(r) == SUMMARY_COLUMNS for r in data["summary"])
    assert data["cleanup"] == []


def test_the_scale_benchmark_draws_its_curves(tiny_run):
    out, results, _, _ = tiny_run
    svg = (out / "scale.svg").read_text()
    assert svg.startswith("<svg") and svg.rstrip().endswith("</svg>")
    for title in ("load all (s)", "idle CPU (% of a core)", "PSS (MiB)", "SIGTERM → exit (s)"):
        assert title in svg
    # one point a mode and count in each of the four panels, with its value
    assert svg.count("<circle") == 4 * 3 * 2
    rows = results["scale"].tables[0].rows
    assert all(int(r["processes"]) >= 1 for r in rows)
    per_node = [r for r in rows if r["mode"].startswith("isolated, per-node")]
    # the container, one process a node, and the warm spare (the next node's, made ahead)
    assert [int(r["processes"]) for r in per_node] == [3, 4]


def test_summary_has_a_row_per_measure(tiny_run):
    _, results, _, summary = tiny_run
    text = summary.read_text()
    assert "| " + " | ".join(SUMMARY_COLUMNS) + " |" in text
    for r in results.values():
        for row in r.summary:
            assert f"| {row['benchmark']} | {row['measure']} | {row['mode']} |" in text


def test_a_benchmark_runs_as_its_documented_command(tmp_path):
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "cloneguard.bench.load_latency",
            "--n",
            "1",
            "--modes",
            "thread",
            "--out",
            str(tmp_path),
        ],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert "| mode | n | → LOADED at client: median |" in done.stdout
    assert (tmp_path / "load_latency.md").exists() and (tmp_path / "load_latency.json").exists()


def test_the_discovery_benchmark_probes_from_fresh_processes(tmp_path):
    from cloneguard.bench import discovery

    result = discovery.run(probes=2, nodes=[1], modes=["thread"], settle=0.5, out=tmp_path, quiet=True)
    assert result.cleanup == []
    [trials] = result.raw["trials"].values()
    assert len(trials) == 2
    # A container that answers its services is found by a fresh participant
    # (in the probe's 5 s), and the node is seen no later than its service;
    # the loaded node is seen too.
    for t in trials:
        assert t["service_s"] is not None and t["node_s"] <= t["service_s"]
        assert t["all_nodes_s"] is not None
    assert (tmp_path / "discovery.md").exists()


def test_the_cost_of_protection_keys_is_measured_where_the_cpu_has_them_and_said_why_not_elsewhere(tiny_run):
    out, _, _, _ = tiny_run
    data = json.loads((out / "pkeys_cost.json").read_text())
    assert data["tables"][0]["columns"] == [
        "measure",
        "pairs",
        "A: median",
        "B: median",
        "A ÷ B: median of the pairs' ratios",
        "95% interval",
        "verdict (≤ +5%)",
    ]
    why = pkeys_cost.keys_missing()
    if why is not None:
        assert len(data["tables"]) == 1 and data["tables"][0]["rows"] == [] and data["goals"] == []
        assert [r["verdict"] for r in data["summary"]] == [f"not measured: {why}"]
        assert f"Not measured on this machine: {why}." in (out / "pkeys_cost.md").read_text()
        return
    rows = data["tables"][0]["rows"]
    assert [r["measure"].split(" (")[0] for r in rows] == [
        "LoadNode → LOADED at client",
        "intra-process delivery, 1KiB plain message: publish → callback",
        "intra-process delivery, 1MiB plain message: publish → callback",
        "malloc/free 64 B, node process",
        "malloc/free 4096 B, node process",
    ]
    # the tiny preset's 2 pairs: ratios, but too few for a 95% interval
    assert all(r["pairs"] == "2" and r["A ÷ B: median of the pairs' ratios"].endswith("%") for r in rows)
    assert all(r["verdict (≤ +5%)"].startswith("undecided: 2 pairs give no 95% interval") for r in rows)
    # instructions, single-stepped: A's workers held keys, B's none
    steps = data["tables"][1]["rows"]
    assert [r["measure"] for r in steps] == [f"malloc/free {s} B, node process (instructions)" for s in (64, 4096)]
    assert all(float(r["A: keys on"]) > 0 and float(r["B: keys off"]) > 0 for r in steps)
    instr = data["raw"]["instructions"]
    assert instr["A"]["keys"] and not instr["B"]["keys"]


@pytest.mark.parametrize("endpoints", ["all", "minimal"])
def test_the_participants_benchmark_compares_the_two_shapes_per_count(tmp_path, endpoints):
    from cloneguard.bench import participants

    result = participants.run(counts=[1, 2], settle=0.1, idle=0.2, endpoints=endpoints, out=tmp_path, quiet=True)
    [said] = [note for note in result.notes if note.startswith("Each node's endpoints: ")]
    assert ("no parameter services" in said) == (endpoints == "minimal")
    rows = result.tables[0].rows
    assert [(r["nodes"], r["shape"]) for r in rows] == [
        (str(n), participants.SHAPES[s]) for n in (1, 2) for s in ("one", "per-node")
    ]
    # a participant of its own brings its own Fast DDS threads with it
    assert all(int(rows[i + 1]["threads"]) > int(rows[i]["threads"]) for i in (0, 2))
    assert [r["nodes"] for r in result.tables[1].rows] == ["1", "2"]
    assert (tmp_path / "participants.md").exists()


def test_the_scale_benchmark_runs_under_a_discovery_server_of_its_own(tmp_path):
    """In a process of its own (Fast DDS reads ROS_DISCOVERY_SERVER at a
    process's first participant): the loads it times are discovered
    through its server, which knew of the nodes, and nothing is left."""
    import os

    from cloneguard.bench import discovery_server as ds

    env = {k: v for k, v in os.environ.items() if k != ds.VARIABLE}
    done = subprocess.run(
        [sys.executable, "-m", "cloneguard.bench.scale", "--discovery-server", "--counts", "2",
         "--modes", "isolated-per-node", "thread", "--settle", "0.2", "--idle", "0.2", "--out", str(tmp_path)],
        cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=180,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    data = json.loads((tmp_path / "scale-discovery-server.json").read_text())
    rows = data["tables"][0]["rows"]
    assert [r["nodes"] for r in rows] == ["2", "2"] and not any("failed" in r["load all (s)"] for r in rows)
    [note] = [n for n in data["notes"] if n.startswith("Under a discovery server")]
    # its own node, the benchmark's client, the container and its 2 nodes at least
    assert int(note.rsplit("up to ", 1)[1].split()[0]) >= 5, note
    assert (tmp_path / "scale-discovery-server.svg").exists()


def test_the_idle_cpu_of_fast_dds_is_read_from_the_threads_fast_dds_names(client):
    """The scale table's Fast DDS column counts the threads Fast DDS runs:
    this process's own participant (the test's client) has some."""
    import os

    from cloneguard.bench.scale import dds_thread_ticks
    from cloneguard.harness import procfs

    assert client.list() == []  # the client's participant is up and talking
    me = os.getpid()
    ticks, threads = dds_thread_ticks([me]), procfs.threads(me)
    assert ticks and all(pid == me and threads[tid][0].startswith("dds.") for pid, tid in ticks)
    assert len(ticks) < len(threads)  # not every thread of the process


def test_a_discovery_server_profile_is_the_no_shm_one_made_a_server():
    import xml.etree.ElementTree as ET

    from cloneguard.bench import discovery_server as ds

    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    root = ET.fromstring(ds.server_profile(12345))
    [rtps] = root.findall(".//f:participant[@is_default_profile='true']/f:rtps", ns)
    assert rtps.findtext("f:useBuiltinTransports", namespaces=ns) == "false"  # no shared memory
    assert rtps.findtext("f:prefix", namespaces=ns) == ds.SERVER_PREFIX
    assert rtps.findtext("f:builtin/f:discovery_config/f:discoveryProtocol", namespaces=ns) == "SERVER"
    udp = rtps.find("f:builtin/f:metatrafficUnicastLocatorList/f:locator/f:udpv4", ns)
    assert udp is not None
    assert (udp.findtext("f:address", namespaces=ns), udp.findtext("f:port", namespaces=ns)) == ("127.0.0.1", "12345")
    # the profile's announcement period and library settings stay
    assert rtps.find("f:builtin/f:discovery_config/f:leaseAnnouncement", ns) is not None
    assert root.findtext("f:library_settings/f:intraprocess_delivery", namespaces=ns) == "OFF"


def test_the_memory_watch_benchmark_leaks_only_in_a_memory_cgroup_of_its_own(tmp_path):
    """One trial: a leak in a fresh container in a 512 MiB cgroup, its end
    recorded against the trigger the container logged; where no memory
    cgroup can be made, nothing leaks and the report says why."""
    from cloneguard.bench import memory_watch

    result = memory_watch.run(rates=[1.0], trials=1, limit="512M", delay=1.0, out=tmp_path, quiet=True)
    assert result.cleanup == []
    data = json.loads((tmp_path / "memory_watch.json").read_text())
    assert data["command"].startswith("python -m cloneguard.bench.memory_watch ")
    if data["raw"]["unavailable"]:
        assert [t["rows"] for t in data["tables"]] == [[], []]
        assert data["notes"][0].startswith("Not measured on this machine: no memory cgroup can be made")
        return
    assert [len(t["rows"]) for t in data["tables"]] == [1, 1]
    [trial] = data["raw"]["trials"]["1.0"]
    assert (trial["limit_seen"], trial["trigger"]) == (512 << 20, (512 - 64) << 20)
    assert trial["ended_by_watch"] or trial["oom_kills"] > 0
    assert "| leak asked (GiB/s) | achieved (GiB/s) |" in (tmp_path / "memory_watch.md").read_text()


def test_the_accounting_benchmark_steps_and_times_each_tree_in_its_own_workers(tmp_path):
    """This checkout as both A and B (a real A is a second tree built in
    place): each worker imports its tree's container and preloads its
    guard, the stepper counts instructions per size and allocator and puts
    B's to the guard's lines, the pairs give ratios (1 pair: no interval)."""
    from cloneguard.bench import accounting_cost

    result = accounting_cost.run(
        a=REPO_ROOT, b=REPO_ROOT, n=1, repeat=1, steps=10, pairs_scale=0.01, out=tmp_path, quiet=True
    )
    assert result.cleanup == []
    data = json.loads((tmp_path / "accounting_cost.json").read_text())
    assert data["command"].startswith("python -m cloneguard.bench.accounting_cost --a ")
    assert all(t["counts_memory"] for t in data["raw"]["trees"].values())  # this checkout's guard counts
    measures = [f"{a}, malloc/free {s}" for a in ("glibc", "jemalloc") for s in ("64 B", "4 KiB", "256 KiB")]
    instr, timed, where = data["tables"]
    assert [r["measure"] for r in instr["rows"]] == measures
    assert all(float(r["A"]) > 0 and float(r["B"]) > 0 for r in instr["rows"])
    # B's instructions put to the guard's accounting functions through its debug information
    assert [r["measure"] for r in where["rows"]] == measures
    assert all(float(r["block_within_budget"]) > 0 and float(r["count_got"]) > 0 for r in where["rows"])
    assert [r["measure"] for r in timed["rows"]] == measures
    assert all(r["pairs"] == "1" and r["verdict (≤ +2%)"].startswith("undecided") for r in timed["rows"])


def test_the_scale_benchmark_judges_the_default_profile_at_96_nodes():
    from cloneguard.bench import scale
    from cloneguard.bench.modes import isolated_default, label

    default = isolated_default()
    assert label(default).endswith("(the default)")
    row = {"load_all_ns": 2.5e9, "idle_cpu_pct": 20.0, "pss_kb": 300 * 1024, "exit_ns": None}
    goals = scale.default_goals({default: {96: row}}, 96)
    assert [(g.goal, g.measure, g.met) for g in goals] == [
        ("default profile load all ≤ 3 s", "at 96 nodes", True),
        ("default profile idle CPU ≤ 15% of a core", "at 96 nodes", False),
        ("default profile PSS ≤ 270 MiB", "at 96 nodes", False),
        ("default profile SIGTERM → exit ≤ 2 s", "at 96 nodes", False),  # it did not exit at all
    ]
    assert [g.met for g in scale.default_goals({default: {}}, 96)] == [None] * 4  # not measured
