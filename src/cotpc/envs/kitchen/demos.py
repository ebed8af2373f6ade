"""A scripted demonstrator for the ordered Franka Kitchen variant (no human demos can be had here).

The paper replays 50 human demos (relay-policy-learning); those cannot be downloaded on our machines, so a scripted
controller stands in for them (docs/kitchen.md):

- **Control**: resolved-rate inverse kinematics on MuJoCo's ``end_effector`` site: the Cartesian pose error becomes a
  twist (position and orientation, speed-limited), damped least squares turns it into arm joint velocities, joints
  that sit at a limit and would move further out are dropped from the solve, and a null-space term keeps the arm
  near its initial posture. The base environment turns a velocity action into a position target from the current
  joint positions, so the arm sags under gravity and lags the command; the controller adds the gravity torque over
  the actuator gain (feed-forward), doubles the commanded motion (the measured lag: a joint covers about half of
  the commanded step) and integrates the remaining joint error while the arm is nearly still (integral action, for
  loads such as the kettle). Its outputs are the environment's own 9-dim actions.
- **Sub-tasks**: one script per sub-task, reading object poses from the simulator (the demonstrator is privileged):
  grasp and twist a knob (bottom and top burner), push the light switch lever, push the slide cabinet handle,
  grasp or pinch a handle and follow the door's arc (hinge cabinet, microwave), push the kettle along the stove to
  the back burner. Why each is done the way it is (what failed first) is in docs/kitchen.md. Scripts are chained in
  the requested order, with a retreat and sometimes a via point between them.
- **Diversity, on purpose** (the paper's demos are human and sub-optimal): each attempt draws a style (speeds,
  pauses, action noise, how far past the completion threshold to go, via points between sub-tasks) and each
  sub-task its variants (where along a handle to grasp or push, the slide cabinet's hand pose, how far a door's
  target leads the door, waypoint noise). The initial scene varies with the seed (the environment's reset).

A demo is kept only if it completes the 4 sub-tasks in order within the horizon, and the recorded actions are then
replayed in a fresh environment from the same seed and goal and must succeed again (at the same step). The
privileged ``key_steps`` (the step index after which each sub-task is counted) are stored for scoring subskill
discovery only.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from cotpc.data.trajectories import Episode, TrajectorySet, save_trajectories
from cotpc.envs.spec import check_demo_flags
from cotpc.envs.kitchen.env import (ENV_ID, HORIZON, NUM_REQUESTED, SEEDS, SUBTASKS, FrankaKitchenOrderedEnv, check_seed,
                               validate_tasks)

DT = 0.08  # the base environment's control period (40 MuJoCo steps of 2 ms)
# Gripper frames (columns: the site's x, y and z axes in world coordinates). The site's z axis is the approach
# direction and its y axis the direction the fingers close along. FORWARD is the arm's initial grasp pose:
# pointing at the kitchen wall (+y), fingers closing along x, the site's x axis up.
FORWARD = np.column_stack([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
TIP = 0.045
KETTLE_FRONT = 0.135  # the kettle's body: its front face is this far in front of its origin
PINCH = 0.03  # the pinch grasp's site sits this far in front of the microwave handle's axis (fingertips on the door)


def rot(axis: str, angle: float) -> np.ndarray:
    """Rotation matrix about a world axis."""
    c, s = np.cos(angle), np.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def rotation_error(target: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Rotation vector (world frame) that turns ``current`` into ``target``."""
    E = target @ current.T
    angle = np.arccos(np.clip((np.trace(E) - 1.0) / 2.0, -1.0, 1.0))
    axis = np.array([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]])
    norm = np.linalg.norm(axis)
    if norm < 1e-9:  # no rotation, or exactly half a turn (never commanded here)
        return np.zeros(3)
    return axis / norm * angle


