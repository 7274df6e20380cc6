"""Other physics engines for the suite's robots: the same MJCF simulated by DART (``dartpy``)."""

from offdyn_bench.engines.dart_env import DART_ENV_CLASSES, DART_ROBOTS, DartHopperEnv, DartWalker2dEnv, make_dart_env
from offdyn_bench.engines.dart_world import COLLISION_DETECTORS, DartWorld, build_dart_world

__all__ = ["COLLISION_DETECTORS", "DART_ENV_CLASSES", "DART_ROBOTS", "DartHopperEnv", "DartWalker2dEnv", "DartWorld",
           "build_dart_world", "make_dart_env"]
