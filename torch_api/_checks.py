"""Argument checks shared by the loop and its parts (``ValueError`` naming the value)."""

from __future__ import annotations

import math
import numbers
import warnings

import torch

HUGE_LAMBDA = 1e6  # λ above this shrinks θ towards 0 whatever the data: warned about
TINY_LAMBDA = 1e-10  # λ below this vanishes beside a design's entries: a singular one stays so


def all_finite(t: torch.Tensor) -> bool:
    """Whether every entry of ``t`` is finite. A finite sum proves it (NaN and ±inf propagate
    through a sum, or cancel into NaN), so the entry-wise test runs only when the sum is not
    finite (a bad entry, or finite entries that overflow): one reduction instead of a mask."""
    return bool(torch.isfinite(t.sum())) or bool(torch.isfinite(t).all())


def _check_lambda(lam: float) -> None:
    """λ must be a finite number in [TINY_LAMBDA, ∞); a huge one (θ shrunk to about 0) is
    warned about. A smaller λ is lost in rounding (``1 + 1e-300 == 1``): the fit of a design
    with an unvisited action fails, after the rewards were bought."""
    if isinstance(lam, bool) or not (isinstance(lam, numbers.Real) and lam > 0):
        raise ValueError(f"lam must be > 0, got {lam!r}")
    if not math.isfinite(lam):
        raise ValueError(f"lam must be finite, got {lam}")
    if lam < TINY_LAMBDA:
        raise ValueError(
            f"lam must be >= {TINY_LAMBDA:g} (a smaller ridge is lost in rounding and leaves a "
            f"singular design unsolvable), got {lam:g}"
        )
    if lam > HUGE_LAMBDA:
        warnings.warn(
            f"lam = {lam:g} is huge: the ridge penalty dominates every design and θ shrinks to "
            "about 0 whatever the rewards",
            RuntimeWarning,
            stacklevel=3,
        )


def _check_schedule(schedule) -> list[int]:
    """Episodes bought per iteration ``(M_1, …, M_L)``: a non-empty list of integers >= 1."""
    if not schedule or not all(
        isinstance(m, numbers.Integral)
        and not isinstance(m, bool)
        and m >= 1
        or isinstance(m, float)
        and m.is_integer()
        and m >= 1
        for m in schedule
    ):
        raise ValueError(
            "schedule must be a non-empty list of integer episode counts >= 1, "
            f"got {list(schedule)}"
        )
    return [int(m) for m in schedule]


def _check_choice(name: str, value, choices: tuple) -> None:
    """``value`` must be one of ``choices``."""
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")


def _count(name: str, value, minimum: int = 1) -> int:
    """``value`` as an int >= minimum; a non-integer (2.5, True, "3") is refused."""
    integral = isinstance(value, numbers.Integral) or (
        isinstance(value, float) and value.is_integer()
    )
    if isinstance(value, bool) or not integral:
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value!r}")
    return int(value)


def _check_seed(seed) -> int:
    """A seed: an integer (2.5, True or "3" are refused)."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    return int(seed)


def _check_finite(name: str, values) -> tuple[float, ...]:
    """``values`` as a tuple of finite real numbers."""
    values = tuple(values)
    if not all(
        isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) for v in values
    ):
        raise ValueError(f"{name} must be finite numbers, got {list(values)}")
    return values


def _check_device(device) -> torch.device:
    """``device`` as a ``torch.device`` that is there (a CUDA device needs a GPU torch sees)."""
    try:
        device = torch.device("cpu" if device is None else device)
    except (RuntimeError, TypeError) as error:
        raise ValueError(f"device must name a torch device, got {device!r} ({error})") from None
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0 or (device.index or 0) >= count:
            raise ValueError(f"device {str(device)!r}: torch sees {count} CUDA GPUs here")
    return device


def _check_not_meta(name: str, *tensors: torch.Tensor) -> None:
    """Refuse tensors on the ``meta`` device (shapes without values): every check of their
    values would fail inside torch with ``Tensor.item() cannot be called on meta tensors``."""
    for tensor in tensors:
        if isinstance(tensor, torch.Tensor) and tensor.device.type == "meta":
            raise ValueError(
                f"{name} is on the meta device (a shape without values, "
                f"{tuple(tensor.shape)}): give real tensors, e.g. on 'cpu' or 'cuda'"
            )
