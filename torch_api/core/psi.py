"""The sample estimate psi_hat of the Bellman-residual basis (paper eq. 14, 20).

``psi_hat(s, a; D) = phi(s, a) - γ mean_{s' in D(s, a)} Σ_a' pi(a'|s') phi(s', a')``.

``D(s, a)`` is the set of transitions of the data set ``D`` that start at ``(s, a)``:

- ``"grouped"``: finite state spaces; every transition with exactly that ``(s, a)``.
- ``"single"``: continuous states; the transition itself (the paper's choice, footnote 1).
- ``"knn"``: continuous states; the ``k`` transitions of ``D`` with the same action nearest in
  state (Euclidean), the transition itself included (the paper's footnote 1 suggestion).

Where an episode *terminated* at ``s'`` the bootstrap term is dropped (``Σ_a' … = 0``). A
*truncated* episode (a time limit, as in the paper's fixed-length episodes) keeps it: the
process did not end there, only the recording did.
"""

from __future__ import annotations

import torch
from torch import nn

from torch_api._checks import _check_not_meta, all_finite

__all__ = [
    "PsiHat",
    "expected_next_features",
    "knn_mean",
    "psi_hat",
    "state_action_groups",
    "unique_inverse",
]

PSI_MODES = ("grouped", "single", "knn")


def expected_next_features(next_phi_all: torch.Tensor, next_probs: torch.Tensor) -> torch.Tensor:
    """``Σ_a' pi(a'|s') phi(s', a')`` (eq. 14, 20): ``[..., A, B], [..., A] -> [..., B]``."""
    if next_probs.shape != next_phi_all.shape[:-1]:
        raise ValueError(
            f"next_probs must have shape {tuple(next_phi_all.shape[:-1])}, got "
            f"{tuple(next_probs.shape)}"
        )
    return (next_probs.unsqueeze(-1).to(next_phi_all.dtype) * next_phi_all).sum(-2)


