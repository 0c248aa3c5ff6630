"""How the host splits a sweep into worker units (crater_synth.dataset.dispatch), without rendering."""

from __future__ import annotations

import pytest

from crater_synth.dataset.dispatch import WORKER_STARTUP_RENDERS, blocks_per_crater, makespan, split_contiguous


def _units(sizes, blocks):
    return [len(b) for n, k in zip(sizes, blocks) for b in split_contiguous(list(range(n)), k) if n]


@pytest.mark.parametrize(
    "sizes, workers, expected",
    [
        ([22500, 22500, 22500], 2, [2, 2, 2]),  # the paper sweep: 6 equal units, no crater rendered alone
        ([1440, 1440, 1440], 2, [2, 2, 2]),  # the 60 x 24 grid
        ([288, 288, 288], 2, [2, 2, 2]),  # sweep=demo: 6 units beat 3 (one rendered alone)
        ([4, 4, 4], 2, [1, 1, 1]),  # the tests' tiny sweeps: a start-up costs more than the imbalance
        ([22500], 2, [2]),  # one crater: one block per worker
        ([22500, 22500], 2, [1, 1]),
        ([100, 0, 5], 2, [2, 0, 1]),  # a crater with nothing left to render gets no worker
        ([22500, 22500, 22500], 1, [1, 1, 1]),
    ],
)
def test_blocks_per_crater(sizes, workers, expected):
    assert blocks_per_crater(sizes, workers) == expected


def test_balanced_split_finishes_sooner_than_one_block_per_crater():
    sizes, workers = [22500] * 3, 2
    one_each = makespan(_units(sizes, [1, 1, 1]), workers)
    balanced = makespan(_units(sizes, blocks_per_crater(sizes, workers)), workers)
    ideal = sum(sizes) / workers
    assert balanced < 0.8 * one_each
    assert balanced <= 1.05 * ideal + 3 * WORKER_STARTUP_RENDERS


def test_every_render_is_in_exactly_one_unit():
    sizes = [1000, 37, 5000, 1]
    for workers in (1, 2, 3, 8):
        blocks = blocks_per_crater(sizes, workers)
        assert all(1 <= b <= n for b, n in zip(blocks, sizes))
        assert sum(_units(sizes, blocks)) == sum(sizes)


def test_refined_blocks_split_a_shared_patch_only_when_it_pays():
    """Navigation frames on shared patches (start-up ~10 frames): 3 patches of ~20 frames on 2 workers
    finish sooner with one split (taken largest first); a handful of small patches stay whole."""
    sizes, startup = [21, 22, 21], 10
    refined = blocks_per_crater(sizes, 2, startup, refine=True)
    assert sum(refined) == 4
    lpt = sorted(_units(sizes, refined), reverse=True)
    assert makespan(lpt, 2, startup) < 0.9 * makespan(_units(sizes, blocks_per_crater(sizes, 2, startup)), 2, startup)
    assert blocks_per_crater([3, 2, 2, 2, 3], 2, startup, refine=True) == [1] * 5
    assert blocks_per_crater([64], 2, startup, refine=True) == [2]
    assert blocks_per_crater([64], 1, startup, refine=True) == [1]
    for workers in (1, 2, 3):
        blocks = blocks_per_crater([40, 1, 30, 0, 50], workers, startup, refine=True)
        assert all(1 <= b <= n for b, n in zip(blocks, [40, 1, 30, 0, 50]) if n) and blocks[3] == 0
        assert sum(_units([40, 1, 30, 0, 50], blocks)) == 121
