"""dofsynth: synthetic shallow depth-of-field training data and the networks that learn from it.

Conventions everywhere: images in files are sRGB-encoded; blurring and compositing happen in
linear light, float32. Depth is normalized disparity in [0, 1] (1 = nearest, 0 = infinity).
The signed circle-of-confusion radius in pixels is `c = max_coc * (disparity - focus)`.
"""
__version__ = "0.1.0"
from dofsynth.aperture import Disk, Polygon  # noqa: E402
from dofsynth.render import render_planes  # noqa: E402
