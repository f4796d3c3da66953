"""TorchRL's own DQN at the rewarded budget of the library's showcase, beside AL and PL:
CartPole-v1 and Acrobot-v1.

DQN as TorchRL's example ``sota-implementations/dqn/dqn_cartpole.py`` builds it (an MLP
``QValueActor`` of 120 and 84 ReLU units, ``EGreedyModule``, a ``Collector``, a
``TensorDictReplayBuffer``, ``DQNLoss`` with a delayed target and ``HardUpdate``) with that
example's ``config_cartpole.yaml`` settings, untuned (:data:`TORCHRL_CONFIG`). TorchRL has no
Acrobot DQN config: Acrobot-v1 gets the same CartPole config, untuned, scaled the same way.
The example spends 500,100 frames; here a run of task i buys ``--frames[i]`` (CartPole
10,000: the showcase buys about 8,200 rewarded transitions a run; Acrobot 15,000: the
showcase's Acrobot cap), so the two settings counted in frames, the ε annealing and the random
frames before learning, are scaled by ``frames / 500,100`` (:func:`scaled`; unscaled, the
10,000 random frames would be the whole budget and the network would never train). TorchRL's
``Collector`` draws random actions for whole batches: the scaled 200 (CartPole) and 300
(Acrobot) random frames are its first batch of 1,000 (it warns so).

Each seed's greedy policy is then tested as the library's showcase tests its last iteration
(``examples/torchrl_pipeline.py``): 5 test episodes of at most 500 steps in a seeded
``SerialEnv``, seed ``derive_seed(seed, L, "evaluation")`` with the showcase's L of the task
(:data:`LIBRARY_ITERATIONS`), the mean return. With ``--library`` the showcase's JSON files
(``python examples/torchrl_pipeline.py --env <task> --seeds 10``, each naming its env) give
AL's and PL's last greedy returns on the same seeds, and ``--out`` gets the data file, one row
and three baselines per task::

    python benchmarks/dqn_baseline.py --seeds 10 --envs CartPole-v1 Acrobot-v1 \\
        --frames 10000 15000 --library results/budget/lib_cartpole/torchrl_pipeline.json \\
        results/budget/lib_acrobot/torchrl_pipeline.json --out docs/results/data/dqn_baseline.json
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch
import tyro
from tensordict.nn import TensorDictSequential
from torchrl.collectors import Collector
from torchrl.data import Composite, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import (
    Compose,
    ExplorationType,
    GymEnv,
    RewardSum,
    SerialEnv,
    StepCounter,
    TransformedEnv,
)
from torchrl.envs.utils import set_exploration_type
from torchrl.modules import MLP, EGreedyModule, QValueActor
from torchrl.objectives import DQNLoss, HardUpdate

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # (benchmarks.summarize)

from torch_api.runs.files import write_text_atomic  # noqa: E402
from torch_api.streams import derive_seed  # noqa: E402

TORCHRL_CONFIG = {  # sota-implementations/dqn/config_cartpole.yaml (pytorch/rl), as read
    "total_frames": 500_100,
    "frames_per_batch": 1000,
    "eps_start": 1.0,
    "eps_end": 0.05,
    "annealing_frames": 250_000,
    "init_random_frames": 10_000,
    "buffer_size": 10_000,
    "batch_size": 128,
    "lr": 2.5e-4,
    "gamma": 0.99,
    "hard_update_freq": 50,
    "num_updates": 100,  # gradient steps per collected batch
    "num_cells": [120, 84],
    "loss_function": "l2",
}
ROOT = Path(__file__).resolve().parents[1]
LIBRARY_ITERATIONS = {"CartPole-v1": 8, "Acrobot-v1": 6}  # the showcase's L: its last test's seed


@dataclass
class Args:
    """DQN (TorchRL's example, untuned) at the library's rewarded budget."""

    seeds: int = 10
    """runs: seeds seed, seed+1, … (the library's showcase runs the same seeds)"""
    seed: int = 0
    """first seed"""
    envs: tuple[str, ...] = ("CartPole-v1",)
    """the Gymnasium environments"""
    frames: tuple[int, ...] = (10_000,)
    """rewarded transitions (env steps) a DQN run buys, one number per env"""
    test_episodes: int = 5
    """greedy test episodes (the showcase's)"""
    test_steps: int = 500
    """longest test episode (the showcase's)"""
    library: tuple[str, ...] = ()
    """the showcase's torchrl_pipeline.json files on these seeds (AL and PL), merged per env"""
    out_dir: str = "results/dqn_baseline"
    """where each seed's result is stored as it finishes (a rerun skips the stored ones)"""
    library_code: str = ""
    """which code made the --library files (e.g. a commit), written into the data file"""
    out: str = ""
    """the data file to write (docs/results/data/dqn_baseline.json), or empty"""


def scaled(frames: int) -> dict:
    """The example's settings with the frame-counted ones scaled to a budget of ``frames``."""
    ratio = frames / TORCHRL_CONFIG["total_frames"]
    config = dict(TORCHRL_CONFIG, total_frames=frames)
    config["annealing_frames"] = max(1, round(ratio * TORCHRL_CONFIG["annealing_frames"]))
    config["init_random_frames"] = round(ratio * TORCHRL_CONFIG["init_random_frames"])
    return config


def make_env(env_id: str, max_steps: int | None = None) -> TransformedEnv:
    """The example's env: raw observations, episode return and step count."""
    return TransformedEnv(GymEnv(env_id), Compose(RewardSum(), StepCounter(max_steps=max_steps)))


def train(env_id: str, config: dict, seed: int) -> tuple[QValueActor, dict]:
    """One DQN run of ``config["total_frames"]`` env steps; the Q-network and its counts."""
    torch.manual_seed(derive_seed(seed, 0, "policy"))
    env = make_env(env_id)
    env.set_seed(derive_seed(seed, 0, "rewarded_env"))
    action = env.full_action_spec["action"]
    mlp = MLP(
        in_features=env.observation_spec["observation"].shape[-1],
        out_features=action.space.n,
        num_cells=config["num_cells"],
        activation_class=torch.nn.ReLU,
    )
    model = QValueActor(module=mlp, spec=Composite(action=action), in_keys=["observation"])
    greedy = EGreedyModule(
        spec=model.spec,
        eps_init=config["eps_start"],
        eps_end=config["eps_end"],
        annealing_num_steps=config["annealing_frames"],
    )
    collector = Collector(
        env,
        TensorDictSequential(model, greedy),
        frames_per_batch=config["frames_per_batch"],
        total_frames=config["total_frames"],
        init_random_frames=config["init_random_frames"],
        auto_register_policy_transforms=False,  # as the recorded runs (TorchRL 0.15's default)
    )
    buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(config["buffer_size"]), batch_size=config["batch_size"]
    )
    loss = DQNLoss(value_network=model, loss_function=config["loss_function"], delay_value=True)
    loss.make_value_estimator(gamma=config["gamma"])
    target = HardUpdate(loss, value_network_update_interval=config["hard_update_freq"])
    optimizer = torch.optim.Adam(loss.parameters(), lr=config["lr"])
    frames = updates = 0
    for data in collector:
        data = data.reshape(-1)
        buffer.extend(data)
        frames += data.numel()
        greedy.step(data.numel())
        if frames < config["init_random_frames"]:
            continue
        for _ in range(config["num_updates"]):
            value = loss(buffer.sample())["loss"]
            optimizer.zero_grad()
            value.backward()
            optimizer.step()
            target.step()
            updates += 1
        collector.update_policy_weights_()
    collector.shutdown()
    return model, {"frames": frames, "gradient_steps": updates}


def test(args: Args, env_id: str, model: QValueActor, seed: int) -> float:
    """The showcase's test: greedy, ``test_episodes`` seeded rows of ≤ ``test_steps`` steps."""
    test_seed = derive_seed(seed, LIBRARY_ITERATIONS.get(env_id, 8), "evaluation")
    torch.manual_seed(test_seed)
    rows = SerialEnv(args.test_episodes, partial(make_env, env_id, args.test_steps))
    rows.set_seed(test_seed)  # (as the showcase seeds its test rows)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = rows.rollout(args.test_steps, model, break_when_any_done=False)
    rows.close()
    done = rollout["next", "done"].squeeze(-1).long()  # [E, steps]
    live = (done.cumsum(-1) - done) == 0  # each row's steps up to its first episode's end
    return float((rollout["next", "reward"].squeeze(-1) * live).sum(-1).mean())


def run_seed(args: Args, env_id: str, config: dict, seed: int, out: Path) -> dict:
    """One seed's run and test, stored in ``out/<env>_seed<seed>.json`` (read back if there,
    made with the same frames and test seed)."""
    path, tested = out / f"{env_id}_seed{seed}.json", LIBRARY_ITERATIONS.get(env_id, 8)
    if path.is_file():
        stored = json.loads(path.read_text())
        same = (stored["frames"], stored.get("test_iteration", 8))
        if same == (config["total_frames"], tested):
            return stored | {"task": env_id}
    started = time.perf_counter()
    model, counts = train(env_id, config, seed)
    result = {"task": env_id, "seed": seed, "greedy_test_return": test(args, env_id, model, seed)}
    result["test_iteration"] = tested  # (the test's seed: derive_seed(seed, this, "evaluation"))
    result |= counts | {"seconds": time.perf_counter() - started}
    write_text_atomic(path, json.dumps(result))
    print(f"DQN {env_id} seed {seed}: greedy test return {result['greedy_test_return']:.1f}")
    return result


def stats(values) -> dict:
    x = np.asarray(values, dtype=np.float64)
    se = float(x.std(ddof=1) / math.sqrt(x.size)) if x.size > 1 else None
    return {"mean": float(x.mean()), "se": se, "trials": int(x.size)}


def library_runs(paths: tuple[str, ...]) -> dict:
    """``{env: {"args": the showcase's settings, mode: {seed: (last greedy test return,
    rewarded transitions)}}}`` of the showcase's JSON files (``examples/torchrl_pipeline.py``),
    merged per env (the env its ``args`` name)."""
    out: dict = {}
    for path in paths:
        data = json.loads(Path(path).read_text())
        task = out.setdefault(data["args"].get("env", "CartPole-v1"), {"args": data["args"]})
        for mode, by_seed in data["runs"].items():
            for seed, run in by_seed.items():
                last = run["history"][-1]
                numbers = (last["greedy_test_return"], last["rewarded_transitions"])
                task.setdefault(mode, {})[int(seed)] = numbers
    return out


def schedule_of(settings: dict) -> str:
    """The showcase's schedule, e.g. ``showcase (120, 4 × 7)``."""
    first, m, L = (settings.get(k) for k in ("first_episodes", "episodes", "iterations"))
    return f"showcase ({first}, {m} × {L - 1})" if None not in (first, m, L) else "showcase"


def task_parts(env_id: str, frames: int, runs: list[dict], library: dict) -> tuple[list, list]:
    """One task's baselines (DQN, the library's AL and PL on the seeds both hold) and its
    AL-vs-PL row (paired over those seeds)."""
    import numpy as np

    from benchmarks.summarize import paired_difference, verdict

    dqn = {r["seed"]: r for r in runs}
    baselines = [
        {
            "task": env_id,
            "learner": f"DQN (TorchRL's example, {frames:,} frames)",
            "seeds": sorted(dqn),
            "return": stats([r["greedy_test_return"] for r in runs]),
            "rewarded_transitions": float(np.mean([r["frames"] for r in runs])),
            "seconds": float(np.mean([r["seconds"] for r in runs])),
        }
    ]
    paired = sorted(set(library.get("AL", {})) & set(library.get("PL", {})) & set(dqn))
    for mode in ("AL", "PL") if paired else ():
        held = [library[mode][s] for s in paired]
        baselines.append(
            {
                "task": env_id,
                "learner": f"library {mode} (examples/torchrl_pipeline.py)",
                "seeds": paired,
                "return": stats([h[0] for h in held]),
                "rewarded_transitions": float(np.mean([h[1] for h in held])),
                "seconds": None,  # (a JSON written on --resume holds the resumed seconds)
            }
        )
    if len(paired) < 2:
        return baselines, []
    al, pl = ([library[m][s][0] for s in paired] for m in ("AL", "PL"))
    diff = paired_difference(al, pl)
    settings = library.get("args", {})
    tested = LIBRARY_ITERATIONS.get(env_id, 8)
    if settings.get("iterations", tested) != tested:
        warning = f"warning: {env_id}'s showcase ran L = {settings['iterations']}, DQN's test"
        print(f"{warning} seeds use L = {tested} (LIBRARY_ITERATIONS)", file=sys.stderr)
    row = {
        "task": env_id,
        "schedule": f"{env_id}: {schedule_of(settings)}",
        "measure": "greedy_test_return",
        "iteration": settings.get("iterations", LIBRARY_ITERATIONS.get(env_id)),
        "al": stats(al),
        "pl": stats(pl),
        "difference": diff,
        "verdict": verdict(diff["mean"], diff["p"]),
        "rewarded_transitions": {
            m: float(np.mean([library[m][s][1] for s in paired])) for m in ("AL", "PL")
        },
    }
    return baselines, [row]


def data_file(args: Args, configs: dict, runs: list[dict], library: dict, wall: float) -> dict:
    """The results' data file: per task, AL vs PL paired over the seeds both hold (``rows``)
    and every learner's greedy return at the budget (``baselines``), with DQN's settings."""
    from benchmarks.summarize import commit_of, machine

    load = __import__("os").getloadavg()
    baselines, rows = [], []
    for env_id, frames in zip(args.envs, args.frames, strict=True):
        mine = [r for r in runs if r["task"] == env_id]
        b, r = task_parts(env_id, frames, mine, library.get(env_id, {}))
        baselines, rows = baselines + b, rows + r
    tasks, tasks_flag = " and ".join(args.envs), " ".join(args.envs)
    return {
        "experiment": "dqn_baseline",
        "title": f"{tasks}: TorchRL's DQN beside the library's AL and PL at one rewarded budget",
        "task": f"{tasks}, DQN baseline",
        "command": f"python benchmarks/dqn_baseline.py --seeds {args.seeds} --envs {tasks_flag}"
        f" --frames {' '.join(map(str, args.frames))} --library {' '.join(args.library)}",
        "commit": commit_of(ROOT),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": machine(load, load, "when the data file was written"),
        "wall_seconds": wall,
        "measures": ["greedy_test_return"],
        "better": "higher",
        "digits": 1,
        "note": f"Greedy test return: {args.test_episodes} seeded test episodes of at most "
        f"{args.test_steps} steps, the library showcase's test of its last iteration. DQN: "
        "TorchRL's sota-implementations/dqn/config_cartpole.yaml, untuned, with the ε annealing "
        "and the random frames scaled to the budget (dqn_config; TorchRL's Collector draws "
        "random actions for whole batches, so for its first 1,000 frames); TorchRL has no "
        "Acrobot DQN config, so Acrobot-v1 runs the same CartPole config, untuned, scaled the "
        "same way. DQN buys exactly its frames; the library's runs buy at most their schedule's "
        "episodes (each ends early when the episode does).",
        "library_code": args.library_code,
        "torchrl_config": TORCHRL_CONFIG,
        "dqn_config": configs,
        "args": asdict(args),
        "rows": rows,
        "baselines": baselines,
        "dqn_runs": runs,
    }


def main(argv: list[str] | None = None) -> dict:
    args = tyro.cli(Args, args=argv, description=__doc__)
    if len(args.frames) != len(args.envs):
        print(f"error: --frames needs one number per env ({len(args.envs)})", file=sys.stderr)
        raise SystemExit(2)
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    configs = {e: scaled(f) for e, f in zip(args.envs, args.frames, strict=True)}
    seeds = list(range(args.seed, args.seed + args.seeds))
    torch.set_num_threads(1)
    runs = [run_seed(args, e, configs[e], s, out) for e in args.envs for s in seeds]
    wall = sum(r["seconds"] for r in runs)  # (each seed's own: a rerun reads them back)
    for e in args.envs:
        returns = [r["greedy_test_return"] for r in runs if r["task"] == e]
        print(f"DQN {e}, {len(seeds)} seeds: {stats(returns)}")
    payload = data_file(args, configs, runs, library_runs(args.library), wall)
    for b in payload["baselines"]:
        print(f"{b['task']} {b['learner']}: {b['return']} over seeds {b['seeds']}")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(Path(args.out), json.dumps(payload, indent=1))
        print(f"wrote {args.out}")
    return payload


if __name__ == "__main__":
    main()
