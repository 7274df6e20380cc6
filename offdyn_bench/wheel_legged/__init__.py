"""The wheel-legged balancer (issue 12; H2O's real-robot validation, simulated).

``env``: the Gymnasium MuJoCo environment and its two tasks. ``pairs``: the source/target task
pairs and the target's effects. ``operator``: the human-operator controller whose recordings are
the target datasets. Kept apart so that registering the pairs imports no MuJoCo env module.
"""