class IKController:
    """Resolved-rate IK on the end-effector site, producing the base environment's velocity actions."""

    KP, KR = 5.0, 4.0  # Cartesian gains (1/s): the commanded twist is gain * error, speed-limited
    MIN_SPEED = 0.06  # m/s
    DAMPING = 0.05  # damped least squares
    # Joint weights of the least-squares solution: rolls about the approach axis mostly by the wrist's last joint
    # (spread over the other joints they drive joint 6 into its limit).
    WEIGHTS = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 4.0])
    NULL_GAIN = 0.5  # pull towards the initial posture in the null space
    LAG_GAIN = 2.0  # a joint covers about half of the commanded step within one control period (measured)
    KI, I_MAX, I_STILL = 0.3, 0.1, 0.01  # integral action: gain, bound (rad), only when commanded steps < I_STILL

    def __init__(self, model, data, home: np.ndarray):
        import mujoco  # the optional [kitchen] extra

        self.mujoco = mujoco
        self.model, self.data = model, data
        self.site = model.site("end_effector").id
        # Joint limits: the model's range and the base environment's position bounds (ctrl clipping), with a margin.
        bounds = np.array([[-2.9, 2.9], [-1.8, 1.8], [-2.9, 2.9], [-3.1, 0.0], [-2.9, 2.9], [0.0, 3.8], [-2.9, 2.9]])
        self.lo = np.maximum(model.jnt_range[:7, 0], bounds[:, 0]) + 0.03
        self.hi = np.minimum(model.jnt_range[:7, 1], bounds[:, 1]) - 0.03
        self.gain = model.actuator_gainprm[:7, 0].copy()
        self.home = np.array(home[:7], dtype=np.float64)
        self.jacp = np.zeros((3, model.nv))
        self.jacr = np.zeros((3, model.nv))
        self.integral = np.zeros(7)
        self.expected: Optional[np.ndarray] = None

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        return self.data.site_xpos[self.site].copy(), self.data.site_xmat[self.site].reshape(3, 3).copy()

    def action(self, pos: np.ndarray, R: np.ndarray, grip: float, speed: float, wspeed: float = 1.5) -> np.ndarray:
        """One action towards the pose (``pos``, ``R``); ``grip`` the finger velocity (+1 open, -1 close)."""
        q = self.data.qpos[:7].copy()
        p, Rc = self.pose()
        e = np.asarray(pos) - p
        # Speed-limited proportional approach, with a floor so the last centimetres do not take many steps.
        v = e / max(np.linalg.norm(e), 1e-9) * min(speed, self.KP * np.linalg.norm(e) + self.MIN_SPEED)
        v *= min(1.0, np.linalg.norm(e) / DT / max(np.linalg.norm(v), 1e-9))  # no overshoot within one step
        w = self.KR * rotation_error(R, Rc)
        w *= min(1.0, wspeed / max(np.linalg.norm(w), 1e-9))
        self.mujoco.mj_jacSite(self.model, self.data, self.jacp, self.jacr, self.site)
        J = np.vstack([self.jacp[:, :7], self.jacr[:, :7]])
        twist = np.concatenate([v, w])
        free = np.ones(7, dtype=bool)
        for _ in range(7):  # drop joints at a limit that the solution would push further out, and solve again
            Jf = J[:, free]
            W = np.diag(self.WEIGHTS[free])
            pinv = W @ Jf.T @ np.linalg.inv(Jf @ W @ Jf.T + self.DAMPING ** 2 * np.eye(6))
            dq = np.zeros(7)
            dq[free] = pinv @ twist + (np.eye(free.sum()) - pinv @ Jf) @ (self.NULL_GAIN * (self.home - q)[free])
            nxt = q + dq * DT
            out = free & (((nxt < self.lo) & (dq < 0)) | ((nxt > self.hi) & (dq > 0)))
            if not out.any():
                break
            free &= ~out
        if self.expected is not None and np.abs(dq).max() * DT < self.I_STILL:
            # Integral action: the joint motion the last command did not achieve (loads the feed-forward misses).
            self.integral = np.clip(self.integral + self.KI * (self.expected - q), -self.I_MAX, self.I_MAX)
        self.expected = q + dq * DT
        return self._command(dq, grip)

    def _command(self, dq: np.ndarray, grip: float) -> np.ndarray:
        gravity = self.data.qfrc_bias[:7] / self.gain  # the position offset that holds the arm against gravity
        arm = (self.LAG_GAIN * dq * DT + gravity + self.integral) / (2.0 * DT)  # 1.0 = 2 rad/s over DT
        return np.concatenate([np.clip(arm, -1.0, 1.0), [grip, grip]])


class _EpisodeOver(Exception):
    """The environment ended the episode (success, a violation) or the horizon was reached."""


@dataclass
class Style:
    """How one attempt moves (drawn per attempt; see :func:`sample_style`)."""

    speed: float  # transit speed (m/s)
    work_speed: float  # speed while pushing, pulling or carrying (m/s)
    pause_prob: float  # chance of a pause before each phase
    noise: float  # std of the Gaussian noise added to the arm actions
    margin: float  # how far past the completion threshold to drive an object, in [0, 1] of the remaining range
    via_prob: float  # chance of a random via point between sub-tasks


