"""Process memory for the benchmarks (Linux ``/proc/self``): the resident size and its peak, and a
reset of the peak so that one step's own peak can be read."""
from __future__ import annotations


def status_kb(field: str) -> int:
    """A line of /proc/self/status in kB (``VmRSS`` now, ``VmHWM`` the peak); where there is none,
    the process's peak from getrusage (kB on Linux), or 0."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    try:
        import resource
        return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
    except (ImportError, OSError):
        return 0


def reset_peak() -> bool:
    """Reset ``VmHWM`` to the current resident size (Linux ≥ 4.0); False where that is not possible."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False
