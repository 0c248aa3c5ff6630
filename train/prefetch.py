"""Training batches built ahead of the step that uses them, in worker processes (torch's ``DataLoader``).

A training draws each batch in two parts: a *plan* (which samples, where, how turned), drawn from the run's
seeded generator, and the *build* of that plan (reading frames from disk, cropping, computing targets).
Here the plans are drawn in the training process, in order, and only the builds go to the workers, so a
run with workers draws exactly the batches of a run without them: the generator is never touched in a
worker, and the loader hands batches back in plan order. What the workers buy is overlap: a streamed
detection set reads a frame per drawn crop (~9 ms at 256 px), 16 a step, which on a GPU would otherwise
bound the step.

Workers are spawned, not forked: a forked child inherits torch's thread pools broken and hangs (as in
``train.data``), so ``build`` must be picklable. A build that fails in a worker raises its own exception
in the training process, not the loader's wrapper of it, so a bad frame reads as it would without workers.
"""

from __future__ import annotations

from typing import Callable, Iterator

from torch.utils.data import DataLoader, Dataset, Sampler

PREFETCH_BATCHES = 2  # batches each worker builds ahead (torch's default prefetch_factor)


class _Failed:
    """A build's exception, carried back from a worker to be raised as itself."""

    def __init__(self, error: BaseException):
        self.error = error


class _Builds(Dataset):
    """A "dataset" whose index is a plan: item ``plan`` is ``build(plan)``, or its failure."""

    def __init__(self, build: Callable):
        self.build = build

    def __getitem__(self, plan):
        try:
            return self.build(plan)
        except Exception as e:  # raised again, as itself, where the batch is used (_raised)
            return _Failed(e)


class _Plans(Sampler):
    """``n`` plans, each ``draw()`` called in the training process when the loader asks for the next one."""

    def __init__(self, draw: Callable, n: int):
        self.draw, self.n = draw, n

    def __len__(self) -> int:
        return self.n

    def __iter__(self):
        return (self.draw() for _ in range(self.n))


def prefetched(draw: Callable, build: Callable, n: int, workers: int = 0, pin_memory: bool = False) -> Iterator:
    """``build(draw())`` ``n`` times, in order. ``workers`` 0: each built here when asked for; else by that
    many worker processes, ``PREFETCH_BATCHES`` each ahead of the training (``pin_memory`` for a GPU's
    copies). ``build`` must be picklable: the workers are spawned."""
    if workers == 0:
        return (build(draw()) for _ in range(n))
    loader = DataLoader(
        _Builds(build),
        sampler=_Plans(draw, n),
        batch_size=None,  # each plan is a whole batch already
        num_workers=workers,
        prefetch_factor=PREFETCH_BATCHES,
        pin_memory=pin_memory,
        multiprocessing_context="spawn",
    )
    return _raised(iter(loader))


def _raised(batches: Iterator) -> Iterator:
    for batch in batches:
        if isinstance(batch, _Failed):
            raise batch.error
        yield batch
