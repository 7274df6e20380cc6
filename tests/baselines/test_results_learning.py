"""Fast tests of ``baselines.results.learning``'s generalization beyond InvertedPendulum: the dataset
each task trains on, the budget-dependent warm-up, the normalization against task-specific
references, and the published InvertedPendulum results left as they were."""

from __future__ import annotations

import json

import numpy as np
import pytest

from baselines.results import learning
from baselines.results.learning import RESULTS, STEPS


def test_dataset_is_the_official_human_operator_data_for_the_wheel_legged_robot_only():
    assert learning.dataset_mode("wheellegged-standstill") == "official"
    assert learning.dataset_mode("wheellegged-movestraight") == "official"
    assert learning.official_dataset_id("wheellegged-standstill") == "offdyn/wheellegged-standstill/human-operator-v0"
    # The published InvertedPendulum results: sac-source's seed-0 policy collects the dataset.
    assert learning.dataset_mode("invertedpendulum-rail-offset-hard") == "collect"
    assert learning.dataset_spec("collect", learning.Path("runs/x")) == "collect:runs/x:5000"
    assert learning.dataset_spec("official", learning.Path("runs/x")) is None


def test_warmup_is_the_published_one_at_the_default_budget_and_a_quarter_below_it():
    assert learning.method_overrides("dap") == learning.METHODS["dap"][1]
    assert learning.method_overrides("darc", STEPS)["warmup_steps"] == "3000"
    assert learning.method_overrides("dap-u", 8000)["warmup_steps"] == "2000"
    assert "warmup_steps" not in learning.method_overrides("h2o", 8000)


def test_normalization_uses_the_task_specific_best_return():
    assert np.allclose(learning.normalized([888.2, 177842.7, 89365.45], 888.2, 177842.7), [0.0, 100.0, 50.0])
    assert np.allclose(learning.normalized([[3.6], [1000.0]], 3.6, 1000.0), [[0.0], [100.0]])


def _evaluation(returns: dict[int, list[float]]) -> dict:
    return {"seeds": [{"seed": seed, "returns": r} for seed, r in returns.items()]}


def test_summary_of_an_official_dataset_task_records_its_references_and_wall_times(tmp_path):
    runs = tmp_path / "wheellegged-standstill"
    for name, level in (("sac-source", 10_000.0), ("dap", 30_000.0), ("dap-u", 40_000.0)):
        out = learning.run_folder(runs, name)
        out.mkdir(parents=True)
        returns = {seed: [level + 1000.0 * seed] * 3 for seed in range(learning.SEEDS)}
        (out / "evaluation.json").write_text(json.dumps(_evaluation(returns)))
        (out / "wall_time.json").write_text(json.dumps({"train_s": 60.0, "evaluate_s": 6.0}))
    lengths = {str(seed): {"lengths": [6000, 6000, 300], "to_time_limit": [True, True, False]}
               for seed in range(learning.SEEDS)}
    (learning.run_folder(runs, "dap") / "episode_lengths.json").write_text(json.dumps(lengths))
    refs = {"random_return": 1000.0, "best_return": 101_000.0,
            "random_reference": {"source": "the manifest's random reference"},
            "best_reference": {"label": "clean controller", "agent": "pkg.mod:factory", "returns": [101_000.0]}}
    summary = learning.summarize("wheellegged-standstill", runs, ["sac-source", "dap", "dap-u"], steps=8000,
                                 mode="official", refs=refs, command="python -m baselines.results.learning --x")
    assert summary["best_return"] == 101_000.0 and summary["steps"] == 8000
    assert summary["dataset_id"] == "offdyn/wheellegged-standstill/human-operator-v0"
    assert summary["warmup_steps"] == 2000 and summary["best_reference"]["agent"] == "pkg.mod:factory"
    dap = summary["methods"]["dap"]
    assert dap["overrides"]["warmup_steps"] == "2000"
    assert dap["iqm_return"] == pytest.approx(32_000.0)  # IQM of 30k..34k
    assert dap["iqm_normalized"] == pytest.approx(31.0)  # (32k - 1k) / (101k - 1k)
    assert dap["wall_time_s"] == {"train_s": 60.0, "evaluate_s": 6.0}
    assert dap["episodes_to_time_limit"] == "10 of 15" and dap["mean_episode_length_per_seed"]["0"] == 4100.0
    assert "episodes_to_time_limit" not in summary["methods"]["dap-u"]
    assert summary["claims"]["dap >= 2x rl-on-source (IQM return)"]["holds"]  # 32k >= 2 x 12k
    assert summary["claims"]["dap-u > dap"]["holds"]
    md = learning.markdown(summary)
    assert "100 = clean controller 101000.0" in md and "| n/a | 1.0 min / 0.1 min |" in md and "| 10 of 15 |" in md


@pytest.mark.parametrize("task", ["invertedpendulum-rail-offset-hard", "invertedpendulum-action-delay-1",
                                  "invertedpendulum-reversed-motor"])
def test_published_invertedpendulum_results_render_as_committed(task):
    """The generalized script keeps the published format: their markdown renders from their JSON as committed."""
    stem = RESULTS / f"learning-{task}"
    summary = json.loads(stem.with_suffix(".json").read_text())
    assert "dataset_id" not in summary and "best_reference" not in summary
    assert learning.markdown(summary) == stem.with_suffix(".md").read_text()
