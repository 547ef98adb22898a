"""Online lazy Q-learning, beyond the paper: the agent gathers its own pushes in MJX.

The paper learns from one static random dataset (§V-A-3).  Here the data grows in
rounds (``config.online``, :class:`lazyq_jax.config.OnlineConfig`):

* round 0: the paper's pipeline on the random dataset of ``config.collect``: the
  neighbourhoods of §V-A-2 and ``train.cycles`` cycles of §IV-E;
* round ``r >= 1``: roll out the current lazy policy (Eq. 9) with exploration in
  batched MJX episodes (:func:`make_rollout`, one ``lax.scan``), relabel every
  simulated move for ``collect.n_goals`` goals with Eq. (15)'s rewards as in
  §V-A-3, append; find the grown dataset's neighbourhoods; train ``online.cycles``
  more cycles from the current parameters (targets from the frozen network of each
  cycle, Eq. 11-12).

Static shapes: the dataset lives in arrays of a fixed capacity
(``online.max_moves * collect.n_goals`` rows, the first ``n_valid`` valid; the
training skips batches of padding), the grids have fixed bounds
(:func:`online_bounds`) and capacity, and the policy's search windows are rounded
up to powers of two: the rollout, the training cycle and the evaluation compile
once per run, not per round (``rounds.jsonl`` records the compiled-program counts).

Files in the run directory: ``dataset.npz`` (round 0, the ordinary cached random
dataset), ``online/round_<r>.npz`` (the moves round ``r`` added), ``checkpoints/``
(one per training cycle), ``metrics.jsonl`` (per cycle), ``online/rounds.jsonl``
(per round: moves, pushes, positives per goal octant, protocol A rates, seconds).
``resume=True`` continues from the newest intact checkpoint and ends with the same
parameters and data as an uninterrupted run.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import shutil
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from lazyq_jax.checkpoint import CheckpointError, latest_cycle, load_latest_intact, save_checkpoint
from lazyq_jax.config import Config, to_dict
from lazyq_jax.data import (DatasetError, dataset_summary, episodes_to_transitions, load_dataset,
                            save_dataset)
from lazyq_jax.env import PushEnv, disk_moved, push_reward, sample_outside_disk
from lazyq_jax.evaluate import (direction_rates, eval_keys, policy_act, protocol_a, protocol_b,
                                summarize_a, summarize_b)
from lazyq_jax.neighbours import build_index
from lazyq_jax.pipeline import RunDirError, neighbours_for, prepare_dataset, run_keys
from lazyq_jax.policy import LazyPolicy, lazy_policy
from lazyq_jax.targets import bootstrap_table
from lazyq_jax.train import make_train_for
from lazyq_jax.types import Transitions, pad_transitions

_ONLINE_TAG = 0x6F6E6C6E  # the key stream of the online rounds' episodes


def _log(msg: str) -> None:
    tqdm.write(msg)


def capacity_rows(config: Config) -> int:
    """Rows of the static dataset arrays: ``online.max_moves`` moves x ``n_goals`` goals."""
    return config.online.max_moves * config.collect.n_goals


def round_quota(config: Config, round0_moves: int) -> int:
    """Simulated moves each online round may add: the budget left after round 0, split evenly."""
    o = config.online
    return max(0, (o.max_moves - round0_moves) // o.rounds)


def online_bounds(config: Config) -> tuple[float, float, float, float]:
    """Fixed grid bounds covering every state of round 0 and of any online episode
    (a start within ``online.start_range`` plus ``max_steps`` moves), so every round's
    grids have the same shapes."""
    c, o = config.collect, config.online
    step = c.push.action_length
    r = max(c.start_range + (c.moves_per_start - 1) * step, o.start_range + o.max_steps * step)
    r += 1e-3
    return -r, -r, r, r


def make_rollout(config: Config):
    """``rollout(policy, key) -> dict`` of one round's episodes (pure, jittable).

    ``online.episodes`` episodes in one ``lax.scan`` of ``online.max_steps`` moves: goal
    uniform in ``[-pi, pi)``, the disk at the origin, the finger as in
    :class:`~lazyq_jax.config.OnlineConfig`; the move is the lazy policy's (Eq. 9) with
    exploration.  An episode ends at the first move that moves the disk; its later
    moves are recorded as zero displacements and dropped by
    :func:`~lazyq_jax.data.episodes_to_transitions`.  Leaves ``[episodes, max_steps, ...]``
    (``s, a, s_next, delta, moved``; ``g, r``: ``n_goals`` relabelled goals and their
    Eq. (15) rewards per move) and ``goal[episodes]``.
    """
    push, o, n_goals = config.collect.push, config.online, config.collect.n_goals
    env = PushEnv(push)
    b, c = o.episodes, push.action_length

    def start(key, g):
        behind = None if o.start == "anywhere" else (
            lambda x: x @ jnp.stack([jnp.cos(g), jnp.sin(g)]) < 0)
        return sample_outside_disk(key, jnp.zeros(2), o.start_range, push.contact_distance, behind)

    def rollout(policy: LazyPolicy, key: jax.Array) -> dict:
        k_goal, k_start, k_run, k_label = jax.random.split(key, 4)
        goals = jax.random.uniform(k_goal, (b,), jnp.float32, -jnp.pi, jnp.pi)
        finger = jax.vmap(start)(jax.random.split(k_start, b), goals)
        step = jax.vmap(env.step)

        def move(carry, k):
            state, done = carry
            k_pol, k_eps, k_dir, k_noise = jax.random.split(k, 4)
            s = state.relative
            greedy, _, found = lazy_policy(policy, k_pol, s, goals)
            phi = jnp.arctan2(greedy[:, 1], greedy[:, 0])
            phi = phi + o.angle_noise * jax.random.normal(k_noise, (b,))
            explore = (jax.random.uniform(k_eps, (b,)) < o.epsilon) | ~found
            phi = jnp.where(explore, jax.random.uniform(k_dir, (b,), jnp.float32, -jnp.pi, jnp.pi), phi)
            action = c * jnp.stack([jnp.cos(phi), jnp.sin(phi)], -1)
            new, delta = step(state, action)
            live = ~done
            delta = jnp.where(live[:, None], delta, 0.0)
            moved = disk_moved(delta, push.move_threshold)
            state = jax.tree.map(lambda n, old: jnp.where(live[:, None], n, old), new, state)
            return (state, done | moved), (s, action, state.relative, delta, moved)

        init = (env.reset(finger, jnp.zeros_like(finger)), jnp.zeros(b, bool))
        _, out = jax.lax.scan(move, init, jax.random.split(k_run, o.max_steps))
        s, a, s_next, delta, moved = (jnp.swapaxes(x, 0, 1) for x in out)  # [B, T, ...]
        labels = jax.random.uniform(k_label, (b, o.max_steps, n_goals), jnp.float32, -jnp.pi, jnp.pi)
        reward = push_reward(delta[:, :, None, :], labels, move_threshold=push.move_threshold,
                             cos_threshold=push.cos_threshold)
        return {"s": s, "a": a, "s_next": s_next, "delta": delta, "moved": moved, "g": labels,
                "r": reward, "goal": goals}

    return rollout


def episode_outcomes(eps: dict, cos_threshold: float) -> dict:
    """Counts over one round's episodes: pushed (the disk moved), pushed toward the
    episode's own goal (``cos >= cos_threshold``, protocol A's test)."""
    moved = np.asarray(eps["moved"])  # [B, T]
    pushed = moved.any(axis=1)
    first = np.argmax(moved, axis=1)
    delta = np.asarray(eps["delta"])[np.arange(moved.shape[0]), first]  # [B, 2]
    goal = np.asarray(eps["goal"])
    cos = ((delta[:, 0] * np.cos(goal) + delta[:, 1] * np.sin(goal))
           / np.maximum(np.linalg.norm(delta, axis=1), 1e-12))
    correct = pushed & (cos >= cos_threshold)
    diagonal = ~np.isclose(np.mod(np.round(goal / (np.pi / 4)), 2), 0)
    return {"episodes": int(pushed.size), "pushed": int(pushed.sum()), "correct": int(correct.sum()),
            "diagonal_episodes": int(diagonal.sum()), "diagonal_correct": int((correct & diagonal).sum())}


class OnlineFunctions:
    """The jitted programs of an online run (see :func:`online_functions`)."""

    def __init__(self, base: Config):
        self.trainer = make_train_for(base)
        self.run_cycle = jax.jit(self.trainer.run_cycle)
        gamma = base.train.gamma
        self.values = jax.jit(lambda state, data: bootstrap_table(self.trainer.value_fn(state), data, gamma))
        self.rollout = jax.jit(make_rollout(base))
        env = PushEnv(base.collect.push)
        small = dataclasses.replace(base.eval, episodes_per_direction=base.online.eval_episodes)
        self.small_eval = small
        self.protocol_a_small = jax.jit(lambda p, k: protocol_a(env, policy_act(p), k, small))
        full, half = base.eval, base.collect.push.table_half_size
        self.protocol_a = jax.jit(lambda p, k: protocol_a(env, policy_act(p), k, full))
        self.protocol_b = jax.jit(lambda p, k: protocol_b(env, policy_act(p), k, full, half))

    def compiled(self) -> dict:
        """Compiled programs per jitted function so far (one each when nothing recompiles)."""
        return {name: getattr(self, name)._cache_size() for name in
                ("run_cycle", "values", "rollout", "protocol_a_small")}


def online_functions(config: Config) -> OnlineFunctions:
    """The jitted programs of ``config``'s online runs, built once per process and shared by
    every seed (they depend on everything but the seeds)."""
    return _functions(dataclasses.replace(config, seed=0,
                                          eval=dataclasses.replace(config.eval, seed=0)))


@functools.lru_cache(maxsize=4)
def _functions(base: Config) -> OnlineFunctions:
    return OnlineFunctions(base)


def _pow2(n: int) -> int:
    return 1 << max(int(n) - 1, 0).bit_length()


def online_policy(config: Config, fns: OnlineFunctions, state, data: Transitions, n_valid: int,
                  max_level: int, window: int = 0) -> LazyPolicy:
    """The lazy policy (Eq. 9) on the first ``n_valid`` rows of the padded ``data``, with
    the fixed bounds and capacity of the run.  ``window``: the search window the
    policy's static capacities are sized for, at least the data's own (it is raised to
    that, as a power of two): a window kept from round to round keeps the shapes, so
    the rollout and the evaluation do not recompile.  Results do not depend on it."""
    nc = config.neighbours
    s, g = np.asarray(data.s[:n_valid]), np.asarray(data.g[:n_valid])
    index = build_index(s, g, k=nc.k, radius_s=nc.radius_s, radius_g=nc.radius_g, growth=nc.growth,
                        max_level=max_level, bounds=online_bounds(config), capacity=data.size)
    index = index.replace(max_window=max(int(window), _pow2(index.max_window)))
    return LazyPolicy(index, data.a, fns.values(state, data), float(config.collect.push.action_length))


def _grown_window(policy: LazyPolicy, n_valid: int, capacity: int) -> int:
    """A search window for the whole run from the first policy's: its own scaled by how
    much the data may still grow (the density near the disk grows at most that much if
    the new data spread like the old), as a power of two."""
    return _pow2(-(-policy.index.max_window * capacity // n_valid))


def _round_path(run_dir: Path, r: int) -> Path:
    return run_dir / "online" / f"round_{r}.npz"


def _rounds_with_data(config: Config, cycle: int) -> int:
    """Online rounds whose data a checkpoint at ``cycle`` was trained on (or was being)."""
    t0, oc = config.train.cycles, config.online.cycles
    return 0 if cycle <= t0 else min(config.online.rounds, -(-(cycle - t0) // oc))


def load_online_data(config: Config, run_dir: Path, rounds: int) -> tuple[Transitions, list[int]]:
    """Round 0's dataset and the moves of online rounds ``1..rounds``, concatenated
    (unpadded); with the rows after each round."""
    data, stored, seed = load_dataset(run_dir / "dataset.npz")
    if stored != config.collect or seed != config.seed:
        raise DatasetError(f"{run_dir}/dataset.npz was not collected with this run's config and seed")
    parts, rows = [data], [data.size]
    for r in range(1, rounds + 1):
        part, _, seed = load_dataset(_round_path(run_dir, r))
        if seed != config.seed:
            raise DatasetError(f"{_round_path(run_dir, r)} belongs to seed {seed}, not {config.seed}")
        parts.append(part)
        rows.append(rows[-1] + part.size)
    return jax.tree.map(lambda *x: jnp.concatenate(x), *parts), rows


def collect_round(config: Config, fns: OnlineFunctions, state, data: Transitions, n_valid: int,
                  r: int, quota: int, window: int = 0) -> tuple[Transitions, dict]:
    """Round ``r``'s new transitions (at most ``quota`` moves) and its counts; ``window``:
    see :func:`online_policy`."""
    o = config.online
    policy = online_policy(config, fns, state, data, n_valid, config.eval.max_level, window)
    key = jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(config.seed), _ONLINE_TAG), r)
    eps = jax.device_get(fns.rollout(policy, key))
    new = episodes_to_transitions(eps, config.collect.n_goals)
    moves = new.size // config.collect.n_goals
    if moves > quota:  # the budget: the first `quota` moves in (episode, step) order
        new = jax.tree.map(lambda x: x[:quota * config.collect.n_goals], new)
    counts = episode_outcomes(eps, config.collect.push.cos_threshold)
    counts["moves_simulated"] = moves
    counts["moves_kept"] = min(moves, quota)
    counts["max_moves_per_round"] = o.episodes * o.max_steps
    return new, counts


def _append(padded: Transitions, n_valid: int, new: Transitions) -> Transitions:
    end = n_valid + new.size
    if end > padded.size:
        raise AssertionError(f"internal error: {end} rows exceed the capacity {padded.size}")
    return jax.tree.map(lambda x, y: x.at[n_valid:end].set(y), padded, new)


def fit_online(config: Config, run_dir: str | Path, *, resume: bool = False,
               overwrite: bool = False, progress: bool = True):
    """Round 0, then ``config.online.rounds`` rounds of collect -> relabel -> neighbours
    -> train (see the module docstring), a checkpoint per cycle, metrics per round.

    ``resume``/``overwrite`` as in :func:`lazyq_jax.pipeline.fit`.  Returns
    ``(state, data, n_valid, fns)``: the final parameters, the padded dataset and its
    valid rows, and the run's compiled functions.
    """
    o, tc = config.online, config.train
    if o.rounds < 1:
        raise ValueError("fit_online needs config.online.rounds >= 1 (use pipeline.fit otherwise)")
    run_dir = Path(run_dir)
    ckpt_dir, rounds_path = run_dir / "checkpoints", run_dir / "online" / "rounds.jsonl"
    metrics_path = run_dir / "metrics.jsonl"
    state = None
    if latest_cycle(ckpt_dir) is not None:
        if overwrite:
            shutil.rmtree(ckpt_dir)
            shutil.rmtree(run_dir / "online", ignore_errors=True)
        elif resume:
            try:
                found = load_latest_intact(ckpt_dir, expect=config, warn=_log)
            except CheckpointError as e:
                raise CheckpointError(f"{e}; to start this run afresh, pass --overwrite") from None
            state = None if found is None else found[0]
        else:
            raise RunDirError(f"{run_dir} already holds checkpoints of a run; continue it with "
                              "--resume, replace it with --overwrite, or pick another --run-dir")
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "online").mkdir(exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps(to_dict(config), indent=1))
    fns = online_functions(config)
    t = time.perf_counter()
    round0 = prepare_dataset(config, run_dir, progress)
    n_goals = config.collect.n_goals
    quota = round_quota(config, round0.size // n_goals)
    cycle = 0 if state is None else int(state.cycle)
    done_rounds = _rounds_with_data(config, cycle)
    data, rows = load_online_data(config, run_dir, done_rounds) if done_rounds else (round0, [round0.size])
    n_valid = data.size
    data = pad_transitions(data, capacity_rows(config))
    _log(f"online: round 0 has {round0.size // n_goals:,} moves; {o.rounds} rounds of at most "
         f"{quota:,} moves (budget {o.max_moves:,}; {time.perf_counter() - t:.1f} s)")
    if state is None:
        state = fns.trainer.init(run_keys(config)["train"])  # the initial parameters of pipeline.fit
        metrics_path.write_text("")
        rounds_path.write_text("")
    else:
        _log(f"resume: from cycle {cycle} (round {done_rounds})")
        _keep_lines(metrics_path, lambda rec: rec["cycle"] <= cycle)
        _keep_lines(rounds_path, lambda rec: rec["round"] < done_rounds
                    or (rec["round"] == done_rounds and _round_end(config, rec["round"]) <= cycle))

    window = _grown_window(online_policy(config, fns, state, data, n_valid, config.eval.max_level),
                           n_valid, data.size)
    for r in range(done_rounds, o.rounds + 1):
        timing, counts_path = {}, _round_path(run_dir, r).with_suffix(".json")
        if r > done_rounds:  # collect this round's data (rounds up to done_rounds are loaded)
            t = time.perf_counter()
            new, counts = collect_round(config, fns, state, data, n_valid, r, quota, window)
            save_dataset(_round_path(run_dir, r), new, config.collect, seed=config.seed)
            counts_path.write_text(json.dumps(counts))
            data, n_valid = _append(data, n_valid, new), n_valid + new.size
            rows.append(n_valid)
            timing["collect_s"] = round(time.perf_counter() - t, 2)
        counts = json.loads(counts_path.read_text()) if r and counts_path.exists() else None
        end = _round_end(config, r)
        if int(state.cycle) >= end and any(rec["round"] == r for rec in read_rounds(run_dir)):
            continue
        t = time.perf_counter()
        first = tc.cycles + (r - 1) * o.cycles if r else None
        idx = jax.block_until_ready(neighbours_for(config, data, first, n_valid=n_valid,
                                                   bounds=online_bounds(config)))
        timing["neighbours_s"] = round(time.perf_counter() - t, 2)
        t = time.perf_counter()
        while int(state.cycle) < end:
            tc0 = time.perf_counter()
            state, metrics = fns.run_cycle(state, data, idx, jnp.int32(n_valid))
            metrics = jax.device_get(metrics)
            save_checkpoint(ckpt_dir, state, config)
            record = {"cycle": int(state.cycle), "round": r, "seconds": round(time.perf_counter() - tc0, 2),
                      **{k: np.asarray(v).round(5).tolist() for k, v in metrics.items()}}
            with metrics_path.open("a") as f:
                f.write(json.dumps(record) + "\n")
        timing["train_s"] = round(time.perf_counter() - t, 2)
        t = time.perf_counter()
        policy = online_policy(config, fns, state, data, n_valid, config.eval.max_level, window)
        window = max(window, policy.index.max_window)
        summary = summarize_a(jax.device_get(fns.protocol_a_small(policy, eval_keys(config.eval)[0])),
                              fns.small_eval)
        timing["eval_s"] = round(time.perf_counter() - t, 2)
        part = Transitions(**{k: getattr(data, k)[rows[-2] if r else 0:n_valid]
                              for k in ("s", "a", "s_next", "r", "g", "done")})
        record = {"round": r, "cycle": int(state.cycle), "moves_total": n_valid // n_goals,
                  "moves_added": part.size // n_goals, "rows": n_valid,
                  "pushes_added": int(np.asarray(part.done).sum()) // n_goals,
                  "reward_by_goal_octant": dataset_summary(part, n_goals)["reward_by_goal_octant"],
                  "episodes": counts, "protocol_a": {**direction_rates(summary),
                                                     "per_goal": summary["per_goal"]},
                  "seconds": timing,
                  "compiled": fns.compiled()}
        with rounds_path.open("a") as f:
            f.write(json.dumps(record) + "\n")
        a = record["protocol_a"]
        _log(f"round {r}/{o.rounds}: {record['moves_total']:,} moves (+{record['moves_added']:,}, "
             f"{record['pushes_added']} pushes); protocol A axis {a['axis_correct_rate']:.0%} "
             f"diagonal {a['diagonal_correct_rate']:.0%} all {a['overall_correct_rate']:.0%}; "
             + ", ".join(f"{k} {v:.1f}" for k, v in timing.items()))
    return state, data, n_valid, fns


def _round_end(config: Config, r: int) -> int:
    """The cycle count at the end of round ``r``."""
    return config.train.cycles + r * config.online.cycles


def _keep_lines(path: Path, keep) -> None:
    if path.exists():
        lines = [line for line in path.read_text().splitlines() if line and keep(json.loads(line))]
        path.write_text("".join(line + "\n" for line in lines))


def evaluate_online(config: Config, run_dir: str | Path, state, data: Transitions, n_valid: int,
                    fns: OnlineFunctions, *, figures: bool = True) -> dict:
    """Protocols A and B (``config.eval``) of the final online policy; writes
    ``run_dir/eval/results.json`` (the schema of :func:`lazyq_jax.evaluate.evaluate_run`)
    and the figures, with the learning curve of ``online/rounds.jsonl``."""
    run_dir = Path(run_dir)
    t = time.perf_counter()
    cfg = config.eval
    policy = online_policy(config, fns, state, data, n_valid, cfg.max_level)
    k_a, k_b = eval_keys(cfg)
    rollouts_a = jax.device_get(fns.protocol_a(policy, k_a))
    rollouts_b, targets = jax.device_get(fns.protocol_b(policy, k_b))
    results = {"protocol_a": summarize_a(rollouts_a, cfg), "protocol_b": summarize_b(rollouts_b),
               "seed": cfg.seed, "eval_config": to_dict(cfg),
               "checkpoint": str(run_dir / "checkpoints" / str(int(state.cycle))),
               "moves": n_valid // config.collect.n_goals,
               "seconds": round(time.perf_counter() - t, 1)}
    out = run_dir / "eval"
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=1))
    if figures:
        from lazyq_jax import plots

        plots.write_all(run_dir / "figures", fns.trainer.value_fn(state), results, rollouts_b,
                        targets, config, cfg)
        plots.online_curve([read_rounds(run_dir)], run_dir / "figures" / "online_curve.png")
    return results


def read_rounds(run_dir: str | Path) -> list[dict]:
    """The per-round records of an online run (``online/rounds.jsonl``)."""
    path = Path(run_dir) / "online" / "rounds.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines() if line]



def evaluate_online_run(run_dir: str | Path, state, config: Config, *, figures: bool = True) -> dict:
    """:func:`evaluate_online` of a saved online run (its newest checkpoint ``state`` and
    ``config``, whose ``eval`` section may differ from the run's): the datasets of the
    rounds that checkpoint was trained on are reloaded, nothing is retrained."""
    run_dir = Path(run_dir)
    data, rows = load_online_data(config, run_dir, _rounds_with_data(config, int(state.cycle)))
    fns = online_functions(config)
    return evaluate_online(config, run_dir, state, pad_transitions(data, capacity_rows(config)),
                           rows[-1], fns, figures=figures)
