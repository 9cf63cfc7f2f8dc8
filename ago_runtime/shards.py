"""`--shard K/N`: split a dataset's keyframes across N machines with no coordination.

Shard K of N (1 <= K <= N) takes the K-th of N contiguous runs of the keyframes in dataset order (scene
name, then time): indices [floor((K-1) * n / N), floor(K * n / N)) of the n selected keyframes. The runs
cover every keyframe exactly once, differ in size by at most one, and keep neighbouring keyframes
together (pseudo-labels superimpose neighbours). Every machine computes the same split from the same
dataset, so shards need nothing but the option; each writes its own frames, resumably, into its own or
a shared output folder.
"""

from __future__ import annotations

from typing import Sequence

from ago_runtime.errors import AgoInputError


def parse_shard(text: str | None) -> tuple[int, int] | None:
    """'K/N' -> (K, N); None -> None; anything else is one AgoInputError naming --shard."""
    if text is None:
        return None
    try:
        k, n = (int(v) for v in str(text).split("/"))
    except ValueError:
        k, n = 0, 0
    if not (n >= 1 and 1 <= k <= n):
        raise AgoInputError("--shard", f"expected K/N with 1 <= K <= N (e.g. 2/8), got {text!r}")
    return k, n


def shard_indices(indices: Sequence[int], shard: tuple[int, int] | None) -> list[int]:
    """The K-th of N contiguous runs of `indices` (all of them when shard is None)."""
    indices = list(indices)
    if shard is None:
        return indices
    k, n = shard
    total = len(indices)
    return indices[(k - 1) * total // n: k * total // n]
