"""OGBench's pointmaze suite beyond medium-navigate: the stitch recipe against OGBench's own
BFS, giant's episode layout, the teleport maze's env against OGBench's step by step, its
evaluation's teleports, and the per-dataset settings (applied where OGBench varies them and
nowhere else).  Nothing downloads (``env_only=True``)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import ogbench
import pytest

from lazyq_jax import tasks
from lazyq_jax.config import ConfigError, override
from lazyq_jax.tasks.base import run_protocol, seed_acts
from lazyq_jax.tasks.pointmaze import get_maze, navigate, oracle_action, stitch, task_protocol
from lazyq_jax.tasks.pointmaze.config import DATASETS, PointMazeEvalConfig
from lazyq_jax.tasks.pointmaze.maze import STEP_SCALE


@pytest.fixture(scope="module")
def teleport_env():
    env = ogbench.make_env_and_datasets("pointmaze-teleport-navigate-v0", env_only=True)
    yield env
    env.close()


def test_stitch_recipe_statistics():
    """5000 x 201 in OGBench; here 60 x 201 on large: every goal cell exactly 4 BFS moves from
    the start cell by OGBench's own BFS (``get_oracle_subgoal``'s map), the goal never changes,
    starts and goals within +-1 of their cells' centres, one terminal per episode."""
    maze = get_maze("large")
    env = ogbench.make_env_and_datasets("pointmaze-large-stitch-v0", env_only=True)
    u = env.unwrapped
    episodes, steps = 60, 201
    d = stitch(maze, np.random.default_rng(3), episodes, steps)
    term = d["terminals"].reshape(episodes, steps)
    assert term[:, -1].all() and not term[:, :-1].any()
    obs = d["observations"].reshape(episodes, steps, 2)
    goals = d["goals"].reshape(episodes, steps, 2)
    assert (goals == goals[:, :1]).all()  # never resampled, reached or not
    start_cells, goal_cells = maze.xy_to_ij(obs[:, 0]), maze.xy_to_ij(goals[:, 0])
    assert np.abs(obs[:, 0] - maze.ij_to_xy(start_cells)).max() <= 1.0
    assert np.abs(goals[:, 0] - maze.ij_to_xy(goal_cells)).max() <= 1.0
    for s, g in zip(start_cells, goal_cells):
        _, bfs = u.get_oracle_subgoal(u.ij_to_xy(tuple(s)), u.ij_to_xy(tuple(g)))
        assert bfs[s[0], s[1]] == 4, (s, g)
    # 4 cells is ~16 units: the oracle reaches most goals well inside 201 steps and stays
    reached = d["successes"].reshape(episodes, steps)
    assert reached.any(1).mean() > 0.8
    env.close()


def test_stitch_goal_distribution_is_uniform_over_the_ring():
    """The goal cell is uniform over the cells exactly 4 moves away (chi-square-free check:
    every cell of one start's ring within 5 binomial sd of its expected count)."""
    maze = get_maze("medium")
    rng = np.random.default_rng(4)
    d = stitch(maze, rng, 4000, 2)
    starts = maze.xy_to_ij(d["observations"][::2])
    goals = maze.xy_to_ij(d["goals"][::2])
    start = tuple(np.unique(starts, axis=0)[0])
    sel = (starts == start).all(1)
    ring = np.argwhere(maze.dist[start] == 4)
    counts = np.array([((goals[sel] == c).all(1)).sum() for c in ring])
    n, p = sel.sum(), 1 / len(ring)
    assert counts.sum() == n
    assert np.all(np.abs(counts - n * p) <= 5 * np.sqrt(n * p * (1 - p))), counts


