"""offdyn-bench: source/target task pairs, datasets, baselines and gap diagnosis for
off-dynamics reinforcement learning.

Importing the package registers every task pair's two Gymnasium ids (and nothing else). The env
classes (``make_robot_env``, ``set_full_state``) load on first use: registration needs only the
task grid, and the command line starts faster without Gymnasium's MuJoCo env modules.
"""

from __future__ import annotations

import importlib
from typing import Any

from offdyn_bench.effects import EFFECT_KINDS, ChannelEffect, Effect, ModelEffect
from offdyn_bench.errors import InvalidParameterError, OffdynError, UnknownNameError
from offdyn_bench.tasks import TASKS, TaskPair, get_task, register_tasks
from offdyn_bench.versions import __version__, versions

register_tasks()

_LAZY = {"make_robot_env": "offdyn_bench.envs", "set_full_state": "offdyn_bench.envs"}

__all__ = [
    "__version__", "versions",
    "Effect", "ModelEffect", "ChannelEffect", "EFFECT_KINDS",
    "TaskPair", "TASKS", "get_task", "register_tasks",
    "make_robot_env", "set_full_state",
    "OffdynError", "UnknownNameError", "InvalidParameterError",
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value  # later look-ups skip this function
        return value
    raise AttributeError(f"module 'offdyn_bench' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
