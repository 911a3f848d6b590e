"""What a span of work cost the process, and how busy the rest of the machine was meanwhile.

The wall seconds of a job depend on what runs beside it: two jobs on two cores each take longer
than one alone, because they share memory bandwidth and caches, and more jobs than cores share the
cores themselves. The process's CPU seconds (user + system, all its threads:
:func:`time.process_time`) count only the time its own threads ran, so they depend much less on the
neighbours; they are the time measure the report compares runs with on a CPU.

A :class:`Usage` holds, for a span:

* ``wall_seconds``: elapsed time;
* ``cpu_seconds``: this process's CPU time (all threads);
* ``threads``: the compute threads the process used (``torch.get_num_threads()``; the numba kernels
  follow it, :mod:`rtsplat.raster.numba_runtime`);
* ``other_busy_core_seconds``: CPU time that *other* processes used meanwhile: the machine's busy
  time (``/proc/stat``: user, nice, system, irq and softirq time summed over all cores) minus this
  process's CPU time, at least 0; None where ``/proc/stat`` cannot be read (not Linux).

and derives ``cpu_share`` = cpu / (wall x threads), the share of its threads' time the process got
to run (below 1: it waited for cores, or its threads waited on each other), and
``other_busy_cores`` = other_busy_core_seconds / wall, the mean number of cores kept busy by other
processes: 1.0 is one other single-threaded job running beside it the whole time. This measures the
neighbours by what they did rather than by what they are: any process counts (other workflow jobs,
other users), a short one for exactly as long as it ran, and it needs no sampling. It counts the
machine as ``/proc/stat`` sees it: in a container that is the host (or virtual machine), whose other
processes compete for the same cores unless the container is pinned to its own; time a hypervisor
gave to other virtual machines (steal) is not counted. It cannot exceed the cores this process left
free: on a machine with more runnable threads than cores it shows the cores full, and ``cpu_share``
below 1 shows that the process waited. The kernel accounts that time in clock ticks
(``SC_CLK_TCK``, usually 1/100 s per core), so a span of a few seconds carries an error of a few
hundredths of a core-second.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

PROC_STAT = "/proc/stat"
# the /proc/stat "cpu" line: user nice system idle iowait irq softirq steal guest guest_nice; guest time
# is already inside user and nice, idle and iowait are not work, steal is other virtual machines' time
BUSY_FIELDS = (0, 1, 2, 5, 6)
STEAL_FIELD = 7


def _cpu_line_seconds(fields: tuple[int, ...], path: str) -> float | None:
    """The sum of ``fields`` of ``path``'s "cpu" line, in seconds (summed over cores); None without it."""
    try:
        with open(path) as f:
            line = f.readline().split()
        ticks = sum(int(line[1 + i]) for i in fields)
    except (OSError, ValueError, IndexError):
        return None
    return ticks / os.sysconf("SC_CLK_TCK")


def machine_busy_seconds(path: str = PROC_STAT) -> float | None:
    """CPU seconds all processes of the machine used since boot (summed over cores), None without
    ``/proc/stat``."""
    return _cpu_line_seconds(BUSY_FIELDS, path)


def machine_steal_seconds(path: str = PROC_STAT) -> float | None:
    """CPU seconds the hypervisor gave to other virtual machines since boot (summed over cores), None
    without ``/proc/stat``."""
    return _cpu_line_seconds((STEAL_FIELD,), path)


def machine_cpus() -> int:
    """The cores of the machine (all of them, not only those this process may run on)."""
    return os.cpu_count() or 1


@dataclass(frozen=True)
class Usage:
    """Wall and CPU seconds of a span, the threads used and the CPU time of other processes meanwhile."""

    wall_seconds: float = 0.0
    cpu_seconds: float = 0.0
    threads: int = 1
    other_busy_core_seconds: float | None = 0.0

    def __add__(self, other: Usage) -> Usage:
        """Two spans together (the threads of the later one, ``other``)."""
        busy = (None if self.other_busy_core_seconds is None or other.other_busy_core_seconds is None
                else self.other_busy_core_seconds + other.other_busy_core_seconds)
        return Usage(self.wall_seconds + other.wall_seconds, self.cpu_seconds + other.cpu_seconds,
                     other.threads, busy)

    @property
    def cpu_share(self) -> float | None:
        """cpu / (wall x threads): 1 when every thread ran the whole time."""
        return self.cpu_seconds / (self.wall_seconds * self.threads) if self.wall_seconds > 0 else None

    @property
    def other_busy_cores(self) -> float | None:
        """The mean number of cores other processes kept busy during the span."""
        if self.other_busy_core_seconds is None or self.wall_seconds <= 0:
            return None
        return self.other_busy_core_seconds / self.wall_seconds

    def to_dict(self) -> dict:
        def rounded(x, digits):
            return None if x is None else round(x, digits)

        return {"wall_seconds": round(self.wall_seconds, 3), "cpu_seconds": round(self.cpu_seconds, 3),
                "threads": self.threads, "cpu_share": rounded(self.cpu_share, 3),
                "other_busy_core_seconds": rounded(self.other_busy_core_seconds, 2),
                "other_busy_cores": rounded(self.other_busy_cores, 3), "cpus": machine_cpus()}

    @classmethod
    def from_dict(cls, data: dict) -> Usage:
        return cls(float(data["wall_seconds"]), float(data["cpu_seconds"]), int(data["threads"]),
                   None if data.get("other_busy_core_seconds") is None else float(data["other_busy_core_seconds"]))


class UsageClock:
    """Measures a :class:`Usage` from its creation (or :meth:`restart`) to :meth:`read`."""

    def __init__(self, threads: int | None = None):
        self.threads = threads
        self.restart()

    def restart(self) -> None:
        self._wall, self._cpu, self._busy = time.perf_counter(), time.process_time(), machine_busy_seconds()

    def read(self) -> Usage:
        """The usage since the start (the clock keeps running)."""
        wall, cpu, busy = time.perf_counter() - self._wall, time.process_time() - self._cpu, machine_busy_seconds()
        other = None if busy is None or self._busy is None else max(0.0, busy - self._busy - cpu)
        return Usage(wall, cpu, self.threads if self.threads is not None else compute_threads(), other)


def compute_threads() -> int:
    """The threads the compute kernels use: torch's intra-op threads, which the numba kernels follow."""
    import torch

    return torch.get_num_threads()
