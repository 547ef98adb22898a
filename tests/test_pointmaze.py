"""OGBench's pointmaze: the env against OGBench's own gymnasium env, the navigate recipe's
statistics, the ``.npz`` loader, goal relabelling against GCDataset's distribution, the
evaluation against OGBench's env loop, and the whole task at smoke scale through the CLI.

Nothing downloads: ``ogbench.make_env_and_datasets(..., env_only=True)`` builds the env."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import ogbench
import pytest
from conftest import cli

from lazyq_jax import agents, tasks
from lazyq_jax.config import ConfigError, override
from lazyq_jax.data import DatasetError, load_dataset, save_dataset
from lazyq_jax.keys import purpose_key
from lazyq_jax.run import load_policy
from lazyq_jax.run.rundir import write_json
from lazyq_jax.run.runner import eval_stamp, stored_evaluation
from lazyq_jax.run.sources import dataset_meta, seed_dataset
from lazyq_jax.tasks.base import CORRECT, run_protocol, seed_acts
from lazyq_jax.tasks.pointmaze import (
    get_maze,
    load_npz,
    navigate,
    oracle_action,
    relabel,
    save_npz,
    task_protocol,
    trajectory_transitions,
)
from lazyq_jax.tasks.pointmaze.config import PointMazeEvalConfig


@pytest.fixture(scope="module")
def maze():
    return get_maze("medium")


@pytest.fixture(scope="module")
def gym_env():
    env = ogbench.make_env_and_datasets("pointmaze-medium-navigate-v0", env_only=True)
    yield env
    env.close()


def test_maze_geometry_is_ogbench(maze, gym_env):
    u = gym_env.unwrapped
    assert (maze.map == u.maze_map).all()
    assert len(maze.free) == 26 and len(maze.vertex) == 21  # shared/DESIGN.md §8
    for ij in maze.free:
        assert tuple(maze.ij_to_xy(ij)) == u.ij_to_xy(ij)
        xy = maze.ij_to_xy(ij) + np.array([1.9, -1.9])
        assert tuple(maze.xy_to_ij(xy)) == u.xy_to_ij(xy)
    # the oracle subgoal of OGBench's env, from every free cell's corner to every vertex goal
    rng = np.random.default_rng(0)
    for start in maze.free:
        for goal in maze.vertex[::4]:
            xy = maze.ij_to_xy(start) + rng.uniform(-1.5, 1.5, 2)
            goal_xy = np.asarray(maze.ij_to_xy(goal))
            sub, _ = u.get_oracle_subgoal(xy, goal_xy)
            d = sub - xy
            # Same float64 formula; only |d| may be summed another way (NumPy's norm of one
            # vector is a dot product, of a batch a reduction: with or without FMA by CPU), a
            # rounding or two in |d| and so in a unit component: 8 ulps of 1.0 bound it.
            np.testing.assert_allclose(maze.subgoal_direction(xy[None], goal_xy[None])[0],
                                       d / (np.linalg.norm(d) + 1e-6), rtol=0,
                                       atol=8 * np.finfo(np.float64).eps)


def test_step_equals_ogbench_env_with_wall_contacts(maze, gym_env):
    """The same actions (clipped) from the same start: positions within 1e-5 (float64) at
    every step, with many wall contacts on the way."""
    u = gym_env.unwrapped
    rng = np.random.default_rng(1)
    contacts, worst = 0, 0.0
    for start, drift in [((0.0, 0.0), (1.0, 0.3)), ((16.0, 8.0), (-0.2, -1.0)), ((8.0, 16.0), (0.7, 0.7))]:
        gym_env.reset(seed=0)
        u.set_xy(np.asarray(start))
        q = np.asarray(start, np.float64)[None]
        actions = np.clip(rng.normal(size=(150, 2)) * 0.8 + np.asarray(drift), -1, 1)
        for a in actions:
            ob, *_ = gym_env.step(a)
            contacts += u.data.ncon
            q = maze.step(q, a[None])
            worst = max(worst, float(np.abs(q[0] - ob[:2]).max()))
    assert contacts > 50, "the sequences must push into walls"
    # 0 seen; the bound: our batches start MuJoCo's constraint solver cold, the env warm-starts
    # it, so they agree to the solver's tolerance (1e-8 relative forces), far below 1e-5
    assert worst <= 1e-5
    # clipping: an action beyond the box moves as its clip
    np.testing.assert_array_equal(maze.step(np.zeros((1, 2)), np.array([[3.0, -0.5]])),
                                  maze.step(np.zeros((1, 2)), np.array([[1.0, -0.5]])))


def test_navigate_recipe_statistics(maze):
    episodes, steps = 40, 301
    d = navigate(maze, np.random.default_rng(2), episodes, steps)
    n = episodes * steps
    assert d["observations"].shape == d["actions"].shape == (n, 2)
    term = d["terminals"].reshape(episodes, steps)
    assert term[:, -1].all() and not term[:, :-1].any()
    assert np.abs(d["actions"]).max() <= 1.0
    obs = d["observations"].reshape(episodes, steps, 2)
    starts = maze.xy_to_ij(obs[:, 0])
    assert all(tuple(c) in maze.free for c in starts)
    # starts within +-1 of their cell's centre (OGBench's noise)
    assert np.abs(obs[:, 0] - maze.ij_to_xy(starts)).max() <= 1.0
    goals = d["goals"].reshape(episodes, steps, 2)
    goal_cells = maze.xy_to_ij(goals.reshape(-1, 2))
    assert all(tuple(c) in maze.vertex for c in np.unique(goal_cells, axis=0))
    # a new goal after each success, none otherwise
    succ = d["successes"].reshape(episodes, steps)
    changed = np.any(goals[:, 1:] != goals[:, :-1], axis=-1)
    np.testing.assert_array_equal(changed, succ[:, :-1])
    assert succ.sum() / episodes > 1.5  # ~9 goals per 1001-step episode; ~2.7 per 301 steps
    # the action noise: N(0, 0.5) around the oracle direction where the clip is inactive
    direction = maze.subgoal_direction(obs.reshape(-1, 2).astype(np.float64),
                                       goals.reshape(-1, 2).astype(np.float64))
    residual = d["actions"] - direction
    free = np.abs(d["actions"]) < 0.999
    # a clip-free component's noise given |direction + noise| < 1 is a truncated normal; use the
    # components whose direction is ~0 (moving along the other axis): truncation at +-1 = 2 sd
    centred = free & (np.abs(direction) < 0.05)
    sd = residual[centred].std()
    truncated_sd = 0.5 * np.sqrt(1 - 2 * 2 * np.exp(-2) / np.sqrt(2 * np.pi) / 0.9545)
    assert abs(sd - truncated_sd) < 0.02, (sd, truncated_sd)


def test_npz_round_trip_and_transitions(tmp_path):
    """A hand-made file in OGBench's format: two trajectories of 4 and 3 steps."""
    obs = np.arange(14, dtype=np.float32).reshape(7, 2)
    acts = -obs
    term = np.array([0, 0, 0, 1, 0, 0, 1], bool)
    path = save_npz(tmp_path / "tiny.npz", {"observations": obs, "actions": acts, "terminals": term})
    d = load_npz(path)
    np.testing.assert_array_equal(d["observations"], obs)
    steps = trajectory_transitions(d)
    # OGBench's non-compact transitions: each trajectory's last observation has no successor
    np.testing.assert_array_equal(steps["s"], obs[[0, 1, 2, 4, 5]])
    np.testing.assert_array_equal(steps["s_next"], obs[[1, 2, 3, 5, 6]])
    np.testing.assert_array_equal(steps["a"], acts[[0, 1, 2, 4, 5]])
    np.testing.assert_array_equal(steps["last"], [2, 2, 2, 4, 4])


