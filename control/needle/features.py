"""Needle image features: each camera image reduced to what the needle tracker reads.

The particle filter (:mod:`.needle_tracker`) scores particles on a distance map of thin
features; the sub-pixel refinement (:mod:`.needle_refine`) reads the crest of a smoothed
thin-line response across the wire and its fall at the wire's ends. One pass of
morphology per image gives all three.

Pure math on arrays; pixels and digital numbers (DN).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from oralnav.control.errors import NeedleError


@dataclass(frozen=True)
class NeedleFeatures:
    """One image reduced for the needle tracker.

    ``distance`` (px, float32): distance of every pixel to the nearest thin-feature pixel,
    for the particle filter's score. ``ridge`` (DN, float32): the thin-line response
    clipped, closed and smoothed across the wire, which peaks on the wire's centreline
    whatever its shading, for the sub-pixel refinement (:mod:`.needle_refine`).
    ``ends`` (DN, float32): the same response unclipped and smoothed, whose half-height
    point along the wire sits on a flat end (the clipped ridge's sits a pixel or two
    out). ``level`` (DN): the response threshold used.
    """

    distance: np.ndarray
    ridge: np.ndarray
    ends: np.ndarray
    level: float


def feature_maps(image: np.ndarray, wire_px: float, contrast: float = 12.0,
                 ignore: np.ndarray | None = None) -> NeedleFeatures:
    """Reduce a mono8 ``image`` to the needle tracker's feature maps.

    Thin features are lines narrower than about ``wire_px`` pixels that differ from their
    surroundings by ``contrast`` DN or more (or three times the image's median response,
    when noise is stronger), dark or bright: the morphological black-hat
    (closing minus image: dark lines) and top-hat (image minus opening: bright lines,
    such as a needle's highlights) with a square window of about twice the wire width;
    wider structures, such as the pad's edges, pass both unchanged. ``ignore`` (bool mask)
    removes known features, such as a drawn incision, from both maps.
    """
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim != 2:
        raise NeedleError(f"needle features need a mono8 image, got {img.dtype} "
                          f"with shape {img.shape}")
    if not wire_px > 0:
        raise NeedleError(f"wire width must be > 0 px, got {wire_px}")
    k = max(3, 2 * int(math.ceil(wire_px)) + 1)
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
    # the bright hat's window only just exceeds the wire: a highlight lies within the
    # wire and a wire against a dark backdrop is as wide as the wire, while a strip of
    # tissue between a dark thing and the tissue's edge (the tip just short of the
    # edge) is often wider, and read as wire it runs an end on to the edge
    kb = max(3, 2 * (int(math.ceil(wire_px)) // 2) + 1)
    kernel_b = cv2.getStructuringElement(cv2.MORPH_RECT, (kb, kb))
    # a light blur first: the hats of raw sensor noise span its whole range over a window
    smooth = cv2.GaussianBlur(img, (3, 3), 0)
    dark = cv2.morphologyEx(smooth, cv2.MORPH_BLACKHAT, kernel)
    bright = cv2.morphologyEx(smooth, cv2.MORPH_TOPHAT, kernel_b)
    if ignore is not None:
        # before anything spreads them: blurred, a masked line would bleed into the
        # needle's crest where the two pass close
        mask = np.asarray(ignore, dtype=bool)
        if mask.shape != img.shape:
            raise NeedleError(f"ignore mask is {mask.shape}, the image {img.shape}")
        dark[mask] = 0
        bright[mask] = 0
    response = cv2.max(dark, bright)
    # the threshold rises above the noise: most pixels are background, so the median
    # response is the noise's typical hat height
    level = max(contrast, 3.0 * float(np.median(response[::4, ::4])))
    feature = response >= level
    # the crest: a soft silhouette of the thin features, blurred across the wire so its
    # profile peaks on the centreline. The response is clipped at a few times the
    # threshold so the wire's inside reads uniform whatever its shading (a metallic wire
    # has dark rims and a bright streak, not centred on its axis when it is lit from the
    # side: their raw sum peaks off the axis), and closed so a streak that matches the
    # background does not split the wire in two; anti-aliased edge pixels keep their
    # partial values, which is what places the edges, and so the axis, to sub-pixel
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    closed = cv2.morphologyEx(response, cv2.MORPH_CLOSE, disc)
    # clipping commutes with the closing (both are monotone), so one closing serves both
    soft = cv2.min(closed, np.full_like(closed, min(255, int(round(3.0 * level)))))
    sigma = max(0.8, wire_px / 3.0)
    ridge = cv2.GaussianBlur(soft.astype(np.float32), (0, 0), sigma)
    ends = cv2.GaussianBlur(closed.astype(np.float32), (0, 0), sigma)
    src = np.where(feature, 0, 255).astype(np.uint8)
    return NeedleFeatures(cv2.distanceTransform(src, cv2.DIST_L2, cv2.DIST_MASK_3), ridge,
                          ends, level)


def feature_distance(image: np.ndarray, wire_px: float, contrast: float = 12.0,
                     ignore: np.ndarray | None = None) -> np.ndarray:
    """Distance (px, float32, same shape as ``image``) from every pixel to the nearest
    thin-feature pixel: :attr:`NeedleFeatures.distance` of :func:`feature_maps`."""
    return feature_maps(image, wire_px, contrast, ignore).distance
