"""From a sampled `Scene` to the three layered planes, the all-in-focus image, the disparity map
and the coverages (no blur: the renderer blurs the planes; highlights are left to it too).

All pixels are linear light float32. Resampling: cv2 INTER_AREA when shrinking (both sides not
larger than the source), INTER_LINEAR otherwise. Foregrounds are resampled premultiplied
(colour x alpha together with alpha) and turned back to straight colour, so no dark or bright
fringes come from the transparent surround; an object placed at half its size or less is
resampled from the level of its area-halved pyramid (`dofsynth.image.pyramid_level`) that is
still at least the placed size, which the library caches (`AssetLibrary.premultiplied`).

With `background.margin` m > 0 (every sample since schema 5) the planes are composed on a canvas
m px larger on every side (`SceneLayers.canvas`: the photo around the crop, the ramp continued,
objects with their true extent and cut ones repeated past their cut line), which the targets are
rendered from; the frame's planes, all-in-focus image, depth and coverages are its frame part.

`SceneLayers.disparity` is, at each pixel, the disparity of the front-most plane whose alpha is
>= 0.5 there (the background's map where neither foreground reaches 0.5): the depth a
depth sensor or a matting-free annotation would report.
"""
from __future__ import annotations

import math
import mmap
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from dofsynth import jit
from dofsynth.assets import Asset, AssetLibrary
from dofsynth.assets.placement import ObjectParams, placed_size
from dofsynth.image import pyramid_level, resize
from dofsynth.render.frame import grab
from dofsynth.render.planes import Plane, alpha_box, background_disparity
from dofsynth.scene import Scene

COVER_THRESHOLD = 0.5


@dataclass
class SceneLayers:
    planes: list[Plane]        # back to front: background (opaque, disparity map), middle, front
    disparity: np.ndarray      # (H, W) float32: front-most plane with alpha >= 0.5
    boxes: list = field(default_factory=list)  # per cutout: (row slice, column slice) of alpha > 0, or None
    canvas: list[Plane] | None = None  # the planes extended `margin` px past every frame edge, for the
    margin: int = 0                    # blur (`planes` are views of their frame part); None: `planes`

    @property
    def blur_planes(self) -> list[Plane]:
        """What the renderer takes: the canvas planes, or the frame's when there is no margin."""
        return self.planes if self.canvas is None else self.canvas

    @property
    def aif(self) -> np.ndarray:
        """(H, W, 3) float32 linear: the planes composited "over", no blur (made on access from
        the planes' current colour)."""
        return self.aif_rows(0, self.planes[0].shape[0])

    def aif_rows(self, r0: int, r1: int) -> np.ndarray:
        """Rows r0:r1 of `aif` (same values): lets an encoder work in blocks without the frame."""
        out = np.array(self.planes[0].rgb[r0:r1], dtype=np.float32, copy=True)
        for p, box in zip(self.planes[1:], self.boxes or [_alpha_box(p.alpha) for p in self.planes[1:]]):
            if box is None or box[0].stop <= r0 or box[0].start >= r1:
                continue
            rows = slice(max(box[0].start, r0), min(box[0].stop, r1))
            a = np.ascontiguousarray(p.alpha[rows, box[1]])
            keep = np.subtract(np.float32(1.0), a)
            # region * keep + rgb * a, each product and the sum rounded once as numpy would, by
            # OpenCV on whole pixels (numpy's loops over one channel of 3-value pixels are slow)
            region = out[rows.start - r0:rows.stop - r0, box[1]]
            rgb = np.ascontiguousarray(p.rgb[rows, box[1]])
            region[...] = cv2.add(cv2.multiply(region, cv2.merge([keep, keep, keep])),
                                  cv2.multiply(rgb, cv2.merge([a, a, a])))
        return out

    @property
    def cover(self) -> np.ndarray:
        """(H, W, 2) float32: (front alpha, middle alpha), made on demand (saves memory)."""
        return np.stack([self.planes[2].alpha, self.planes[1].alpha], axis=2).astype(np.float32)


def background_image(rgb: np.ndarray, crop, flip: bool, h: int, w: int, out: np.ndarray | None = None) -> np.ndarray:
    """The background photo's (x, y, w, h) `crop` (flipped first with `flip`) resampled to
    (h, w, 3); written into `out` (a view of a larger canvas) when given. `rgb` >= 0 (as
    `AssetLibrary.load_background` gives it) stays so: area and linear resampling weigh
    with weights >= 0."""
    x, y, cw, ch = (int(v) for v in crop)
    part = rgb[y:y + ch, x:x + cw]
    if flip:
        part = part[:, ::-1]
    return resize(part, w, h, out=out)