@pytest.mark.parametrize("bad, message", [
    ({"observations": np.zeros((4, 2)), "actions": np.zeros((4, 2))}, "lacks"),
    ({"observations": np.zeros((4, 3)), "actions": np.zeros((4, 2)), "terminals": np.ones(4, bool)},
     "columns"),
    ({"observations": np.zeros((4, 2)), "actions": np.zeros((4, 2)), "terminals": np.zeros(4, bool)},
     "terminal"),
    ({"observations": np.zeros((4, 2)), "actions": np.zeros((3, 2)), "terminals": np.ones(4, bool)},
     "need observations"),
    ({"observations": np.full((4, 2), np.nan), "actions": np.zeros((4, 2)), "terminals": np.ones(4, bool)},
     "finite"),
])
def test_npz_loader_says_what_is_wrong(tmp_path, bad, message):
    path = tmp_path / "bad.npz"
    np.savez(path, **bad)
    with pytest.raises(DatasetError, match=message):
        load_npz(path)
    with pytest.raises(DatasetError, match="no dataset file"):
        load_npz(tmp_path / "missing.npz")


def test_goal_relabelling_frequencies():
    """GCDataset's value goals: current p 0.2, geometric future p 0.5 (clipped at the
    trajectory's last transition), random p 0.3; success exactly when the goal is the
    transition's own state."""
    n_traj, length = 200, 500
    s = np.stack([np.arange(n_traj * length), np.zeros(n_traj * length)], -1).astype(np.float32)
    last = np.repeat(np.arange(1, n_traj + 1) * length - 1, length)
    steps = {"s": s, "a": np.zeros_like(s), "s_next": s + 1, "last": last}
    data, kind = relabel(np.random.default_rng(3), steps, 2, p_cur=0.2, p_traj=0.5, discount=0.99)
    m = len(kind)
    assert m == 2 * n_traj * length
    freq = np.bincount(kind, minlength=3) / m
    tol = 5 * np.sqrt(0.25 / m)  # 5 binomial standard deviations
    np.testing.assert_allclose(freq, [0.2, 0.5, 0.3], atol=tol)
    idx = np.tile(np.arange(len(s)), 2)
    goal_idx = data.g[:, 0].astype(np.int64)  # states are their own index here
    np.testing.assert_array_equal(data.done, goal_idx == idx)
    np.testing.assert_array_equal(data.r, data.done.astype(np.float32) - 1)
    # each copy keeps its trajectories: the last row of row r's trajectory, in r's copy
    np.testing.assert_array_equal(data.traj_last, np.repeat([0, len(s)], len(s)) + np.tile(last, 2))
    assert (goal_idx[kind == 0] == idx[kind == 0]).all()
    future = kind == 1
    off = goal_idx[future] - idx[future]
    remaining = last[idx[future]] - idx[future]
    assert (off[remaining > 0] >= 1).all() and (off[remaining == 0] == 0).all()
    assert (off <= remaining).all()  # never beyond the trajectory
    # E[min(G, L)] = (1 - 0.99^L) / 0.01 for G ~ geometric(0.01) and L steps left
    exact = np.mean((1 - 0.99 ** remaining) / 0.01)
    se = off.std() / np.sqrt(len(off))
    assert abs(off.mean() - exact) < 5 * se, (off.mean(), exact, se)


