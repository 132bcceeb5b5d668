"""Benchmark processes that start together: spawned workers waiting on one barrier."""
from __future__ import annotations


def spawn_on_barrier(target, worker_args: list[tuple], timeout: float, what: str) -> list:
    """Run ``target(*args, barrier, results)`` in one spawned process per entry of ``worker_args``
    (no fork of a process that holds torch threads), all waiting on one barrier before they
    time anything; each puts ("ok", value) or ("error", message) on ``results``. Returns the
    values; raises a RuntimeError naming ``what`` if a process failed."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    barrier, results = ctx.Barrier(len(worker_args)), ctx.Queue()
    workers = [ctx.Process(target=target, args=(*args, barrier, results)) for args in worker_args]
    for w in workers:
        w.start()
    outcomes = [results.get(timeout=timeout) for _ in workers]
    for w in workers:
        w.join()
    errors = [value for status, value in outcomes if status == "error"]
    if errors:
        raise RuntimeError(f"a {what} process failed: {errors[0]}")
    return [value for _, value in outcomes]