def beyond_frame(rgb: np.ndarray, crop, flip: bool, h: int, w: int, m: int, out: np.ndarray | None = None) -> np.ndarray:
    """The background photo around its crop on a canvas of (h + 2m, w + 2m): the photo's own
    pixels `m` output px past each frame edge, at the crop's scale, where it has them, its edge
    replicated where it does not (>= 0 as `background_image`'s). With `out` (that canvas),
    only its part outside the frame [m:m + h, m:m + w] is written: the frame is
    `background_image`'s, which the caller puts there (this one's resampling grid may be up to
    half a px off there); without, a new canvas, frame included."""
    x, y, cw, ch = (int(v) for v in crop)
    ph, pw = rgb.shape[:2]
    sx, sy = cw / w, ch / h
    x0, x1 = max(0, math.floor(x - m * sx)), min(pw, math.ceil(x + cw + m * sx))
    y0, y1 = max(0, math.floor(y - m * sy)), min(ph, math.ceil(y + ch + m * sy))
    window = rgb[y0:y1, x0:x1]
    part_w, part_h = max(1, round((x1 - x0) / sx)), max(1, round((y1 - y0) / sy))
    if flip:  # as `background_image`: flipped before resampling (in the flipped photo's columns)
        window, x0, x = window[:, ::-1], pw - x1, pw - x - cw
    part = resize(window, part_w, part_h)
    oy, ox = m + round((y0 - y) / sy), m + round((x0 - x) / sx)  # where the window lands on the canvas
    H, W = h + 2 * m, w + 2 * m
    # canvas pixel (i, j) is part's (i - oy, j - ox): the window where it lands, its edge beyond
    if out is None:
        return np.array(grab(part, -oy, H - oy, -ox, W - ox, True), copy=True)
    for ys, xs in ((slice(0, m), slice(0, W)), (slice(m + h, H), slice(0, W)),  # above, below, left, right
                   (slice(m, m + h), slice(0, m)), (slice(m, m + h), slice(m + w, W))):
        grab(part, ys.start - oy, ys.stop - oy, xs.start - ox, xs.stop - ox, True, out[ys, xs])
    return out


def extend_cut_sides(rgb: np.ndarray, alpha: np.ndarray, x0: int, y0: int, size: tuple[int, int], sides) -> None:
    """In place: an object placed with its extent at (x0, y0), `size` (w, h), on a canvas,
    continued past each cut side in `sides` (ObjectParams.anchored) to the canvas edge by
    repeating its last row or column there: it is cut by its photo, not by the scene, and goes
    on beyond the frame (as the renderer replicates a cutout that reaches the canvas's edge)."""
    H, W = alpha.shape
    x1, y1 = x0 + size[0], y0 + size[1]
    cols = slice(max(x0, 0), min(x1, W))
    r0, r1 = max(y0, 0), min(y1, H)
    if "bottom" in sides and 0 < y1 < H:
        rgb[y1:, cols], alpha[y1:, cols] = rgb[y1 - 1, cols], alpha[y1 - 1, cols]
        r1 = H
    if "top" in sides and 0 < y0 < H:
        rgb[:y0, cols], alpha[:y0, cols] = rgb[y0, cols], alpha[y0, cols]
        r0 = 0
    if "right" in sides and 0 < x1 < W:
        rgb[r0:r1, x1:], alpha[r0:r1, x1:] = rgb[r0:r1, x1 - 1:x1], alpha[r0:r1, x1 - 1:x1]
    if "left" in sides and 0 < x0 < W:
        rgb[r0:r1, :x0], alpha[r0:r1, :x0] = rgb[r0:r1, x0:x0 + 1], alpha[r0:r1, x0:x0 + 1]


def ramp_beyond(bgp, h: int, w: int, m: int) -> np.ndarray:
    """A ramp's disparity over the canvas (broadcast (h + 2m, w + 2m)): the frame's linear ramp
    (`background_disparity`'s convention: b0 at the left column or the bottom row) continued
    past its edges, clipped to [0, 1]. Its frame part equals the frame's map up to float
    rounding, which is why it is not folded into that function (depth bytes would move)."""
    horizontal = bgp.direction == "horizontal"
    n = w if horizontal else h
    t = (np.arange(n + 2 * m, dtype=np.float64) - m) / max(n - 1, 1)
    if not horizontal:
        t = 1.0 - t  # b1 at the top row, b0 at the bottom one
    line = np.clip(bgp.b0 + (bgp.b1 - bgp.b0) * t, 0.0, 1.0).astype(np.float32)
    return np.broadcast_to(line[None, :] if horizontal else line[:, None], (h + 2 * m, w + 2 * m))


