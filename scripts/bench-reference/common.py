"""Shared helpers for the PyTorch reference benchmarks (timing, peak RSS, threads, JSON output)."""

import json
import resource
import sys
import time

import torch


def set_threads(threads: int) -> None:
    """`threads` > 0: use that many intra-op threads (0 = PyTorch's default, i.e. all cores)."""
    if threads > 0:
        torch.set_num_threads(threads)
        try:
            torch.set_num_interop_threads(threads)
        except RuntimeError:  # already set (parallel work has started)
            pass


def peak_rss_mib() -> float:
    """Peak resident set size of this process in MiB (Linux ru_maxrss is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def median(xs):
    """Upper median, as the Rust benches (`xs[len/2]` after sorting)."""
    s = sorted(xs)
    return s[len(s) // 2]


def time_ms(fn, runs: int, warmup: int = 1):
    """Call `fn` `warmup` times untimed, then `runs` times; return the list of wall times in ms."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(max(runs, 1)):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return times


def emit(record: dict) -> None:
    """Print one JSON line (the same keys as the Rust bench, plus "impl":"pytorch")."""
    record = dict(record)
    record["impl"] = "pytorch"
    print(json.dumps(record), flush=True)


def log(*args) -> None:
    print(*args, file=sys.stderr, flush=True)
