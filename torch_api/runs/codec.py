"""TensorDicts as bytes without pickle: what the run's store keeps of every episode batch.

A blob is an 8-byte header length, a JSON header (keys, dtypes, shapes, offsets) and the raw
little-endian tensor data; decoding checks every size against the header and never executes
anything it reads.
"""

from __future__ import annotations

import json
import math
import struct

import torch
from tensordict import TensorDict, TensorDictBase

__all__ = ["decode_tensordict", "encode_tensordict"]

MAX_HEADER_BYTES = 1 << 20  # a tensor blob's JSON header is never larger
_DTYPES = {
    str(d).removeprefix("torch."): d
    for d in (
        torch.float16,
        torch.bfloat16,
        torch.float32,
        torch.float64,
        torch.int8,
        torch.int16,
        torch.int32,
        torch.int64,
        torch.uint8,
        torch.bool,
    )
}

# -- tensors without pickle -----------------------------------------------------------------


def encode_tensordict(td: TensorDictBase) -> bytes:
    """A TensorDict as bytes: 8-byte header length, JSON header, raw little-endian tensor data.

    Example:
        >>> td = TensorDict({"a": torch.arange(3), ("n", "b"): torch.ones(3, 2)}, [3])
        >>> bool((decode_tensordict(encode_tensordict(td)) == td).all())
        True
    """
    leaves, chunks, offset = [], [], 0
    for key in sorted(td.keys(include_nested=True, leaves_only=True), key=str):
        value = td.get(key).detach().cpu().contiguous()
        name = str(value.dtype).removeprefix("torch.")
        if name not in _DTYPES:
            raise ValueError(f"cannot store a tensor of dtype {value.dtype} (key {key!r})")
        data = value.view(torch.uint8).numpy().tobytes() if value.numel() else b""
        path = list(key) if isinstance(key, tuple) else [key]
        leaves.append({"key": path, "dtype": name, "shape": list(value.shape), "offset": offset})
        chunks.append(data)
        offset += len(data)
    header = json.dumps({"batch_size": list(td.batch_size), "leaves": leaves}).encode()
    return struct.pack("<Q", len(header)) + header + b"".join(chunks)


def decode_tensordict(blob: bytes) -> TensorDict:
    """Inverse of :func:`encode_tensordict`; sizes are checked before anything is built.

    Raises:
        ValueError: a header or a size that does not fit the bytes, an unknown dtype.
    """
    if len(blob) < 8:
        raise ValueError("tensor blob shorter than its header length")
    (size,) = struct.unpack("<Q", blob[:8])
    if size > MAX_HEADER_BYTES or 8 + size > len(blob):
        raise ValueError(f"tensor header of {size} bytes does not fit a blob of {len(blob)}")
    header = json.loads(blob[8 : 8 + size].decode())
    data = memoryview(blob)[8 + size :]
    batch_size = [int(b) for b in header["batch_size"]]
    out = TensorDict({}, batch_size=batch_size)
    end = 0
    for leaf in header["leaves"]:
        dtype = _DTYPES.get(leaf["dtype"])
        if dtype is None:
            raise ValueError(f"unknown dtype {leaf['dtype']!r} in a tensor blob")
        shape = [int(s) for s in leaf["shape"]]
        if any(s < 0 for s in shape):
            raise ValueError(f"negative size in shape {shape}")
        nbytes = math.prod(shape) * torch.empty((), dtype=dtype).element_size()
        start = int(leaf["offset"])
        if start != end or start + nbytes > len(data):
            raise ValueError(f"tensor of {nbytes} bytes at {start} outside {len(data)} bytes")
        raw = bytearray(data[start : start + nbytes])
        end = start + nbytes
        tensor = torch.frombuffer(raw, dtype=torch.uint8) if nbytes else torch.empty(0)
        tensor = tensor.view(dtype).reshape(shape) if nbytes else torch.empty(shape, dtype=dtype)
        out.set(tuple(leaf["key"]), tensor)
    if end != len(data):
        raise ValueError(f"{len(data) - end} bytes after the last tensor")
    return out
