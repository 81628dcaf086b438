"""The next training batch, built in a background thread while the current step trains.

A batch is a pure function of the global step (:func:`seqshape.data.windows.batch_for_step`),
so building it early changes nothing but the time it takes: reading and decompressing track
files (``np.load``/zlib release the GIL) and cutting windows overlap the network's step. One
worker thread, one batch ahead; the dataset is only touched by one thread at a time (a
request waits for the batch in flight before it builds another).
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor

import torch

from seqshape.data.windows import WindowDataset, batch_for_step


class BatchPrefetcher:
    """Batches of ``windows`` for consecutive global steps, one built ahead.

    ``get(step)`` returns :func:`~seqshape.data.windows.batch_for_step` of ``step`` and starts
    building ``step + 1``. A request for another step than the one prepared waits for the
    prepared one, discards it and builds the requested batch in the calling thread. An error
    while building (e.g. an unreadable track file) is raised by the ``get`` of that step, as
    without prefetching. ``enabled=False`` builds every batch in the calling thread. Use as a
    context manager, or call :meth:`close`.
    """

    def __init__(self, windows: WindowDataset, batch_size: int, rank: int = 0, world: int = 1,
                 enabled: bool = True):
        self.windows, self.batch_size, self.rank, self.world = windows, batch_size, rank, world
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="seqshape-batches") \
            if enabled else None
        self._pending: tuple[int, Future] | None = None

    def _build(self, step: int) -> dict[str, torch.Tensor]:
        return batch_for_step(self.windows, step, self.batch_size, self.rank, self.world)

    def get(self, step: int) -> dict[str, torch.Tensor]:
        """The batch of global ``step`` (and the next one started in the background)."""
        batch = None
        if self._pending is not None:
            pending_step, future = self._pending
            self._pending = None
            if pending_step == step:
                batch = future.result()
            else:
                future.exception()  # wait: the worker must be done with the dataset
        if batch is None:
            batch = self._build(step)
        if self._pool is not None:
            self._pending = (step + 1, self._pool.submit(self._build, step + 1))
        return batch

    def close(self) -> None:
        """Wait for the batch in flight (its result or error is dropped), stop the thread."""
        if self._pending is not None:
            self._pending[1].exception()
            self._pending = None
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def __enter__(self) -> BatchPrefetcher:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
