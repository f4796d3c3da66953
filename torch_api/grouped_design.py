"""psi_hat (eq. 20) and weights (eq. 21) of finite-state data, one row per (s, a) group.

With ``psi_mode="grouped"`` every sample of one ``(s, a)`` in one data set has the same
psi_hat row: ``phi(s, a) − γ · mean over the group of Σ_a' pi(a'|s') phi(s', a')``, and the
next-state term depends on s' alone. So the rows need not be built per sample: per data set
this module finds the distinct ``(s, a)`` (at most S·A) and the distinct next states, evaluates
the basis and the policy on those only, and forms each group's mean next-state term from the
counts of its transitions to each next state. What stays per sample is what has no feature
dimension: the group of each sample and its per-decision importance weight.

The moments the criterion needs are then sums over groups, ``Σ_g (Σ_{i∈g} w_i) x_g x_gᵀ``
(:func:`group_sums`), equal to the per-sample sums up to the order of floating-point addition
(tested against :func:`torch_api.design.build_design` to 1e-12).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from tensordict import TensorDictBase

from torch_api.design import taken_probs
from torch_api.episodes import taken_sample_probs
from torch_api.psi import PsiHat, expected_next_features, state_action_groups, unique_inverse
from torch_api.weights import per_decision_weights

__all__ = ["GroupedDesign", "grouped_design", "group_sums"]


class GroupedDesign(NamedTuple):
    """Finite-state design of data sets ``[..., M, N]`` (``n = M·N`` samples each).

    Attributes:
        x: psi_hat of each group ``[..., G, B]`` (G: the most groups of any data set; unused
            slots hold finite rows that no sample points to).
        group: each sample's group slot ``[..., n]`` (long, in ``[0, G)``).
        w: per-decision weight of each sample ``[..., n]`` (0 where masked).
        mask: ``[..., n]``.
    """

    x: torch.Tensor
    group: torch.Tensor
    w: torch.Tensor
    mask: torch.Tensor


def _slots(ids: torch.Tensor, items: int, n: int) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Per-item dense slots of ids ``[items·n]`` that never repeat across items: each sample's
    slot ``[items·n]``, each (item, slot)'s first sample ``[items, S]`` (padded with the
    item's first sample) and S, the most distinct ids of any item."""
    _, inverse = unique_inverse(ids)
    count = int(inverse.max()) + 1 if inverse.numel() else 0
    positions = torch.arange(ids.numel(), device=ids.device)
    first = torch.full((count,), ids.numel(), dtype=torch.long, device=ids.device)
    first.scatter_reduce_(0, inverse, positions, "amin")
    owner = first // n  # the item of each distinct id (ids are item-distinct)
    per_item = torch.bincount(owner, minlength=items)
    start = torch.cumsum(per_item, 0) - per_item
    order = torch.argsort(owner * ids.numel() + first)  # by item, then by first appearance
    rank = torch.empty_like(order)
    rank[order] = torch.arange(count, device=ids.device)
    slot_of_id = rank - start[owner]
    width = int(per_item.max()) if items else 0
    firsts = (torch.arange(items, device=ids.device) * n).unsqueeze(-1).repeat(1, width)
    firsts[owner, slot_of_id] = first
    return slot_of_id[inverse], firsts, width


