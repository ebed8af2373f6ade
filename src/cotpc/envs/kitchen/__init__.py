"""The paper's ordered Franka Kitchen variant (``cotpc/FrankaKitchenOrdered-v0``): the environment (``env.py``),
the scripted demonstrator (``demos.py``), rollouts with the paper's two numbers (``rollout.py``). Needs the
``kitchen`` extra to run; importing ``env.py`` does not import mujoco. See docs/kitchen.md.
"""
