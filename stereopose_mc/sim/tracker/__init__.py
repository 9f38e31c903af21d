"""A feature tracker on rendered stereo images and its truth audit (docs/images.md)."""