def sample_style(rng: np.random.Generator) -> Style:
    return Style(speed=rng.uniform(0.45, 0.65), work_speed=rng.uniform(0.2, 0.35), pause_prob=rng.uniform(0.0, 0.3),
                 noise=rng.uniform(0.0, 0.04), margin=rng.uniform(0.2, 0.8), via_prob=rng.uniform(0.0, 0.6))


class ScriptedRun:
    """Drives one environment episode with the scripted sub-task skills, recording what happens.

    Skills call :meth:`move`, :meth:`hold` and :meth:`set_grip`, which step the environment; when the episode ends
    (or reaches the horizon) they raise :class:`_EpisodeOver`, which :meth:`run` catches."""

    def __init__(self, env, obs: np.ndarray, rng: np.random.Generator, style: Style):
        self.env, self.rng, self.style = env, rng, style
        self.model, self.data = env.model, env.data
        self.ctrl = IKController(env.model, env.data, env.base_qpos)
        self.grip = 1.0
        self.obs, self.actions = [np.asarray(obs, dtype=np.float32)], []
        self.key_steps: dict[str, int] = {}
        self.info: dict = {}
        self.attempted: list[str] = []

    # ---- primitives -------------------------------------------------------------------------------------------
    def step(self, pos, R, speed: float) -> None:
        """One environment step towards the pose (pos, R), with the style's action noise."""
        if len(self.actions) >= HORIZON:
            raise _EpisodeOver
        action = self.ctrl.action(pos, R, self.grip, speed)
        action[:7] = np.clip(action[:7] + self.rng.normal(0.0, self.style.noise, size=7), -1.0, 1.0)
        action = action.astype(np.float32)  # step with exactly what is stored, so that replays are exact
        obs, _, terminated, _, info = self.env.step(action)
        self.actions.append(action)
        self.obs.append(obs)
        self.info = info
        for name in info["step_completed"]:
            self.key_steps[name] = len(self.actions)  # index of the first state in which the sub-task counts
        if terminated:
            raise _EpisodeOver

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        return self.ctrl.pose()

    def maybe_pause(self) -> None:
        if self.rng.random() < self.style.pause_prob:
            self.hold(int(self.rng.integers(1, 5)))

    def move(self, pos, R, speed: float | None = None, tol: float = 0.012, rtol: float = 0.06,
             max_steps: int = 45, until=None) -> bool:
        """Step towards (pos, R) until within tolerance, ``until()`` holds, or ``max_steps``; True if reached."""
        speed = speed or self.style.speed
        for _ in range(max_steps):
            if until is not None and until():
                return True
            p, Rc = self.pose()
            if np.linalg.norm(np.asarray(pos) - p) < tol and np.linalg.norm(rotation_error(R, Rc)) < rtol:
                return True
            self.step(pos, R, speed)
        return False

    def hold(self, steps: int) -> None:
        p, R = self.pose()
        for _ in range(steps):
            self.step(p, R, self.style.speed)

    def set_grip(self, grip: float, steps: int = 3) -> None:
        """Open (+1) or close (-1) the fingers while holding the pose."""
        self.grip = grip
        self.hold(steps)

    def site(self, name: str) -> np.ndarray:
        return self.data.site(name).xpos.copy()

    def qpos(self, i: int) -> float:
        return float(self.data.qpos[i])

    def jitter(self, scale: float) -> np.ndarray:
        return self.rng.uniform(-scale, scale, size=3)

    def retreat(self, dy: float = -0.12, dz: float = 0.0) -> None:
        """Let go and back away from the object along the approach axis."""
        self.set_grip(1.0, 2)
        p, R = self.pose()
        self.move(p + np.array([0.0, dy, dz]) + self.jitter(0.015), R, max_steps=20, tol=0.03)

    def approach(self, target: np.ndarray, R: np.ndarray, standoff: float = 0.13, side: float = 0.0) -> None:
        """Go to a point in front of ``target`` (-y, and ``side`` along x), aligned, then straight in to ``target``."""
        pre = target + np.array([side, -standoff, 0.0]) + self.jitter(0.02) * [1, 0.5, 1]
        self.move(pre, R, tol=0.03, rtol=0.1, max_steps=50)
        self.maybe_pause()
        self.move(target, R, speed=self.style.work_speed, tol=0.01, rtol=0.05, max_steps=16)

    # ---- sub-task skills (object poses are read from the simulator) ----------------------------------------------
    def knob(self, site: str, joint: int) -> None:
        """Grasp the knob's fin from the front and twist it (negative knob angle = about world +y)."""
        grasp = self.site(site) + np.array([0.0, -0.03 + self.rng.uniform(-0.004, 0.004), self.rng.uniform(-0.012, 0.012)])
        self.set_grip(1.0, 1)
        self.approach(grasp, FORWARD)
        self.set_grip(-1.0, 3)
        self.maybe_pause()
        target = -(0.7 + 0.3 * self.style.margin)  # inside the completion window [-1.18, -0.58] of the goal -0.88
        twist = rot("y", -target + 0.35) @ FORWARD  # the fin slips a little in the fingers: turn further
        self.move(grasp, twist, speed=self.style.work_speed, max_steps=40, until=lambda: self.qpos(joint) <= target)
        self.retreat()

    def light_switch(self) -> None:
        """Push the switch lever's tip towards -x with closed fingers."""
        tip = self.site("light_site")
        start = tip + np.array([0.045, -0.03, self.rng.uniform(-0.008, 0.008)])
        self.grip = -1.0
        self.approach(start, FORWARD)
        self.maybe_pause()
        target = -0.42 - 0.25 * self.style.margin  # completed below about -0.39 (goal -0.69, range [-0.7, 0])
        self.move(start + np.array([-0.2, 0.0, 0.0]), FORWARD, speed=self.style.work_speed, max_steps=40,
                  until=lambda: self.qpos(17) <= target)
        self.retreat()

    def slide_cabinet(self) -> None:
        """Push the slide cabinet's handle towards +x: closed fingers on its left (hand level, or rolled upright),
        or open fingers around it. Next to an open hinge door only the upright hand fits (the hand is 20 cm wide
        across the fingers)."""
        handle = self.site("slide_site") + np.array([0.0, -0.025, self.rng.uniform(-0.1, 0.1)])
        variant = "upright" if self.qpos(21) > 0.3 else self.rng.choice(["level", "upright", "around"])
        R = rot("y", -np.pi / 2) @ FORWARD if variant == "upright" else FORWARD
        if variant == "around":
            self.grip, start = 1.0, handle
        else:
            self.grip, start = -1.0, handle + np.array([-0.045, 0.0, 0.0])
        if variant == "upright":  # roll the hand in free space, right of the handle, clear of an open hinge door
            self.move(start + np.array([0.12, -0.2, 0.0]) + self.jitter(0.02), R, tol=0.04, rtol=0.15, max_steps=30)
        self.approach(start, R, side=0.07)  # from the right: an open hinge door's handle sticks out on the left
        self.maybe_pause()
        target = 0.1 + 0.2 * self.style.margin  # completed above 0.07 (goal 0.37, range [0, 0.44])
        self.move(start + np.array([0.35, 0.0, 0.0]), R, speed=self.style.work_speed, max_steps=40,
                  until=lambda: self.qpos(19) >= target)
        self.retreat()

    def follow_arc(self, joint: int, hinge: np.ndarray, sign: float, target: float, ahead: float,
                   yaw_follow: float = 1.0, max_steps: int = 60) -> bool:
        """Move the hand along the arc of a door turning about a vertical axis through ``hinge``, the target leading
        the door's angle by ``ahead`` (rad), until the angle passes ``target`` (True) or the door stops following.
        The hand turns by ``yaw_follow`` times the door's turn (1: rigidly with the door)."""
        p0, R0 = self.pose()
        angle0 = self.qpos(joint)
        history = [angle0]
        for _ in range(max_steps):
            angle = self.qpos(joint)
            if sign * (angle - target) >= 0:
                return True
            if len(history) > 4 and sign * (angle - history[-4]) < 0.015:
                return False  # the grip slipped: the door no longer follows
            turn = rot("z", angle + sign * ahead - angle0)
            yaw = rot("z", yaw_follow * (angle + sign * ahead - angle0))
            self.step(hinge + turn @ (p0 - hinge), yaw @ R0, self.style.work_speed)
            history.append(self.qpos(joint))
        return False

    def back_off(self, distance: float = 0.1, up: float = 0.0) -> None:
        """Open the fingers and move back along the approach axis."""
        self.set_grip(1.0, 2)
        p, R = self.pose()
        self.move(p - distance * R[:, 2] + np.array([0.0, 0.0, up]), R, max_steps=20, tol=0.03)

    def hinge_cabinet(self) -> None:
        """Grasp the right door's vertical handle from the front and follow the door's arc without turning the hand
        (the fingers slide round the round handle). Turning the hand with the door makes the handle creep out of the
        fingers (MuJoCo's soft friction against the door's friction loss) after 0.3-0.9 rad; if it slips anyway,
        grasp again where it is."""
        height = self.rng.uniform(-0.1, 0.1)
        ahead = self.rng.uniform(0.15, 0.25)
        # completed above about 1.16 (goal 1.45 with the left door at 0; range [0, 1.57])
        target = 1.25 + 0.2 * self.style.margin
        for attempt in range(2):
            R = rot("z", self.qpos(21)) @ FORWARD  # face the door where it is now
            grasp = self.site("hinge_site2") + np.array([0.0, 0.0, height]) - 0.01 * R[:, 2]
            self.set_grip(1.0, 1)
            if attempt == 0:
                self.approach(grasp, R)
            else:
                self.move(grasp - 0.06 * R[:, 2], R, tol=0.015, rtol=0.08, max_steps=20)
                self.move(grasp, R, speed=self.style.work_speed, tol=0.008, rtol=0.05, max_steps=20)
            self.set_grip(-1.0, 3)
            self.maybe_pause()
            done = self.follow_arc(21, self.data.body("hingerightdoor").xpos.copy(), +1.0, target, ahead, yaw_follow=0.0)
            self.back_off(0.06 if not done else 0.1)
            if done:
                return

    def microwave(self) -> None:
        """Pinch the door's handle from the front (it sits almost flush with the door, so the fingertips rest on the
        door) and pull it along the door's arc without turning the hand; grasp again if it slips. (Turning the hand
        with the door stretches the arm beyond its reach.)"""
        height = self.rng.uniform(-0.08, 0.08)
        target = -0.55 - 0.3 * self.style.margin  # completed below -0.45 (goal -0.75; range [-2.09, 0])
        for attempt in range(2):
            R = rot("z", self.qpos(22)) @ FORWARD  # face the door where it is now
            grasp = self.site("microhandle_site") + np.array([0.0, 0.0, height]) - PINCH * R[:, 2]
            self.set_grip(1.0, 1)
            if attempt == 0:
                self.approach(grasp, R)
            else:
                self.move(grasp - 0.06 * R[:, 2], R, tol=0.015, rtol=0.08, max_steps=20)
                self.move(grasp, R, speed=self.style.work_speed, tol=0.008, rtol=0.05, max_steps=20)
            self.set_grip(-1.0, 3)
            self.maybe_pause()
            done = self.follow_arc(22, self.data.body("microdoorroot").xpos.copy(), -1.0, target,
                                   self.rng.uniform(0.06, 0.12), yaw_follow=0.0)
            self.back_off(0.06 if not done else 0.1)
            if done or self.qpos(22) < -0.45:
                return

    def kettle(self) -> None:
        """Push the kettle along the stove towards the back left burner with the hand pointing down, the open
        fingertips low on the body's front face (so it slides without tipping). (Lifting it by the handle fails:
        with the fingers closing vertically the lower finger cannot hold its 0.9 kg; from above, the hand runs into
        the knobs over the back burner. Pushing with the hand level needs the elbow folded against its limit.)"""
        kettle = self.data.qpos[23:26].copy()
        q = self.data.qpos[26:30]
        yaw = 2.0 * np.arctan2(q[3], q[0])  # the kettle only turns about the vertical axis
        R = rot("z", yaw) @ rot("x", -np.pi / 2) @ FORWARD  # pointing down, fingers spread along the front face
        forward = rot("z", yaw) @ np.array([0.0, 1.0, 0.0])
        contact = kettle + rot("z", yaw) @ np.array([self.rng.uniform(-0.03, 0.03), -KETTLE_FRONT - 0.017, 0.0])
        contact[2] = kettle[2] + TIP + self.rng.uniform(0.04, 0.06)  # fingertips 4-6 cm above the stove
        self.set_grip(1.0, 1)
        self.move(contact + np.array([0.0, -0.04, 0.12]) + self.jitter(0.02), R, tol=0.03, rtol=0.1, max_steps=40)
        self.maybe_pause()
        self.move(contact - 0.03 * forward, R, tol=0.012, rtol=0.06, max_steps=20)
        goal_y = 0.55 + 0.15 * self.style.margin  # goal 0.75; completed from about y 0.47 with the kettle upright
        push = contact + (goal_y - kettle[1]) * forward
        self.move(push, R, speed=self.style.work_speed, tol=0.01, max_steps=45,
                  until=lambda: self.data.qpos[24] >= goal_y)
        self.set_grip(1.0, 1)
        p, R = self.pose()
        self.move(p + np.array([0.0, -0.05, 0.12]), R, max_steps=15, tol=0.03)

    # ---- chaining ---------------------------------------------------------------------------------------------------
    def transit(self) -> None:
        """Between sub-tasks, sometimes pass through a random via point in the free space in front of the kitchen."""
        if self.rng.random() < self.style.via_prob:
            via = np.array([self.rng.uniform(-0.45, -0.15), self.rng.uniform(0.15, 0.35), self.rng.uniform(2.0, 2.3)])
            self.move(via, FORWARD, tol=0.05, rtol=0.3, max_steps=25)

    def run(self, tasks) -> bool:
        """Do the sub-tasks in order; True if the environment reports success."""
        try:
            for name in tasks:
                self.attempted.append(name)
                self.transit()
                SKILLS[name](self)
                if name not in self.env.tracker.completed:
                    return False  # the skill failed (a violation would have ended the episode)
        except _EpisodeOver:
            pass
        return bool(self.info.get("success"))


