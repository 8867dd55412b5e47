"""Generated textured test images shared by the feature, tilt, matching and retrieval tests."""

from __future__ import annotations

import cv2
import numpy as np


def textured_image(rng: np.random.Generator, h: int = 240, w: int = 320) -> np.ndarray:
    """Random filled shapes, lines and text, lightly blurred (uint8, (h, w))."""
    img = np.full((h, w), int(rng.integers(90, 160)), np.uint8)
    for _ in range(int(0.0006 * h * w)):
        kind, col = int(rng.integers(4)), int(rng.integers(0, 256))
        x, y, s = (
            int(rng.integers(0, w)),
            int(rng.integers(0, h)),
            int(rng.integers(4, max(6, min(h, w) // 6))),
        )
        if kind == 0:
            cv2.circle(img, (x, y), s, col, -1, cv2.LINE_AA)
        elif kind == 1:
            cv2.rectangle(img, (x, y), (x + s, y + int(rng.integers(4, 40))), col, -1)
        elif kind == 2:
            end = (int(rng.integers(0, w)), int(rng.integers(0, h)))
            cv2.line(img, (x, y), end, col, int(rng.integers(1, 4)), cv2.LINE_AA)
        else:
            cv2.fillPoly(img, [(rng.random((3, 2)) * s * 2 + [x, y]).astype(np.int32)], col, cv2.LINE_AA)
    for _ in range(int(0.0001 * h * w) + 1):
        text = "".join(rng.choice(list("ABCDEFGHKMNPRSTWXYZ0123456789"), 4))
        org = (int(rng.integers(0, w - 60)), int(rng.integers(20, h)))
        cv2.putText(
            img,
            text,
            org,
            cv2.FONT_HERSHEY_SIMPLEX,
            float(rng.uniform(0.5, 1.2)),
            int(rng.integers(0, 256)),
            2,
            cv2.LINE_AA,
        )
    return cv2.GaussianBlur(img, (0, 0), 0.7)
