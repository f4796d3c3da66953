"""Identical design rows merged: what ``bench_j.py`` measures J on (finite state spaces).

Only the benchmarks use it: with grouped psi_hat a chain-walk data set has at most ``S × A``
distinct design rows, and the cost of :func:`torch_api.core.solve.j_criterion` and
:func:`torch_api.core.solve.weighted_ridge` on the aggregate stops growing with n.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

__all__ = ["AggregatedRows", "aggregate_identical_rows"]


class AggregatedRows(NamedTuple):
    """Identical design rows merged, for data sets with at most ``S × A`` distinct psi_hat rows.

    Attributes:
        x: the distinct rows ``[..., G, B]`` (zero-padded where a batch item has fewer).
        w: ``Σ w`` over each row's copies ``[..., G]`` (0 on padding).
        sq_weights: ``Σ w²`` over each row's copies ``[..., G]``.
        r: the weighted mean reward ``Σ w r / Σ w`` of each row ``[..., G]`` (0 where ``Σ w = 0``),
            so that ``Σ_g w_g x_g r_g`` equals the sum over the original rows; None without r.
        num_samples: the original ``n`` (the normalisation must not change).
    """

    x: torch.Tensor
    w: torch.Tensor
    sq_weights: torch.Tensor
    r: torch.Tensor | None
    num_samples: int


def _row_groups(rows: torch.Tensor, owner: torch.Tensor) -> torch.Tensor:
    """Dense ids ``[R]`` equal iff two rows ``[R, B]`` are identical and share an owner.

    A random projection gives each row a 1-D key, grouped by a sort-based 1-D unique; the
    grouping is then verified exactly (every row equals its group's representative) and, in the
    unlikely case two different rows share a key, redone with ``torch.unique(dim=0)``.
    """
    gen = torch.Generator(device="cpu").manual_seed(0x5EED)
    direction = torch.randn(rows.shape[-1], generator=gen, dtype=torch.float64).to(rows.device)
    key = rows.to(torch.float64) @ direction
    # owners apart: offset keys by the owner index beyond the keys' own range
    span = float(key.abs().max()) * 2 + 1 if key.numel() else 1.0
    _, inverse = torch.unique(key + owner.to(torch.float64) * span, return_inverse=True)
    first = torch.full(
        (int(inverse.max()) + 1,), rows.shape[0], dtype=torch.long, device=rows.device
    )
    first.scatter_reduce_(0, inverse, torch.arange(rows.shape[0], device=rows.device), "amin")
    if torch.equal(rows[first][inverse], rows) and torch.equal(owner[first][inverse], owner):
        return inverse
    keyed = torch.cat([owner.unsqueeze(-1).to(rows.dtype), rows], dim=-1)
    return torch.unique(keyed, dim=0, return_inverse=True)[1]


def aggregate_identical_rows(
    x: torch.Tensor, w: torch.Tensor, r: torch.Tensor | None = None
) -> AggregatedRows:
    """Merge bit-identical rows of a design, summing their weights (finite state spaces).

    With grouped psi_hat (docs/algorithm.md) a chain-walk data set has at most ``S × A = 20``
    distinct rows however many samples it holds, so the cost of :func:`j_criterion` and
    :func:`weighted_ridge` on the aggregate stops growing with n. Pass
    ``num_samples=out.num_samples`` and ``sq_weights=out.sq_weights`` to keep results identical.

    Args:
        x: ``[..., n, B]``; w: ``[..., n]``; r: optional ``[..., n]``.

    Returns:
        :class:`AggregatedRows` with ``G`` = the largest number of distinct rows of any batch item.
    """
    if w.shape != x.shape[:-1] or (r is not None and r.shape != w.shape):
        raise ValueError(
            f"w (and r) must have shape {tuple(x.shape[:-1])}, got {tuple(w.shape)}"
            + ("" if r is None else f" and {tuple(r.shape)}")
        )
    lead, (n, num_features) = x.shape[:-2], x.shape[-2:]
    flat_x = x.reshape(-1, n, num_features)
    batch = flat_x.shape[0]
    rows = flat_x.reshape(-1, num_features)
    owner_of_row = torch.arange(batch, device=x.device).repeat_interleave(n)
    inverse = _row_groups(rows, owner_of_row)
    num_groups = int(inverse.max()) + 1
    first = torch.full((num_groups,), rows.shape[0], dtype=torch.long, device=x.device)
    first.scatter_reduce_(0, inverse, torch.arange(rows.shape[0], device=x.device), "amin")
    uniq_rows, owner = rows[first], owner_of_row[first]
    counts = torch.bincount(owner, minlength=batch)
    slot_start = torch.cumsum(counts, 0) - counts
    order = torch.argsort(owner, stable=True)  # groups of one batch item next to each other
    rank = torch.empty_like(order)
    rank[order] = torch.arange(num_groups, device=x.device)
    slot = rank - slot_start[owner]
    groups = int(counts.max())
    out_x = x.new_zeros(batch, groups, num_features)
    out_x[owner, slot] = uniq_rows
    flat_slot = owner * groups + slot
    target = flat_slot[inverse]
    wd = w.reshape(-1).to(torch.float64)
    w_sum = torch.zeros(batch * groups, dtype=torch.float64, device=x.device).index_add_(
        0, target, wd
    )
    w_sq = torch.zeros_like(w_sum).index_add_(0, target, wd.pow(2))
    r_mean = None
    if r is not None:
        wr = torch.zeros_like(w_sum).index_add_(0, target, wd * r.reshape(-1).to(torch.float64))
        r_mean = torch.where(w_sum > 0, wr / w_sum.clamp_min(1e-300), torch.zeros_like(wr))
        r_mean = r_mean.reshape(*lead, groups)
    return AggregatedRows(
        x=out_x.reshape(*lead, groups, num_features),
        w=w_sum.reshape(*lead, groups),
        sq_weights=w_sq.reshape(*lead, groups),
        r=r_mean,
        num_samples=n,
    )
