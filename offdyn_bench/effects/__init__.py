"""One vocabulary of dynamics effects: model effects and channel effects."""

from offdyn_bench.effects.base import EFFECT_KINDS, Effect, effects_from_dicts, effects_to_dicts
from offdyn_bench.effects.channel import (
    ActionBias,
    ActionDeadzone,
    ActionDelay,
    ActionGain,
    ActionNoise,
    ActionSaturation,
    ChannelEffect,
    CONTROL_COST_ON,
    ChannelEffects,
    ControlCostOn,
    ObsBias,
    ObsDelay,
    ObsNoise,
)
from offdyn_bench.effects.model import (
    Armature,
    BodyOffset,
    ContactSolimp,
    ContactSolref,
    Damping,
    Friction,
    FrictionCone,
    FrictionLoss,
    Gear,
    GeomSize,
    Gravity,
    Integrator,
    JointLimit,
    JointLimitSoftness,
    JointRange,
    LimbSize,
    Mass,
    ModelEffect,
    NoSlip,
    apply_model_effects,
    compile_model,
    split_effects,
)
from offdyn_bench.effects.layout import MazeLayout  # after model: a model effect of its own module

__all__ = [
    "EFFECT_KINDS", "Effect", "ModelEffect", "ChannelEffect", "ChannelEffects", "CONTROL_COST_ON", "ControlCostOn",
    "effects_from_dicts", "effects_to_dicts", "compile_model", "apply_model_effects", "split_effects",
    "Gravity", "Friction", "Mass", "Damping", "FrictionLoss", "Armature", "Gear", "JointRange",
    "JointLimit", "JointLimitSoftness", "BodyOffset", "GeomSize", "LimbSize", "ContactSolref",
    "ContactSolimp", "FrictionCone", "Integrator", "NoSlip", "MazeLayout",
    "ActionNoise", "ActionDeadzone", "ActionBias", "ActionGain", "ActionSaturation", "ActionDelay",
    "ObsNoise", "ObsBias", "ObsDelay",
]
