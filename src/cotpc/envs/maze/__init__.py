"""Moving Maze (``cotpc/MovingMaze-v0``), the embedded default: the environment and its rules (``env.py``),
the planner demonstrator (``demos.py``) and its figure (``figure.py``), rollouts on a split's configs
(``rollout.py``). See docs/moving-maze.md.
"""