def grouped_design(episodes: TensorDictBase, policy, psi: PsiHat) -> GroupedDesign:
    """The finite-state design of every ``[M, N]`` data set of ``episodes ``[..., M, N]``
    under the evaluation policy ``policy`` (see the module; ``psi.mode`` must be "grouped").
    The policy's parameters' leading dims (e.g. trials) must prefix ``[...]``."""
    if psi.mode != "grouped":
        raise ValueError(f"grouped_design needs psi_mode 'grouped', got {psi.mode!r}")
    *lead, m, steps = episodes.shape
    n, items = m * steps, math.prod(lead)
    mask = episodes["mask"].reshape(items, n)
    obs = episodes["observation"].reshape(items, n, -1).to(torch.float64)
    next_obs = episodes["next", "observation"].reshape(items, n, -1).to(torch.float64)
    action = episodes["action"].reshape(items, n)
    terminated = episodes.get(("next", "terminated"), None)
    keep = mask if terminated is None else mask & ~terminated.reshape(items, n)
    # padding steps may hold anything: give them the item's first state, so every row is finite
    obs = torch.where(mask.unsqueeze(-1), obs, obs[:, :1])
    next_obs = torch.where(mask.unsqueeze(-1), next_obs, next_obs[:, :1])
    action = torch.where(mask, action, action[:, :1])

    group, first, width = _slots(state_action_groups(obs, action).reshape(-1), items, n)
    state_ids = state_action_groups(next_obs, torch.zeros_like(action)).reshape(-1)
    nxt, next_first, next_width = _slots(state_ids, items, n)
    flat_obs, flat_next = obs.reshape(items * n, -1), next_obs.reshape(items * n, -1)
    rep_obs = flat_obs[first].reshape(*lead, width, -1)  # one state per (s, a) group
    rep_action = action.reshape(-1)[first].reshape(*lead, width)
    rep_next = flat_next[next_first].reshape(*lead, next_width, -1)  # one per next state

    basis = psi.basis
    phi = basis.phi(rep_obs, rep_action).reshape(items, width, -1)  # [L, G, B]
    next_probs = policy.action_probs(rep_next)
    if hasattr(basis, "expected_phi"):  # the basis's block-structured form, as in PsiHat
        next_features = basis.expected_phi(rep_next, next_probs)
    else:
        next_features = expected_next_features(basis.phi_all(rep_next), next_probs)
    next_features = next_features.reshape(items * next_width, -1)  # [L·G', B]

    # Σ over each group's kept transitions of the next-state term, by (group, next state) pair
    item = torch.arange(items, device=mask.device).repeat_interleave(n)
    slot = item * width + group  # each sample's (item, group) row of the [L·G] tables
    pair = slot * next_width + nxt
    pairs, pair_of = unique_inverse(pair[keep.reshape(-1)])
    pair_count = torch.bincount(pair_of, minlength=pairs.numel()).to(torch.float64)
    pair_group = pairs // next_width  # item·G + group slot
    pair_next = (pair_group // width) * next_width + pairs % next_width  # item·G' + next slot
    bootstrap = torch.zeros(items * width, phi.shape[-1], dtype=torch.float64, device=phi.device)
    bootstrap.index_add_(0, pair_group, pair_count.unsqueeze(-1) * next_features[pair_next])
    members = torch.zeros(items * width, dtype=torch.float64, device=phi.device)
    members.index_add_(0, slot, mask.reshape(-1).to(torch.float64))
    mean = bootstrap / members.clamp_min(1).unsqueeze(-1)
    x = phi.to(torch.float64) - psi.gamma * mean.reshape(items, width, -1)

    probs = policy.action_probs(rep_obs).reshape(items, width, -1)  # pi(·|s) of each group
    target = probs.reshape(items * width, -1)[slot].reshape(*mask.shape, -1)
    target = taken_probs(target, action).reshape(episodes.shape)
    w = per_decision_weights(target, taken_sample_probs(episodes), episodes["mask"])
    return GroupedDesign(
        x=x.reshape(*lead, width, -1),
        group=group.reshape(*lead, n),
        w=w.reshape(*lead, n),
        mask=mask.reshape(*lead, n),
    )


def group_sums(values: torch.Tensor, group: torch.Tensor, width: int) -> torch.Tensor:
    """``Σ`` of sample values ``[..., n]`` within each group slot: ``[..., width]``."""
    lead = values.shape[:-1]
    items = lead.numel()
    flat_group = group.reshape(items, group.shape[-1])
    offsets = torch.arange(items, device=values.device).unsqueeze(-1) * width
    index = (flat_group + offsets).reshape(-1)
    out = torch.zeros(items * width, dtype=values.dtype, device=values.device)
    return out.index_add_(0, index, values.reshape(-1)).reshape(*lead, width)
