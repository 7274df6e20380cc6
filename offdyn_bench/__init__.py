"""offdyn-bench: source/target task pairs, datasets, baselines and gap diagnosis for
off-dynamics reinforcement learning.

Importing the package registers every task pair's two Gymnasium ids (and nothing else).
"""

from offdyn_bench.effects import EFFECT_KINDS, ChannelEffect, Effect, ModelEffect
from offdyn_bench.envs import make_robot_env, set_full_state
from offdyn_bench.errors import InvalidParameterError, OffdynError, UnknownNameError
from offdyn_bench.tasks import TASKS, TaskPair, get_task, register_tasks
from offdyn_bench.versions import __version__, versions

register_tasks()

__all__ = [
    "__version__", "versions",
    "Effect", "ModelEffect", "ChannelEffect", "EFFECT_KINDS",
    "TaskPair", "TASKS", "get_task", "register_tasks",
    "make_robot_env", "set_full_state",
    "OffdynError", "UnknownNameError", "InvalidParameterError",
]
