"""Grey images and figure annotations: any micrograph as float grey in [0, 1], and the scale bars, their text, panel
letters and label boxes burnt into it (``annotation_mask``), which are not particles.

A leaf of drgan.data: drgan.data.polarity and drgan.data.classical both read images through it.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from drgan.core.errors import DataError


def as_grey(image: np.ndarray) -> np.ndarray:
    """float32 (H, W) grey in [0, 1] from a grey or RGB(A) array: 8/16-bit integers by their type's range, floats as
    they are when within [0, 1], else by their own min and max."""
    array = np.asarray(image)
    if array.ndim == 3 and array.shape[-1] in (3, 4):
        weights = np.array([0.299, 0.587, 0.114])  # ITU-R BT.601, as drgan.data.images.read_grey
        array = (
            array[..., :3].astype(np.float64) @ weights if array.dtype.kind == "f" else _unit(array[..., :3]) @ weights
        )
    elif array.ndim == 3 and array.shape[-1] == 1:
        array = array[..., 0]
    if array.ndim != 2:
        raise DataError(f"particle image of shape {np.shape(image)}: expected one grey (H, W) or RGB (H, W, 3) image")
    return _unit(array).astype(np.float32)


def _unit(array: np.ndarray) -> np.ndarray:
    if array.dtype.kind in "ui":
        return array.astype(np.float64) / float(np.iinfo(array.dtype).max if array.dtype.kind == "u" else 1)
    array = array.astype(np.float64)
    low, high = float(np.nanmin(array)), float(np.nanmax(array))
    if low >= 0 and high <= 1:
        return array
    return (array - low) / (high - low) if high > low else np.zeros_like(array)


BAR_LABEL_GAP = 1.5  # a scale bar's label lies at most this many character heights above or below the bar
BAR_LABEL_SPAN = 0.25  # x the bar's length: and over its span widened by this much either side


def _beside(char: tuple[slice, slice], bar: tuple[slice, slice]) -> bool:
    """Whether a character's box lies where a scale bar's label is written: above or below the (horizontal) bar, at
    most BAR_LABEL_GAP character heights from it (the character's own height, or a tenth of the bar's length where
    that is more: anti-aliased text breaks into fragments), over the bar's span widened by BAR_LABEL_SPAN of its
    length either side (a vertical bar: the same turned by 90 degrees)."""
    (cr, cc), (br, bc) = char, bar
    if br.stop - br.start > bc.stop - bc.start:  # a vertical bar: swap rows and columns
        (cr, cc), (br, bc) = (cc, cr), (bc, br)
    length = bc.stop - bc.start
    gap = max(br.start - cr.stop, cr.start - br.stop)
    height = max(cr.stop - cr.start, 0.1 * length)
    margin = BAR_LABEL_SPAN * length
    return gap <= BAR_LABEL_GAP * height and cc.start >= bc.start - margin and cc.stop <= bc.stop + margin


def _bar_shaped(long_: int, narrow: int, short: int) -> bool:
    """A group's box (its long and narrow side, px) is a scale bar's: long, thin, and both against the image's
    shorter side ``short``."""
    return long_ >= 4 * narrow and long_ >= 0.04 * short and narrow <= 0.06 * short


def _char_shaped(long_: int, thick: float, short: int) -> bool:
    """A group is a character's: its box's long side ``long_`` of character size against ``short``, drawn with
    strokes (widest inscribed disc ``thick``) much thinner than it."""
    return 3 <= long_ <= 0.15 * short and thick <= max(2.5, 0.45 * long_)


# Annotations are drawn in (nearly) pure black or white: pixels within this of 0 or 1 are candidates.
ANNOTATION_LEVEL = 0.06
EDGE_BAND = 0.2  # text and panel letters lie within this share of the image size from an edge
CHAR_DENSITY_SHARE = 0.5  # characters near an edge are text unless the inside holds at least half their density
FRAME_SHARE = 0.15  # a label box or data bar is masked with a margin of this share of its narrow side (its frame)


def annotation_mask(grey: np.ndarray) -> np.ndarray:
    """Scale bars, their text, panel letters and label boxes: bool (H, W).

    A candidate is an 8-connected group of pixels within ANNOTATION_LEVEL of pure black or pure white. It is an
    annotation when it is a solid bar (long, thin, filling its box; anywhere), a solid box (a rectangle that fills
    its box and lies within EDGE_BAND of an edge), an info band (across most of the width along the top or bottom,
    holes filled: a microscope's data bar with its text) or a character: small, drawn with strokes much thinner
    than its height, within EDGE_BAND of an edge (but not when groups of that shape and level lie inside the image
    at CHAR_DENSITY_SHARE of the edges' density or more: then they are the image's own, such as the black gaps of a
    dense packing), or right above or below a solid bar of their grey, over its span (`_beside`: a scale bar's
    label is text, however dense the image's own marks of that grey). Boxes and bands are masked whole, with their
    frame (FRAME_SHARE). Particles are blobs (their thickness is their size) and are not drawn in exactly one grey,
    so they stay. A scale bar that resampling softened out of those levels is found within SOFT_LEVEL, with its label
    (`_soft_bars`). The mask is grown by 2 px (anti-aliased edges)."""
    grey = np.asarray(grey, np.float32)
    mask = np.zeros(grey.shape, bool)
    for candidates in (grey <= ANNOTATION_LEVEL, grey >= 1 - ANNOTATION_LEVEL):
        if candidates.mean() > 0.5:  # a saturated background, not a drawing on the image
            continue
        _mark_level(candidates, mask)
    mask |= _soft_bars(grey, mask)
    if mask.any():
        mask = ndi.binary_dilation(mask, iterations=2)
    return mask


def _mark_level(candidates: np.ndarray, mask: np.ndarray) -> None:
    """The annotations drawn in one grey (the candidates: pixels near pure black, or near pure white) marked in
    ``mask``: boxes, bands and bars as `_mark_shapes` finds them, then the characters that count."""
    h, w = candidates.shape
    labels, n = ndi.label(candidates, structure=np.ones((3, 3)))
    if n == 0:
        return
    chars, char_boxes, bars, inner_chars = _mark_shapes(candidates, labels, n, mask)
    for box, own in _crossing_bars(candidates, mask):
        mask[box] |= own
        bars.append(box)
    # Characters count when near an edge (panel letters, scale-bar text); the rest stay particles or grain. Unless
    # the inside holds them about as densely: then this level draws the image itself (a dense packing's black
    # gaps, a bright film's white specks), and its character-shaped groups near an edge are more of the same.
    band = EDGE_BAND * min(h, w)
    inner_area = max(0, h - 2 * band) * max(0, w - 2 * band)
    if (
        inner_chars
        and inner_area
        and inner_chars / inner_area >= CHAR_DENSITY_SHARE * chars.sum() / (h * w - inner_area)
    ):
        chars[:] = False
    # A scale bar's label is text however dense the image's own marks: characters of its grey beside it.
    for index, box in char_boxes.items():
        chars[index] |= any(_beside(box, bar) for bar in bars)
    mask |= chars[labels]


def _mark_shapes(candidates: np.ndarray, labels: np.ndarray, n: int, mask: np.ndarray):
    """Each 8-connected group of one grey classified by its shape: info bands and solid boxes (masked with their
    frame) and solid bars (masked; those off the border kept as scale bars) are marked in ``mask``; returns
    (near-edge character flags per label, character boxes, scale bars, character-shaped groups away from the
    edges)."""
    h, w = candidates.shape
    short = min(h, w)
    band = EDGE_BAND * short
    boxes = ndi.find_objects(labels)
    thickness = ndi.distance_transform_edt(candidates)
    chars = np.zeros(n + 1, bool)
    char_boxes: dict[int, tuple[slice, slice]] = {}
    bars: list[tuple[slice, slice]] = []  # scale bars (not a line along the border)
    inner_chars = 0  # character-shaped groups away from every edge: the image's own (gaps, grain), not text
    for index, box in enumerate(boxes, start=1):
        rows, cols = box
        bh, bw = rows.stop - rows.start, cols.stop - cols.start
        own = labels[box] == index
        area = int(own.sum())
        if area < 3:
            continue
        fill = area / (bh * bw)
        thick = 2.0 * float(thickness[box][own].max())  # stroke width: the widest inscribed disc
        edge = min(rows.start, cols.start, h - rows.stop, w - cols.stop)  # px to the nearest border
        near_edge = edge <= band
        long_, narrow = max(bh, bw), min(bh, bw)
        bar = _bar_shaped(long_, narrow, short) and fill >= 0.75
        filled = ndi.binary_fill_holes(own).mean()
        box_ = near_edge and filled >= 0.92 and narrow >= 0.03 * short and long_ <= 0.5 * short
        char = _char_shaped(long_, thick, short)
        # an info band: a microscope's data bar kept in a figure (JPEG grey, so not found by read_grey's exact
        # black/white rows): across most of the width, along the top or bottom, its text inside
        band_ = bw >= 0.6 * w and bh <= 0.3 * h and (rows.start <= band or h - rows.stop <= band) and filled >= 0.8
        if band_ or box_:
            # a solid box with its frame: figures draw label boxes and data bars with a grey or anti-aliased
            # border (JPEG rings besides), a bright or dark ring around the box that is not a particle
            m = int(min(max(2.0, FRAME_SHARE * narrow), 0.03 * short))
            mask[max(rows.start - m, 0) : rows.stop + m, max(cols.start - m, 0) : cols.stop + m] = True
        elif bar:
            mask[box] |= own
            if edge > 0:  # not a line along the border
                bars.append(box)
        elif char:
            chars[index] = near_edge
            char_boxes[index] = box
            inner_chars += not near_edge
    return chars, char_boxes, bars, inner_chars


def _drawn_bar(own: np.ndarray, short: int, fill: float) -> bool:
    """A group (its pixels in its box) is drawn as a scale bar is: long and thin (`_bar_shaped`), filling ``fill`` of
    its box, of one width (+-1 px) over SOFT_EVEN of its length: solid and straight, as no particle is."""
    bh, bw = own.shape
    if not _bar_shaped(max(bh, bw), min(bh, bw), short) or own.mean() < fill:
        return False
    widths = own.sum(axis=0 if bw >= bh else 1)
    return bool(np.mean(np.abs(widths - np.median(widths)) <= 1) >= SOFT_EVEN)


# A bar drawn across particles is taken only when at least this wide (px) and this long (x the image's shorter side):
# the bright contact lines and black gaps between packed particles are straight for 20-30 px, but 1-2 px wide.
CROSSING_WIDTH = 3
CROSSING_LENGTH = 0.15


def _crossing_bars(candidates: np.ndarray, found: np.ndarray) -> list[tuple[tuple[slice, slice], np.ndarray]]:
    """Scale bars drawn across particles of their own grey (EMPS 226dc58f03: a white bar over bright spheres):
    joined to the particles' saturated highlights, their group is no bar. Opened with a line of a bar's least length
    (`_bar_shaped`) along one axis and then the other, the highlights fall away and the bar remains; it is taken when
    drawn as a bar (`_drawn_bar`) at least CROSSING_WIDTH px wide and CROSSING_LENGTH long, within EDGE_BAND of an
    edge (where figures put scale bars; a particle's own saturated core may be as straight) but not along the border,
    and not found already. Returns (box, pixels in the box) per bar."""
    h, w = candidates.shape
    short = min(h, w)
    length = max(3, int(np.ceil(0.04 * short)))
    bars = []
    for line in (np.ones((1, length), bool), np.ones((length, 1), bool)):  # horizontal bars, then vertical ones
        labels, _ = ndi.label(ndi.binary_opening(candidates, line), structure=np.ones((3, 3)))
        for index, box in enumerate(ndi.find_objects(labels), start=1):
            rows, cols = box
            own = labels[box] == index
            edge = min(rows.start, cols.start, h - rows.stop, w - cols.stop)
            drawn = min(own.shape) >= CROSSING_WIDTH and max(own.shape) >= CROSSING_LENGTH * short
            if (
                drawn
                and 0 < edge <= EDGE_BAND * short
                and found[box][own].mean() < 0.5
                and _drawn_bar(own, short, SOFT_FILL)
            ):
                bars.append((box, own))
    return bars


# A figure averaged down, resampled or saved as JPEG no longer draws its scale bar in pure white or black (a white
# bar and its label may peak at 0.92): such a bar is taken within SOFT_LEVEL of either end, where it is drawn as a
# bar is and no particle is: solid and straight.
SOFT_LEVEL = 0.15
SOFT_FILL = 0.9  # of its box
SOFT_EVEN = 0.9  # share of the bar's length over which its width is its median width, +-1 px


def _soft_bars(grey: np.ndarray, found: np.ndarray) -> np.ndarray:
    """Scale bars within SOFT_LEVEL of black or white that `annotation_mask`'s pure levels missed, and the
    characters of their grey beside them (`_beside`). A bar here must look drawn: long and thin as a bar
    (`annotation_mask`), filling SOFT_FILL of its box, of one width (+-1 px) over SOFT_EVEN of its length, within
    EDGE_BAND of an edge and not along the border: at this level an elongated particle may be bright or dark enough,
    but it is not a solid strip of constant width aligned with the image."""
    h, w = grey.shape
    short = min(h, w)
    out = np.zeros((h, w), bool)
    for candidates in (grey <= SOFT_LEVEL, grey >= 1 - SOFT_LEVEL):
        if candidates.mean() > 0.5:
            continue
        labels, n = ndi.label(candidates, structure=np.ones((3, 3)))
        boxes = ndi.find_objects(labels)
        bars = []
        for index, box in enumerate(boxes, start=1):
            rows, cols = box
            bh, bw = rows.stop - rows.start, cols.stop - cols.start
            long_, narrow = max(bh, bw), min(bh, bw)
            edge = min(rows.start, cols.start, h - rows.stop, w - cols.stop)
            if not (_bar_shaped(long_, narrow, short) and 0 < edge <= EDGE_BAND * short):
                continue
            own = labels[box] == index
            if found[box][own].mean() < 0.5 and _drawn_bar(own, short, SOFT_FILL):
                out[box] |= own
                bars.append(box)
        if not bars:
            continue
        thickness = ndi.distance_transform_edt(candidates)
        for index, box in enumerate(boxes, start=1):
            rows, cols = box
            long_ = max(rows.stop - rows.start, cols.stop - cols.start)
            own = labels[box] == index
            if own.sum() < 3:
                continue
            thick = 2.0 * float(thickness[box][own].max())
            if _char_shaped(long_, thick, short) and any(_beside(box, bar) for bar in bars):
                out[box] |= own
    return out
