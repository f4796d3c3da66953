"""TorchRL's own DQN at the rewarded budget of the library's CartPole showcase, beside AL and PL.

DQN as TorchRL's example ``sota-implementations/dqn/dqn_cartpole.py`` builds it (an MLP
``QValueActor`` of 120 and 84 ReLU units, ``EGreedyModule``, a ``Collector``, a
``TensorDictReplayBuffer``, ``DQNLoss`` with a delayed target and ``HardUpdate``) with that
example's ``config_cartpole.yaml`` settings, untuned (:data:`TORCHRL_CONFIG`). The example
spends 500,100 frames; here a run buys ``--frames`` (10,000: the showcase buys about 8,200
rewarded transitions a run), so the two settings counted in frames, the ε annealing and the
random frames before learning, are scaled by ``frames / 500,100`` (:func:`scaled`; unscaled,
the 10,000 random frames would be the whole budget and the network would never train).

Each seed's greedy policy is then tested as the library's showcase tests its last iteration
(``examples/torchrl_pipeline.py``): 5 test episodes of at most 500 steps in a seeded
``SerialEnv``, seed ``derive_seed(seed, L, "evaluation")`` with L = 8, the mean return. With
``--library`` the showcase's JSON (``python examples/torchrl_pipeline.py --seeds 10``) gives
AL's and PL's last greedy returns on the same seeds, and ``--out`` gets the data file::

    python benchmarks/dqn_baseline.py --seeds 10 \\
        --library results/torchrl_pipeline/torchrl_pipeline.json
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
LIBRARY_ITERATIONS = 8  # L of the showcase's CartPole run: its last test uses (seed, 8)


@dataclass
class Args:
    """DQN (TorchRL's example, untuned) at the library's rewarded budget."""

    seeds: int = 10
    """runs: seeds seed, seed+1, … (the library's showcase runs the same seeds)"""
    seed: int = 0
    """first seed"""
    env: str = "CartPole-v1"
    """the Gymnasium environment"""
    frames: int = 10_000
    """rewarded transitions (env steps) a DQN run buys"""
    test_episodes: int = 5
    """greedy test episodes (the showcase's)"""
    test_steps: int = 500
    """longest test episode (the showcase's)"""
    library: tuple[str, ...] = ()
    """the showcase's torchrl_pipeline.json files on these seeds (AL and PL), merged"""
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


def test(args: Args, model: QValueActor, seed: int) -> float:
    """The showcase's test: greedy, ``test_episodes`` seeded rows of ≤ ``test_steps`` steps."""
    test_seed = derive_seed(seed, LIBRARY_ITERATIONS, "evaluation")
    torch.manual_seed(test_seed)
    rows = SerialEnv(args.test_episodes, partial(make_env, args.env, args.test_steps))
    rows.set_seed(test_seed)  # (as the showcase seeds its test rows)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        rollout = rows.rollout(args.test_steps, model, break_when_any_done=False)
    rows.close()
    done = rollout["next", "done"].squeeze(-1).long()  # [E, steps]
    live = (done.cumsum(-1) - done) == 0  # each row's steps up to its first episode's end
    return float((rollout["next", "reward"].squeeze(-1) * live).sum(-1).mean())


def run_seed(args: Args, config: dict, seed: int, out: Path) -> dict:
    """One seed's run and test, stored in ``out/seed<seed>.json`` (read back if there)."""
    path = out / f"{args.env}_seed{seed}.json"
    if path.is_file():
        return json.loads(path.read_text())
    started = time.perf_counter()
    model, counts = train(args.env, config, seed)
    result = {"seed": seed, "greedy_test_return": test(args, model, seed), **counts}
    result["seconds"] = time.perf_counter() - started
    write_text_atomic(path, json.dumps(result))
    print(f"DQN {args.env} seed {seed}: greedy test return {result['greedy_test_return']:.1f}")
    return result


def stats(values) -> dict:
    x = np.asarray(values, dtype=np.float64)
    se = float(x.std(ddof=1) / math.sqrt(x.size)) if x.size > 1 else None
    return {"mean": float(x.mean()), "se": se, "trials": int(x.size)}


def library_runs(paths: tuple[str, ...]) -> dict:
    """``{mode: {seed: (last greedy test return, rewarded transitions)}}`` of the
    showcase's JSON files (``examples/torchrl_pipeline.py``), merged."""
    out: dict = {}
    for path in paths:
        for mode, by_seed in json.loads(Path(path).read_text())["runs"].items():
            for seed, run in by_seed.items():
                last = run["history"][-1]
                numbers = (last["greedy_test_return"], last["rewarded_transitions"])
                out.setdefault(mode, {})[int(seed)] = numbers
    return out


def data_file(args: Args, config: dict, runs: list[dict], library: dict, wall: float) -> dict:
    """The results' data file: AL vs PL paired over the seeds both hold (``rows``) and every
    learner's greedy return at the budget (``baselines``), with DQN's settings."""
    from benchmarks.summarize import commit_of, machine, paired_difference, verdict

    load = __import__("os").getloadavg()
    dqn = {r["seed"]: r for r in runs}
    baselines = [
        {
            "task": args.env,
            "learner": f"DQN (TorchRL's example, {args.frames:,} frames)",
            "seeds": sorted(dqn),
            "return": stats([r["greedy_test_return"] for r in runs]),
            "rewarded_transitions": float(np.mean([r["frames"] for r in runs])),
            "seconds": float(np.mean([r["seconds"] for r in runs])),
        }
    ]
    rows = []
    paired = sorted(set(library.get("AL", {})) & set(library.get("PL", {})) & set(dqn))
    for mode in ("AL", "PL"):
        held = [library.get(mode, {})[s] for s in paired]
        if held:
            baselines.append(
                {
                    "task": args.env,
                    "learner": f"library {mode} (examples/torchrl_pipeline.py)",
                    "seeds": paired,
                    "return": stats([h[0] for h in held]),
                    "rewarded_transitions": float(np.mean([h[1] for h in held])),
                    "seconds": None,  # (a JSON written on --resume holds the resumed seconds)
                }
            )
    if len(paired) > 1:
        al, pl = ([library[m][s][0] for s in paired] for m in ("AL", "PL"))
        diff = paired_difference(al, pl)
        rows.append(
            {
                "schedule": "showcase (120, 4 × 7)",
                "measure": "greedy_test_return",
                "iteration": LIBRARY_ITERATIONS,
                "al": stats(al),
                "pl": stats(pl),
                "difference": diff,
                "verdict": verdict(diff["mean"], diff["p"]),
                "rewarded_transitions": {
                    m: float(np.mean([library[m][s][1] for s in paired])) for m in ("AL", "PL")
                },
            }
        )
    return {
        "experiment": "dqn_baseline",
        "title": f"{args.env}: TorchRL's DQN beside the library's AL and PL at one rewarded budget",
        "task": f"{args.env}, DQN baseline",
        "command": f"python benchmarks/dqn_baseline.py --seeds {args.seeds} --frames {args.frames}"
        f" --library {' '.join(args.library)}",
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
        "and the random frames scaled to the budget (dqn_config).",
        "library_code": args.library_code,
        "torchrl_config": TORCHRL_CONFIG,
        "dqn_config": config,
        "args": asdict(args),
        "rows": rows,
        "baselines": baselines,
        "dqn_runs": runs,
    }


def main(argv: list[str] | None = None) -> dict:
    args = tyro.cli(Args, args=argv, description=__doc__)
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    config, seeds = scaled(args.frames), list(range(args.seed, args.seed + args.seeds))
    torch.set_num_threads(1)
    runs = [run_seed(args, config, s, out) for s in seeds]
    wall = sum(r["seconds"] for r in runs)  # (each seed's own: a rerun reads them back)
    print(f"DQN {args.env}, {len(seeds)} seeds: {stats([r['greedy_test_return'] for r in runs])}")
    payload = data_file(args, config, runs, library_runs(args.library), wall)
    for b in payload["baselines"]:
        print(f"{b['learner']}: {b['return']} over seeds {b['seeds']}")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(Path(args.out), json.dumps(payload, indent=1))
        print(f"wrote {args.out}")
    return payload


if __name__ == "__main__":
    main()
