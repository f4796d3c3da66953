"""Counter-based random streams (Philox4x32-10) in torch, shared by ``torch_api`` and ``envs``.

Every number is a pure function of a key and a counter, computed for all streams of a batch
in one tensor operation: see :mod:`counter_rng.streams`. This package imports only torch.
"""

from counter_rng.philox import philox4x32, philox4x32_int
from counter_rng.streams import CounterStreams, derive_key, derive_keys, fresh_key

__all__ = [
    "CounterStreams",
    "derive_key",
    "derive_keys",
    "fresh_key",
    "philox4x32",
    "philox4x32_int",
]
