"""The verification's comparison in torch (issue 31's GPU path) against the numpy one, on
the CPU: the same terms to the bit, for windows with every kind of pixel (agreeing,
occluded, in front of the observed surface, sensor holes, outside the mask)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.method.refinement.verification import compare_depth, verify_poses
from pipeline.method.refinement.verification_torch import compare_depth_batch


def _windows(seed: int, B: int = 6, h: int = 40, w: int = 50) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """B rendered windows (B, h, w) float32 mm of a box at 800 mm moved by each pose,
    one observed window (h, w) with an occluder, holes and a background wall, and a mask."""
    rng = np.random.default_rng(seed)
    observed = np.full((h, w), 1200.0, np.float32)
    observed[8:30, 10:38] = 800.0 + rng.normal(0.0, 2.0, (22, 28)).astype(np.float32)
    observed[20:26, 5:20] = 650.0  # an occluder in front of the object
    observed[rng.random((h, w)) < 0.05] = 0.0  # sensor holes
    mask = np.zeros((h, w), bool)
    mask[9:31, 11:37] = True
    rendered = np.zeros((B, h, w), np.float32)
    for b in range(B):
        dy, dx = rng.integers(-6, 7, 2)
        y0, x0 = 8 + dy, 10 + dx
        rendered[b, max(y0, 0):y0 + 22, max(x0, 0):x0 + 28] = 800.0 + b * 6.0 + rng.normal(0.0, 1.0)
    rendered[1] = 0.0  # a pose that renders nothing in the window
    return rendered, observed, mask


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_torch_terms_are_numpys_to_the_bit(seed):
    rendered, observed, mask = _windows(seed)
    evidence = np.linspace(0.0, 0.25, len(rendered))
    for tol in (5.0, 10.0, 17.3):
        got = compare_depth_batch(rendered, observed, mask, tol, evidence, device="cpu")
        want = [compare_depth(r, observed, mask, tol, e) for r, e in zip(rendered, evidence)]
        assert got == want  # dataclass equality: every term and the value, exactly
    assert {v.free_space > 0 for v in want} == {True, False} and any(v.silhouette == 0.0 for v in want)


def test_a_tolerance_on_a_float32_boundary_decides_as_numpy_does():
    """A difference of exactly 0.25 mm against a tolerance just below it that rounds to
    0.25 in float32: numpy compares the float32 depths with the tolerance in float32
    (agreeing), and so must torch (in float64 the pixels would be free space)."""
    tol = 0.25 - 1e-9
    observed = np.full((4, 4), 500.0, np.float32)
    rendered = np.full((2, 4, 4), 499.75, np.float32)
    mask = np.ones((4, 4), bool)
    got = compare_depth_batch(rendered, observed, mask, tol, [0.0, 0.1], device="cpu")
    assert got == [compare_depth(r, observed, mask, tol, e) for r, e in zip(rendered, [0.0, 0.1])]
    assert got[0].depth_fit == 1.0 and got[0].free_space == 0.0


def test_an_empty_mask_and_no_renders():
    rendered, observed, _ = _windows(3, B=2)
    mask = np.zeros_like(observed, dtype=bool)
    got = compare_depth_batch(rendered, observed, mask, 5.0, [0.0, 0.0], device="cpu")
    assert got == [compare_depth(r, observed, mask, 5.0) for r in rendered] and got[0].coverage == 0.0
    assert compare_depth_batch(np.zeros((0, 40, 50), np.float32), observed, mask, 5.0, [], device="cpu") == []


def test_mismatched_windows_and_evidence_are_refused():
    rendered, observed, mask = _windows(0, B=2)
    with pytest.raises(ValueError, match="windows differ"):
        compare_depth_batch(rendered[:, :-1], observed, mask, 5.0, [0.0, 0.0], device="cpu")
    with pytest.raises(ValueError, match="3 evidence values for 2 renders"):
        compare_depth_batch(rendered, observed, mask, 5.0, [0.0, 0.0, 0.0], device="cpu")


class _Crops:
    """A renderer that hands out prepared windows in order, as Renderer.render_depth_crop."""

    def __init__(self, crops: np.ndarray):
        self.crops, self.asked = list(crops), []

    def render_depth_crop(self, key, R, t, K, window):
        self.asked.append((key, window))
        return self.crops.pop(0)


def test_verify_poses_compares_every_render_on_both_paths():
    """verify_poses cuts the window out of the image's depth and mask, renders each pose
    once, and gives the same verifications in numpy and in torch."""
    rendered, observed, mask = _windows(4, B=3)
    depth = np.zeros((100, 120), np.float32)
    full_mask = np.zeros((100, 120), bool)
    window = (30, 20, 50, 40)  # x0, y0, w, h
    depth[20:60, 30:80], full_mask[20:60, 30:80] = observed, mask
    poses = [(np.eye(3), np.zeros(3))] * 3
    out = {}
    for device in (None, "cpu"):
        renderer = _Crops(rendered)
        out[device] = verify_poses(renderer, 7, poses, np.eye(3), depth, full_mask, window, 8.0, [0.0, 0.1, 0.2],
                                   device)
        assert renderer.asked == [(7, window)] * 3
    assert out["cpu"] == out[None] == [compare_depth(r, observed, mask, 8.0, e)
                                       for r, e in zip(rendered, [0.0, 0.1, 0.2])]