SKILLS = {
    "bottom burner": lambda run: run.knob("knob2_site", 11),
    "top burner": lambda run: run.knob("knob4_site", 15),
    "light switch": ScriptedRun.light_switch,
    "slide cabinet": ScriptedRun.slide_cabinet,
    "hinge cabinet": ScriptedRun.hinge_cabinet,
    "microwave": ScriptedRun.microwave,
    "kettle": ScriptedRun.kettle,
}
assert tuple(SKILLS) == SUBTASKS


@dataclass
class DemoResult:
    seed: int
    tasks: tuple[str, ...]
    obs: np.ndarray  # (N+1, 44)
    actions: np.ndarray  # (N, 9)
    key_steps: np.ndarray  # (4,) index of the first state in which each requested sub-task counts
    attempts: int


def replay(env, seed: int, tasks, actions: np.ndarray) -> tuple[np.ndarray, list[dict]]:
    """Step ``actions`` from ``reset(seed, tasks)``; returns the observations and the infos."""
    obs, info = env.reset(seed=seed, options={"tasks": list(tasks)})
    observations, infos = [obs], []
    for action in actions:
        obs, _, terminated, truncated, info = env.step(action)
        observations.append(obs)
        infos.append(info)
        if terminated or truncated:
            break
    return np.array(observations, dtype=np.float32), infos


