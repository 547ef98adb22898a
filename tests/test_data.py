"""Data collection (§V-A-3) and dataset files."""

import json
import zipfile

import jax
import numpy as np
import pytest

from lazyq_jax.config import ConfigError
from lazyq_jax.data import DatasetError, load_dataset, save_dataset
from lazyq_jax.tasks.push import CollectConfig, push_reward
from lazyq_jax.tasks.push.collect import collect, dataset_summary
from lazyq_jax.types import Transitions

CFG = CollectConfig(n_starts=96, n_goals=7, chunk_size=48, start_range=0.5)


@pytest.fixture(scope="module")
def data():
    return collect(jax.random.key(3), CFG, progress=False)


def test_shapes_dtypes_and_ranges(data):
    n = data.size
    assert n % CFG.n_goals == 0 and n <= CFG.n_starts * 2 * CFG.n_goals
    for name in ("s", "a", "s_next"):
        assert getattr(data, name).shape == (n, 2) and getattr(data, name).dtype == np.float32
    assert data.r.shape == data.g.shape == data.done.shape == (n,)
    assert data.done.dtype == bool
    g = np.asarray(data.g)
    assert g.min() >= -np.pi and g.max() < np.pi
    np.testing.assert_allclose(np.linalg.norm(np.asarray(data.a), axis=1), 0.1, rtol=1e-5)
    assert np.all(np.linalg.norm(np.asarray(data.s), axis=1) > 0.3)  # finger never starts in the disk


def test_rewards_match_eq15_and_episodes_end_at_a_move(data):
    s, a, s_next = (np.asarray(x) for x in (data.s, data.a, data.s_next))
    # s is relative to the disk: s' - s = a - delta_disk
    delta = a - (s_next - s)
    np.testing.assert_array_equal(np.asarray(data.r), np.asarray(push_reward(delta, data.g)))
    moved = np.linalg.norm(delta, axis=1) >= 0.01
    np.testing.assert_array_equal(np.asarray(data.done), moved)
    assert moved.any(), "the small config should move the disk at least once"
    # Rows come in blocks of n_goals per move, episode-major: a first move, then the
    # second move only if the first did not move the disk.
    blocks = s.reshape(-1, CFG.n_goals, 2)
    assert np.all(blocks == blocks[:, :1])
    done = np.asarray(data.done).reshape(-1, CFG.n_goals)[:, 0]
    a_blocks, next_blocks = a[::CFG.n_goals], s_next[::CFG.n_goals]
    i = episodes = 0
    while i < len(done):
        first, i, episodes = i, i + 1, episodes + 1
        if not done[first]:
            np.testing.assert_array_equal(blocks[i, 0], next_blocks[first])  # continues
            np.testing.assert_array_equal(a_blocks[i], a_blocks[first])  # same direction
            i += 1
    assert episodes == CFG.n_starts


def test_same_seed_same_data_independent_of_chunking(data):
    again = collect(jax.random.key(3), CFG, progress=False)
    other_chunks = collect(jax.random.key(3), CollectConfig(**{**CFG.__dict__, "chunk_size": 96}),
                           progress=False)
    other_seed = collect(jax.random.key(4), CFG, progress=False)
    for name in ("s", "a", "s_next", "r", "g", "done"):
        np.testing.assert_array_equal(getattr(again, name), getattr(data, name))
        np.testing.assert_array_equal(getattr(other_chunks, name), getattr(data, name))
    assert not np.array_equal(np.asarray(other_seed.s)[:10], np.asarray(data.s)[:10])


def test_summary_counts(data):
    summary = dataset_summary(data, CFG.n_goals)
    assert summary["rows"] == data.size
    total = sum(o["positive"] + o["negative"] + o["zero"] for o in summary["reward_by_goal_octant"])
    assert total == data.size
    assert summary["moves_that_moved_disk"] == int(np.asarray(data.done).sum()) // CFG.n_goals


def test_save_load_round_trip(tmp_path, data):
    path = save_dataset(tmp_path / "d.npz", data, {"seed": 3, "what": "push"})
    loaded, meta = load_dataset(path)
    assert meta == {"seed": 3, "what": "push"}
    for name in ("s", "a", "s_next", "r", "g", "done"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(data, name))
        assert getattr(loaded, name).dtype == getattr(data, name).dtype


@pytest.mark.parametrize("goal", ["vector", "none"])
def test_round_trip_of_other_goal_kinds(tmp_path, goal):
    rng = np.random.default_rng(0)
    n, f = 11, lambda *shape: rng.normal(size=shape).astype(np.float32)
    g = f(n, 3) if goal == "vector" else None
    data = Transitions(s=f(n, 5), a=f(n, 3), s_next=f(n, 5), r=f(n), g=g, done=rng.random(n) < 0.3)
    loaded, _ = load_dataset(save_dataset(tmp_path / "d.npz", data))
    assert (loaded.g is None) == (goal == "none")
    for name in ("s", "a", "s_next", "r", "done") + (("g",) if g is not None else ()):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(data, name))


def test_bad_files_give_clear_errors(tmp_path, data):
    with pytest.raises(DatasetError, match="no such dataset"):
        load_dataset(tmp_path / "missing.npz")
    good = save_dataset(tmp_path / "good.npz", data, {"seed": 3}).read_bytes()
    (tmp_path / "trunc.npz").write_bytes(good[: len(good) // 2])
    with pytest.raises(DatasetError, match="truncated"):
        load_dataset(tmp_path / "trunc.npz")
    (tmp_path / "text.npz").write_text("hello")
    with pytest.raises(DatasetError, match="trunc|unreadable"):
        load_dataset(tmp_path / "text.npz")
    np.savez(tmp_path / "foreign.npz", x=np.zeros(3))
    with pytest.raises(DatasetError, match="not a lazyq-jax dataset"):
        load_dataset(tmp_path / "foreign.npz")

    def rewrite(name, meta_update=None, arrays_update=None):
        with np.load(tmp_path / "good.npz") as z:
            arrays = {k: z[k] for k in z.files}
        header = json.loads(arrays.pop("header").tobytes())
        header.update(meta_update or {})
        arrays.update(arrays_update or {})
        np.savez(tmp_path / name, header=np.frombuffer(json.dumps(header).encode(), np.uint8), **arrays)
        return tmp_path / name

    with pytest.raises(DatasetError, match="version 99"):
        load_dataset(rewrite("v99.npz", {"version": 99}))
    with pytest.raises(DatasetError, match="'r'"):
        load_dataset(rewrite("shape.npz", arrays_update={"r": np.zeros(5, np.float32)}))
    with pytest.raises(DatasetError, match="'g' is missing"):
        with np.load(tmp_path / "good.npz") as z:
            arrays = {k: z[k] for k in z.files if k != "g"}
        np.savez(tmp_path / "nog.npz", **arrays)
        load_dataset(tmp_path / "nog.npz")
    np.savez(tmp_path / "old.npz", meta=np.zeros(3, np.uint8))
    with pytest.raises(DatasetError, match="older lazyq-jax"):
        load_dataset(tmp_path / "old.npz")
    assert zipfile.is_zipfile(tmp_path / "good.npz")


def test_bad_configs():
    with pytest.raises(ConfigError, match="n_goals"):
        CollectConfig(n_goals=0)
    with pytest.raises(ConfigError, match="start_range"):
        CollectConfig(start_range=0.2)
    with pytest.raises(TypeError, match="CollectConfig"):
        collect(jax.random.key(0), {"n_starts": 3})
