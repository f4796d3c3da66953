"""Random streams whose every number is a pure function of (key, counter): :class:`CounterStreams`.

A :class:`CounterStreams` holds S keys, one per stream. Row blocks of a draw belong to streams:
the leading dimension of a draw's shape is split into S equal, consecutive blocks, block s
drawn from stream s. The numbers of stream s in the c-th draw (``calls`` counts the draws made
so far) are the 32-bit words 0, 1, … of

    Philox4x32-10(key = keys[s], counter = (j, 0, c mod 2**32, c >> 32)),  j = 0, 1, …

word i being lane ``i % 4`` of counter ``j = i // 4``. Nothing else enters: not the other
streams, not the device, not how many streams share the draw. So a batch of T trials draws, for
each trial, exactly what that trial alone would, in one vectorised computation without a loop
over trials; and trials split into chunks, worker processes or Ray tasks draw the same numbers.

Conversions of a word w (exact in float64, identical on every device):
- uniform: ``(w + 0.5) / 2**32``, in the open interval (0, 1), resolution 2**-32;
- integers in ``[low, high)``: ``low + (w · (high - low)) >> 32`` (Lemire's multiply-shift;
  its bias is below ``(high - low) / 2**32``);
- normal: Box-Muller of consecutive pairs of uniforms ``(u1, u2)``: ``sqrt(-2 ln u1)`` times
  ``cos(2π u2)`` and ``sin(2π u2)``, the numbers in that order.

Keys are 63-bit non-negative ints. :func:`derive_keys` makes new keys from a key and up to three
integers (e.g. trial, iteration, role) with the same Philox function, vectorised over keys.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import torch

from counter_rng.philox import MASK32, _rounds, key_schedule, philox4x32_int

__all__ = ["CounterStreams", "KEY_BITS", "derive_key", "derive_keys", "fresh_key"]

KEY_BITS = 63  # keys fit a signed 64-bit integer (SQLite, JSON, torch.int64)
AHEAD_WORDS = 1 << 17  # at most this many words of draws computed ahead of their use
_DERIVE = 0x6B657973  # the counter's last word when keys are derived ("keys"), never a draw's
_TWO_PI = 2.0 * math.pi


def fresh_key() -> int:
    """A key from fresh entropy (the operating system's), leaving torch's generators alone."""
    return int.from_bytes(os.urandom(8), "little") >> (64 - KEY_BITS)


def _key_words(key: int) -> tuple[int, int]:
    key = int(key) % (1 << 64)
    return key & MASK32, key >> 32


def derive_key(key: int, a: int = 0, b: int = 0, c: int = 0) -> int:
    """The key derived from ``key`` and the integers ``a, b, c`` (each < 2**32): the first two
    words of ``Philox4x32-10(key, counter = (a, b, c, 0x6B657973))`` as a 63-bit int.

    Example:
        >>> derive_key(0, 1, 2) == derive_key(0, 1, 2) != derive_key(0, 2, 1)
        True
    """
    w0, w1, _, _ = philox4x32_int((a, b, c, _DERIVE), _key_words(key))
    return (w0 | (w1 << 32)) >> (64 - KEY_BITS)


def derive_keys(keys, a=0, b=0, c=0) -> torch.Tensor:
    """:func:`derive_key` of many keys at once: ``keys [S]`` (ints or int64) and integers or
    int64 tensors ``a, b, c`` broadcast against them -> int64 ``[S]``, in one computation.

    Example:
        >>> keys = derive_keys(torch.tensor([5, 6]), torch.arange(2), 7)
        >>> keys.tolist() == [derive_key(5, 0, 7), derive_key(6, 1, 7)]
        True
    """
    keys = torch.as_tensor(keys, dtype=torch.int64)
    words = [torch.as_tensor(w, dtype=torch.int64, device=keys.device) for w in (a, b, c)]
    shape = torch.broadcast_shapes(keys.shape, *(w.shape for w in words))
    c0, c1, c2 = (w.expand(shape) & MASK32 for w in words)
    c3 = torch.full(shape, _DERIVE, dtype=torch.int64, device=keys.device)
    schedule = key_schedule(keys & MASK32, (keys >> 32) & MASK32).expand(-1, 2, *shape)
    out = _rounds(torch.stack([c2, c0]), torch.stack([c1, c3]), schedule)
    return (out[0] | (out[1] << 32)) >> (64 - KEY_BITS) & ((1 << KEY_BITS) - 1)


class CounterStreams:
    """S random streams, stream s keyed by ``keys[s]`` (see the module for the exact numbers).

    Args:
        keys: one key (an int: one stream) or S keys (ints or an int64 tensor).
        calls: the draws already made (a stream continued elsewhere; normally 0).

    Example:
        >>> both = CounterStreams([11, 22])
        >>> alone = CounterStreams(22)
        >>> x, y = both.uniform((6, 2)), alone.uniform((3, 2))  # stream 1 gets rows 3-5
        >>> torch.equal(x[3:], y), both.calls
        (True, 1)
        >>> CounterStreams(5).integers(1, 11, (4,)).tolist()  # a draw is a pure function
        [8, 1, 10, 10]
    """

    def __init__(self, keys, *, calls: int = 0) -> None:
        keys = torch.as_tensor(keys, dtype=torch.int64).reshape(-1).cpu()
        if not len(keys):
            raise ValueError("CounterStreams needs at least one key")
        if (keys < 0).any():
            raise ValueError(f"keys must be non-negative 63-bit ints, got {keys.min().item()}")
        self.keys = keys
        self.calls = int(calls)
        self._schedules: dict[torch.device, torch.Tensor] = {}
        # draws computed ahead: (shape, device, first call, words [k, S, per stream])
        self._ahead: tuple | None = None
        self._run = 1  # how many draws of the same shape to compute at once next time

    def __len__(self) -> int:
        return len(self.keys)

    def __repr__(self) -> str:
        return f"CounterStreams({len(self)} streams, calls={self.calls})"

    def __getstate__(self) -> dict:  # what was computed ahead is not part of the state
        return {"keys": self.keys, "calls": self.calls}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["keys"], calls=state["calls"])

    def select(self, index: slice | Sequence[int]) -> CounterStreams:
        """The streams ``keys[index]`` alone, at the same position (e.g. a chunk's trials)."""
        return CounterStreams(self.keys[index], calls=self.calls)

    def restart(self) -> CounterStreams:
        """The same streams from their first draw."""
        return CounterStreams(self.keys)

    def _schedule(self, device: torch.device) -> torch.Tensor:
        if device not in self._schedules:  # [rounds, 2, S, 1]
            keys = self.keys.to(device).unsqueeze(-1)
            self._schedules[device] = key_schedule(keys & MASK32, (keys >> 32) & MASK32)
        return self._schedules[device]

    def _words(self, shape: Sequence[int], device) -> torch.Tensor:
        """The next draw's 32-bit words, int64 of ``shape`` (rows split over the streams).

        Runs of draws of one shape (an env's steps, a policy's actions) are computed several at
        a time (up to :data:`AHEAD_WORDS` words): draw c's words are the same function of
        (key, c) either way, only the number of tensor operations per draw falls.
        """
        shape = torch.Size(shape)
        device = torch.device("cpu" if device is None else device)
        streams = len(self)
        rows = shape[0] if len(shape) else 1
        if rows % streams:
            raise ValueError(f"{rows} rows do not split into {streams} equal blocks (streams)")
        per_stream = shape.numel() // streams
        call, self.calls = self.calls, self.calls + 1
        ahead = self._ahead
        if ahead is not None and ahead[:2] == (shape, device):
            offset = call - ahead[2]
            if 0 <= offset < len(ahead[3]):
                return ahead[3][offset].reshape(shape)
            self._run = min(2 * self._run, max(1, AHEAD_WORDS // max(shape.numel(), 1)))
        else:
            self._run = 1
        words = self._draws(call, self._run, per_stream, device)  # [k, S, per stream]
        self._ahead = (shape, device, call, words)
        return words[0].reshape(shape)

    def _draws(self, call: int, count: int, per_stream: int, device) -> torch.Tensor:
        """The words of draws ``call … call + count - 1``: ``[count, S, per_stream]``."""
        streams, quads = len(self), -(-per_stream // 4)
        calls = torch.arange(call, call + count, dtype=torch.int64, device=device)
        shape = (count, streams, quads)
        j = torch.arange(quads, dtype=torch.int64, device=device).expand(shape)
        c2 = (calls & MASK32).reshape(count, 1, 1).expand(shape)
        c3 = (calls >> 32).reshape(count, 1, 1).expand(shape)
        x02 = torch.stack([c2, j])  # (c2, c0)
        x13 = torch.stack([torch.zeros_like(j), c3])  # (c1, c3)
        schedule = self._schedule(device).unsqueeze(2)  # [rounds, 2, 1, S, 1]
        words = _rounds(x02, x13, schedule)  # [4, k, S, q]
        return words.permute(1, 2, 3, 0).reshape(count, streams, 4 * quads)[..., :per_stream]

    def uniform(self, shape: Sequence[int], *, device=None) -> torch.Tensor:
        """float64 uniforms in (0, 1) of ``shape``: ``(w + 0.5) / 2**32``."""
        return self._words(shape, device).to(torch.float64).add_(0.5).mul_(2.0**-32)

    def integers(self, low: int, high: int, shape: Sequence[int], *, device=None):
        """int64 integers in ``[low, high)`` of ``shape``: ``low + (w·(high - low)) >> 32``."""
        span = int(high) - int(low)
        if not 0 < span <= 2**31:
            raise ValueError(f"need low < high and high - low <= 2**31, got [{low}, {high})")
        return (self._words(shape, device) * span >> 32) + int(low)

    def normal(self, shape: Sequence[int], *, device=None) -> torch.Tensor:
        """float64 standard normals of ``shape`` (Box-Muller of consecutive uniform pairs)."""
        shape = torch.Size(shape)
        streams = len(self)
        rows = shape[0] if len(shape) else 1
        per_stream = shape.numel() // max(streams, 1)
        pairs = -(-per_stream // 2)
        if rows % streams:
            raise ValueError(f"{rows} rows do not split into {streams} equal blocks (streams)")
        u = self.uniform((streams, pairs, 2), device=device)
        radius = u[..., 0].log().mul_(-2.0).sqrt_()
        angle = u[..., 1].mul(_TWO_PI)
        z = torch.stack([radius * angle.cos(), radius * angle.sin()], -1)
        return z.reshape(streams, 2 * pairs)[:, :per_stream].reshape(shape)