class Demonstrator:
    """Plans verified demos with its own two environments (one to act in, one to replay in)."""

    def __init__(self, max_attempts: int = 6):
        self.env = FrankaKitchenOrderedEnv()
        self.replay_env = FrankaKitchenOrderedEnv()
        self.max_attempts = max_attempts
        # Per sub-task: [times attempted, times completed], over every attempt (the demonstrator's own success).
        self.stats = {name: [0, 0] for name in SUBTASKS}
        self.attempts = 0

    def demo(self, seed: int, tasks, max_attempts: Optional[int] = None) -> Optional[DemoResult]:
        """A verified demo of ``tasks`` from the scene of ``seed``, or None after ``max_attempts`` styles."""
        tasks = validate_tasks(tasks)
        for attempt in range(max_attempts or self.max_attempts):
            self.attempts += 1
            obs, _ = self.env.reset(seed=seed, options={"tasks": list(tasks)})
            rng = np.random.default_rng([seed, attempt])
            run = ScriptedRun(self.env, obs, rng, sample_style(rng))
            ok = run.run(tasks)
            for name in run.attempted:
                self.stats[name][0] += 1
                self.stats[name][1] += name in self.env.tracker.completed
            if not ok:
                continue
            actions = np.array(run.actions, dtype=np.float32)
            observations, infos = replay(self.replay_env, seed, tasks, actions)
            # Kept only if the replay succeeds at the same (last) step and sees the same states.
            if (len(infos) == len(actions) and infos[-1]["success"]
                    and np.allclose(observations, np.array(run.obs, dtype=np.float32), atol=1e-4)):
                key_steps = np.array([run.key_steps[name] for name in tasks], dtype=np.int64)
                return DemoResult(seed, tasks, observations, actions, key_steps, attempt + 1)
        return None


