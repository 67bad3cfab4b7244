"""dct preflight's checks of this computer: clock sync, CPUs and governors, real-time
scheduling, disk; the machine's answers are faked."""
from __future__ import annotations

from pathlib import Path

from runtime.app.preflight.computer import check_clock_sync, check_cpus, check_disk, check_realtime
from runtime.loop.realtime_setup import RealtimeConfig, RealtimeGrant
from tests.runtime.app.preflight.helpers import by_name


def test_clock_sync_paths():
    def runner(answers):
        return lambda argv: answers.get(argv[0])

    assert check_clock_sync(runner({"timedatectl": "yes\n"})).status == "PASS"
    c = check_clock_sync(runner({"timedatectl": "no\n"}))
    assert c.status == "WARN" and "not synchronized" in c.message and "set-ntp" in c.text()
    assert check_clock_sync(runner({"chronyc": "Leap status     : Normal\n"})).status == "PASS"
    assert check_clock_sync(runner({"chronyc": "Leap status     : Not synchronised\n"})).status == "WARN"
    c = check_clock_sync(runner({}))
    assert c.status == "WARN" and c.ok


def fake_governors(root: Path, governors) -> Path:
    for i, g in enumerate(governors):
        d = root / "sys" / "devices" / "system" / "cpu" / f"cpu{i}" / "cpufreq"
        d.mkdir(parents=True)
        (d / "scaling_governor").write_text(g + "\n")
    return root


def test_cpu_count_and_governor(tmp_path):
    fast = fake_governors(tmp_path / "a", ["performance"] * 4)
    c = by_name(check_cpus(RealtimeConfig(cpus=[1]), getaffinity=lambda p: {0, 1, 2, 3}, sys_root=fast))
    assert c["cpus"].status == "PASS" and "pinned to [1]" in c["cpus"].message
    assert c["cpu_governor"].status == "PASS"
    slow = fake_governors(tmp_path / "b", ["powersave", "performance"])
    c = by_name(check_cpus(RealtimeConfig(), getaffinity=lambda p: {0}, sys_root=slow))
    assert c["cpus"].status == "FAIL" and "1 usable CPU" in c["cpus"].message
    assert c["cpu_governor"].status == "WARN" and "cpu0=powersave" in c["cpu_governor"].message
    c = by_name(check_cpus(RealtimeConfig(cpus=[5]), getaffinity=lambda p: {0, 1}, sys_root=tmp_path / "none"))
    assert c["cpus"].status == "FAIL" and "[5]" in c["cpus"].message
    assert c["cpu_governor"].status == "WARN" and "no cpufreq" in c["cpu_governor"].message


def grant(fifo: bool, affinity: bool) -> RealtimeGrant:
    return RealtimeGrant(fifo_requested=True, fifo_priority=50, fifo_granted=fifo,
                         fifo_reason=None if fifo else "Operation not permitted [EPERM]; RLIMIT_RTPRIO is 0; fix: x",
                         cpus_requested=(0, 1), affinity_granted=affinity,
                         affinity_reason=None if affinity else "Invalid argument [EINVAL]; fix: y", cpus_now=(0, 1))


def test_sched_fifo_and_affinity_allowed_or_refused():
    c = by_name(check_realtime(RealtimeConfig(), request=lambda *a, **k: grant(True, True)))
    assert c["sched_fifo"].status == "PASS" and c["cpu_affinity"].status == "PASS"
    c = by_name(check_realtime(RealtimeConfig(cpus=[1]), request=lambda *a, **k: grant(False, False)))
    assert c["sched_fifo"].status == "WARN" and "the loop will run SCHED_OTHER" in c["sched_fifo"].message
    assert "EPERM" in c["sched_fifo"].message and "LimitRTPRIO=50" in c["sched_fifo"].text()
    assert c["cpu_affinity"].status == "WARN" and "will not be pinned" in c["cpu_affinity"].message


def test_sched_fifo_real_request_never_changes_this_thread():
    import os

    before = os.sched_getscheduler(0), os.sched_getaffinity(0)
    checks = check_realtime(RealtimeConfig())
    assert {c.name for c in checks} == {"sched_fifo", "cpu_affinity"} and all(c.ok for c in checks)
    assert (os.sched_getscheduler(0), os.sched_getaffinity(0)) == before


def test_disk_paths(tmp_path):
    class Usage:
        def __init__(self, gb):
            self.free = gb * 1e9

    assert check_disk(tmp_path, 1.0, disk_usage=lambda p: Usage(100)).status == "PASS"
    c = check_disk(tmp_path, 1.0, disk_usage=lambda p: Usage(2))
    assert c.status == "WARN" and "2.0 GB free" in c.message
    c = check_disk(tmp_path / "logs" / "new", 1.0, disk_usage=lambda p: Usage(0.5))
    assert c.status == "FAIL" and "need 1 GB" in c.message
