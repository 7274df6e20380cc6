"""The Adroit env classes of Gymnasium-Robotics, imported without its release notice.

Apart from the task grid (:mod:`offdyn_bench.robotics.adroit`) so that listing tasks never
imports Gymnasium-Robotics; ``offdyn_bench.envs`` subclasses these like every robot's env.
"""

import contextlib
import io

# Gymnasium-Robotics prints a release notice to stderr on import (about the v1 dense rewards of
# door, hammer and relocate, changed in its 1.2.1); the suite pins 1.4.2, so the notice would only
# clutter every command that builds an env.
with contextlib.redirect_stderr(io.StringIO()):
    from gymnasium_robotics.envs.adroit_hand.adroit_door import AdroitHandDoorEnv
    from gymnasium_robotics.envs.adroit_hand.adroit_hammer import AdroitHandHammerEnv
    from gymnasium_robotics.envs.adroit_hand.adroit_pen import AdroitHandPenEnv
    from gymnasium_robotics.envs.adroit_hand.adroit_relocate import (
        AdroitHandRelocateEnv,
    )

__all__ = ["AdroitHandDoorEnv", "AdroitHandHammerEnv", "AdroitHandPenEnv", "AdroitHandRelocateEnv"]
