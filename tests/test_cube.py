"""OGBench's cube-single-play: the batched env against OGBench's own gymnasium env, the play
recipe against OGBench's data script (re-enacted with OGBench's env and oracle), the oracle's
noise against the recipe's numbers, the evaluation against OGBench's env loop, the feature maps
by hand, the relabelled data, the ``.npz`` loader, and the task at smoke scale through the CLI.

Nothing downloads: ``gymnasium.make("cube-single-v0")`` builds OGBench's env from the package.
Tolerances are zero where the same OGBench code runs on the same float64 state (the batch only
changes which Python object steps an episode's ``MjData``); anything else says why."""

import json
import warnings

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import ogbench.manipspace  # noqa: F401  (registers cube-single-v0)
import pytest
from conftest import cli
from ogbench.manipspace.oracles.plan.cube_plan import CubePlanOracle

from lazyq_jax import tasks
from lazyq_jax.config import ConfigError, override
from lazyq_jax.data import DatasetError
from lazyq_jax.tasks.cube import cube_features, evaluate_episodes, goal_features, goal_of, play_data
from lazyq_jax.tasks.cube.config import CubeCollectConfig, CubeEvalConfig
from lazyq_jax.tasks.cube.dataset import NOISE_SCALE, global_rng, load_npz, make_oracle, play, save_npz
from lazyq_jax.tasks.cube.env import (OBS, EpisodeBatch, cube_position, effector_position,
                                      worker_envs)

warnings.filterwarnings("ignore", module="gymnasium")

CENTER = np.array([0.425, 0.0, 0.0])


def test_the_batch_steps_as_ogbenchs_env():
    """Four episodes of the five tasks side by side (two worker envs) against one OGBench env
    each: the same start, the same goal cube, then the same observations and success flags for
    40 steps of random actions (some outside the box: both clip... OGBench's env does not, so
    the reference gets them clipped, as OGBench's evaluation clips them).  The start, the goal's
    cube part and the path after it agree to 1e-9 in observation units
    (1e-10 m): OGBench settles the goal scene with unseeded random arm actions, which reach the
    cube only through the constraint solve (a CI machine saw 2.8e-17 in the goal), and leave
    the solver another warm start (5e-15 m seen once the gripper touches the cube), so the
    tolerance is far above that rounding and far below the 0.04 m success radius."""
    seeds, task_ids = [11, 12, 13, 14], [1, 3, 4, 5]
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1.3, 1.3, (40, 4, 5))
    batch = EpisodeBatch(4, "task", workers=2)
    obs0, infos = batch.reset(seeds, task_ids)
    traj, succ = [obs0], []
    for t in range(40):
        o, s, _ = batch.step(actions[t])
        traj.append(o)
        succ.append(s)
    batch.close()
    ref = gymnasium.make("cube-single-v0").unwrapped
    for i in range(4):
        ob, info = ref.reset(seed=seeds[i], options=dict(task_id=task_ids[i]))
        np.testing.assert_allclose(ob, obs0[i], rtol=0, atol=1e-9)
        # the goal's cube part is the same; its arm part is OGBench's unseeded random (env.py)
        np.testing.assert_allclose(info["goal"][OBS["cube_pos"]], infos[i]["goal"][OBS["cube_pos"]],
                                   rtol=0, atol=1e-9)
        for t in range(40):
            ob, _, _, _, info = ref.step(np.clip(actions[t, i], -1, 1))
            np.testing.assert_allclose(ob, traj[t + 1][i], rtol=0, atol=1e-9)
            assert info["success"] == succ[t][i]
    assert obs0.shape == (4, 28)


def test_a_stepped_subset_leaves_the_others_alone():
    batch = EpisodeBatch(3, "task", workers=1)
    obs0, _ = batch.reset([1, 2, 3], [1, 2, 3])
    obs, _, infos = batch.step(np.ones((3, 5)), live=np.array([True, False, True]))
    batch.close()
    assert np.isnan(obs[1]).all() and infos[1] is None and not np.isnan(obs[[0, 2]]).any()
    np.testing.assert_array_equal(batch.datas[1].qpos[:6], obs0[1, :6])  # not stepped


