"""Mutual nearest neighbour + FGINN ratio matching."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from textured_images import textured_image

from planarloc.features import matching as matching
from planarloc.features.extract import Features, extract_features
from planarloc.features.matching import match_features, match_query_to_refs
from planarloc.geometry.validation import InputError


def make_features(desc: np.ndarray, kp: np.ndarray | None = None) -> Features:
    desc = np.asarray(desc, np.float32)
    desc = desc / np.linalg.norm(desc, axis=1, keepdims=True)
    if kp is None:
        kp = np.arange(len(desc))[:, None] * np.array([[100.0, 0.0]])  # 100 px apart
    return Features(np.asarray(kp, np.float32), desc, np.ones(len(desc), np.float32))


def unit(i: int, dim: int = 128) -> np.ndarray:
    v = np.zeros(dim)
    v[i] = 1.0
    return v


def reference_matches(q: Features, r: Features, ratio, mutual, radius) -> np.ndarray:
    """Brute-force definition of the matcher on the full similarity matrix."""
    S = q.descriptors.astype(np.float64) @ r.descriptors.T.astype(np.float64)
    j1 = S.argmax(axis=1)
    keep = np.ones(len(S), bool)
    if mutual:
        keep &= S.argmax(axis=0)[j1] == np.arange(len(S))
    if ratio is not None:
        dist_px = np.linalg.norm(r.keypoints[None, :, :] - r.keypoints[j1][:, None, :], axis=2)
        far = dist_px >= radius
        far[np.arange(len(S)), j1] = False
        s2 = np.where(far, S, -np.inf).max(axis=1)
        d1 = np.sqrt(np.maximum(2 - 2 * S[np.arange(len(S)), j1], 0))
        d2 = np.sqrt(np.maximum(2 - 2 * s2, 0))
        keep &= d1 < ratio * d2
    i = np.flatnonzero(keep)
    return np.stack([i, j1[i]], axis=1)


def test_homography_warp_recovers_true_correspondences():
    rng = np.random.default_rng(0)
    img = textured_image(rng, 300, 400)
    H = np.array([[0.95, 0.10, 12.0], [-0.08, 0.97, 8.0], [2e-4, -1e-4, 1.0]])
    warped = cv2.warpPerspective(img, H, (400, 300), flags=cv2.INTER_LINEAR, borderValue=128)
    q, r = extract_features(img), extract_features(warped)
    m = match_features(q, r)
    assert m.dtype == np.int64 and m.shape[1] == 2 and len(m) >= 80
    pred = cv2.perspectiveTransform(q.keypoints[m[:, 0]].reshape(-1, 1, 2).astype(np.float64), H).reshape(
        -1, 2
    )
    err = np.linalg.norm(r.keypoints[m[:, 1]] - pred, axis=1)
    assert np.mean(err < 2.0) >= 0.9
    assert np.all(np.diff(m[:, 0]) > 0)  # sorted, each query keypoint at most once


def test_non_mutual_pair_is_dropped():
    # q0 and q1 both prefer r0, but r0 prefers q1 -> (0, 0) is not mutual.
    q = make_features([unit(0) + 0.6 * unit(1), unit(0) + 0.1 * unit(1), unit(5)])
    r = make_features([unit(0), unit(9), unit(5) + 0.05 * unit(6)])
    m = match_features(q, r, ratio=None)
    assert {tuple(x) for x in m} == {(1, 0), (2, 2)}
    m_all = match_features(q, r, ratio=None, mutual=False)
    assert {tuple(x) for x in m_all} == {(0, 0), (1, 0), (2, 2)}


def test_ambiguous_match_fails_ratio_test_unless_neighbours_are_copies():
    # q0 is equally close to r0 and r1: ambiguous when r0 and r1 are different places ...
    q = make_features([unit(0) + unit(1) + 0.02 * unit(2), unit(7)])
    r_desc = [unit(0) + unit(1) + 0.03 * unit(3), unit(0) + unit(1) + 0.04 * unit(4), unit(7) + 0.1 * unit(8)]
    far_apart = make_features(r_desc, kp=np.array([[10.0, 10.0], [200.0, 10.0], [50.0, 90.0]]))
    assert {tuple(x) for x in match_features(q, far_apart)} == {(1, 2)}
    assert {tuple(x) for x in match_features(q, far_apart, ratio=None)} == {(0, 0), (1, 2)}
    # ... but passes FGINN when r1 is a copy of r0 at the same place (e.g. another tilt).
    copies = make_features(r_desc, kp=np.array([[10.0, 10.0], [12.0, 11.0], [50.0, 90.0]]))
    assert {tuple(x) for x in match_features(q, copies)} == {(0, 0), (1, 2)}
    assert {tuple(x) for x in match_features(q, copies, fginn_radius=0.0)} == {(1, 2)}


@pytest.mark.parametrize("radius", [0.0, 10.0])
@pytest.mark.parametrize("mutual", [True, False])
def test_blocked_matcher_equals_brute_force(monkeypatch, radius, mutual):
    rng = np.random.default_rng(1)
    base = np.abs(rng.standard_normal((300, 32)))
    qd = base[:200] + 0.3 * np.abs(rng.standard_normal((200, 32)))
    q = make_features(qd, kp=rng.random((200, 2)) * 100)
    r = make_features(base, kp=rng.random((300, 2)) * 100)
    monkeypatch.setattr(matching, "_BLOCK_ELEMENTS", 300 * 37)  # several query blocks, last one partial
    got = match_features(q, r, ratio=0.9, mutual=mutual, fginn_radius=radius)
    assert np.array_equal(got, reference_matches(q, r, 0.9, mutual, radius))
    assert len(got) > 20


def test_match_query_to_refs_equals_pairwise():
    rng = np.random.default_rng(2)
    q = make_features(np.abs(rng.standard_normal((80, 16))), kp=rng.random((80, 2)) * 50)
    refs = [
        make_features(np.abs(rng.standard_normal((n, 16))), kp=rng.random((n, 2)) * 50) for n in (60, 1, 90)
    ]
    refs.append(
        Features(np.zeros((0, 2), np.float32), np.zeros((0, 16), np.float32), np.zeros(0, np.float32))
    )
    out = match_query_to_refs(q, refs)
    assert len(out) == 4
    for r, m in zip(refs, out, strict=True):
        assert np.array_equal(m, match_features(q, r))
    assert out[3].shape == (0, 2)


def test_empty_features_give_empty_matches():
    empty = Features(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32), np.zeros(0, np.float32))
    f = make_features(np.eye(3, 128))
    for a, b in ((empty, f), (f, empty), (empty, empty)):
        m = match_features(a, b)
        assert m.shape == (0, 2) and m.dtype == np.int64


def test_bad_inputs_raise():
    f128 = make_features(np.eye(3, 128))
    f64 = make_features(np.eye(3, 64))
    with pytest.raises(InputError, match="dimensions differ"):
        match_features(f128, f64)
    with pytest.raises(InputError, match="dimensions differ"):
        match_query_to_refs(f128, [f128, f64])
    unnormalised = Features(f128.keypoints, f128.descriptors * 3.0, f128.scales)
    with pytest.raises(InputError, match="L2-normalised"):
        match_features(f128, unnormalised)
    with pytest.raises(InputError, match="keypoints"):
        match_features(f128, Features(np.zeros((2, 2), np.float32), f128.descriptors, f128.scales))
    with pytest.raises(InputError, match="Features"):
        match_features(f128, f128.descriptors)  # type: ignore[arg-type]
    for kwargs in ({"ratio": 0.0}, {"ratio": 1.5}, {"fginn_radius": -1.0}):
        with pytest.raises(InputError):
            match_features(f128, f128, **kwargs)


def _read_only(f: Features) -> Features:
    for a in (f.keypoints, f.descriptors, f.scales):
        a.setflags(write=False)
    return f


def test_features_that_can_change_are_validated_on_every_call():
    """A map image's read-only features are checked once; features that can still be written
    (writeable, or a read-only view of a writeable array) are checked again on every call."""
    q = make_features(np.eye(3, 128))
    ref = _read_only(make_features(np.eye(3, 128)))
    first = match_features(q, ref)
    assert matching._validated.get(ref) is ref.descriptors  # kept: nothing can change it
    assert np.array_equal(match_features(q, ref), first)

    writeable = make_features(np.eye(3, 128))
    match_features(q, writeable)
    assert writeable not in matching._validated
    writeable.descriptors[0] *= 3.0  # no longer unit norm: the next call must say so
    with pytest.raises(InputError, match="row 0"):
        match_features(q, writeable)

    base = make_features(np.eye(3, 128))
    view = Features(base.keypoints, base.descriptors[:], base.scales)
    view.descriptors.setflags(write=False)
    view.keypoints.setflags(write=False)
    match_features(q, view)
    assert view not in matching._validated
    base.descriptors[1] *= 2.0  # written through the writeable base
    with pytest.raises(InputError, match="row 1"):
        match_features(q, view)


def test_decoded_map_features_are_validated_once(monkeypatch):
    """Features decoded from a map (read-only, :func:`planarloc.map.codec.decode_features`) are
    norm-checked at their first match only."""
    from planarloc.map import codec

    rng = np.random.default_rng(0)
    f = make_features(rng.normal(size=(50, 128)), rng.random((50, 2)) * 500)
    kp_blob = np.concatenate([f.keypoints.ravel(), f.scales]).astype("<f4").tobytes()
    desc_blob = f.descriptors.astype("<f4").tobytes()
    decoded = codec.decode_features(50, kp_blob, 128, "float32", desc_blob, "float32")
    checks = []
    einsum = np.einsum
    monkeypatch.setattr(matching.np, "einsum", lambda *a, **k: checks.append(1) or einsum(*a, **k))
    for _ in range(3):
        match_query_to_refs(f, [decoded, decoded])
    assert len(checks) == 3 + 1  # the query once per call, the map image once in all
