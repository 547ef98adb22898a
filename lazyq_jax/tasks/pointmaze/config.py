"""The pointmaze task's settings: its data (OGBench's navigate recipe or a user's ``.npz``), its
evaluation (OGBench's five tasks) and its presets."""

from __future__ import annotations

import dataclasses

from lazyq_jax.config import Config, NeighbourConfig, TrainConfig, _check, _counts, _positive
from lazyq_jax.tasks.pointmaze.dataset import RECIPES
from lazyq_jax.tasks.pointmaze.maze import MAZES


@dataclasses.dataclass(frozen=True)
class PointMazeCollectConfig:
    """The dataset of one seed (:mod:`lazyq_jax.tasks.pointmaze.dataset`).

    ``maze``: OGBench's ``medium`` (default), ``large``, ``giant`` or ``teleport``.
    ``recipe``: ``navigate`` or ``stitch`` (:mod:`~lazyq_jax.tasks.pointmaze.dataset`).
    ``episodes`` x ``episode_steps`` env steps of the recipe with action noise ``noise``
    (OGBench's ``pointmaze-*-navigate-v0``: 1000 x 1001, giant 500 x 2001;
    ``pointmaze-*-stitch-v0``: 5000 x 201; noise 0.5: :func:`dataset_collect`), or, with ``dataset``
    set, the trajectories of that OGBench ``.npz`` file instead (the same file for every seed;
    the seeds then differ in goals and training only).  ``goals_per_transition`` relabelled
    copies of every transition, goals drawn as OGBench's value goals: the current state with
    ``p_curgoal``, a geometric(``1 - discount``) future state with ``p_trajgoal``, a random
    state with the rest (``discount`` must be the training discount).
    """

    maze: str = "medium"
    recipe: str = "navigate"
    episodes: int = 1000
    episode_steps: int = 1001
    noise: float = 0.5
    dataset: str | None = None
    goals_per_transition: int = 1
    p_curgoal: float = 0.2
    p_trajgoal: float = 0.5
    discount: float = 0.99

    def __post_init__(self) -> None:
        _check(self.maze in MAZES, f"PointMazeCollectConfig.maze must be one of {MAZES}, got {self.maze!r}")
        _check(self.recipe in RECIPES,
               f"PointMazeCollectConfig.recipe must be one of {RECIPES}, got {self.recipe!r}")
        _counts(self, "episodes", "goals_per_transition")
        _counts(self, "episode_steps", minimum=2)
        _positive(self, "noise")
        _check(self.dataset is None or (isinstance(self.dataset, str) and bool(self.dataset)),
               f"PointMazeCollectConfig.dataset must be a path to an OGBench .npz or None, got {self.dataset!r}")
        for name in ("p_curgoal", "p_trajgoal"):
            v = getattr(self, name)
            _check(isinstance(v, (int, float)) and not isinstance(v, bool) and 0.0 <= v <= 1.0,
                   f"PointMazeCollectConfig.{name} must be in [0, 1], got {v!r}")
        _check(self.p_curgoal + self.p_trajgoal <= 1.0 + 1e-9,
               f"PointMazeCollectConfig: p_curgoal + p_trajgoal = {self.p_curgoal + self.p_trajgoal} "
               "exceeds 1 (the rest is the random goals' share)")
        _check(isinstance(self.discount, float) and 0.0 < self.discount < 1.0,
               f"PointMazeCollectConfig.discount must be a float in (0, 1), got {self.discount!r}")


@dataclasses.dataclass(frozen=True)
class PointMazeEvalConfig:
    """OGBench's evaluation: for each of ``tasks`` (1-5: ``env.unwrapped.task_infos``), start
    and goal at their cells with the +-1 noise, ``episodes_per_task`` episodes of at most
    ``max_steps`` steps, actions clipped to ``[-1, 1]^2``, success within 1.0 of the goal
    (the episode ends); the success rate is averaged over the episodes, then the tasks.
    ``seed``: an offset added to each seed's evaluation seed."""

    seed: int = 0
    tasks: tuple[int, ...] = (1, 2, 3, 4, 5)
    episodes_per_task: int = 50
    max_steps: int = 1000

    def __post_init__(self) -> None:
        _counts(self, "episodes_per_task", "max_steps")
        _counts(self, "seed", minimum=0)
        tasks = tuple(self.tasks)
        _check(len(tasks) > 0 and all(isinstance(t, int) and 1 <= t <= 5 for t in tasks)
               and len(set(tasks)) == len(tasks),
               f"PointMazeEvalConfig.tasks must be distinct task numbers in 1-5, got {self.tasks!r}")
        object.__setattr__(self, "tasks", tasks)


