"""The relative-navigation filters: the scenario's EKF / IEKF built on ``core.kalman``."""