COMBO_ATTEMPTS = 3


def draw_combination(rng: np.random.Generator) -> tuple[str, ...]:
    """A random ordered request of 4 distinct sub-tasks."""
    return tuple(SUBTASKS[i] for i in rng.permutation(len(SUBTASKS))[:NUM_REQUESTED])


def generate(split: str, num: int, combos: list[tuple[str, ...]], offset: int = 0, seed_tries: int = 4,
             demonstrator: Optional[Demonstrator] = None, num_combinations: int = 0,
             combo_rng: Optional[np.random.Generator] = None) -> tuple[TrajectorySet, dict]:
    """``num`` verified demos of ``split``. Demo k tries scene ``lo + offset + k + j * num`` with combination
    ``combos[(k + j) % len(combos)]`` for j = 0, 1, ... until the demonstrator solves one (all seeds inside the
    split's range; usually j = 0).

    With ``combo_rng`` (the training split), ``combos`` is filled first, up to ``num_combinations``: demo k < that
    number draws new distinct ordered requests until one is solved on its scene (so the combinations are the first
    ones drawn that the demonstrator solves within ``COMBO_ATTEMPTS`` styles; docs/kitchen.md)."""
    demonstrator = demonstrator or Demonstrator()
    lo, hi = SEEDS.range(split)
    if lo + offset + num * seed_tries > hi:
        raise ValueError(f"{num} demos x {seed_tries} seeds at offset {offset} do not fit the {split} seed range")
    start = time.perf_counter()
    attempts0 = demonstrator.attempts
    stats0 = {k: list(v) for k, v in demonstrator.stats.items()}
    episodes, skipped, rejected = [], [], []
    for k in range(num):
        result = None
        if combo_rng is not None and len(combos) < num_combinations:
            for _ in range(50):
                tasks = draw_combination(combo_rng)
                if tasks in combos or tasks in rejected:
                    continue
                # Accept a combination only if it is solved within a few styles (a fair chance on other scenes).
                result = demonstrator.demo(lo + offset + k, tasks, max_attempts=COMBO_ATTEMPTS)
                if result is not None:
                    combos.append(tasks)
                    break
                rejected.append(tasks)
        for j in range(seed_tries if result is None else 0):
            # The slot's combination first; if its scene defeats the demonstrator, the next scene with the next
            # (still seen) combination.
            seed, tasks = lo + offset + k + j * num, combos[(k + j) % len(combos)]
            check_seed(seed, split)
            result = demonstrator.demo(seed, tasks)
            if result is not None:
                break
            skipped.append([seed, list(tasks)])
        if result is None:
            raise RuntimeError(f"kitchen demonstrator: demo {k} of {split} failed on {seed_tries} scenes")
        success = np.zeros(len(result.actions), dtype=bool)
        success[-1] = True
        episodes.append(Episode(
            obs=result.obs, actions=result.actions, success=success, episode_id=k,
            reset_kwargs={"seed": int(result.seed), "options": {"tasks": list(result.tasks)}},
            control_mode="joint_velocity",
            extras={"key_steps": result.key_steps},
            extra_attrs={"key_steps": {"description": "index of the first state in which each requested sub-task "
                                                      "counts, in the requested order (privileged; for scoring "
                                                      "subskill discovery only)"}},
        ))
    lengths = np.array([ep.num_steps for ep in episodes])
    per_task = {name: {"attempted": demonstrator.stats[name][0] - stats0[name][0],
                       "completed": demonstrator.stats[name][1] - stats0[name][1]} for name in SUBTASKS}
    for v in per_task.values():
        v["success_rate"] = round(v["completed"] / v["attempted"], 3) if v["attempted"] else None
    attempts = demonstrator.attempts - attempts0
    report = {
        "split": split,
        "demos": len(episodes),
        "combinations": len({tuple(ep.reset_kwargs["options"]["tasks"]) for ep in episodes}),
        "length": {"mean": round(float(lengths.mean()), 1), "min": int(lengths.min()), "max": int(lengths.max())},
        "attempts": attempts,
        "demo_success_rate": round(len(episodes) / attempts, 3),
        "skipped": skipped,  # [seed, combination] pairs the demonstrator failed on
        "rejected_combinations": [list(t) for t in rejected],
        "subtask_success": per_task,
        "seconds": round(time.perf_counter() - start, 1),
    }
    env_info = {"env_id": ENV_ID, "env_kwargs": {}, "max_episode_steps": HORIZON}
    meta = {
        "source_type": "scripted",
        "source_desc": "cotpc Franka Kitchen demonstrator: resolved-rate IK skills chained in the requested order, "
                       "with deliberate diversity; every demo replayed and verified",
        "split": split,
        "goal_in": "episodes[i].reset_kwargs.options.tasks (the requested sub-tasks, in order)",
        "report": report,
    }
    return TrajectorySet(episodes=episodes, env_info=env_info, meta=meta), report