def check(config: Config) -> None:
    c = config.collect
    _check(abs(c.discount - config.train.gamma) < 1e-12,
           f"collect.discount={c.discount} (the geometric goal offsets) must equal train.gamma="
           f"{config.train.gamma}; set both")


# Lazy Q on the maze.  Value information must travel over a hundred steps (tasks 1 and 4: ~130
# steps of at most 0.2 per axis), one step per cycle: many short cycles (one epoch each)
# rather than the paper's 10 x 10.  Neighbourhoods in (state, goal) space: 0.5 in x, y (2.5 steps) and
# 1.0 in the goal (OGBench's success radius); 93 % of the transitions have k = 20 members at
# level 0 on the default data.  Local models with state and goal offsets (the value changes by
# ~5 per unit across the state and the goal ball, an action by one step): seed 0, 58.0 % of
# OGBench's evaluation against 22.4 % with state offsets only (docs/pointmaze.md).  The policy
# takes two levels: a subgoal among the states the neighbours' trajectories reached 25 steps
# later (HIQL's subgoal_steps), then Eq. (9)'s step towards it: 64.8 % over 5 seeds against
# 42.0 % for the one-level step on the same trained V (docs/pointmaze.md).  The targets take
# each neighbour's return over up to 10 steps of its own trajectory (train.target_steps): the
# one-step target kept V on the straight line through the walls; with 10 steps V ranks the
# pairs across walls like V* (docs/pointmaze.md, "Multi-step lazy targets").  The near subgoal
# heads for a far one, among the states the neighbours' trajectories reached 100 steps later
# (neighbours.far_subgoal_steps): the two-level step stopped at V's local maxima 25 steps
# wide on the large and giant mazes (docs/pointmaze.md, "Where the policy stops").
_NEIGHBOURS = NeighbourConfig(k=20, radius_s=0.5, radius_g=1.0, max_level=8,
                              local_model="action+state+goal", subgoal_steps=25, far_subgoal_steps=100)
_TRAIN = TrainConfig(gamma=0.99, cycles=300, epochs=1, batch_size=4096, learning_rate=1e-3,
                     target_steps=10)
_SMOKE_TRAIN = TrainConfig(gamma=0.99, cycles=3, epochs=1, batch_size=256, target_batch_size=4096,
                           target_steps=10)


def dataset_id(maze: str, recipe: str) -> str:
    """OGBench's dataset name without its version: ``pointmaze-{maze}-{recipe}``."""
    return f"pointmaze-{maze}-{recipe}"


DATASETS = tuple(dataset_id(m, r) for r in RECIPES for m in MAZES)


def discount(maze: str) -> float:
    """OGBench's discount for a maze's datasets: 0.995 in giant (``impls/hyperparameters.sh``:
    every method but GCBC), else 0.99.  A setting of the dataset, so lazy Q takes it too."""
    return 0.995 if maze == "giant" else 0.99


def dataset_collect(maze: str, recipe: str) -> PointMazeCollectConfig:
    """OGBench's recipe for ``pointmaze-{maze}-{recipe}-v0`` (``data_gen_scripts/commands.sh``):
    navigate 1000 episodes x 1001 steps (giant 500 x 2001), stitch 5000 x 201; noise 0.5; the
    value goals' discount the maze's (:func:`discount`)."""
    if recipe == "stitch":
        episodes, steps = 5000, 201
    else:
        episodes, steps = (500, 2001) if maze == "giant" else (1000, 1001)
    return PointMazeCollectConfig(maze=maze, recipe=recipe, episodes=episodes, episode_steps=steps,
                                  discount=discount(maze))


def presets(maze: str = "medium", recipe: str = "navigate", task: str = "pointmaze") -> dict[str, Config]:
    """``paper`` (the CPU default: OGBench's data of ``pointmaze-{maze}-{recipe}``, 300
    one-epoch cycles, the full evaluation; the same lazy Q settings for every dataset but the
    discount, which is the dataset's) and ``smoke`` (a tiny end-to-end run)."""
    gamma = discount(maze)
    paper = Config(task=task, collect=dataset_collect(maze, recipe), eval=PointMazeEvalConfig(),
                   neighbours=_NEIGHBOURS, train=dataclasses.replace(_TRAIN, gamma=gamma))
    smoke = dataclasses.replace(
        paper, collect=dataclasses.replace(paper.collect, episodes=20, episode_steps=101),
        eval=PointMazeEvalConfig(episodes_per_task=2, max_steps=30),
        train=dataclasses.replace(_SMOKE_TRAIN, gamma=gamma),
        neighbours=dataclasses.replace(_NEIGHBOURS, k=8, radius_s=1.0, radius_g=2.0))
    return {"paper": paper, "smoke": smoke}
