"""AntMaze's Dict observations in the learning stack: flattened once, the same way for training,
datasets and evaluation (``offdyn_bench.envs.flat_observations``)."""

from __future__ import annotations

import dataclasses

import gymnasium
import numpy as np

from baselines.data import load_dataset
from baselines.train import train
from offdyn_bench.datasets.build import build_dataset
from offdyn_bench.datasets.install import resolve_root
from offdyn_bench.datasets.recipes import default_recipe
from offdyn_bench.envs import flat_observations, flatten_observation_rows
from offdyn_bench.evaluate import evaluate
from offdyn_bench.tasks import get_task

TASK = "antmazesmall-layout-blocked"


def test_stored_dict_observations_flatten_like_the_env_wrapper():
    env = get_task(TASK).make("target")
    flat = flat_observations(env)
    assert isinstance(flat.observation_space, gymnasium.spaces.Box)
    observation, _ = env.reset(seed=0)
    rows = flatten_observation_rows({key: value[None] for key, value in observation.items()}, env.observation_space)
    np.testing.assert_array_equal(rows[0], gymnasium.spaces.flatten(env.observation_space, observation))
    assert flat_observations(get_task("hopper-gravity-0.5").make("target")).observation_space.shape == (11,)


def test_antmaze_trains_evaluates_and_loads_its_minari_dataset(tmp_path):
    pair = get_task(TASK)
    recipe = dataclasses.replace(default_recipe(TASK, "random", num_transitions=150), reference_episodes=1)
    build_dataset(recipe, root=resolve_root(None))
    dataset, provenance = load_dataset(recipe.dataset_id, pair)
    width = flat_observations(pair.make("target")).observation_space.shape[0]
    assert dataset.observations.shape == (150, width) and provenance["kind"] == "minari"
    out = tmp_path / "run"
    result = train("sac-source", TASK, steps=30, out=out, eval_every=30, eval_episodes=1, progress=False,
                   overrides={"random_steps": "10", "sac.hidden_sizes": "[16, 16]", "sac.batch_size": "8"})
    assert np.isfinite(result["mean_return"])
    record = evaluate(out, episodes=1, progress=False)
    assert len(record["seeds"]) == 1