def print_report(report: dict) -> None:
    length = report["length"]
    print(f"{report['split']}: {report['demos']} demos, {report['combinations']} ordered combinations, length mean "
          f"{length['mean']} (min {length['min']}, max {length['max']}); {report['attempts']} attempts "
          f"({100 * report['demo_success_rate']:.0f}% kept), {report['seconds']} s")
    rates = ", ".join(f"{name} {v['completed']}/{v['attempted']}" for name, v in report["subtask_success"].items()
                      if v["attempted"])
    print(f"  demonstrator success per sub-task (all attempts): {rates}")


def write_splits(out: Path, train: int = 50, test: int = 90, val: int = 0, seed: int = 0,
                 num_combinations: int = 20) -> dict[str, Path]:
    """Demos of each split, written as ``out/<split>.{h5,json}``: ``num_combinations`` ordered requests drawn with
    ``seed`` by the training split (:func:`generate`), shared by every split (validation and test configs use
    combinations seen in training, with initial scenes from their own seed ranges). Prints and stores (in each JSON, ``report``) demo lengths and the
    demonstrator's success rate per sub-task. Returns the paths of the .h5 files."""
    start = time.perf_counter()
    combos: list[tuple[str, ...]] = []  # filled by the training split
    demonstrator = Demonstrator()
    paths = {}
    for split, num in (("train", train), ("val", val), ("test", test)):
        if num <= 0:
            continue
        if split != "train" and not combos:
            raise ValueError("validation and test demos use the training demos' combinations: need train > 0")
        trajectories, report = generate(split, num, combos, offset=seed, demonstrator=demonstrator,
                                        num_combinations=num_combinations,
                                        combo_rng=np.random.default_rng(seed) if split == "train" else None)
        h5_path, _ = save_trajectories(Path(out) / split, trajectories)
        print_report(report)
        print(f"  -> {h5_path}")
        paths[split] = h5_path
    print(f"generated in {time.perf_counter() - start:.1f} s")
    return paths


