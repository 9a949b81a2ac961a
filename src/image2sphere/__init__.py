"""Image2Sphere: probability distributions over 3D rotations from a single image."""

from image2sphere import _torchvision_guard

_torchvision_guard.install()

__version__ = "0.1.0"
