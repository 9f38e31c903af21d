"""Rendered stereo images of the target (docs/images.md): scene, ray-cast renderer, sensor."""
