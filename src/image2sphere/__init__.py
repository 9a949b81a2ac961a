"""Image2Sphere: probability distributions over 3D rotations from a single image."""

import os

# Large CPU tensors (full-grid logits: 75 MB per batch of 64 at level 4) spend most of their time
# in first-touch page faults. PyTorch's allocator can back allocations of 2 MB and more with
# transparent huge pages; it reads this switch once, at torch's first allocation, so it only takes
# effect when image2sphere is imported before torch. Set THP_MEM_ALLOC_ENABLE=0 to opt out.
os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

from image2sphere import _torchvision_guard  # noqa: E402  (imports torch)

_torchvision_guard.install()

__version__ = "0.1.0"
