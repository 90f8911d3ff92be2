"""A privileged scripted expert for Adroit Door (``AdroitHandDoor-v1``).

The expert grasps the handle, turns the latch by rolling the forearm, yanks the door and lets
go while the door swings fast enough to coast past the success angle. It cannot simply follow
the handle: near the success angle the handle is out of the arm's reach and the door's edge
sweeps through where the forearm would have to be. After letting go, the hand moves out of the
handle's way and the forearm slides back, out of the door's sweep.

Every decision is a function of the current state, so the policy keeps no memory and works in
batched collectors that restart episodes at any step. Under drift noise it recovers by the same
rules: a hand that slipped off the handle re-approaches and grasps again, and a door that
stopped short is grasped and yanked again (tested from 0.3 and 0.6 rad open; from 0.9 rad the
handle is too far out to yank it hard enough).

The arm actuators are soft position servos (force ``gain * ctrl - stiffness * q``), so the
expert picks the command that yields the joint torque it wants: the arm is torque controlled,
with a Cartesian impedance on the palm site, feed-forward forces along the latch and hinge arcs,
and gravity and Coriolis compensation computed on a private copy of the MuJoCo model. The wrist
and finger actuators are position servos and get joint targets.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from torchrl_dalir import keys

OBS_DIM = 39  # the gym observation
NQ = NV = 30  # arm (4), wrist (2), fingers (22), door hinge, latch
STATE_DIM = OBS_DIM + NQ + NV  # TaskSpec.privileged_state for Door
ACTION_DIM = 28

_ARM = slice(0, 4)  # ARTz (slide), ARRx, ARRy, ARRz (forearm roll)
_ROLL = 3
_DOOR, _LATCH = 28, 29
_FINGER_FLEXION = [7, 8, 9, 11, 12, 13, 15, 16, 17, 20, 21, 22]  # joints (= actuators) of the FF/MF/RF/LF flexion


@dataclass(frozen=True)
class DoorExpertGains:
    """The expert's constants (SI units: N, m, rad, s).

    Args:
        palm_stiffness, palm_damping: Cartesian impedance of the palm site towards the handle
            while grasping.
        approach_stiffness, approach_damping: the same while approaching, in free motion.
        max_impedance_force: the impedance force is clipped to this norm (fast, bounded approach).
        damping_compensation: fraction of the arm joints' passive damping cancelled.
        pregrasp_offset: the palm approaches from this far in front of the door.
        approach_height: ... and this high above the handle, lowering onto it as it slides in,
            so the open fingers pass over the handle.
        lineup_tolerance, lineup_ramp: the palm slides in fully while it is within
            ``lineup_tolerance`` of the approach line (or of the wanted height), and backs off
            fully ``lineup_ramp`` further out.
        grasp_radius: palm-handle distance under which the fingers close.
        hold_radius: the grasp radius once the fingers are closed (a hysteresis kept by the
            hand's own posture, so the policy needs no memory).
        finger_flexion: flexion target of the grasping fingers.
        roll_stiffness, roll_damping: forearm-roll PD gains.
        roll_lead: while turning the latch, the roll target leads the latch angle by this much.
        latch_force: feed-forward push along the latch arc while turning it.
        latch_open: latch angle at which the bolt clears the frame and pulling starts.
        pull_force: feed-forward pull along the hinge arc, scaled by how closed the fingers are.
        release_margin: let go once the door swings this many times faster than it must to
            coast to ``coast_target``.
        keep_clear_margin: stay clear while a door the hand does not hold swings this many
            times faster than it must.
        coast_target: door angle the release speed is computed for (success is at 1.35).
        door_inertia, door_friction, door_damping: effective hinge inertia (door and latch), dry
            friction and viscous damping of the coasting door; the inertia is fitted to coasting
            runs in the simulator.
        retreat_force: after letting go, the palm is pushed this hard along the door towards
            the hinge and away from the door, out of the handle's way ...
        retreat_slide, retreat_stiffness: ... while the forearm slides back towards this
            ``ARTz`` position, out of the door's sweep.
    """

    palm_stiffness: float = 1000.0
    palm_damping: float = 100.0
    approach_stiffness: float = 2500.0
    approach_damping: float = 200.0
    max_impedance_force: float = 200.0
    damping_compensation: float = 0.5
    pregrasp_offset: float = 0.08
    approach_height: float = 0.03
    lineup_tolerance: float = 0.02
    lineup_ramp: float = 0.02
    grasp_radius: float = 0.04
    hold_radius: float = 0.07
    finger_flexion: float = 1.3
    roll_stiffness: float = 350.0
    roll_damping: float = 10.0
    roll_lead: float = 0.4
    latch_force: float = 150.0
    latch_open: float = 1.3
    pull_force: float = 250.0
    release_margin: float = 1.4
    keep_clear_margin: float = 0.8
    coast_target: float = 1.4
    door_inertia: float = 1.03
    door_friction: float = 2.0
    door_damping: float = 1.0
    retreat_force: float = 150.0
    retreat_slide: float = -0.3
    retreat_stiffness: float = 300.0


def door_model_path() -> str:
    import gymnasium_robotics

    return os.path.join(
        os.path.dirname(gymnasium_robotics.__file__), "envs", "assets", "adroit_hand", "adroit_door.xml"
    )


class DoorScriptedPolicy(nn.Module):
    """Maps Door's ``privileged_state`` ``[..., 99]`` to an action ``[..., 28]`` in ``[-1, 1]``.

    Stateless: the action depends on the current state only (observation 39, ``qpos`` 30,
    ``qvel`` 30), so batched collectors may restart episodes at any step. The batch is flattened
    and looped over in numpy on a private MuJoCo model of the same scene.

    Args:
        gains: the controller's constants; the defaults are the tuned expert.

    Example:
        >>> DoorScriptedPolicy()(torch.zeros(3, 99)).shape  # builds the scene's MuJoCo model (no simulator runs)
        torch.Size([3, 28])
        >>> from torchrl_dalir import make_env
        >>> from torchrl_dalir.experts import make_expert  # the same policy as a TensorDict module
        >>> make_env("door", render=False).rollout(200, make_expert("door"))["next", "success"].any()  # doctest: +SKIP
        tensor(True)
    """

    in_keys = [keys.PRIVILEGED_STATE]

    def __init__(self, gains: DoorExpertGains | None = None):
        super().__init__()
        import mujoco

        self.gains = gains or DoorExpertGains()
        self._mj = mujoco
        self.model = mujoco.MjModel.from_xml_path(door_model_path())
        self.data = mujoco.MjData(self.model)
        m = self.model
        if (m.nq, m.nv, m.nu) != (NQ, NV, ACTION_DIM):
            raise RuntimeError(f"unexpected Door model sizes nq={m.nq}, nv={m.nv}, nu={m.nu}")
        self._grasp_site = m.site("S_grasp").id
        self._handle_site = m.site("S_handle").id
        low, high = m.actuator_ctrlrange[:, 0].copy(), m.actuator_ctrlrange[:, 1].copy()
        self._ctrl_mean, self._ctrl_half_range = 0.5 * (low + high), 0.5 * (high - low)
        # arm actuators: force = gain * ctrl + bias * q (the env keeps the XML's arm gains)
        self._arm_gain = m.actuator_gainprm[_ARM, 0].copy()
        self._arm_bias = m.actuator_biasprm[_ARM, 1].copy()
        self._arm_passive_damping = m.dof_damping[_ARM].copy()
        self._jac_palm = np.zeros((3, NV))
        self._jac_handle = np.zeros((3, NV))
        self._bias = np.zeros(NV)
        self._hand_flexion = np.array(_FINGER_FLEXION) - 4  # the same joints among the 24 hand actuators
        self.last_phase = ""  # the phase of the last single-state call, for debugging and tests
        # the coasting speed as a table over the door angle: a bisection per step costs more
        self._coast_angles = np.linspace(0.0, self.gains.coast_target, 141)
        self._coast_speeds = np.array([self.coast_speed(a) for a in self._coast_angles])

    # -- the controller --------------------------------------------------------------------

    def coast_speed(self, door_angle: float) -> float:
        """Hinge speed (rad/s) at which a released door coasts to ``coast_target``.

        Solves ``I v dv/dtheta = -(f + b v)``: ``I (v/b - f/b^2 ln(1 + b v / f)) = target - angle``.
        """
        g = self.gains
        gap = g.coast_target - door_angle
        if gap <= 0:
            return 0.0
        f, b, inertia = g.door_friction, g.door_damping, g.door_inertia
        lo, hi = 0.0, 50.0
        for _ in range(40):
            v = 0.5 * (lo + hi)
            if inertia * (v / b - f / b**2 * math.log1p(b * v / f)) < gap:
                lo = v
            else:
                hi = v
        return 0.5 * (lo + hi)

    def act(self, state: np.ndarray) -> np.ndarray:
        """The action for one state ``[99]`` (float64 numpy)."""
        mj, m, d, g = self._mj, self.model, self.data, self.gains
        qpos, qvel = state[OBS_DIM : OBS_DIM + NQ], state[OBS_DIM + NQ :]
        d.qpos[:] = qpos
        d.qvel[:] = qvel
        mj.mj_kinematics(m, d)
        mj.mj_comPos(m, d)
        mj.mj_comVel(m, d)
        mj.mj_rne(m, d, 0, self._bias)  # gravity and Coriolis forces
        mj.mj_jacSite(m, d, self._jac_palm, None, self._grasp_site)
        mj.mj_jacSite(m, d, self._jac_handle, None, self._handle_site)

        door, door_speed, latch = qpos[_DOOR], qvel[_DOOR], qpos[_LATCH]
        palm = d.site_xpos[self._grasp_site]
        handle = state[32:35]  # the real handle: the door frame's position is random per episode
        palm_velocity = self._jac_palm @ qvel
        handle_velocity = self._jac_handle @ qvel
        latch_arc = _unit(self._jac_handle[:, _LATCH])
        door_arc = _unit(self._jac_handle[:, _DOOR])
        front = np.array([math.sin(door), -math.cos(door), 0.0])  # the door's outward normal
        along = np.array([math.cos(door), math.sin(door), 0.0])  # along the door, towards the hinge

        error = handle - palm
        # closed fingers widen the grasp radius: a physical hysteresis that needs no memory
        flexion = qpos[_FINGER_FLEXION].mean() / g.finger_flexion
        closed = flexion > 0.5
        grip = min(max((flexion - 0.4) / 0.35, 0.0), 1.0)  # pull only as hard as the fingers hold
        grasped = math.sqrt(error @ error) < (g.hold_radius if closed else g.grasp_radius)
        need = float(np.interp(door, self._coast_angles, self._coast_speeds, right=0.0))
        swinging = door > 0.1 and (
            door_speed > g.release_margin * need or (not grasped and door_speed > g.keep_clear_margin * need)
        )

        hand = np.zeros(ACTION_DIM - 4)  # wrist and finger joint targets
        feed_forward = np.zeros(3)
        roll_target = latch
        if swinging:
            phase = "retreat"
        elif not grasped:
            phase = "approach"
            # come in from in front of and above the handle, so the open fingers pass over it;
            # back off while the palm is off the approach line or too low
            ahead = max(-(error @ front), 0.0)
            above = -error[2]
            sideways = error - (error @ front) * front
            sideways[2] = 0.0
            wanted_above = g.approach_height * min(ahead / g.pregrasp_offset, 1.0)
            miss = max(math.sqrt(sideways @ sideways) - g.lineup_tolerance, 0.0)
            miss += max(wanted_above - above - g.lineup_tolerance, 0.0)
            back_off = g.pregrasp_offset * min(miss / g.lineup_ramp, 1.0)
            target = handle + back_off * front + np.array([0.0, 0.0, wanted_above])
            handle_velocity = np.zeros(3)
        else:
            target = handle
            hand[self._hand_flexion] = g.finger_flexion
            if latch < g.latch_open and door < 0.05:
                phase = "unlatch"
                feed_forward = g.latch_force * latch_arc
                roll_target = latch + g.roll_lead
            else:
                phase = "pull"
                feed_forward = g.pull_force * grip * door_arc

        if phase == "retreat":
            # open the hand, get out of the handle's way and slide the forearm back, out of the
            # swinging door's sweep
            force = g.retreat_force * _unit(along + front)
            torque = self._jac_palm[:, _ARM].T @ force + self._bias[_ARM]
            torque[0] += g.retreat_stiffness * (g.retreat_slide - qpos[0])
        else:
            if phase == "approach":  # free motion: stiffer, to hold the line against disturbances
                stiffness, damping = g.approach_stiffness, g.approach_damping
            else:
                stiffness, damping = g.palm_stiffness, g.palm_damping
            force = stiffness * (target - palm) + damping * (handle_velocity - palm_velocity)
            norm = math.sqrt(force @ force)
            if norm > g.max_impedance_force:
                force *= g.max_impedance_force / norm
            torque = self._jac_palm[:, _ARM].T @ (force + feed_forward) + self._bias[_ARM]
            torque += g.damping_compensation * self._arm_passive_damping * qvel[_ARM]
            torque[_ROLL] += g.roll_stiffness * (roll_target - qpos[_ROLL]) - g.roll_damping * qvel[_ROLL]

        ctrl = np.empty(ACTION_DIM)
        ctrl[_ARM] = (torque - self._arm_bias * qpos[_ARM]) / self._arm_gain
        ctrl[4:] = hand
        self.last_phase = phase
        return np.clip((ctrl - self._ctrl_mean) / self._ctrl_half_range, -1.0, 1.0)

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        if state.shape[-1] != STATE_DIM:
            raise ValueError(
                f"DoorScriptedPolicy expects Door's privileged_state with {STATE_DIM} entries "
                f"(observation {OBS_DIM}, qpos {NQ}, qvel {NV}); got shape {tuple(state.shape)}"
            )
        flat = state.detach().reshape(-1, STATE_DIM).to("cpu", torch.float64).numpy()
        actions = np.empty((len(flat), ACTION_DIM), dtype=np.float32)
        for i, row in enumerate(flat):
            actions[i] = self.act(row)
        return torch.from_numpy(actions).reshape(*state.shape[:-1], ACTION_DIM).to(state.device)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / (math.sqrt(v @ v) + 1e-9)
