"""The ManiSkill3 tasks (Stack Cube, Peg Insertion, ...): their settings and seed ranges (``env.py``), motion-planned
demos (``demos.py``), rollouts on a split's seeds (``rollout.py``). Needs the ``maniskill`` extra to run;
importing ``env.py`` does not import mani_skill. See docs/maniskill.md.
"""
