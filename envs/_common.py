"""Machinery the environments share: argument checks, the done-spec and the random streams.

Every env of this package draws its randomness from counter-based streams it owns
(:class:`RandomStreams`, on :mod:`counter_rng`), never from global state, and can give equal
consecutive blocks of its rows (one block per independent trial) a stream each, so that a
batched run of many trials reproduces one-at-a-time runs. The done-spec is the same for every
env: ``done``, ``terminated`` and ``truncated`` as bool ``[*batch, 1]``.

Nothing here imports ``torch_api`` (:mod:`counter_rng` is a floor below both).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torchrl.data import Categorical, Composite

from counter_rng import CounterStreams, fresh_key
from counter_rng.streams import KEY_BITS

__all__ = [
    "RandomStreams",
    "check_positive_int",
    "check_seed",
    "done_spec",
    "fresh_seed",
]


def check_positive_int(value, name: str) -> int:
    """``value`` if it is an int >= 1 (not a bool), else ``ValueError`` naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be a positive int, got {value!r}")
    return value


def check_seed(seed) -> int | None:
    """``seed`` if it is an int or None (not a bool), else ``ValueError``."""
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
        raise ValueError(f"seed must be an int or None, got {seed!r}")
    return seed


def fresh_seed() -> int:
    """A seed from fresh entropy; leaves torch's global generator alone."""
    return fresh_key()


def done_spec(shape: torch.Size, device: torch.device) -> Composite:
    """``done``, ``terminated`` and ``truncated``: bool ``[*shape, 1]`` flags.

    Example:
        >>> spec = done_spec(torch.Size([3]), torch.device("cpu"))
        >>> sorted(spec.keys()), spec["done"].shape
        (['done', 'terminated', 'truncated'], torch.Size([3, 1]))
    """
    flag = Categorical(2, shape=(*shape, 1), dtype=torch.bool, device=device)
    return Composite(
        done=flag.clone(),
        terminated=flag.clone(),
        truncated=flag.clone(),
        shape=shape,
        device=device,
    )


class RandomStreams:
    """An env's random streams: one counter-based stream, or one per block of rows.

    :meth:`seed` sets the single stream (``None``: fresh entropy) and drops any block streams;
    :meth:`set_block_seeds` gives each of ``len(seeds)`` equal, consecutive blocks of the
    ``rows`` rows a stream of its own, so block ``b`` draws exactly what a one-block env seeded
    with ``seeds[b]`` would (:class:`counter_rng.CounterStreams`: every number a pure function
    of the block's key and the draw's counter, all blocks in one computation). The draws are
    made on the CPU, so a seed gives the same numbers whatever the env's device.

    Args:
        rows: the env's number of rows (the batch's element count).
        what: the rows' name in error messages (``"rows"``, ``"arms"``).

    Example:
        >>> streams = RandomStreams(rows=4)
        >>> streams.set_block_seeds([1, 2])
        >>> a = streams.uniform(torch.Size([4]))
        >>> alone = RandomStreams(rows=2)
        >>> alone.seed(2)
        >>> torch.equal(a[2:], alone.uniform(torch.Size([2])))
        True
    """

    def __init__(self, *, rows: int, what: str = "rows") -> None:
        self.rows = rows
        self.what = what
        self.single = CounterStreams(fresh_seed())
        self.blocks: CounterStreams | None = None

    @property
    def current(self) -> CounterStreams:
        """The streams the next whole-batch draw comes from (the blocks' where set)."""
        return self.single if self.blocks is None else self.blocks

    def seed(self, seed: int | None) -> None:
        """One stream keyed by ``seed`` (``None``: fresh entropy); no block streams."""
        self.single = CounterStreams(_key(fresh_seed() if seed is None else seed))
        self.blocks = None

    def set_block_seeds(self, seeds: Sequence[int]) -> None:
        """One stream per block: ``len(seeds)`` must divide the number of rows."""
        keys = torch.as_tensor(seeds, dtype=torch.int64).reshape(-1)
        if not len(keys) or self.rows % len(keys):
            raise ValueError(
                f"seeds must split the {self.rows} {self.what} into equal blocks, "
                f"got {len(keys)} seeds"
            )
        self.blocks = CounterStreams(keys & _KEY_MASK)

    def uniform(self, shape: torch.Size) -> torch.Tensor:
        """float64 uniforms in (0, 1), the leading dim split over the block streams."""
        return self.current.uniform(shape)

    def integers(self, low: int, high: int, shape: torch.Size) -> torch.Tensor:
        """int64 integers in ``[low, high)``, the leading dim split over the block streams."""
        return self.current.integers(low, high, shape)

    def normal(self, shape: torch.Size) -> torch.Tensor:
        """float64 standard normals, the leading dim split over the block streams."""
        return self.current.normal(shape)


_KEY_MASK = (1 << KEY_BITS) - 1


def _key(seed: int) -> int:
    """A stream's key of a seed: the seed itself where it is a 63-bit key, else its low bits."""
    return int(seed) & _KEY_MASK