@pytest.mark.parametrize("max_steps", [130, 300])
def test_evaluation_matches_ogbench_env_loop(maze, gym_env, max_steps):
    """The oracle controller in our batched protocol and in OGBench's own env loop
    (``terminate_at_goal``, success after the step) from the same starts and goals: the same
    outcomes and step counts (130 steps: tasks 1, 2 and 4 time out; 300: all reach)."""
    cfg = PointMazeEvalConfig(episodes_per_task=2, max_steps=max_steps)
    program = task_protocol("medium", cfg)
    act = lambda policy: (lambda key, s, g: jnp.asarray(oracle_action_j(s, g)))
    oracle_action_j = lambda s, g: jax.pure_callback(
        lambda s, g: oracle_action(maze, s, g).astype(np.float32),
        jax.ShapeDtypeStruct(s.shape, jnp.float32), s, g, vmap_method="broadcast_all")
    ro = run_protocol(program, seed_acts(act), jnp.zeros((1,)), jax.random.PRNGKey(5)[None])
    starts, goals = np.asarray(ro.agent)[0, 0], np.asarray(ro.ctx["goal"])[0]
    u = gym_env.unwrapped
    for b in range(len(starts)):
        gym_env.reset(seed=0)
        u.set_goal(goal_xy=goals[b].astype(np.float64))
        u.set_xy(starts[b].astype(np.float64))
        xy, success, t = starts[b].astype(np.float64), False, 0
        while t < cfg.max_steps and not success:
            a = oracle_action(maze, np.float32(xy)[None], goals[b][None])[0]
            ob, _, _, _, info = gym_env.step(np.clip(a, -1, 1))
            xy, success, t = ob[:2], bool(info["success"]), t + 1
        assert success == (ro.outcome[0, b] == CORRECT)
        assert abs(t - int(ro.steps[0, b])) <= 1, (t, ro.steps[0, b])  # float32 positions here
    outcomes = set(np.asarray(ro.outcome[0]).tolist())
    assert outcomes == ({CORRECT} if max_steps == 300 else {CORRECT, 0})