def state_action_groups(
    obs: torch.Tensor, action: torch.Tensor, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Group id of each sample's exact ``(s, a)``, separately per batch item.

    Args:
        obs: ``[..., n, d]``; action: ``[..., n]`` indices; mask: optional bool ``[..., n]``.

    Returns:
        long ``[..., n]`` ids, non-negative and below ``4 · numel`` (not necessarily
        consecutive): two samples share an id iff they belong to the same batch item and have
        bit-identical ``(s, a)``. Masked samples get a group of their own.
    """
    if action.shape != obs.shape[:-1]:
        raise ValueError(
            f"action must have shape {tuple(obs.shape[:-1])}, got {tuple(action.shape)}"
        )
    flat_obs = obs.reshape(-1, obs.shape[-1])
    rows = flat_obs.shape[0]
    n = obs.shape[-2] if obs.ndim >= 2 else 1
    flat_action = action.reshape(-1).long()
    num_actions = int(flat_action.max()) + 1 if rows else 1
    # (batch item, action) are small integers already: combine them arithmetically.
    key = (torch.arange(rows, device=obs.device) // max(n, 1)) * num_actions + flat_action
    # Observations compare bit for bit (as integers): one 1-D unique per column.
    for column in flat_obs.to(torch.float64).unbind(-1):
        count, col_ids = _value_ids(column)
        key = key * count + col_ids
        if rows and int(key.max()) >= 4 * rows:  # keep ids small (and far from overflow)
            _, key = unique_inverse(key)
    if mask is not None:  # a masked row keys on its own position, never joining a real group
        own = (int(key.max()) + 1 if rows else 0) + torch.arange(rows, device=obs.device)
        key = torch.where(mask.reshape(-1), key, own)
        if rows and int(key.max()) >= 4 * rows:
            _, key = unique_inverse(key)
    return key.reshape(obs.shape[:-1])


def unique_inverse(ids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``torch.unique(ids, return_inverse=True)`` of int64 ids ``[n]``: the distinct values
    (ascending) and each id's index among them, the same tensors to the bit.

    Where the ids are non-negative and below ``4 · n`` (the group ids of this module) they are
    ranked through a dense table of that size in linear time (no sort): a table of which
    values occur, its running count giving each value's rank.

    Example:
        >>> ids = torch.tensor([5, 2, 5, 0])
        >>> [t.tolist() for t in unique_inverse(ids)]
        [[0, 2, 5], [2, 1, 2, 0]]
    """
    n = ids.numel()
    if not n or int(ids.min()) < 0 or int(ids.max()) >= 4 * n:
        return torch.unique(ids, return_inverse=True)
    present = torch.zeros(int(ids.max()) + 1, dtype=torch.bool, device=ids.device)
    present[ids] = True
    rank = torch.cumsum(present, 0) - 1
    return torch.nonzero(present).squeeze(-1), rank[ids]


def _value_ids(column: torch.Tensor) -> tuple[int, torch.Tensor]:
    """The number of distinct float64 values (bit for bit) of ``column [n]`` and each
    value's rank among them (ascending bit patterns, as a unique of the bits would give).

    Small non-negative whole numbers (state numbers, grid cells) are ranked densely: for
    floats with the sign bit clear the bit patterns are in the order of the values, so the
    ranks equal those of the bits."""
    n = column.numel()
    whole = n and bool(
        (column == column.trunc()).all() & ~torch.signbit(column).any() & (column < 4 * n).all()
    )
    values, ids = unique_inverse(column.long()) if whole else _bits_unique(column)
    return values.numel(), ids


def _bits_unique(column: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.unique(column.view(torch.int64), return_inverse=True)


def _group_mean(values: torch.Tensor, groups: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    flat_v = values.reshape(-1, values.shape[-1])
    flat_g = groups.reshape(-1)
    keep = mask.reshape(-1).to(flat_v.dtype)
    size = int(flat_g.max()) + 1 if flat_g.numel() else 0
    sums = flat_v.new_zeros(size, flat_v.shape[-1]).index_add_(0, flat_g, flat_v * keep[:, None])
    counts = flat_v.new_zeros(size).index_add_(0, flat_g, keep)
    mean = sums / counts.clamp_min(1)[:, None]
    return mean[flat_g].reshape(values.shape)


def knn_mean(
    obs: torch.Tensor,
    action: torch.Tensor,
    values: torch.Tensor,
    k: int,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Mean of ``values`` over the ``k`` nearest samples with the same action, per batch item.

    Args:
        obs: ``[..., n, d]``; action: ``[..., n]``; values: ``[..., n, B]``; k ≥ 1;
        mask: optional bool ``[..., n]`` (masked samples are never neighbours).

    Returns:
        ``[..., n, B]``. A sample with fewer than ``k`` same-action neighbours averages over
        those it has (itself at least).
    """
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    if mask is None:
        mask = torch.ones(action.shape, dtype=torch.bool, device=obs.device)
    dist = torch.cdist(obs.to(torch.float64), obs.to(torch.float64))
    same = (action.unsqueeze(-1) == action.unsqueeze(-2)) & mask.unsqueeze(-2)
    dist = torch.where(same, dist, torch.inf)
    # The sample itself is always its own nearest neighbour, even if masked.
    dist.diagonal(dim1=-2, dim2=-1).fill_(-1.0)
    k_eff = min(k, obs.shape[-2])
    near_d, near_i = dist.topk(k_eff, dim=-1, largest=False)
    valid = torch.isfinite(near_d).to(values.dtype)
    gathered = torch.gather(
        values.unsqueeze(-3).expand(*near_i.shape[:-1], *values.shape[-2:]),
        -2,
        near_i.unsqueeze(-1).expand(*near_i.shape, values.shape[-1]),
    )
    return (gathered * valid.unsqueeze(-1)).sum(-2) / valid.sum(-1, keepdim=True)


def _check_finite_rows(name: str, values: torch.Tensor, mask: torch.Tensor | None) -> None:
    """Refuse NaN or inf in the rows ``values [..., n, F]`` the mask ``[..., n]`` keeps (a
    padding row may hold anything): a finite sum proves all is well, and only otherwise are the
    rows looked at."""
    if all_finite(values):
        return
    bad = ~torch.isfinite(values).all(-1)
    if mask is not None:
        bad &= mask.bool()
    if bad.any():
        raise ValueError(
            f"{name} contains NaN or inf (in {int(bad.sum())} of {bad.numel()} samples): "
            "their psi_hat rows would be NaN"
        )


def psi_hat(
    phi: torch.Tensor,
    next_features: torch.Tensor,
    gamma: float,
    *,
    terminated: torch.Tensor | None = None,
    groups: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """psi_hat rows from basis rows and next-state expectations (eq. 20).

    Args:
        phi: ``phi(s, a)`` of each sample, ``[..., n, B]``.
        next_features: ``Σ_a' pi(a'|s') phi(s', a')`` of each sample, ``[..., n, B]``.
        gamma: discount γ in (0, 1].
        terminated: optional bool ``[..., n]``: the bootstrap is dropped there.
        groups: optional ``[..., n]`` ids from :func:`state_action_groups`; the next-state term
            is averaged within each group (finite state spaces). None: single-sample form.
        mask: optional bool ``[..., n]``; masked samples (padding) are left out of every group
            mean and their own rows are zero.

    Raises:
        ValueError: NaN or inf in ``phi`` or ``next_features`` on a sample the mask keeps.

    Returns:
        ``[..., n, B]`` in float64 (the dtype of the weights and of the solve downstream),
        whatever the dtype of ``phi``.
    """
    if not 0 < gamma <= 1:
        raise ValueError(f"gamma must lie in (0, 1], got {gamma}")
    _check_not_meta("phi", phi)
    _check_not_meta("next_features", next_features)
    phi, next_features = phi.to(torch.float64), next_features.to(torch.float64)
    if next_features.shape != phi.shape:
        raise ValueError(
            f"next_features must have shape {tuple(phi.shape)}, got {tuple(next_features.shape)}"
        )
    if mask is None:
        mask = torch.ones(phi.shape[:-1], dtype=torch.bool, device=phi.device)
    bootstrap = next_features
    if terminated is not None:
        if terminated.shape != phi.shape[:-1]:
            raise ValueError(
                f"terminated must have shape {tuple(phi.shape[:-1])}, got {tuple(terminated.shape)}"
            )
        bootstrap = bootstrap * (~terminated.bool()).unsqueeze(-1).to(bootstrap.dtype)
    if groups is not None:
        bootstrap = _group_mean(bootstrap, groups, mask)
    # (a padding row is 0 whatever it holds: NaN · 0 would be NaN)
    out = torch.where(mask.bool().unsqueeze(-1), phi - gamma * bootstrap, 0.0)
    if not all_finite(out):  # one reduction; the inputs are looked at only to name the culprit
        _check_finite_rows("phi", phi, mask)
        _check_finite_rows("next_features", next_features, mask)
        raise ValueError("psi_hat rows overflow: phi - gamma · next_features is inf")
    return out


class PsiHat(nn.Module):
    """psi_hat of eq. 20 for a data set, given a basis and an evaluation policy's probabilities.

    Args:
        basis: a module with ``phi(obs, action) -> [..., B]`` and ``phi_all(obs) -> [..., A, B]``
            (e.g. :class:`~torch_api.core.basis.GaussianActionBasis`).
        gamma: discount γ in (0, 1].
        mode: ``"grouped"`` (finite states), ``"single"`` (the paper's continuous-state choice)
            or ``"knn"``.
        k: neighbours for ``mode="knn"``.

    Example:
        >>> from torch_api.core.basis import GaussianActionBasis
        >>> basis = GaussianActionBasis(centers=torch.tensor([[1.0], [5.0]]), tau=1.5,
        ...                             num_actions=2)
        >>> psi = PsiHat(basis=basis, gamma=0.9, mode="grouped")
        >>> obs, nxt = torch.randint(1, 4, (8, 1)).float(), torch.randint(1, 4, (8, 1)).float()
        >>> action = torch.randint(0, 2, (8,))
        >>> psi(obs, action, nxt, torch.full((8, 2), 0.5)).shape
        torch.Size([8, 6])
    """

    def __init__(self, *, basis: nn.Module, gamma: float, mode: str = "single", k: int = 5):
        super().__init__()
        if mode not in PSI_MODES:
            raise ValueError(f"mode must be one of {PSI_MODES}, got {mode!r}")
        if not 0 < gamma <= 1:
            raise ValueError(f"gamma must lie in (0, 1], got {gamma}")
        if mode == "knn" and k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        self.basis = basis
        self.gamma = float(gamma)
        self.mode = mode
        self.k = int(k)

    @property
    def row_local(self) -> bool:
        """Whether a sample's psi_hat row depends on that sample alone (``mode="single"``).

        Grouped and k-NN rows average over other samples of the same data set, so their data
        set must be passed whole.
        """
        return self.mode == "single"

    def forward(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        next_obs: torch.Tensor,
        next_probs: torch.Tensor,
        terminated: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """psi_hat rows of a data set.

        Args:
            obs: ``[..., n, d]``; action: ``[..., n]`` indices; next_obs: ``[..., n, d]``.
            next_probs: evaluation-policy probabilities at ``s'``, ``[..., n, A]``.
            terminated: optional bool ``[..., n]``; mask: optional bool ``[..., n]``.

        Returns:
            ``[..., n, B]`` in float64.
        """
        _check_not_meta("obs", obs)
        _check_not_meta("next_obs", next_obs)
        _check_finite_rows("obs", obs, mask)
        _check_finite_rows("next_obs", next_obs, mask)
        obs64, next64 = obs.to(torch.float64), next_obs.to(torch.float64)
        phi = self.basis.phi(obs64, action)
        if hasattr(self.basis, "expected_phi"):  # block-structured fast path
            next_features = self.basis.expected_phi(next64, next_probs)
        else:
            next_features = expected_next_features(self.basis.phi_all(next64), next_probs)
        groups = state_action_groups(obs, action, mask) if self.mode == "grouped" else None
        if self.mode == "knn":
            if terminated is not None:
                keep = (~terminated.bool()).unsqueeze(-1).to(next_features.dtype)
                next_features = next_features * keep
                terminated = None
            next_features = knn_mean(obs64, action, next_features, self.k, mask)
        return psi_hat(
            phi, next_features, self.gamma, terminated=terminated, groups=groups, mask=mask
        )
