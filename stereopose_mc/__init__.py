"""stereopose_mc: Monte Carlo experiments for stereo-vision-based relative pose, motion
and inertia-ratio estimation of uncooperative space objects."""

__version__ = "0.1.0"
