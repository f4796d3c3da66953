"""Machinery the environments share: argument checks, the done-spec and the random streams.

Every env of this package draws its randomness from ``torch.Generator`` objects it owns
(:class:`RandomStreams`), never from global state, and can give equal consecutive blocks of its
rows (one block per independent trial) a stream each, so that a batched run of many trials
reproduces one-at-a-time runs. The done-spec is the same for every env: ``done``,
``terminated`` and ``truncated`` as bool ``[*batch, 1]``.

Nothing here imports ``torch_api``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torchrl.data import Categorical, Composite

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
    return int(torch.Generator().seed())


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
    """An env's random streams: one ``torch.Generator`` (on the CPU), or one per block of rows.

    :meth:`seed` sets the single stream (``None``: fresh entropy) and drops any block streams;
    :meth:`set_block_seeds` gives each of ``len(seeds)`` equal, consecutive blocks of the
    ``rows`` rows a stream of its own, so block ``b`` draws exactly what a one-block env seeded
    with ``seeds[b]`` would. :meth:`draw` calls a torch sampler with the right generator(s).

    Args:
        rows: the env's number of rows (the batch's element count).
        what: the rows' name in error messages (``"rows"``, ``"arms"``).

    Example:
        >>> streams = RandomStreams(rows=4)
        >>> streams.seed(0)
        >>> streams.set_block_seeds([1, 2])
        >>> a = streams.draw(torch.rand, torch.Size([4]))
        >>> b = torch.rand((2,), generator=torch.Generator().manual_seed(2))
        >>> torch.equal(a[2:], b)
        True
    """

    def __init__(self, *, rows: int, what: str = "rows") -> None:
        self.rows = rows
        self.what = what
        self.rng = torch.Generator()
        self.block_rngs: list[torch.Generator] | None = None

    def seed(self, seed: int | None) -> None:
        """One stream seeded with ``seed`` (``None``: fresh entropy); no block streams."""
        if seed is None:
            seed = fresh_seed()
        self.rng = torch.Generator().manual_seed(int(seed))
        self.block_rngs = None

    def set_block_seeds(self, seeds: Sequence[int]) -> None:
        """One stream per block: ``len(seeds)`` must divide the number of rows."""
        if not seeds or self.rows % len(seeds):
            raise ValueError(
                f"seeds must split the {self.rows} {self.what} into equal blocks, "
                f"got {len(seeds)} seeds"
            )
        self.block_rngs = [torch.Generator().manual_seed(int(seed)) for seed in seeds]

    def draw(
        self, sampler: Callable[..., torch.Tensor], shape: torch.Size, *args, **kwargs
    ) -> torch.Tensor:
        """``sampler(*args, shape, generator=..., **kwargs)`` on the CPU.

        With block streams, the leading dimension of ``shape`` is split into equal blocks, each
        drawn from its own stream and concatenated; otherwise the single stream draws it all.
        """
        if self.block_rngs is None:
            return sampler(*args, shape, generator=self.rng, **kwargs)
        rows = shape[0] // len(self.block_rngs)
        return torch.cat(
            [sampler(*args, (rows, *shape[1:]), generator=rng, **kwargs) for rng in self.block_rngs]
        )