def script_episodes(seeds, steps, noise=0.1, smoothing=0.5):
    """OGBench's ``generate_manipspace.py`` main loop for cube-single (play), as written there:
    OGBench's gymnasium env and plan oracle, the global ``np.random`` seeded per episode."""
    env = gymnasium.make("cube-single-v0", terminate_at_goal=False, mode="data_collection",
                         max_episode_steps=steps)
    agent = CubePlanOracle(env=env, noise=noise, noise_smoothing=smoothing)
    out = {k: [] for k in ("observations", "actions", "terminals", "qpos", "qvel", "new_targets")}
    saved = np.random.get_state()
    for env_seed, np_seed in seeds:
        np.random.seed(int(np_seed))
        ob, info = env.reset(seed=int(env_seed))
        agent.reset(ob, info)
        done = False
        while not done:
            if np.random.rand() < 0.0:
                action = env.action_space.sample()
            else:
                action = np.array(agent.select_action(ob, info))
            action = np.clip(action, -1, 1)
            next_ob, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
            out["new_targets"].append(agent.done)
            if agent.done:
                agent_ob, agent_info = env.unwrapped.set_new_target(p_stack=0.0)
                agent.reset(agent_ob, agent_info)
            out["observations"].append(ob)
            out["actions"].append(action)
            out["terminals"].append(done)
            out["qpos"].append(info["prev_qpos"])
            out["qvel"].append(info["prev_qvel"])
            ob = next_ob
    np.random.set_state(saved)
    return {k: np.array(v) for k, v in out.items()}


def test_play_data_are_ogbenchs_script_episode_for_episode(capfd):
    """Two episodes of 120 steps: the recipe's rows equal the script's for the same env seed and
    global random state (float32 as the script saves them), for one worker and for two, and
    the recipe's statistics: episodes of ``steps`` rows ending in one terminal, actions in the
    box, one new target per plan (a plan lasts 4.4 s +- 20 % of its segments: ~88 steps)."""
    steps = 120
    data = play(np.random.default_rng(3), 2, steps, workers=2)
    seeds = np.random.default_rng(3).integers(0, 2**31 - 1, size=(2, 2))
    ref = script_episodes(seeds, steps)
    for k in ("observations", "actions", "qpos", "qvel"):
        np.testing.assert_array_equal(data[k], ref[k].astype(np.float32), err_msg=k)
    np.testing.assert_array_equal(data["terminals"], ref["terminals"])
    np.testing.assert_array_equal(data["new_targets"], ref["new_targets"])
    one = play(np.random.default_rng(3), 2, steps, workers=1)
    np.testing.assert_array_equal(one["observations"], data["observations"])
    capfd.readouterr()
    two = play(np.random.default_rng(3), 2, 30, processes=2, progress=True)  # one episode a spawned process
    np.testing.assert_array_equal(two["actions"], data["actions"].reshape(2, steps, 5)[:, :30].reshape(60, 5))
    assert capfd.readouterr().err.count("cube play data") >= 1  # the first process's bar
    term = data["terminals"].reshape(2, steps)
    assert term[:, -1].all() and not term[:, :-1].any()
    assert np.all(np.abs(data["actions"]) <= 1.0)
    assert data["observations"].shape == (2 * steps, 28) and data["qpos"].shape == (2 * steps, 21)
    plans = data["new_targets"].reshape(2, steps).sum(1)
    assert (plans == 1).all(), plans  # 120 steps: one plan ended (~88 steps), the next has not


