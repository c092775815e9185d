"""Synthetic test videos shared by the tracking and pipeline tests."""

from __future__ import annotations

import cv2
import numpy as np


def paste_two_link_arm(img: np.ndarray, tex: list[np.ndarray], shoulder: np.ndarray, a1: float, a2: float,
                       upper: float = 80.0) -> None:
    """Paste two textured limbs into ``img`` (H, W) in place: the upper one turned by ``a1``
    about ``shoulder``, the forearm by ``a2`` about the elbow ``upper`` pixels along it."""
    H, W = img.shape[:2]
    elbow = shoulder + upper * np.array([np.cos(a1), np.sin(a1)])
    for t, origin, ang in ((tex[0], shoulder, a1), (tex[1], elbow, a2)):
        c, s = np.cos(ang), np.sin(ang)
        M = np.array([[c, -s, origin[0] + 12 * s], [s, c, origin[1] - 12 * c]])
        warped = cv2.warpAffine(t, M, (W, H), flags=cv2.INTER_LINEAR)
        mask = cv2.warpAffine(np.full_like(t, 255), M, (W, H), flags=cv2.INTER_NEAREST) > 0
        img[mask] = warped[mask]


def write_video(path, frames: list[np.ndarray], fourcc: str = "FFV1", fps: float = 25.0) -> str:
    """Write BGR frames (all of one size) with OpenCV; returns the path as a string."""
    H, W = frames[0].shape[:2]
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (W, H))
    assert w.isOpened(), f"OpenCV cannot write {fourcc}"
    for fr in frames:
        w.write(fr)
    w.release()
    return str(path)
