"""The chain walk (paper section 3.5, Figure 1) as a batched TorchRL environment.

States are numbered 1 … S (the observation holds the state *number*, so a Gaussian basis with
centres 1, 3, 5, 7, 9 applies to it directly). Its exact model is :mod:`envs.chain_walk.model`.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from .._common import RandomStreams, check_seed, done_spec, fresh_seed
from ._checks import _check_prob, _check_reward_profile, _check_steps
from .model import (
    DEFAULT_REWARD_PROFILE,
    N_ACTIONS,
    N_STATES,
    SUCCESS_PROB,
    ChainWalkModel,
    chain_walk_model,
)

__all__ = ["ChainWalkEnv"]


class ChainWalkEnv(EnvBase):
    """Batched chain walk (paper section 3.5, Figure 1) as a TorchRL environment.

    States 1 … S, actions 0 = 'L' and 1 = 'R'. The intended move succeeds with probability
    ``success_prob``, otherwise the agent moves one state the other way; a move off either end
    leaves it in place. Reward R(s, a, s') = f(s') (eq. 49); the initial state is uniform. The
    walk never terminates: ``terminated`` is always False, and with ``max_steps`` the episode is
    truncated (``truncated`` = ``done`` = True) on the step that reaches that count.

    The env is stateless in the TorchRL sense: ``_step`` reads the current state from the
    input's ``"observation"`` (the state number as float32 [E, 1]), so stepping a hand-built
    TensorDict from any state is allowed. With ``max_steps`` the step count travels in
    ``"step_count"`` (int64 [E, 1]). All randomness comes from the env's own
    counter-based streams (``set_seed``, ``set_block_seeds``); equal seeds give equal
    trajectories.

    Keys: ``"observation"`` float32 [E, 1]; ``"action"`` int64 [E] (``Categorical(2)``; a
    one-hot [E, 2] action is accepted too); ``"reward"`` float32 [E, 1]; ``"done"``,
    ``"terminated"``, ``"truncated"`` bool [E, 1].

    Args:
        batch_size: number of parallel walks E (an int) or a batch shape.
        reward_profile: f(s') for s' = 1 … S; must have ``n_states`` entries.
        success_prob: probability that the intended move succeeds, in [0, 1].
        max_steps: if given, episodes are truncated after this many steps.
        n_states: number of states S (10 in the paper).
        device: device of the env's tensors (CPU by default). The random numbers are drawn on
            the CPU whatever the device, so a seed gives the same walks on CPU and GPU.
        seed: key of the env's random stream; ``None`` draws a fresh one (not from global state).

    Example:
        >>> env = ChainWalkEnv(batch_size=4, seed=0)
        >>> td = env.rollout(10, break_when_any_done=False)
        >>> td["observation"].shape, td["action"].shape, td["next", "reward"].shape
        (torch.Size([4, 10, 1]), torch.Size([4, 10]), torch.Size([4, 10, 1]))
    """

    def __init__(
        self,
        *,
        batch_size: int | Sequence[int] = 1,
        reward_profile: torch.Tensor | Sequence[float] = DEFAULT_REWARD_PROFILE,
        success_prob: float = SUCCESS_PROB,
        max_steps: int | None = None,
        n_states: int = N_STATES,
        device: torch.device | str | None = None,
        seed: int | None = None,
    ) -> None:
        if isinstance(batch_size, int):
            batch_size = (batch_size,)
        batch_size = torch.Size(batch_size)
        if any(n < 1 for n in batch_size):
            raise ValueError(f"batch_size must hold positive sizes, got {tuple(batch_size)}")
        if isinstance(n_states, bool) or not isinstance(n_states, int) or n_states < 2:
            raise ValueError(f"n_states must be an int >= 2, got {n_states!r}")
        f = _check_reward_profile(reward_profile, n_states)
        self.success_prob = _check_prob(success_prob, "success_prob")
        if max_steps is not None:
            max_steps = _check_steps(max_steps, "max_steps")
        self.max_steps = max_steps
        check_seed(seed)
        super().__init__(
            device=torch.device("cpu") if device is None else device, batch_size=batch_size
        )
        self.n_states = n_states
        self.reward_profile = f.to(self.device)  # float64 [S], for the exact model
        self._f32 = f.to(device=self.device, dtype=torch.float32)
        self.streams = RandomStreams(rows=batch_size.numel())
        self._make_spec()
        self.set_seed(fresh_seed() if seed is None else seed)

    # -- specs --------------------------------------------------------------------------------

    def _make_spec(self) -> None:
        shape = self.batch_size
        observation = {
            "observation": Bounded(
                low=1.0,
                high=float(self.n_states),
                shape=(*shape, 1),
                dtype=torch.float32,
                device=self.device,
            )
        }
        if self.max_steps is not None:
            observation["step_count"] = Bounded(
                low=0,
                high=self.max_steps,
                shape=(*shape, 1),
                dtype=torch.int64,
                device=self.device,
            )
        self.observation_spec = Composite(observation, shape=shape, device=self.device)
        self.action_spec = Categorical(
            N_ACTIONS, shape=shape, dtype=torch.int64, device=self.device
        )
        self.reward_spec = Unbounded(shape=(*shape, 1), dtype=torch.float32, device=self.device)
        self.done_spec = done_spec(shape, self.device)

    # -- seeding ------------------------------------------------------------------------------

    def _set_seed(self, seed: int | None) -> None:
        self.streams.seed(seed)  # drawn on the CPU whatever the env's device

    def set_block_seeds(self, seeds: Sequence[int]) -> None:
        """Give each of ``len(seeds)`` equal, consecutive blocks of rows its own random stream.

        With rows laid out block-major (e.g. one block per independent trial), block ``b``
        then draws exactly what an env of one block seeded with ``seeds[b]`` would: a batched
        run of many trials reproduces one-at-a-time runs. ``set_seed`` returns to one stream.
        """
        self.streams.set_block_seeds(seeds)

    # -- dynamics -----------------------------------------------------------------------------

    def model(self) -> ChainWalkModel:
        """The exact model of this env (float64 tensors on the env's device)."""
        return chain_walk_model(
            self.reward_profile, self.success_prob, n_states=self.n_states, device=self.device
        )

    def _flags(self, truncated: torch.Tensor) -> dict[str, torch.Tensor]:
        terminated = torch.zeros_like(truncated)
        return {"done": truncated | terminated, "terminated": terminated, "truncated": truncated}

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        shape = self.batch_size
        state = self._initial_states().unsqueeze(-1)
        out = {"observation": state.to(torch.float32)}
        if self.max_steps is not None:
            out["step_count"] = torch.zeros((*shape, 1), dtype=torch.int64, device=self.device)
        # Partial reset: rows outside the "_reset" mask keep their state (EnvBase.reset merges
        # the same way; doing it here keeps a direct `_reset` call correct too).
        mask = tensordict.get("_reset", None) if tensordict is not None else None
        if mask is not None and not mask.all():
            for key in out:
                old = tensordict.get(key, None)
                if old is not None:
                    out[key] = torch.where(mask.reshape(*shape, 1), out[key], old)
        out.update(self._flags(torch.zeros((*shape, 1), dtype=torch.bool, device=self.device)))
        return TensorDict(out, batch_size=shape, device=self.device)

    def _action_indices(self, action: torch.Tensor) -> torch.Tensor:
        """Action indices [*E] from indices [*E], [*E, 1] or a one-hot [*E, 2]."""
        n_batch = len(self.batch_size)
        if action.ndim == n_batch + 1 and action.shape[-1] == N_ACTIONS:
            return action.long().argmax(-1)  # one-hot (bool or integer)
        if action.ndim == n_batch + 1 and action.shape[-1] == 1:
            action = action.squeeze(-1)
        if action.shape != self.batch_size:
            raise ValueError(
                f"action must have shape {tuple(self.batch_size)} (indices) or "
                f"{(*self.batch_size, N_ACTIONS)} (one-hot), got {tuple(action.shape)}"
            )
        action = action.long()
        if ((action < 0) | (action >= N_ACTIONS)).any():
            raise ValueError(f"action indices must be 0 ('L') or 1 ('R'), got {action.unique()}")
        return action

    def _initial_states(self) -> torch.Tensor:
        """Uniform initial states ``[*E]`` (long, 1 … S), drawn from the env's streams."""
        shape = (*self.batch_size, 1)
        return self.streams.integers(1, self.n_states + 1, shape).to(self.device).squeeze(-1)

    def _transition(self, state: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Next states ``[*E]`` of states and action indices ``[*E]`` (one uniform per row
        from the env's streams: the intended move succeeds with ``success_prob``)."""
        intended = 2 * action - 1  # 'L' -> -1, 'R' -> +1
        success = self.streams.uniform(self.batch_size).to(self.device) < self.success_prob
        move = torch.where(success, intended, -intended)
        return (state + move).clamp(1, self.n_states)

    def walk(self, choose, num_steps: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Episodes of ``num_steps`` steps without TorchRL's rollout machinery: exactly the
        draws and the numbers of ``reset()`` followed by ``num_steps`` calls of ``step()``
        with the actions ``choose(states [*E] long) -> [*E]`` (action indices).

        For evaluating many policies fast (no TensorDict per step, nothing stored but the
        states and rewards). Returns the states ``[*E, N + 1]`` (long) and the rewards
        ``[*E, N]`` (float32, as ``step`` gives them).

        Example:
            >>> env = ChainWalkEnv(batch_size=3, seed=0)
            >>> states, rewards = env.walk(lambda s: torch.ones_like(s), 4)  # always 'R'
            >>> states.shape, rewards.shape
            (torch.Size([3, 5]), torch.Size([3, 4]))
        """
        state = self._initial_states()
        states, rewards = [state], []
        for _ in range(num_steps):
            action = torch.as_tensor(choose(state), device=self.device).long()
            state = self._transition(state, action)
            states.append(state)
            rewards.append(self._f32[state - 1])
        return torch.stack(states, -1), torch.stack(rewards, -1)

    def walk_tabulated(
        self, action_probs: torch.Tensor, num_steps: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Episodes of policies given as tables, with the actions summed out: one uniform per
        step instead of an action's and a move's.

        The rewards depend on the states alone (eq. 49), and under a policy pi the states are
        a Markov chain that moves right with probability ``q(s) = pi(R|s) p + pi(L|s)(1 − p)``
        (p = ``success_prob``; a move off an end stays). So the walk draws one uniform u per
        row and step and moves right iff ``u < q(s)``: the same law of the states and rewards
        as :meth:`walk` or a rollout of the policy (tested), not the same numbers. The initial
        states are drawn as :meth:`reset` draws them.

        Args:
            action_probs: pi(a|s) ``[K, S, A]`` for states 1 … S, one table per equal,
                consecutive block of the env's rows (e.g. one per trial: row e follows table
                ``e // (E / K)``).
            num_steps: N.

        Returns:
            time-major (step first, as computed): the states ``[N + 1, *E]`` (long) and the
            rewards ``[N, *E]`` (float32).

        Example:
            >>> env = ChainWalkEnv(batch_size=4, seed=0)
            >>> right = torch.tensor([[0.0, 1.0]]).expand(2, 10, 2)  # 2 tables: always 'R'
            >>> states, rewards = env.walk_tabulated(right, 3)
            >>> states.shape, rewards.shape
            (torch.Size([4, 4]), torch.Size([3, 4]))
        """
        rows, tables = self.batch_size.numel(), action_probs.shape[0]
        if action_probs.shape[1:] != (self.n_states, N_ACTIONS) or rows % tables:
            raise ValueError(
                f"action_probs must be [K, {self.n_states}, {N_ACTIONS}] with K dividing the "
                f"{rows} rows, got {tuple(action_probs.shape)}"
            )
        p = self.success_prob
        right = action_probs[..., 1] * p + action_probs[..., 0] * (1.0 - p)  # q(s), [K, S]
        right = right.to(device=self.device, dtype=torch.float64).reshape(-1)
        first = torch.arange(tables, device=self.device).repeat_interleave(rows // tables)
        first = first * self.n_states - 1  # row e's q(s) at first[e] + s
        states = torch.empty(num_steps + 1, rows, dtype=torch.long, device=self.device)
        states[0] = self._initial_states().reshape(-1)
        for step in range(num_steps):
            u = self.streams.uniform(torch.Size([rows])).to(self.device)
            move = torch.where(u < right.index_select(0, first + states[step]), 1, -1)
            torch.clamp(states[step] + move, 1, self.n_states, out=states[step + 1])
        shape = self.batch_size
        return states.reshape(-1, *shape), self._f32[states[1:] - 1].reshape(-1, *shape)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        shape = self.batch_size
        state = tensordict["observation"].reshape(shape).round().long()
        if ((state < 1) | (state > self.n_states)).any():
            raise ValueError(
                f"observation must hold state numbers 1 … {self.n_states}, got {state.unique()}"
            )
        next_state = self._transition(state, self._action_indices(tensordict["action"]))
        out = {
            "observation": next_state.to(torch.float32).unsqueeze(-1),
            "reward": self._f32[next_state - 1].unsqueeze(-1),
        }
        truncated = torch.zeros((*shape, 1), dtype=torch.bool, device=self.device)
        if self.max_steps is not None:
            step_count = tensordict["step_count"] + 1
            out["step_count"] = step_count
            truncated = step_count >= self.max_steps
        out.update(self._flags(truncated))
        return TensorDict(out, batch_size=shape, device=self.device)
