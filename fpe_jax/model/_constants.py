"""The model's fixed numbers, in one JAX-free module: the JAX model (`_rollout`, `_kalman`,
`_estimate`) and the NumPy runner (`fpe_jax.runner`) both import them, so they cannot drift."""

# ---- the rollouts (`_rollout`) ----
MIN_PROFILE_SPEED_MPS = 0.2  # a profile slower than this is no speed reference (ratio held at 1)
MAX_SPEED_RATIO = 3.0  # the profile may at most triple or cut to 0 the current speed
# Where the fit drives never went the car is taken to hold its current offset from the prior
# profile, decaying to it only slowly, with this time constant [s]: a racing car's line changes
# little within a second, and the prior is a guess from the track's shape.
FALLBACK_TAU_S = 3.0
SLOPE_DS_M = 0.5  # half the arc-length step of the target offset's slope [m]

# ---- the track-frame estimators (`_estimate`, `_kalman`) ----
TRACK_FRAME_ITERS = 3  # local-projection iterations per observation of the history window
# The Kalman filter's prior at the oldest observation: the window's robust (Theil-Sen) lines
# there, with these sigmas (on top of the observation noise for the positions). Started instead
# at the oldest observation with zero rates and a wide prior, the filter trusted the first two
# observations' speed and gated every later one out when either was an outlier.
INIT_POS_SIGMA_M = 0.3
INIT_SPEED_SIGMA_MPS = 2.0
INIT_LAT_RATE_SIGMA_MPS = 0.5
# Slope of the gate weight per sigma of Mahalanobis distance: weight 0.98 one sigma inside the
# gate, 0.5 at it, 6e-6 three sigma beyond.
GATE_SHARPNESS = 4.0