@dataclass
class KitchenDemos:
    """Franka Kitchen (the paper's ordered variant, needs `pip install -e '.[kitchen]'`) demos from a scripted
    demonstrator (resolved-rate IK skills, deliberately diverse; every demo replayed and verified); writes
    OUT/train.{h5,json}, OUT/val.{h5,json} and OUT/test.{h5,json}, each from its own disjoint seed range."""

    out: Path
    """Output directory."""
    train: int = 50
    """Number of training demos (the paper's 50; their scenes are the 'seen' configs)."""
    test: int = 90
    """Number of test demos (the paper's 90 unseen configs): requested combinations seen in training, initial
    scenes from the disjoint test seed range."""
    val: int = 0
    """Number of validation demos (combinations seen in training, scenes from the validation seed range), for
    choosing settings without the test configs. 0 = none."""
    seed: int = 0
    """Draws the ordered combinations and offsets each split's seeds (demo k of a split uses its range's start +
    seed + k, or a later seed of the range if the demonstrator fails there)."""
    combinations: int = 20
    """Number of distinct ordered combinations of 4 sub-tasks shared by the splits (the paper: 20 in 50 demos)."""


def make_demos(cfg: KitchenDemos) -> dict[str, Path]:
    """``cotpc demos kitchen``."""
    check_demo_flags("cotpc demos kitchen", {"--train": cfg.train, "--val": cfg.val, "--test": cfg.test},
                     {"--combinations": cfg.combinations}, {"--seed": cfg.seed})
    return write_splits(cfg.out, train=cfg.train, test=cfg.test, val=cfg.val, seed=cfg.seed,
                        num_combinations=cfg.combinations)
