"""rtsplat.usage: a span's CPU seconds, and the CPU time other processes used meanwhile."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rtsplat.usage import PROC_STAT, Usage, UsageClock, machine_busy_seconds, machine_steal_seconds

needs_proc_stat = pytest.mark.skipif(not Path(PROC_STAT).is_file(), reason="no /proc/stat (not Linux)")

# a neighbour: a process that keeps one core busy for the given wall seconds
SPIN = "import sys, time\nend = time.perf_counter() + float(sys.argv[1])\nwhile time.perf_counter() < end: pass\n"
# clock ticks (1/100 s per core) make the machine's and the process's counts differ by a few hundredths
TICK_TOLERANCE = 0.1


def children_cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def test_own_cpu_seconds_count_work_and_not_sleep():
    clock = UsageClock(threads=1)
    time.sleep(0.3)
    asleep = clock.read()
    clock.restart()
    end = time.perf_counter() + 0.3
    while time.perf_counter() < end:
        pass
    busy = clock.read()
    assert asleep.wall_seconds >= 0.3 and asleep.cpu_seconds < 0.1
    assert 0 < busy.cpu_seconds <= busy.wall_seconds * busy.threads + 0.01
    assert busy.cpu_share > asleep.cpu_share


@needs_proc_stat
def test_a_neighbour_that_ran_inside_the_span_is_counted_as_other_busy_time():
    before = children_cpu_seconds()
    clock = UsageClock(threads=1)
    subprocess.run([sys.executable, "-c", SPIN, "0.8"], check=True)
    usage = clock.read()
    neighbour = children_cpu_seconds() - before  # all of it inside the span: it started and ended there
    assert neighbour > 0.2  # it did run (the test means something)
    # every CPU second the neighbour used is in the machine's busy time, and not in this process's own
    assert usage.other_busy_core_seconds >= neighbour - TICK_TOLERANCE
    assert usage.cpu_seconds < neighbour
    assert usage.other_busy_cores == pytest.approx(usage.other_busy_core_seconds / usage.wall_seconds)


def test_machine_busy_time_grows_and_is_none_without_proc_stat(tmp_path):
    assert machine_busy_seconds(str(tmp_path / "missing")) is None
    if Path(PROC_STAT).is_file():
        first = machine_busy_seconds()
        end = time.perf_counter() + 0.2
        while time.perf_counter() < end:
            pass
        assert machine_busy_seconds() >= first + 0.2 - TICK_TOLERANCE


def test_busy_and_steal_time_are_read_from_their_fields_of_the_cpu_line(tmp_path):
    """/proc/stat's "cpu" line: user nice system idle iowait irq softirq steal guest guest_nice (ticks)."""
    stat = tmp_path / "stat"
    stat.write_text("cpu  100 20 30 4000 50 6 7 80 9 10\ncpu0 1 2 3 4 5 6 7 8 9 10\n")
    tick = os.sysconf("SC_CLK_TCK")
    assert machine_busy_seconds(str(stat)) == pytest.approx((100 + 20 + 30 + 6 + 7) / tick)
    assert machine_steal_seconds(str(stat)) == pytest.approx(80 / tick)
    assert machine_steal_seconds(str(tmp_path / "missing")) is None


def test_spans_add_up_and_an_unknown_part_makes_the_sum_unknown():
    a, b = Usage(2.0, 1.5, 1, 0.5), Usage(1.0, 0.5, 2, 1.0)
    total = a + b
    assert (total.wall_seconds, total.cpu_seconds, total.threads, total.other_busy_core_seconds) == (3.0, 2.0, 2, 1.5)
    assert (a + Usage(1.0, 0.5, 1, None)).other_busy_core_seconds is None
    assert Usage.from_dict(total.to_dict()) == total
