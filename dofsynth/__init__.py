"""dofsynth: synthetic shallow depth-of-field training data and the networks that learn from it.

Conventions everywhere: images in files are sRGB-encoded; blurring and compositing happen in
linear light, float32. Depth is normalized disparity in [0, 1] (1 = nearest, 0 = infinity).
The signed circle-of-confusion radius in pixels is `c = max_coc * (disparity - focus)`
(dofsynth.optics.coc_radius).

The package reads as the data flow, each stage importing only earlier ones:
config/files/progress/shipped/rng/color/image/io -> optics -> codecs -> render -> record
(the member table) -> recipe -> assets -> scene -> compose -> sample -> shards -> manifest ->
generate -> qa -> train -> commands/cli (tests/test_layout.py holds the order).
"""
__version__ = "0.1.0"
