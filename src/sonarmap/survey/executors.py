"""Executors of survey chunks: serial, a warm local process pool, dask.distributed."""

from __future__ import annotations

import contextlib
import functools
import os
import queue
import time
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from sonarmap.errors import SonarmapError
from sonarmap.ping import Ping
from sonarmap.survey.plan import ChunkSpec, PingFunction, _default_ping_function, _resolve_config, _tail_parts

__all__ = ["warm_pipeline_once"]


# ============================================================================ executors
def _concat_parts(parts: Sequence[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """One chunk's products from its parts' (in ping order)."""
    return {name: np.concatenate([p[name] for p in parts], axis=0) for name in parts[0]}


def _pool_initializer(parent_pid: int, ping_function: PingFunction | None, counter: Any = None,
                      workers: int = 1) -> None:  # pragma: no cover - runs in workers
    import signal
    import threading

    # Ctrl-C is handled by the parent, which stops the pool; workers must not die half-way.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # warnings raised while a worker reads its chunk print as one line, as the CLI prints its own;
    # a file's cut-off last frame is told by the parent, which opened every file to plan the run
    from sonarmap.errors import show_warning_one_line
    from sonarmap.io import PartialFrameWarning

    warnings.showwarning = show_warning_one_line
    warnings.filterwarnings("ignore", message=r".*; skipped$", category=PartialFrameWarning)

    def watch() -> None:
        # A parent killed with SIGKILL cannot stop its pool: leave instead of idling forever.
        while True:
            time.sleep(0.5)
            try:
                os.kill(parent_pid, 0)
            except ProcessLookupError:
                os._exit(1)
            except OSError:
                pass

    threading.Thread(target=watch, name="sonarmap-parent-watch", daemon=True).start()
    # every worker starts warm, before it takes its first chunk; on a cold numba cache the
    # workers first share the default pipeline's compilation (sonarmap._precompile)
    if ping_function is None:
        _precompile_share(counter, workers)
        warm_pipeline_once()
    else:
        _warm(ping_function)


def _run_serial(chunks, task):  # type: ignore[no-untyped-def]
    for c in chunks:
        yield c, task(c)


def _warm(ping_function: PingFunction | None) -> bool:
    """Run ``ping_function`` (default: the default pipeline) once on a synthetic DIDSON ping, so
    the numba kernels are loaded and the lazy imports done; ``True`` if it worked (a failure is
    swallowed: warming is an optimisation, never a requirement)."""
    try:
        from sonarmap.geometry import preset

        g = preset("didson-hf")
        img = np.random.default_rng(0).random(g.shape, dtype=np.float32) * 0.3
        img[g.n_bins // 2 : g.n_bins // 2 + 8] = 0.9
        fn = ping_function or _default_ping_function()
        fn(Ping(img, g), _resolve_config(None) if ping_function is None else None)
    except Exception:  # noqa: BLE001 - warming must never fail a run
        return False
    return True


def _precompile_share(counter: Any, workers: int) -> int | None:
    """On a cold numba cache, share the default pipeline's compilation with the pool's other
    workers (:func:`sonarmap._precompile.compile_shared` on ``counter``, the pool's shared
    ``multiprocessing.Value``, starting at -1); the number of kernels this worker compiled, None
    when the queue was not used.  Never raises: precompiling is an optimisation."""
    if counter is None or workers < 2:
        return None
    try:
        from sonarmap._precompile import compile_shared, load_signatures

        return compile_shared(counter, load_signatures())
    except Exception:  # noqa: BLE001 - never fail a run for it
        return None


@functools.cache
def warm_pipeline_once() -> bool:
    """Warm this process's default per-ping pipeline (first call only; the pool's workers do it
    when they start).  ``True`` if the warm-up run worked."""
    return _warm(None)


def _is_warm() -> bool:  # pragma: no cover - runs in workers
    """Whether this process has warmed the default pipeline (the pool's workers: at start)."""
    return warm_pipeline_once.cache_info().currsize > 0


_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")

class _ProcessPool:
    """Local worker processes, started warm.

    Workers are spawned (a fresh interpreter: safe with the parent's threads, unlike fork) with
    their numerical libraries on one thread each, since parallelism is across processes; each
    runs the pipeline once before its first chunk (:func:`warm_pipeline_once`) and leaves if the
    parent dies.
    """

    def __init__(self, workers: int, ping_function: PingFunction | None) -> None:
        import concurrent.futures as cf
        import multiprocessing

        self.workers = workers
        # Finished futures arrive here (their done-callbacks): the parent blocks on this queue,
        # not on concurrent.futures.wait, which takes every future's lock at once - a Ctrl-C
        # landing between those acquisitions leaves a lock held, and the executor's own thread
        # then deadlocks the interpreter's exit on it.
        self._done: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._others = {p.pid for p in multiprocessing.active_children()}
        # A spawned worker reads these when it imports numpy; they stay set while the pool runs,
        # since the executor may start a worker at any submit (restored by close()).
        self._saved_env = {v: os.environ.get(v) for v in _THREAD_VARS}
        os.environ.update({v: "1" for v, old in self._saved_env.items() if old is None})
        ctx = multiprocessing.get_context("spawn")
        # the queue of a cold cache's shared compilation (_precompile_share; -1: not decided yet)
        counter = ctx.Value("i", -1)
        self.ex = cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_pool_initializer,
                                         initargs=(os.getpid(), ping_function, counter, workers))
        for _ in range(workers):  # start the workers now: they warm up while the parent plans
            self.ex.submit(os.getpid)

    def start(self, chunks: Sequence[ChunkSpec], part_task: Callable[[ChunkSpec], Any],
              task: Callable[[ChunkSpec], Any] | None = None) -> None:
        """Plan the jobs of ``chunks`` and submit the first ones now, with ``task``.

        Without ``task``, whole chunks also run ``part_task``, which returns the products instead
        of storing them: the workers can start before the store exists - the first chunks of a
        new survey run while this process creates the store (their products are stored here).
        """
        jobs: list[tuple[ChunkSpec, ChunkSpec | None]] = [(c, None) for c in chunks]
        if self.workers > 1:
            jobs = _tail_parts(list(chunks), self.workers)
        self._chunks = [c.index for c in chunks]
        self._part_task = part_task
        self._pending = jobs[::-1]
        self._inflight: dict[Any, tuple[ChunkSpec, ChunkSpec | None]] = {}
        self._fill(task or part_task)

    def _fill(self, task: Callable[[ChunkSpec], Any]) -> None:
        while self._pending and len(self._inflight) < 2 * self.workers:
            c, part = self._pending.pop()
            fut = self.ex.submit(task, c) if part is None else self.ex.submit(self._part_task, part)
            self._inflight[fut] = (c, part)
            fut.add_done_callback(self._done.put)

    def run(self, chunks: Sequence[ChunkSpec], task: Callable[[ChunkSpec], Any],
            part_task: Callable[[ChunkSpec], Any]) -> Iterator[tuple[ChunkSpec, Any]]:
        """Yield ``(chunk, result)`` as chunks finish (at most 2 per worker in flight).

        Whole chunks run ``task``.  With several workers the last chunks are cut into parts run
        with ``part_task`` (returns the products of the part), so the workers finish together
        instead of one worker running the last whole chunk alone (:func:`_tail_parts`); a split
        chunk is yielded once all its parts are back, with its parts' products concatenated.
        Continues what :meth:`start` began, if it was called with the same chunks.
        """
        if getattr(self, "_chunks", None) != [c.index for c in chunks]:
            if getattr(self, "_inflight", None):
                raise SonarmapError("internal: the pool was started on other chunks")
            self.start(chunks, part_task, task)
        pending, inflight = self._pending, self._inflight
        n_parts: dict[int, int] = {}
        for c, part in [*pending, *inflight.values()]:
            if part is not None:
                n_parts[c.index] = n_parts.get(c.index, 0) + 1
        got: dict[int, list[tuple[int, Any]]] = {}
        while pending or inflight:
            self._fill(task)
            done = {self._done.get()}
            with contextlib.suppress(queue.Empty):
                while True:
                    done.add(self._done.get_nowait())
            for fut in sorted(done, key=lambda f: (inflight[f][0].index, inflight[f][1] is not None)):
                c, part = inflight.pop(fut)
                if part is None:
                    yield c, fut.result()
                    continue
                parts = got.setdefault(c.index, [])
                parts.append((part.start, fut.result()))
                if len(parts) == n_parts[c.index]:
                    del got[c.index]
                    yield c, _concat_parts([data for _, data in sorted(parts, key=lambda p: p[0])])

    def close(self, ok: bool) -> None:
        """Shut down; on failure or interrupt, terminate the workers at once."""
        import multiprocessing

        try:
            if ok:
                self.ex.shutdown(wait=True)
                return
            # the pool's workers: this process's children that were not there before the pool
            procs = [p for p in multiprocessing.active_children() if p.pid not in self._others]
            self.ex.shutdown(wait=False, cancel_futures=True)
            for p in procs:
                with contextlib.suppress(Exception):
                    p.terminate()
            for p in procs:
                with contextlib.suppress(Exception):
                    p.join(timeout=5)
        finally:
            for v, old in self._saved_env.items():
                if old is None:
                    os.environ.pop(v, None)


def _run_dask(chunks, task, client):  # type: ignore[no-untyped-def]
    """Yield ``(chunk, products)`` from a dask.distributed cluster (bounded number in flight)."""
    import uuid

    from distributed import as_completed

    run_id = uuid.uuid4().hex[:12]
    nthreads = max(1, sum(client.nthreads().values()))
    pending = list(chunks)[::-1]
    futures: dict[Any, ChunkSpec] = {}
    ac = as_completed()

    def submit() -> None:
        c = pending.pop()
        f = client.submit(task, c, key=f"sonarmap-chunk-{c.index}-{run_id}", pure=False, retries=3)
        futures[f] = c
        ac.add(f)

    try:
        while pending and len(futures) < 2 * nthreads + 1:
            submit()
        for f in ac:
            c = futures.pop(f)
            result = f.result()
            f.release()
            if pending:
                submit()
            yield c, result
    finally:
        if futures:
            client.cancel(list(futures))
