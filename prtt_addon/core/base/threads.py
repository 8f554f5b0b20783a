"""Running chunks of work on a thread pool, with cancellation: the local executor (the Dask one is core/bake/executors/dask_cluster)."""
from __future__ import annotations

import concurrent.futures as cf


def run_chunks(fn, items, threads: int, on_result=None, cancel=None) -> None:
    """Call ``fn(item)`` for every item on ``threads`` threads.

    ``on_result(result)`` runs in the calling thread as chunks finish (progress).
    If any chunk raises (transfer.Cancelled included), ``cancel`` is set so the
    others stop at their next check, pending chunks are dropped, and the
    exception propagates once the running ones have returned.
    """
    with cf.ThreadPoolExecutor(max_workers=max(1, threads)) as ex:
        futures = [ex.submit(fn, item) for item in items]
        try:
            for f in cf.as_completed(futures):
                res = f.result()
                if on_result is not None:
                    on_result(res)
        except BaseException:
            if cancel is not None:
                cancel.set()
            for f in futures:
                f.cancel()
            raise


def map_items(executor, fn, items) -> list:
    """[fn(item) for item in items], on ``executor``'s threads (concurrent.futures)
    when there is one and more than one item, in the items' order."""
    items = list(items)
    return list(executor.map(fn, items)) if executor is not None and len(items) > 1 else [fn(i) for i in items]
