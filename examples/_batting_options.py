"""The batting experiment's options beyond the paper (never the default): per-dimension kernel
widths, episodes that end at the hit, the LSTD-Q fit and flattened importance weights.

Parsed before torch loads, as the rest of the command line (``examples/_cli.py``)."""

from __future__ import annotations

from dataclasses import dataclass

from _cli import field
from _flattening import parse_flattening


@dataclass
class BeyondPaperOptions:
    """The learner's options beyond the paper's section 5 (the defaults are the paper's)."""

    basis_widths: str = field(
        "",
        help=(
            "beyond the paper: kernel widths per state dimension w1,w2,w3,w4 (rad, rad/s, rad, "
            "rad/s) of the paper's 54 centres instead of τ = 3π/2 for all, e.g. "
            "0.785,3.14,0.785,3.14"
        ),
    )
    end_at_hit: bool = field(
        False,
        help=(
            "beyond the paper: episodes terminate at the first bat-ball contact (the ball is gone)"
        ),
    )
    fit: str = field(
        "brm",
        choices=("brm", "lstd"),
        help=(
            "how θ is fitted: brm (the paper: least squares of r on psi_hat) or lstd (beyond the "
            "paper: LSTD-Q, with AL's J of the same learner)"
        ),
    )
    flattening: str = field(
        "1",
        help=(
            "ν of the flattened importance weights w^ν of the fit and of J: 1 (the paper), a "
            "number in [0, 1], or iwcv (beyond the paper: ν chosen every iteration by "
            "importance-weighted cross-validation, docs/flattening.md)"
        ),
    )


def parse_widths(text: str) -> list[float] | None:
    """``"w1,w2,w3,w4"`` -> four floats (None for ""); ValueError if not four positive numbers."""
    if not text:
        return None
    try:
        widths = [float(w) for w in text.split(",")]
    except ValueError:
        widths = []
    if len(widths) != 4 or not all(w > 0 for w in widths):
        raise ValueError(f"--basis-widths must be four positive numbers w1,w2,w3,w4, got {text!r}")
    return widths


def paper_learner(args: BeyondPaperOptions) -> bool:
    """Whether the options are the paper's learner (its basis, fit, weights and episodes)."""
    return (
        not args.basis_widths
        and args.fit == "brm"
        and not args.end_at_hit
        and parse_flattening(args.flattening) == 1.0
    )


def check(args: BeyondPaperOptions) -> str | None:
    """The options' error message, or None."""
    try:
        parse_widths(args.basis_widths)
        parse_flattening(args.flattening)
    except ValueError as error:
        return str(error)
    return None