def test_the_oracles_plan_noise_has_the_recipes_scale_and_smoothing():
    """The plan with the recipe's noise minus the same plan without it (the same random state:
    the keyframes are drawn first) is the smoothed noise: per axis ``0.1 x (0.05, 0.05, 0.05,
    0.3, 1.0) x f`` with ``f = sqrt(sum w^2)`` of scipy's Gaussian kernel (sigma 0.5, radius
    ``int(4 sigma + 0.5) = 2``), lag-1 autocorrelation ``sum w_i w_{i+1} / sum w^2``.  ~100 plans
    of ~88 steps: the std to 5 %, the autocorrelation to 0.06 (a few standard errors)."""
    x = np.arange(-2, 3)
    w = np.exp(-0.5 * x**2 / 0.25)
    w /= w.sum()
    factor, lag1 = np.sqrt(np.sum(w**2)), np.sum(w[:-1] * w[1:]) / np.sum(w**2)
    batch = EpisodeBatch(1, "data_collection")
    obs, infos = batch.reset([5])
    env = batch.envs[0]
    noisy, clean = make_oracle(env, 0.1, 0.5), make_oracle(env, 0.0, 0.5)
    diffs = []
    for k in range(100):
        for oracle in (noisy, clean):
            with global_rng(np.random.RandomState(k)):
                oracle.reset(obs[0], infos[0])
        diffs.append(noisy._plan - clean._plan)
    batch.close()
    d = np.concatenate(diffs)
    np.testing.assert_allclose(d.std(0), 0.1 * NOISE_SCALE * factor, rtol=0.05)
    ac = np.mean([np.mean(p[1:] * p[:-1], 0) / np.mean(p * p, 0) for p in diffs], 0)
    np.testing.assert_allclose(ac, lag1, atol=0.06)


class OracleActs:
    """A test policy that succeeds often and reads only what an agent gets (float32
    observations and goal observations): OGBench's plan oracle without noise, its inputs
    recovered from the observation (the goal's cube position as the target, time = steps x
    0.05 s), keyframes drawn from a per-episode random state."""

    def __init__(self, n):
        self.env = worker_envs("task", 1)[0]
        self.oracles = [make_oracle(self.env, 0.0) for _ in range(n)]
        self.states = [np.random.RandomState(j) for j in range(n)]

    @staticmethod
    def info(ob, goal, t):
        yaw = lambda cs: np.array([np.arctan2(cs[1], cs[0])])
        return {"time": np.array([t * 0.05]), "proprio/effector_pos": effector_position(ob),
                "proprio/effector_yaw": yaw(ob[OBS["effector_yaw"]]),
                "proprio/gripper_opening": ob[OBS["gripper_opening"]] / 3.0,
                "privileged/target_block": 0, "privileged/block_0_pos": cube_position(ob),
                "privileged/block_0_yaw": yaw(ob[OBS["cube_yaw"]]),
                "privileged/target_block_pos": cube_position(goal), "privileged/target_block_yaw": np.zeros(1)}

    def act(self, j, ob, goal, t):
        info = self.info(np.asarray(ob, np.float64), np.asarray(goal, np.float64), t)
        if t == 0:
            with global_rng(self.states[j]):
                self.oracles[j].reset(ob, info)
        return self.oracles[j].select_action(ob, info)