def test_giant_layout_and_the_per_dataset_settings():
    """OGBench's recipes per dataset (commands.sh) and its per-dataset flags
    (hyperparameters.sh): giant's discount 0.995 for every method but GCBC, stitch's actor
    goals half random for every method but GCBC; lazy Q's settings the same everywhere but
    the dataset's discount."""
    assert len(DATASETS) == 8
    papers = {name: tasks.preset(name) for name in DATASETS}
    for name, config in papers.items():
        _, maze, recipe = name.split("-")
        c = config.collect
        assert (c.maze, c.recipe, c.noise) == (maze, recipe, 0.5)
        expect = {"stitch": (5000, 201), "navigate": (500, 2001) if maze == "giant" else (1000, 1001)}
        assert (c.episodes, c.episode_steps) == expect[recipe]
        gamma = 0.995 if maze == "giant" else 0.99
        assert config.train.gamma == c.discount == gamma
        # one set of lazy Q defaults: everything but the discount equals medium-navigate's
        medium = papers["pointmaze-medium-navigate"]
        assert dataclasses.replace(config.train, gamma=0.99) == medium.train
        assert config.neighbours == medium.neighbours and config.eval == medium.eval
        task = tasks.get(name)
        for method in ("gcivl", "gciql", "qrl", "crl", "hiql"):
            fields = task.method_defaults(method)
            assert fields["gamma"] == gamma
            assert fields.get("actor_p_randomgoal", 0.0) == (0.5 if recipe == "stitch" else 0.0)
        assert task.method_defaults("gcbc") == {"width": 512, "depth": 4, "batch_size": 1024}
    assert tasks.get("pointmaze-large-stitch-v0") is tasks.get("pointmaze-large-stitch")
    # a task's data are its dataset's: another maze or recipe through --set is refused, so
    # the discount and the baselines' flags cannot disagree with the data
    for name, sets in (("pointmaze-giant-stitch", ["collect.maze=medium"]),
                       ("pointmaze", ["collect.recipe=stitch"])):
        with pytest.raises(ConfigError, match="choose the dataset by its task"):
            tasks.get(name).check(override(tasks.preset(name), sets))
    assert tasks.preset("pointmaze") == dataclasses.replace(papers["pointmaze-medium-navigate"],
                                                            task="pointmaze")
    # giant navigate: 2001-step episodes of one goal after another
    d = navigate(get_maze("giant"), np.random.default_rng(5), 3, 2001)
    term = np.flatnonzero(d["terminals"])
    np.testing.assert_array_equal(term, [2000, 4001, 6002])


def test_teleport_env_equals_ogbench_step_by_step(teleport_env):
    """The same actions in OGBench's env and here, from starts next to both inbound
    teleporters: every observation within 1e-5, the teleport pending exactly where OGBench
    moved the point, and the point then at one of the outbound teleporters."""
    maze = get_maze("teleport")
    u = teleport_env.unwrapped
    assert (maze.map == u.maze_map).all()
    rng = np.random.default_rng(6)
    teleports, worst = 0, 0.0
    for inbound in maze.teleport_in:
        for trial in range(3):
            teleport_env.reset(seed=trial)
            np.random.seed(trial)
            start = inbound + rng.uniform(-1.8, 1.8, 2)
            while np.linalg.norm(start - inbound) <= maze.teleport_reach:
                start = inbound + rng.uniform(-1.8, 1.8, 2)
            u.set_xy(start)
            xy = start[None]
            for t in range(40):
                a = np.clip((inbound - u.get_xy()) / STEP_SCALE + rng.normal(0, 0.5, 2), -1, 1)
                ob, *_ = teleport_env.step(a)
                seen = maze.step(xy, a[None])
                worst = max(worst, float(np.abs(seen[0] - ob[:2]).max()))
                moved = not np.allclose(u.get_xy(), ob[:2])
                assert bool(maze.teleport_pending(seen)[0]) == moved
                if moved:
                    teleports += 1
                    assert np.min(np.linalg.norm(maze.teleport_out - u.get_xy(), axis=-1)) < 1e-9
                xy = u.get_xy()[None].copy()
    assert teleports >= 6
    assert worst <= 1e-5


def test_teleport_evaluation_teleports():
    """OGBench's evaluation in the teleport maze with the oracle controller: a step that
    ends within 1.5 of an inbound teleporter is followed by a step from an outbound one (the
    next observation within one move of it), and nowhere else does the point jump."""
    maze = get_maze("teleport")
    cfg = PointMazeEvalConfig(episodes_per_task=4, max_steps=200)
    program = task_protocol("teleport", cfg)
    oracle = lambda s, g: jax.pure_callback(
        lambda s, g: oracle_action(maze, s, g).astype(np.float32),
        jax.ShapeDtypeStruct(s.shape, jnp.float32), s, g, vmap_method="broadcast_all")
    ro = run_protocol(program, seed_acts(lambda p: (lambda key, s, g: oracle(s, g))),
                      jnp.zeros((1,)), jax.random.PRNGKey(7)[None])
    path = np.swapaxes(np.asarray(ro.agent)[0], 0, 1)  # [B, T + 1, 2]
    steps = np.asarray(ro.steps)[0]
    jumps = 0
    for b in range(path.shape[0]):
        for t in range(int(steps[b])):
            here, there = path[b, t], path[b, t + 1]
            if t > 0 and maze.teleport_pending(here[None])[0]:
                jumps += 1
                assert np.min(np.linalg.norm(maze.teleport_out - there, axis=-1)) <= STEP_SCALE * np.sqrt(2) + 0.05
            else:
                assert np.linalg.norm(there - here) <= STEP_SCALE * np.sqrt(2) + 1e-4
    assert jumps > 0
