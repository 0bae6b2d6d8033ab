"""Prefix sums by blocks: lists and offsets a GPU builds in parallel, in the order one thread would.

A loop that appends to a list in order (a counting sort's scatter, a list of awake tiles) runs on one thread; on a
GPU that is one thread of thousands. Cut the items into blocks instead: count each block's share in parallel,
add the blocks' totals up in order (add_up_blocks, on one thread: blocks are few), then let each block write its
part from its start. Integer sums, so the result is the same list whatever runs in parallel.
"""
import taichi as ti


@ti.func
def add_up_blocks(totals: ti.template(), blocks):
    """totals[b + 1] holds block b's total (an i32 field, scalar or vector) for b < blocks: in place, in block order,
    totals[b] becomes the sum of the blocks before b (totals[0] = 0, totals[blocks] the whole sum)."""
    ti.loop_config(serialize=True)
    for b in range(blocks + 1):
        if b == 0:
            totals[0] = totals[0] * 0
        else:
            totals[b] += totals[b - 1]