def lazy_zeros(shape) -> np.ndarray:
    """A writable float32 array of zeros in its own anonymous memory map: the kernel maps its
    pages on first touch, so a frame-sized cutout costs time and memory only inside the box
    that is written (np.zeros does the same only while malloc maps such blocks itself; a
    worker keeps frame-sized blocks on its heap, where calloc clears them in full)."""
    count = int(np.prod(shape))
    if not hasattr(mmap, "MAP_PRIVATE"):  # Windows
        return np.zeros(shape, np.float32)
    # private (a shared anonymous map is shmem: no huge pages); unmapped with its last array
    buf = mmap.mmap(-1, max(count, 1) * 4, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    if hasattr(mmap, "MADV_HUGEPAGE"):  # as numpy does for its own large arrays: 2 MiB pages
        buf.madvise(mmap.MADV_HUGEPAGE)
    return np.frombuffer(buf, np.float32, count=count).reshape(shape)


def place_premultiplied(premul: np.ndarray, size: tuple[int, int], params: ObjectParams,
                        h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """An object's premultiplied extent (any pyramid level; >= 0, as `AssetLibrary.premultiplied`
    gives it, which resampling keeps) flipped, resized to `size` (w, h) and put at (params.x,
    params.y) of an (h, w) frame: straight colour (H, W, 3) and alpha (H, W)."""
    if params.flip:
        premul = premul[:, ::-1]
    pw, ph = size
    small = resize(premul, pw, ph)
    out_rgb = lazy_zeros((h, w, 3))
    out_a = lazy_zeros((h, w))
    x0, y0 = max(params.x, 0), max(params.y, 0)
    x1, y1 = min(params.x + pw, w), min(params.y + ph, h)
    if x1 <= x0 or y1 <= y0:
        return out_rgb, out_a
    part = small[y0 - params.y:y1 - params.y, x0 - params.x:x1 - params.x]
    box, box_a = out_rgb[y0:y1, x0:x1], out_a[y0:y1, x0:x1]
    compiled = _UNPREMULTIPLY.get()
    if compiled is not None:
        compiled(part, box, box_a)
        return out_rgb, out_a
    pa = np.minimum(part[..., 3], 1.0, out=box_a)
    col = part[..., :3]
    # straight colour = premultiplied / alpha where alpha > 1e-6, else 0
    inv = np.zeros_like(pa)
    np.divide(np.float32(1.0), pa, out=inv, where=pa > 1e-6)
    for ch in range(3):  # a channel at a time: numpy's loop over 3-value pixels is slow (2.5x)
        np.multiply(col[..., ch], inv, out=box[..., ch])
    return out_rgb, out_a


def _unpremultiply_kernel(part, rgb, alpha):
    """`place_premultiplied`'s last step pixel by pixel (compiled: dofsynth.jit): alpha =
    min(A, 1), colour = premultiplied * (1 / alpha) where alpha > 1e-6, else 0, in float32."""
    lo, one = np.float32(1e-6), np.float32(1.0)
    for r in range(part.shape[0]):
        for c in range(part.shape[1]):
            a = part[r, c, 3]
            a = one if a > one else a  # (NaN stays NaN, as np.minimum keeps it)
            alpha[r, c] = a
            inv = one / a if a > lo else np.float32(0.0)
            for ch in range(3):
                rgb[r, c, ch] = part[r, c, ch] * inv


_UNPREMULTIPLY = jit.Kernel(_unpremultiply_kernel, "void(float32[:, :, :], float32[:, :, :], float32[:, :])")


def _asset(library: AssetLibrary, scene: Scene, role: str) -> Asset:
    asset = library[scene.assets[role].id]
    if asset.sha256 != scene.assets[role].sha256:
        raise ValueError(f"{scene.key}: {role} asset {asset.id} has sha256 {asset.sha256[:12]}..., the scene "
                         f"recorded {scene.assets[role].sha256[:12]}... (the asset changed)")
    return asset


def _alpha_box(alpha: np.ndarray, within=None) -> tuple[slice, slice] | None:
    """Row and column slices of `planes.alpha_box`, or None when alpha is all 0; searched only
    `within` (y0, y1, x0, x1) when given (alpha is 0 outside it)."""
    box = _box(alpha, within)
    return None if box == (0, 0, 0, 0) else (slice(box[0], box[1]), slice(box[2], box[3]))


def _written(x: int, y: int, size: tuple[int, int], sides, h: int, w: int) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1): the part of an (h, w) frame that `place_premultiplied` writes for an
    extent of `size` (w, h) placed at (x, y), grown to the frame's edge on each cut side that
    `extend_cut_sides` continues (alpha is 0 outside it)."""
    y0, y1, x0, x1 = max(y, 0), min(y + size[1], h), max(x, 0), min(x + size[0], w)
    if y1 <= y0 or x1 <= x0:
        return 0, 0, 0, 0
    return (0 if "top" in sides else y0, h if "bottom" in sides else y1,
            0 if "left" in sides else x0, w if "right" in sides else x1)


def scene_layers(scene: Scene, library: AssetLibrary) -> SceneLayers:
    """The planes of `scene` (back to front), its all-in-focus image, disparity and coverages.

    The background plane's alpha is a read-only broadcast 1 and its disparity a float (flat) or
    a read-only broadcast of one row or column (ramp): no frame-sized arrays for them. The
    disparity is updated only inside each cutout's alpha box (outside it the cutout has alpha 0
    and changes nothing); the all-in-focus image is composited the same way on access
    (`SceneLayers.aif`, or `SceneLayers.aif_rows` block by block)."""
    h, w = scene.size
    bgp = scene.background
    m = int(bgp.margin)
    photo = library.load_background(_asset(library, scene, "background"))
    canvas = None
    if m:  # the canvas the blur takes: everything `m` px further; the frame's planes are views of it
        H, W = h + 2 * m, w + 2 * m
        big = np.empty((H, W, 3), np.float32)
        bg_rgb = background_image(photo, bgp.crop, bgp.flip, h, w, out=big[m:m + h, m:m + w])
        beyond_frame(photo, bgp.crop, bgp.flip, h, w, m, out=big)
    else:
        bg_rgb = background_image(photo, bgp.crop, bgp.flip, h, w)
    if bgp.mode == "flat":
        bg_plane_disp = float(np.float32(bgp.b0))
    elif bgp.direction == "horizontal":
        bg_plane_disp = np.broadcast_to(background_disparity(bgp.mode, bgp.b0, bgp.b1, bgp.direction, 1, w), (h, w))
    else:
        bg_plane_disp = np.broadcast_to(background_disparity(bgp.mode, bgp.b0, bgp.b1, bgp.direction, h, 1), (h, w))
    disparity = background_disparity(bgp.mode, bgp.b0, bgp.b1, bgp.direction, h, w)
    ones = np.broadcast_to(np.float32(1.0), (h, w))
    if m:
        canvas = [Plane(rgb=big, alpha=np.broadcast_to(np.float32(1.0), (H, W)),
                        disparity=bg_plane_disp if bgp.mode == "flat" else ramp_beyond(bgp, h, w, m))]
    planes = [Plane(rgb=bg_rgb, alpha=ones, disparity=bg_plane_disp)]
    written = []  # per cutout: the part of the frame its alpha can be > 0 in (where boxes are searched)
    for role, params in (("middle", scene.middle), ("front", scene.front)):
        asset = _asset(library, scene, role)
        _, _, ew, eh = asset.extent
        size = placed_size(params.scale, ew, eh)
        premul = library.premultiplied(asset, pyramid_level((ew, eh), size))
        if canvas is None:
            prgb, pa = place_premultiplied(premul, size, params, h, w)
            written.append(_written(params.x, params.y, size, (), h, w))
        else:
            crgb, ca = place_premultiplied(premul, size, replace(params, x=params.x + m, y=params.y + m), H, W)
            extend_cut_sides(crgb, ca, params.x + m, params.y + m, size, params.anchored)
            y0, y1, x0, x1 = _written(params.x + m, params.y + m, size, params.anchored, H, W)
            canvas.append(Plane(rgb=crgb, alpha=ca, disparity=float(params.disparity),
                                box=_box(ca, (y0, y1, x0, x1))))
            prgb, pa = crgb[m:m + h, m:m + w], ca[m:m + h, m:m + w]
            written.append((max(y0 - m, 0), min(y1 - m, h), max(x0 - m, 0), min(x1 - m, w)))
        planes.append(Plane(rgb=prgb, alpha=pa, disparity=float(params.disparity)))

    boxes = []
    for n, p in enumerate(planes[1:], 1):
        box = _alpha_box(p.alpha, written[n - 1])
        boxes.append(box)
        # the renderer, the boost and validation then look only inside the box
        planes[n] = replace(p, box=(0, 0, 0, 0) if box is None else (box[0].start, box[0].stop, box[1].start, box[1].stop))
        if box is not None:
            d = disparity[box]
            d[p.alpha[box] >= COVER_THRESHOLD] = p.disparity
    return SceneLayers(planes=planes, disparity=disparity, boxes=boxes, canvas=canvas, margin=m)


def _box(alpha: np.ndarray, within=None) -> tuple[int, int, int, int]:
    """A cutout's `Plane.box` ((0, 0, 0, 0) when it is clear), searched only `within` (y0, y1,
    x0, x1) when given (alpha is 0 outside it)."""
    y0, y1, x0, x1 = (0, alpha.shape[0], 0, alpha.shape[1]) if within is None else within
    box = alpha_box(alpha[y0:y1, x0:x1]) if y1 > y0 and x1 > x0 else None
    return (0, 0, 0, 0) if box is None else (box[0] + y0, box[1] + y0, box[2] + x0, box[3] + x0)
