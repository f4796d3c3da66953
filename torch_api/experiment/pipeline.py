"""A user's own TorchRL loop of Algorithm 1, its steps made durable, run by run (a seed each).

What ``examples/torchrl_pipeline.py`` needs that is not its own: rows of an env in one
``SerialEnv`` (:func:`serial_env`), M padded episodes from a ``Collector``
(:func:`collect_padded`), the mean return of seeded test episodes (:func:`mean_return`), the
sampling-policy candidates of eq. 59 (:func:`epsilon_candidates`), and the steps of a run, each
made at most once through its :class:`~torch_api.runs.store.RunStore` with its own seeded
draws, and the run's history (:class:`StoredSteps`). The runs over seeds, their summary and
files: :mod:`torch_api.experiment.seeds`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase
from torchrl.collectors import Collector
from torchrl.envs import EnvBase, SerialEnv
from torchrl.envs.utils import set_exploration_type

from torch_api.core.fit import fit_flattened
from torch_api.data.episodes import as_episodes
from torch_api.policies.families import PAPER_EPSILON_OFFSETS, candidate_epsilons
from torch_api.runs.store import RunStore, StoredRun
from torch_api.streams import derive_seed

__all__ = ["StoredSteps", "collect_padded", "epsilon_candidates", "mean_return", "serial_env"]


def serial_env(make_env: Callable[[], EnvBase], rows: int, seed: int | None = None) -> SerialEnv:
    """``rows`` envs of ``make_env`` in one ``SerialEnv`` ``[rows]``, seeded if ``seed`` is set."""
    env = SerialEnv(rows, make_env)
    if seed is not None:
        env.set_seed(seed)
    return env


def collect_padded(env: EnvBase, policy, num_episodes: int, num_steps: int) -> TensorDictBase:
    """``num_episodes`` rewarded episodes ``[M, N]`` of ``policy`` on ``env`` (one per row, at
    most ``num_steps`` steps), from a TorchRL ``Collector`` yielding whole padded trajectories."""
    collector = Collector(
        env,
        policy,
        frames_per_batch=num_episodes * num_steps,
        total_frames=-1,
        trajs_per_batch=num_episodes,
        traj_format="padded",
        auto_register_policy_transforms=False,
    )
    batch = next(iter(collector))
    collector.shutdown()
    return as_episodes(batch, rewarded=True, num_steps=num_steps, taken_log_prob=True)


def mean_return(
    policy, make_env: Callable[[], EnvBase], rows: int, steps: int, seed: int, exploration
) -> float:
    """The mean return of ``policy`` under ``exploration`` over ``rows`` test episodes of at
    most ``steps`` steps: one rollout of ``rows`` envs of ``make_env`` in a ``SerialEnv``, the
    envs and torch's generator seeded with ``seed``, the steps after each end masked."""
    torch.manual_seed(seed)
    env = serial_env(make_env, rows, seed)
    with set_exploration_type(exploration):
        rollout = env.rollout(steps, policy, break_when_any_done=False)
    env.close()
    done = as_episodes(rollout, rewarded=True)
    return float((done["next", "reward"] * done["mask"]).sum(-1).mean())


def epsilon_candidates(policy, offsets: Sequence[float] = PAPER_EPSILON_OFFSETS) -> dict:
    """The sampling-policy candidates of eq. 59 around the ε-greedy ``policy`` (pi_l, ε_l), by
    name: ``{"ε-greedy θ (ε = 0.150)": policy.with_rule(epsilon=ε_l + offset), ...}``."""
    rules = candidate_epsilons(float(policy.epsilon), offsets)
    return {f"ε-greedy θ (ε = {e:.3f})": policy.with_rule(epsilon=e) for e in rules}


