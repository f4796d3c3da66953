"""``--flattening`` of the examples: ν of the flattened importance weights ``w^ν``
(docs/flattening.md), a number in [0, 1] or one of a script's words (``iwcv``, ``auto``).

Parsed before torch loads, as the rest of the command line (``examples/_cli.py``)."""

from __future__ import annotations


def parse_flattening(text: str, words: tuple[str, ...] = ("iwcv",)) -> float | str:
    """``text`` as ν (a float in [0, 1]) or as one of ``words``; ValueError otherwise."""
    if text in words:
        return text
    try:
        nu = float(text)
    except ValueError:
        *first, last = ("a number in [0, 1]", *words)
        allowed = f"{', '.join(first)} or {last}" if first else last
        raise ValueError(f"--flattening must be {allowed}, got {text!r}") from None
    if not 0.0 <= nu <= 1.0:
        raise ValueError(f"--flattening must lie in [0, 1], got {nu}")
    return nu
