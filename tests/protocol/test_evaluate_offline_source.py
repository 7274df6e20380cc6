"""``evaluate`` on an offline-source run: the source dataset in the record, the command that
retrains it, and a note when it is not the track's official one."""

from __future__ import annotations

from baselines.data import collect_dataset
from baselines.train import train
from offdyn_bench.evaluate import evaluate
from offdyn_bench.tasks import get_task

TASK = "invertedpendulum-gravity-3.0"


def test_an_offline_source_run_is_evaluated_with_its_source_dataset(tmp_path):
    pair = get_task(TASK)
    source, target = tmp_path / "source.npz", tmp_path / "target.npz"
    collect_dataset(pair, "random", 300, 0, side="source").save_npz(source)
    collect_dataset(pair, "random", 200, 1, side="target").save_npz(target)
    out = tmp_path / "run"
    train("dara", TASK, steps=40, out=out, dataset=str(target), source_dataset=str(source), eval_every=40,
          eval_episodes=1, progress=False,
          overrides={"sac.hidden_sizes": "[16, 16]", "sac.batch_size": "16", "classifier_steps": "10"})
    record = evaluate(out, track="offline-source-offline-target", episodes=2, progress=False)
    assert record["source_dataset"]["sha256"] and record["dataset"]["sha256"]
    assert record["source_dataset"]["sha256"] != record["dataset"]["sha256"]
    assert f"--source-dataset {source}" in record["train_command"]
    assert f"--dataset {target}" in record["train_command"]
    notes = " ".join(record["notes"])
    assert "official source dataset is 'offdyn/invertedpendulum-gravity-3p0/source-v0'" in notes
    assert not record["protocol_conformant"]