class StoredSteps:
    """The steps of one run, each made at most once: what ``store`` holds is read back (a
    resumed run buys nothing twice), the rest is made by the caller and committed with
    ``put_*`` before it is used. Each getter returns None where nothing is stored.

    Every draw of iteration l comes from ``derive_seed(seed, l, stream)`` (:meth:`seed_of`):
    torch's generator before the candidates' reward-free episodes (``"reward_free_policy"``)
    and before the rewarded ones (``"policy"``), the envs' rows (``"reward_free_env"``,
    ``"rewarded_env"``), the tests (``"evaluation"``); a resumed run ends with an uninterrupted
    one's numbers.

    Args:
        store: the run's open :class:`~torch_api.runs.store.RunStore`.
        seed: the run's seed.
        iterations: L; a resumed run says where it resumes, one line ``resumed <store> at
            iteration l/L``.

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as d, RunStore(f"{d}/r.db", config={}) as store:
        ...     steps = StoredSteps(store)
        ...     steps.record(1), steps.put_record(1, {"theta": [1.0]}), steps.record(1)
        (None, {'theta': [1.0]}, {'theta': [1.0]})
    """

    def __init__(self, store: RunStore, seed: int = 0, iterations: int | None = None) -> None:
        self.store, self.run_seed, self.started = store, seed, time.perf_counter()
        self.run = store.stored or StoredRun(config=store.config)
        self.resumed = store.stored is not None
        self.bought = 0
        """rewarded episodes bought by this process (not read back)"""
        self.history: list[dict] = []
        """the rows of the iterations so far (:meth:`row`)"""
        if self.resumed and iterations is not None:
            print(f"resumed {store.path} at iteration {len(self.run.records)}/{iterations}")

    def seed_of(self, it: int, stream: str) -> int:
        """The seed of iteration ``it``'s draws of ``stream``: ``derive_seed(seed, it, stream)``."""
        return derive_seed(self.run_seed, it, stream)

    def selection(self, it: int) -> tuple[dict, TensorDictBase] | None:
        """Iteration ``it``'s stored ``(selection, reward-free episodes)``."""
        if it not in self.run.selections:
            return None
        return self.run.selections[it], self.run.free[it]

    def put_selection(self, it: int, selection: dict, free: TensorDictBase):
        """Commit iteration ``it``'s selection (a JSON-able dict) and reward-free episodes."""
        self.store.put_selection(it, selection, free)
        self.run.selections[it], self.run.free[it] = selection, free
        return selection, free

    def episodes(self, it: int, num_episodes: int) -> TensorDictBase | None:
        """Iteration ``it``'s stored rewarded episodes ``[M, N]``, if all M are there."""
        stored = self.run.episodes.get(it, {})
        if len(stored) < num_episodes:
            return None
        return torch.stack([stored[j] for j in range(num_episodes)])

    def put_episodes(self, it: int, episodes: TensorDictBase) -> TensorDictBase:
        """Commit iteration ``it``'s rewarded episodes ``[M, N]``, bought by this process."""
        self.store.put_episodes(it, dict(enumerate(episodes.unbind(0))))
        self.run.episodes[it] = dict(enumerate(episodes.unbind(0)))
        self.bought += episodes.shape[0]
        return episodes

    def choose(
        self, it: int, selector, policy, candidates: Sequence, earlier, flattening
    ) -> tuple[dict, TensorDictBase]:
        """Step 1 of iteration ``it``: the stored choice, else J' of ``candidates`` from
        reward-free episodes (:meth:`SamplingPolicySelector.select
        <torch_api.loop.selector.SamplingPolicySelector.select>`, its env and torch seeded;
        ``earlier``: the rewarded episodes so far, or None), committed. Returns
        ``({"index", "j_mean", "reward_free_transitions"}, reward-free episodes [Z·K·M, N])``."""
        torch.manual_seed(self.seed_of(it, "reward_free_policy"))  # the candidates' draws
        if self.selection(it) is None:
            env_seed = self.seed_of(it, "reward_free_env")
            selector.seed_env(selector.collection_rows(candidates), env_seed)
            choice = selector.select(
                policy, candidates, earlier, iteration=it, flattening=flattening
            )
            free = choice.episodes.reshape(-1, choice.episodes.shape[-1])
            selection = {"index": int(choice.index), "j_mean": choice.j_mean.tolist()}
            selection["reward_free_transitions"] = choice.reward_free_transitions
            free = as_episodes(free, rewarded=False, taken_log_prob=True)
            self.put_selection(it, selection, free)
        return self.selection(it)

    def buy(
        self, it: int, num_episodes: int, rows: Callable[[int, int], EnvBase], policy, num_steps
    ) -> TensorDictBase:
        """Step 2 of iteration ``it``: the stored rewarded episodes ``[M, N]``, else M episodes
        of ``policy`` (torch seeded) on ``rows(M, seed)`` (M rows, seeded) from a ``Collector``
        (:func:`collect_padded`), committed."""
        torch.manual_seed(self.seed_of(it, "policy"))  # the sampler's draws
        if (stored := self.episodes(it, num_episodes)) is not None:
            return stored
        env = rows(num_episodes, self.seed_of(it, "rewarded_env"))
        return self.put_episodes(it, collect_padded(env, policy, num_episodes, num_steps))

    def fit(
        self, it: int, evaluation, episodes, policy, psi, basis, theta, measure, **extra
    ) -> dict:
        """Steps 3-4 of iteration ``it``: the stored record, else θ_l fitted on every rewarded
        ``episodes`` so far (``[M, N]``) under ``evaluation`` (an
        :class:`~torch_api.loop.spec.EvaluationSpec`: BRM or LSTD-Q, λ, flattening ν) with
        importance weights towards ``policy`` (pi_l), committed as a record with its
        ``rewarded_transitions``, ``flattening``, ``ess_percent``, ``theta_change`` (from
        ``theta``), θ (``"theta"``), ``measure(θ_l, seed)``'s entries (e.g. a test return; the
        seed of the ``"evaluation"`` stream) and ``extra``."""
        if (stored := self.record(it)) is not None:
            return stored
        fitted = fit_flattened(evaluation.fit, episodes, policy, psi, basis, evaluation.lam,
                               flattening=evaluation.flattening, grid=evaluation.flattening_grid,
                               folds=evaluation.iwcv_folds)  # fmt: skip
        record = extra | {
            "rewarded_transitions": int(episodes["mask"].sum()),
            "flattening": float(fitted.flattening),
            "ess_percent": float(100 * fitted.ess / fitted.num_samples),
            "theta_change": float((fitted.theta - theta).norm()),
        }
        record |= measure(fitted.theta, self.seed_of(it, "evaluation"))
        return self.put_record(it, record | {"theta": fitted.theta.tolist()})

    def record(self, it: int) -> dict | None:
        """Iteration ``it``'s stored record."""
        return self.run.records.get(it)

    def put_record(self, it: int, record: dict) -> dict:
        """Commit iteration ``it``'s record (a JSON-able dict)."""
        self.store.put_record(it, record)
        self.run.records[it] = record
        return record

    def row(self, it: int, chosen: str, bought: TensorDictBase, selection: dict, record: dict):
        """Iteration ``it``'s row of the run's history, returned and kept for :meth:`result`:
        the sampler ``chosen``, the returns of the ``bought`` episodes ``[M, N]``, then
        ``selection`` and ``record``, but for the selection's index and θ."""
        returns = (bought["next", "reward"] * bought["mask"]).sum(-1).tolist()
        row = {"iteration": it, "chosen": chosen, "bought_returns": returns} | selection | record
        self.history.append({k: v for k, v in row.items() if k not in ("index", "theta")})
        return row

    def result(self, theta: torch.Tensor, label: str) -> dict:
        """The run's ``{"history", "theta", "bought", "seconds"}`` (since these steps were made),
        after one line ``<label>: bought <n> rewarded episodes in this run``."""
        print(f"{label}: bought {self.bought} rewarded episodes in this run")
        seconds = time.perf_counter() - self.started
        return {"history": self.history, "theta": theta.tolist(), "bought": self.bought,
                "seconds": seconds}  # fmt: skip
