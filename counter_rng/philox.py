"""Philox4x32-10, the counter-based generator of Random123, in torch integer arithmetic.

Salmon, Moraes, Dror & Shaw, "Parallel random numbers: as easy as 1, 2, 3" (SC 2011). A
Philox output is a pure function of a 128-bit counter and a 64-bit key: four 32-bit words
``philox4x32(counter, key)``. Each of the ten rounds multiplies two counter words by fixed
constants, keeps the high and low halves of the 64-bit products and mixes them with the other
two words and the round's key; the key is bumped by the Weyl constants between rounds.

Every word is held in an ``int64`` tensor with values in ``[0, 2**32)``. The product of two
such words needs 64 unsigned bits: in ``int64`` it wraps around, and its bit pattern is still
the true product's (two's complement), so the low half is ``p & 0xFFFFFFFF`` and the high half
``(p >> 32) & 0xFFFFFFFF`` (the mask undoes the arithmetic shift's sign extension). Integer
arithmetic is exact on every device, so the words are the same on the CPU and on CUDA.

The published known-answer vectors (Random123's ``tests/kat_vectors``) are checked in
``tests/test_counter_rng.py``; :func:`philox4x32_int` is a plain-Python twin for single values.
"""

from __future__ import annotations

import torch

__all__ = ["MASK32", "ROUNDS", "philox4x32", "philox4x32_int", "key_schedule"]

MASK32 = 0xFFFFFFFF
ROUNDS = 10  # Random123's default for Philox4x32 (7 pass BigCrush; 10 keep a safety margin)
_M0, _M1 = 0xD2511F53, 0xCD9E8D57  # the round multipliers
_W0, _W1 = 0x9E3779B9, 0xBB67AE85  # the key's Weyl increments (golden ratio, sqrt(3) - 1)


def philox4x32_int(counter: tuple[int, int, int, int], key: tuple[int, int], rounds=ROUNDS):
    """Philox4x32 of one counter (four words) and key (two words), in plain Python ints.

    Example:
        >>> [hex(w) for w in philox4x32_int((0, 0, 0, 0), (0, 0))]
        ['0x6627e8d5', '0xe169c58d', '0xbc57ac4c', '0x9b00dbd8']
    """
    c0, c1, c2, c3 = (int(w) & MASK32 for w in counter)
    k0, k1 = (int(w) & MASK32 for w in key)
    for r in range(rounds):
        if r:
            k0, k1 = (k0 + _W0) & MASK32, (k1 + _W1) & MASK32
        p0, p1 = _M0 * c0, _M1 * c2
        c0, c1, c2, c3 = (p1 >> 32) ^ c1 ^ k0, p1 & MASK32, (p0 >> 32) ^ c3 ^ k1, p0 & MASK32
    return c0, c1, c2, c3


def key_schedule(k0: torch.Tensor, k1: torch.Tensor, rounds: int = ROUNDS) -> torch.Tensor:
    """The round keys ``[rounds, 2, *k.shape]`` (int64) of key words ``k0, k1``: round r's key
    is ``(k0 + r·W0, k1 + r·W1) mod 2**32``."""
    r = torch.arange(rounds, dtype=torch.int64, device=k0.device).reshape(-1, *[1] * k0.ndim)
    return torch.stack([(k0 + r * _W0) & MASK32, (k1 + r * _W1) & MASK32], 1)


def _rounds(x02: torch.Tensor, x13: torch.Tensor, keys: torch.Tensor) -> torch.Tensor:
    """The Philox rounds on counter words held as pairs: ``x02 = (c2, c0)``, ``x13 = (c1, c3)``
    ``[2, ...]`` and round keys ``[rounds, 2, ...]`` -> the output words ``[4, ...]``."""
    multipliers = torch.tensor([_M1, _M0], dtype=torch.int64, device=x02.device)
    multipliers = multipliers.reshape(2, *[1] * (x02.ndim - 1))
    for key in keys:
        product = x02 * multipliers  # (p1, p0) = (M1·c2, M0·c0), wrapped into int64
        high = (product >> 32).bitwise_and_(MASK32)  # (hi1, hi0)
        low = product.bitwise_and_(MASK32)  # (lo1, lo0) = the next (c1, c3)
        high.bitwise_xor_(x13).bitwise_xor_(key)  # (hi1 ^ c1 ^ k0, hi0 ^ c3 ^ k1) = (c0, c2)
        x02, x13 = high.flip(0), low
    return torch.stack([x02[1], x13[0], x02[0], x13[1]])


def philox4x32(counter: torch.Tensor, key: torch.Tensor, rounds: int = ROUNDS) -> torch.Tensor:
    """Philox4x32: counter words ``[4, ...]`` and key words ``[2, ...]`` (int64 holding
    unsigned 32-bit values; broadcast against each other) -> output words ``[4, ...]``.

    Example:
        >>> counter = torch.tensor([[0x243F6A88], [0x85A308D3], [0x13198A2E], [0x03707344]])
        >>> key = torch.tensor([[0xA4093822], [0x299F31D0]])
        >>> [hex(w) for w in philox4x32(counter, key).flatten().tolist()]
        ['0xd16cfe09', '0x94fdcceb', '0x5001e420', '0x24126ea1']
    """
    counter, key = counter.to(torch.int64), key.to(torch.int64)
    shape = torch.broadcast_shapes(counter.shape[1:], key.shape[1:])
    x02 = torch.stack([counter[2], counter[0]]).expand(2, *shape)
    x13 = torch.stack([counter[1], counter[3]]).expand(2, *shape)
    return _rounds(x02, x13, key_schedule(key[0], key[1], rounds))