GCIVL = "gcivl:steps=4:width=16:batch_size=32"
QRL = "qrl:steps=4:width=16:batch_size=32:latent_dim=16"
CRL = "crl:steps=4:width=16:batch_size=32:latent_dim=16"
HIQL = "hiql:steps=4:width=16:batch_size=32"
TINY = ["collect.episodes=12", "collect.episode_steps=61", "eval.episodes_per_task=2",
        "eval.max_steps=20", "train.cycles=2", "neighbours.k=8"]


def test_the_task_through_the_cli(tmp_path):
    run_dir = tmp_path / "pm"
    # lazy Q, the closest published method (GCIVL, tiny), QRL (its own value for the figure),
    # CRL, HIQL and the references; GCIQL and GCBC share GCIVL's path through the runner
    # (tests/test_gc_agents.py trains them)
    args = ["study", "--task", "pointmaze", "--preset", "smoke", "--seeds", "2", "--methods",
            f"lazy,{GCIVL},{QRL},{CRL},{HIQL},random,scripted", "--run-dir", str(run_dir), "--no-progress"]
    for a in TINY:
        args += ["--set", a]
    out = cli(*args)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    results = json.loads((run_dir / "results.json").read_text())
    assert results["task"] == "pointmaze" and len(results["methods"]) == 7
    for m in results["methods"].values():
        assert len(m["per_seed"]) == 2
        assert 0.0 <= m["per_seed"][0]["success_rate"] <= 1.0
    assert (run_dir / "figures" / "lazy" / "maze_rollouts.png").exists()
    assert (run_dir / "figures" / "lazy" / "maze_value.png").exists()
    assert any(run_dir.glob("figures/qrl*/maze_value.png"))
    # reload: evaluate lazy Q again from its checkpoints (the same rows; the others kept), and
    # hand user code a policy
    out = cli("evaluate", "--run-dir", str(run_dir), "--methods", "lazy", "--no-figures", "--no-progress")
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    rows = lambda r: {name: (m["per_seed"], m["summary"]) for name, m in r["methods"].items()}
    assert rows(json.loads((run_dir / "results.json").read_text())) == rows(results)
    for method in ("lazy", GCIVL, QRL, CRL, HIQL):
        act = load_policy(run_dir, method)
        a = act(jax.random.PRNGKey(0), jnp.zeros((3, 2)), jnp.full((3, 2), 4.0))
        assert a.shape == (3, 2) and bool(jnp.all(jnp.abs(a) <= 1.0 + 1e-6))


def test_config_errors():
    base = tasks.preset("pointmaze", "smoke")
    with pytest.raises(ConfigError, match="maze"):
        override(base, ["collect.maze=huge"])
    with pytest.raises(ConfigError, match="exceeds 1"):
        override(base, ["collect.p_curgoal=0.6", "collect.p_trajgoal=0.6"])
    with pytest.raises(ConfigError, match="tasks"):
        override(base, ["eval.tasks=0,7"])
    cfg = override(base, ["collect.discount=0.9"])
    with pytest.raises(ConfigError, match="train.gamma"):
        tasks.get("pointmaze").check(cfg)
    assert override(base, ["collect.dataset=/data/x.npz"]).collect.dataset == "/data/x.npz"
    assert override(base, ["eval.tasks=1,3"]).eval.tasks == (1, 3)


