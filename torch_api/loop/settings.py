"""The loop's arguments, checked where they enter (``ValueError`` naming the value)."""

from __future__ import annotations

import math

import torch

from torch_api._checks import (
    _check_choice,
    _check_device,
    _check_finite,
    _check_lambda,
    _check_schedule,
    _check_seed,
    _count,
)
from torch_api.core.fit import FITS
from torch_api.core.psi import PSI_MODES
from torch_api.loop.durable import fingerprint, plain, qualified
from torch_api.loop.selector import SamplingPolicySelector
from torch_api.policies.linear_q import TIE_BREAKS

SLICES = ("all", "episode")  # how rewarded episodes are bought (ActivePolicyIteration)


def check_initial_theta(theta, width: int) -> torch.Tensor:
    """θ_0 as float64 ``[B]`` (default all ones: ``Q̂_0 = Σ_b phi_b``, eq. 58, 67)."""
    if theta is None:
        return torch.ones(width, dtype=torch.float64)
    theta = torch.as_tensor(theta, dtype=torch.float64)
    if theta.shape != (width,):
        raise ValueError(
            f"initial_theta must have shape [{width}] (the basis width), got {tuple(theta.shape)}"
        )
    return theta


def check_loop_settings(
    *,
    tie_break,
    schedule,
    num_steps,
    knn_k,
    num_trials,
    gamma,
    lam,
    rewarded_slice,
    store,
    psi_mode,
    fit,
    selector=None,
    collector=None,
    extra=(0, True),
    env_is_factory=True,
    seed=0,
    device=None,
    candidate_offsets=(),
) -> tuple:
    """The plain settings of :class:`~torch_api.loop.iteration.ActivePolicyIteration`, checked.

    ``store`` is ``(resume or overwrite, checkpoint_path)``; ``collector`` the loop's collector
    factory, if any (or the selector's); ``extra`` is ``(number of extra candidates, active)``.
    Returns ``(schedule, num_steps, knn_k, num_trials, seed, device)`` normalised
    (``candidate_offsets`` is checked finite).
    """
    if selector is not None and not isinstance(selector, SamplingPolicySelector):
        raise ValueError(
            "selector must be a SamplingPolicySelector or None (passive), got "
            f"{type(selector).__name__}"
        )
    collector = collector or getattr(selector, "collector", None)
    _check_choice("tie_break", tie_break, TIE_BREAKS)
    schedule = _check_schedule(schedule)
    num_steps = _count("num_steps", num_steps)
    knn_k = _count("knn_k", knn_k)
    if num_trials is not None:
        num_trials = _count("num_trials", num_trials)
    if not 0 < gamma <= 1:
        raise ValueError(f"gamma must lie in (0, 1], got {gamma}")
    _check_lambda(lam)
    _check_choice("rewarded_slice", rewarded_slice, SLICES)
    if store[0] and store[1] is None:
        raise ValueError("resume and overwrite need a checkpoint_path")
    _check_choice("psi_mode", psi_mode, PSI_MODES)
    _check_choice("fit", fit, FITS)
    if fit == "lstd" and psi_mode != "single":
        raise ValueError(f"fit='lstd' needs psi_mode='single', got {psi_mode!r}")
    if num_trials is not None and collector:
        raise ValueError("a collector (the loop's or the selector's) works without num_trials")
    if num_trials is not None and not env_is_factory:
        raise ValueError("num_trials needs env as a callable batch_size -> env (T·M_l rows)")
    if extra[0] and (num_trials is not None or not extra[1]):
        raise ValueError(
            "extra_candidates are offered to the selector: they need active mode (selector=) "
            "and work without num_trials (a TorchRL actor holds one set of parameters)"
        )
    _check_finite("candidate_offsets", candidate_offsets)
    return schedule, num_steps, knn_k, num_trials, _check_seed(seed), _check_device(device)


def run_settings(loop) -> dict:
    """What gives a run's stored data its meaning, read from the loop's public settings
    (:class:`~torch_api.loop.iteration.ActivePolicyIteration`): a resume must agree on all of
    it. λ, the device, the worker processes and ``evaluate`` are left out: they may change on
    resume (a fit that failed for a bad λ can be redone with a better one)."""
    selector, warm = loop.selector, loop.initial_episodes
    settings = {
        "schedule": loop.schedule,
        "num_steps": loop.num_steps,
        "gamma": loop.gamma,
        "mode": loop.mode,
        "num_repeats": None if selector is None else selector.num_repeats,
        "criterion": None if selector is None else qualified(selector.criterion),
        "num_trials": loop.num_trials,
        "seed": loop.seed,
        "trial_seeds": loop.trial_seeds,
        "psi_mode": loop.psi.mode,
        "knn_k": loop.psi.k,
        "improvement": loop.improvement,
        "beta": loop.beta,
        "tie_break": loop.tie_break,
        "candidate_offsets": list(loop.candidate_offsets),
        "epsilons": loop.family.settings(len(loop.schedule) + 1),
        "initial_theta": loop.initial_theta.tolist(),
        "basis": fingerprint(loop.basis),
        "env": fingerprint(loop.envs(math.prod(loop.trial_dims) * loop.schedule[0])),
        "keep_reward_free": loop.keep_reward_free,
        "rewarded_slice": loop.rewarded_slice,
        "initial_episodes": None
        if warm is None
        else {str(k): plain(v) for k, v in warm.items(True, True)},
        "fit": loop.fit,
    }
    if loop.extra_candidates:  # (left out when there are none: older runs stay resumable)
        settings["extra_candidates"] = [qualified(c) for c in loop.extra_candidates]
    return settings | loop.evaluation.settings()  # ν (left out at 1.0, as before it)
