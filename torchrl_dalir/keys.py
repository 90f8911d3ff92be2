"""TensorDict key names, chosen once and used everywhere.

Observation keys are what the environments emit; the dataset keys label each stored step.
"""

POINT_CLOUD = "point_cloud"  #: [..., N, 3] float32, world frame, cropped and farthest-point sampled
AGENT_POS = "agent_pos"  #: [..., D] float32, robot proprioception only
PRIVILEGED_STATE = "privileged_state"  #: [..., S] float32, simulator state for experts; never a model input
ACTION = "action"  #: [..., A] the action executed at this step
ACTION_CHUNK = "action_chunk"  #: [..., H, A] a predicted chunk
REWARD = "reward"  #: [..., 1] the environment's dense reward (kept for the dense-reward oracle ablation)
SUCCESS = "success"  #: [..., 1] bool, the simulator's task-completion flag
DONE = "done"
TERMINATED = "terminated"
TRUNCATED = "truncated"
IS_INIT = "is_init"  #: written by TorchRL's InitTracker at episode starts
STEP_COUNT = "step_count"  #: written by TorchRL's StepCounter: steps since the episode's start
EPISODE_SEED = "episode_seed"  #: [..., 1] int64, the reset seed of the episode (make_env(..., seed_stride=k) only)
#: [..., H, W, 3] uint8, an RGB render from the task's camera (make_env(..., pixels=size), for videos)
PIXELS = "pixels"

# Dataset (one row per observation of a stored trajectory).
COMPLETION_TARGET = "completion_target"  #: [...] float32, y_t = gamma^(T - t) * y_T
DENSE_REWARD_TARGET = "dense_reward_target"  #: [...] float32 in [0, 1], the oracle ablation's target
TERMINAL_LABEL = "terminal_label"  #: [...] float32, y_T: 1 success, 0 time-out
TRAJECTORY_ID = "trajectory_id"  #: [...] int64, index of the trajectory in its dataset
STEP = "step"  #: [...] int64, t, the index of the observation in its trajectory (0..T)
IS_FINAL = "is_final"  #: [...] bool, the row holds s_T, the observation after the last action
QUALITY = "quality"  #: [...] int64, index into QUALITY_TAGS
SOURCE = "source"  #: [...] int64, index into the dataset's list of sources
NOISE_SCALE = "noise_scale"  #: [...] float32, drift-noise scale of the policy that acted

QUALITY_TAGS = ("expert", "imperfect_success", "failed")  #: what the ``quality`` column indexes

# Training windows.
OBS_MASK = "obs_is_pad"  #: [..., To] bool, observation-history steps padded before the episode start
ACTION_MASK = "action_is_pad"  #: [..., H] bool, chunk steps padded past the episode's last action
FUTURE = "future"  #: sub-tensordict: the observation k steps ahead (the world model's target)
LATENT = "latent"  #: [..., L] s_t of a frozen latent encoder, precomputed once
FUTURE_MASK = "future_is_pad"  #: [...] bool, the episode ended before t + k: the final observation stands in
IMAGINED_LATENT = "imagined_latent"  #: [..., L] s_hat_{t+k} = s_t + W(s_t, a_{t:t+k}) of a recorded chunk

# Latent imagination (the TensorDict modules of torchrl_dalir.modules.world_model).
#: [...] the scorer's logit of eventual task completion (sigmoid: its probability)
COMPLETION_LOGIT = "completion_logit"
MEMBER_LOGITS = "member_logits"  #: [..., E] the completion logit of each scorer-ensemble member
