"""Sweeps: a spec of methods x tasks x seeds run as resumable training-and-evaluation runs,
on this machine (a pool of subprocesses) or on a Ray cluster; see the README's "Sweeps".

* :mod:`~offdyn_bench.sweep.spec`: the spec file and its checks;
* :mod:`~offdyn_bench.sweep.runs`: the spec expanded into runs (folders, commands), protocol refusals;
* :mod:`~offdyn_bench.sweep.execute`: one attempt of one run (train, then evaluate, as subprocesses);
* :mod:`~offdyn_bench.sweep.backends`: ``local`` and ``ray``;
* :mod:`~offdyn_bench.sweep.driver`: retries, the state file, progress, the summary;
* :mod:`~offdyn_bench.sweep.submission`: per-seed evaluations merged for ``leaderboard submit``.

Nothing heavy is imported here.
"""

from offdyn_bench.sweep.spec import SpecError, SweepSpec, TrainingOptions, load_spec, parse_spec

__all__ = ["SpecError", "SweepSpec", "TrainingOptions", "load_spec", "parse_spec"]