def test_the_evaluation_is_ogbenchs_env_loop():
    """Tasks 1-5, one episode each, with :class:`OracleActs`: the outcomes and steps equal
    OGBench's loop (``gymnasium.make("cube-single-v0")``: its 200-step limit and its termination
    at success) on the same reset seeds, the cube paths to 1e-9 m (OGBench's env settles the goal
    scene with unseeded random actions, which leave the contact solver another warm start: seen
    5e-15 m once the gripper touches the cube); and the policy succeeds somewhere, so the
    comparison covers successes."""
    cfg = CubeEvalConfig(episodes_per_task=1, max_steps=200, workers=2)
    policy = OracleActs(5)
    calls = []

    def acts(policies, keys, s, g):
        t = len(calls)
        calls.append(t)
        return np.stack([[policy.act(j, s[0, j], g[0, j], t) for j in range(s.shape[1])]])

    roll = evaluate_episodes(acts, None, jnp.stack([jax.random.PRNGKey(7)]), cfg, "observation")
    ref_policy = OracleActs(5)
    env = gymnasium.make("cube-single-v0")
    outcomes, steps = [], []
    for j in range(5):
        ob, info = env.reset(seed=int(roll.ctx["reset_seed"][0, j]),
                             options=dict(task_id=int(roll.ctx["task"][0, j])))
        goal, done, t = info["goal"].astype(np.float32), False, 0
        path = [cube_position(ob)]
        while not done:
            a = np.clip(ref_policy.act(j, ob.astype(np.float32), goal, t), -1, 1)
            ob, _, terminated, truncated, info = env.step(a)
            done, t = terminated or truncated, t + 1
            path.append(cube_position(ob))
        outcomes.append(bool(info["success"]))
        steps.append(t)
        np.testing.assert_allclose(np.array(path), roll.obj[0, : t + 1, j], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(roll.outcome[0] == 1, outcomes)
    np.testing.assert_array_equal(roll.steps[0], steps)
    assert any(outcomes), outcomes
    np.testing.assert_allclose(roll.ctx["target"][0],
                               [t["goal_xyzs"][0] for t in env.unwrapped.task_infos], atol=2e-3)


def test_feature_maps_by_hand():
    """``cube_features`` against MuJoCo's own quantities of a reset scene (the pinch site, the
    gripper joint, the cube joint), in the observation's units; float32 rounding of numbers
    of order 1 (1e-6); ``goal_features`` of a goal observation is the task's goal position up
    to the cube's settling in OGBench's two goal steps (2 mm, x 10 in observation units)."""
    batch = EpisodeBatch(1, "task")
    obs, infos = batch.reset([21], [4])
    env, data = batch.envs[0], batch.datas[0]
    batch.close()
    pinch = env.model.site("ur5e/robotiq/pinch").id
    opening = np.clip(data.qpos[env.model.joint("ur5e/robotiq/right_driver_joint").id] / 0.8, 0, 1)
    cube = data.joint("object_joint_0").qpos[:3]
    want = np.concatenate([(data.site_xpos[pinch] - CENTER) * 10, [3 * opening], (cube - CENTER) * 10])
    phi = np.asarray(jax.jit(cube_features)(jnp.asarray(obs, jnp.float32)))
    np.testing.assert_allclose(phi[0], want, atol=1e-6)
    goal = np.asarray(goal_features(jnp.asarray(infos[0]["goal"], jnp.float32)))
    np.testing.assert_allclose(goal, (np.array([0.50, 0.2, 0.02]) - CENTER) * 10, atol=0.02)
    np.testing.assert_array_equal(goal_of(infos[0]["goal"], "cube"), goal)
    # and the slices on a made-up observation
    s = jnp.arange(28.0)[None]
    np.testing.assert_array_equal(np.asarray(cube_features(s))[0], [12, 13, 14, 17, 19, 20, 21])
    # lazy Q compares observation goals by their cube position; cube goals are that already
    task, paper = tasks.get("cube-single-play"), tasks.preset("cube-single-play", "paper")
    assert task.problem(paper).goal_features is goal_features
    assert task.problem(override(paper, ["collect.goal_rep=cube"])).goal_features is None


@pytest.fixture(scope="module")
def play_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("cube") / "cube-single-play-tiny.npz"
    return save_npz(path, play(np.random.default_rng(1), 3, 41, workers=2))


def test_relabelled_data_and_the_npz_loader(play_file):
    """The task's data from a user's file: 3 x 40 transitions a copy, OGBench's success (goal
    row = row) exactly where the goal is the row's own state, reward success - 1, each row's
    trajectory end; with cube goals the goal is the goal state's cube position; files of another
    env are refused by name."""
    task = tasks.get("cube-single-play")
    config = override(tasks.preset("cube-single-play", "smoke"),
                      [f"collect.dataset={play_file}", "collect.goal_rep=observation",
                       "collect.goals_per_transition=2"])
    data = task.collect(jax.random.PRNGKey(0), config, progress=False)
    s, g, done = np.asarray(data.s), np.asarray(data.g), np.asarray(data.done)
    assert data.size == 2 * 3 * 40 and g.shape == (240, 28)
    np.testing.assert_array_equal(done, np.all(s == g, axis=-1))  # no state repeats in 40 steps
    np.testing.assert_array_equal(np.asarray(data.r), done - 1.0)
    np.testing.assert_array_equal(np.asarray(data.traj_last)[:120], np.repeat([39, 79, 119], 40))
    raw = load_npz(play_file)
    np.testing.assert_array_equal(s[:40], raw["observations"][:40])
    cube = task.collect(jax.random.PRNGKey(0), override(config, ["collect.goal_rep=cube"]), progress=False)
    np.testing.assert_array_equal(np.asarray(cube.g), g[:, 19:22])
    assert cube.traj_last is None
    bad = play_file.parent / "wide.npz"
    np.savez(bad, observations=np.zeros((4, 37), np.float32), actions=np.zeros((4, 5), np.float32),
             terminals=np.array([0, 0, 0, 1], bool))
    with pytest.raises(DatasetError, match="cube-single's are"):
        load_npz(bad)


def test_seeds_share_the_play_data_of_data_seed():
    """``collect.data_seed``: every seed's trajectories are the play data of that seed (made
    once); without it each seed's key draws its own."""
    c = CubeCollectConfig(episodes=2, episode_steps=21, data_seed=4)
    a, b = play_data(jax.random.PRNGKey(0), c), play_data(jax.random.PRNGKey(1), c)
    assert a is b
    np.testing.assert_array_equal(a["observations"], play(np.random.default_rng(4), 2, 21)["observations"])
    own = play_data(jax.random.PRNGKey(1), CubeCollectConfig(episodes=2, episode_steps=21))
    assert not np.array_equal(own["observations"], a["observations"])


def test_config_is_checked_at_the_boundary():
    with pytest.raises(ConfigError, match="goal_rep"):
        CubeCollectConfig(goal_rep="image")
    with pytest.raises(ConfigError, match="tasks"):
        CubeEvalConfig(tasks=(0, 1))
    with pytest.raises(ConfigError, match="train.gamma"):
        tasks.get("cube-single-play").check(
            override(tasks.preset("cube-single-play", "smoke"), ["train.gamma=0.9"]))
    with pytest.raises(ConfigError, match="feature map"):
        tasks.get("cube-single-play").check(
            override(tasks.preset("cube-single-play", "smoke"), ["neighbours.features=fingertip"]))
    task = tasks.get("cube-single-play")
    assert task.method_defaults("gciql") == {"width": 512, "depth": 4, "batch_size": 1024, "alpha": 1.0}
    assert task.method_defaults("hiql")["subgoal_steps"] == 10


def test_the_task_through_the_cli(tmp_path):
    """The smoke preset (lazy Q on 4 x 100 play transitions, 28-D observation goals searched by
    their cube position) collected, trained and
    evaluated by the CLI: 2 episodes a task, rates in [0, 1], the data cached in the run; and
    evaluated again from the checkpoints to the same outcomes (the episodes' seeds come from
    the evaluation seed, the goal scenes' random steps included)."""
    run_dir = tmp_path / "cube"
    out = cli("train", "--task", "cube-single-play", "--preset", "smoke", "--run-dir", str(run_dir),
              "--no-progress")
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    results = json.loads((run_dir / "results.json").read_text())
    first = results["methods"]["lazy"]["per_seed"]
    assert 0.0 <= first[0]["success_rate"] <= 1.0
    evaluation = json.loads((run_dir / "lazy" / "eval.json").read_text())
    per_task = evaluation["per_seed"][0]["tasks"]["per_task"]
    assert [r["episodes"] for r in per_task] == [2] * 5 and [r["task"] for r in per_task] == [1, 2, 3, 4, 5]
    assert (run_dir / "data" / "0" / "dataset.npz").exists()
    assert (run_dir / "figures" / "lazy" / "cube_rollouts.png").exists()
    out = cli("evaluate", "--run-dir", str(run_dir), "--methods", "lazy", "--no-figures", "--no-progress")
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    assert json.loads((run_dir / "results.json").read_text())["methods"]["lazy"]["per_seed"] == first
