"""Task families from Gymnasium-Robotics: AntMaze layout shifts and Adroit hand shifts.

``mazes`` and ``adroit`` are data (maps, layouts, hand parts) the task grid reads without
importing any physics; ``antmaze`` and ``adroit_envs`` hold the env classes.
"""