def test_collect_is_seeded_and_relabelled(tmp_path):
    """The same key gives the same dataset, another key another; rows are the transitions
    times the goals per transition, with OGBench's reward convention."""
    task = tasks.get("pointmaze")
    cfg = tasks.preset("pointmaze", "smoke")
    cfg = override(cfg, ["collect.goals_per_transition=3"])
    a = task.collect(jax.random.PRNGKey(0), cfg, progress=False)
    b = task.collect(jax.random.PRNGKey(0), cfg, progress=False)
    c = task.collect(jax.random.PRNGKey(1), cfg, progress=False)
    c_cfg = cfg.collect
    assert a.size == 3 * c_cfg.episodes * (c_cfg.episode_steps - 1)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a.s, c.s)
    np.testing.assert_array_equal(np.asarray(a.r), np.asarray(a.done, np.float32) - 1)
    assert 0.15 < float(np.mean(a.done)) < 0.25  # p_curgoal 0.2 (plus rare random hits)
    path = save_dataset(tmp_path / "d.npz", a)
    b, _ = load_dataset(path)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):  # traj_last kept
        np.testing.assert_array_equal(x, y)
    assert b.traj_last is not None
    step = np.linalg.norm(np.asarray(a.s_next) - np.asarray(a.s), axis=-1)
    assert step.max() <= 0.2 * np.sqrt(2) + 1e-5  # qpos += 0.2 a, a in the box


def test_lazy_refuses_underdetermined_local_models():
    """k below the local model's coefficients (1 + n_a + d_s + d_g = 7 with goal offsets on
    the maze) is refused before training, naming both."""
    task = tasks.get("pointmaze")
    cfg = override(tasks.preset("pointmaze", "smoke"),
                   ["neighbours.k=6", "neighbours.local_model=action+state+goal"])
    data = task.collect(jax.random.PRNGKey(0), cfg, progress=False)
    agent = agents.make("lazy", agents.LazyConfig(train=cfg.train, neighbours=cfg.neighbours),
                        problem=task.problem(cfg))
    with pytest.raises(ValueError, match="k=6 is below the 7 coefficients"):
        agent.init(jax.random.PRNGKey(0), data)
    ok = override(cfg, ["neighbours.k=7"])
    agents.make("lazy", agents.LazyConfig(train=ok.train, neighbours=ok.neighbours),
                problem=task.problem(ok)).check_k(data)


def test_a_cached_dataset_without_trajectories_is_collected_anew(tmp_path):
    """pointmaze's rows carry their trajectories (data_version 2): a run directory's dataset
    cached before (no traj_last, meta without the version) is collected again, not reused
    (OGBench's agents would silently lose their goal sampling on it)."""
    task = tasks.get("pointmaze")
    cfg = override(tasks.preset("pointmaze", "smoke"), TINY[:2])
    old = task.collect(purpose_key(0, "collect"), cfg, progress=False).replace(traj_last=None)
    path = tmp_path / "data" / "0" / "dataset.npz"
    save_dataset(path, old, dataset_meta(cfg, 0))
    data, _ = seed_dataset(task, cfg, tmp_path, 0, progress=False)
    assert data.traj_last is not None
    _, meta = load_dataset(path)
    assert meta == dataset_meta(cfg, 0, 2) and meta["data_version"] == 2


def test_a_stored_evaluation_is_reused(tmp_path):
    """An ``eval.json`` written by the runner is found again for the same settings (pointmaze's
    ``eval.tasks`` is a tuple, which JSON gives back as a list), and not for others; an
    evaluation with other policy settings (``evaluate --set``) only for those."""
    config = tasks.preset("pointmaze", "paper")
    stamp = eval_stamp(config, 300, (0,))
    path = tmp_path / "eval.json"
    write_json(path, {**stamp, "seconds": 1.0, "per_seed": [{"seed": 0, "success_rate": 0.5}]})
    assert stored_evaluation(path, eval_stamp(config, 300, [0])) == [{"seed": 0, "success_rate": 0.5}]
    assert stored_evaluation(path, eval_stamp(override(config, ["eval.tasks=[1,2]"]), 300, (0,))) is None
    assert stored_evaluation(path, eval_stamp(config, 200, (0,))) is None
    assert stored_evaluation(tmp_path / "none.json", stamp) is None
    acting = {"neighbours.subgoal_steps": 0}
    assert stored_evaluation(path, eval_stamp(config, 300, (0,), acting)) is None
    write_json(path, {**eval_stamp(config, 300, (0,), acting), "per_seed": [{"seed": 0}]})
    assert stored_evaluation(path, stamp) is None
    assert stored_evaluation(path, eval_stamp(config, 300, (0,), acting)) == [{"seed": 0}]
