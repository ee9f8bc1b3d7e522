"""COCO run-length encoding and the detection file format."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.formats.bop import (
    BopFormatError,
    Detection,
    detection_from_mask,
    load_detections,
    rle_counts_from_string,
    rle_counts_to_string,
    rle_decode,
    rle_encode,
    save_detections,
)


def test_known_rle_is_column_major():
    # Columns read top to bottom: col 0 = 0,1,0 ; col 1 = 1,1,0 -> 0 1 0 1 1 0.
    # Runs: 1 bg, 1 fg, 1 bg, 2 fg, 1 bg. (Row-major would give [1, 3, 2].)
    mask = np.array([[0, 1], [1, 1], [0, 0]], dtype=bool)
    rle = rle_encode(mask)
    assert rle == {"counts": [1, 1, 1, 2, 1], "size": [3, 2]}
    np.testing.assert_array_equal(rle_decode(rle), mask)


def test_first_pixel_set_starts_with_zero_background_run():
    mask = np.zeros((2, 2), bool)
    mask[0, 0] = True
    assert rle_encode(mask)["counts"] == [0, 1, 3]


@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (9, 1), (7, 13), (480, 640)])
def test_round_trip_edge_cases(shape):
    empty = np.zeros(shape, bool)
    full = np.ones(shape, bool)
    assert rle_encode(empty)["counts"] == [empty.size]
    assert rle_encode(full)["counts"] == [0, full.size]
    rng = np.random.default_rng(sum(shape))
    for density in (0.05, 0.5, 0.95):
        m = rng.random(shape) < density
        for mask in (m, empty, full):
            rle = rle_encode(mask)
            assert sum(rle["counts"]) == mask.size
            np.testing.assert_array_equal(rle_decode(rle), mask)
            # The compressed (string) form decodes to the same mask.
            compressed = {"counts": rle_counts_to_string(rle["counts"]), "size": rle["size"]}
            np.testing.assert_array_equal(rle_decode(compressed), mask)


def test_compressed_string_hand_derived():
    # counts [5, 40, 3, 10] in pycocotools' string form, derived by hand:
    #   5  -> one chunk 5, no continuation                    -> chr(48+5)  = '5'
    #   40 -> chunks 8 (|0x20 more) then 1                     -> chr(88) chr(49) = 'X1'
    #   3  -> '3'
    #   10 -> 4th count stores 10 - counts[1] = -30: low 5 bits 2 with more (34 -> 'R'),
    #         then 31 (sign bit 0x10 set, stop)                -> chr(79) = 'O'
    assert rle_counts_from_string("5X13RO") == [5, 40, 3, 10]
    assert rle_counts_to_string([5, 40, 3, 10]) == "5X13RO"
    mask = rle_decode({"counts": "5X13RO", "size": [2, 29]})
    expected = np.repeat([False, True, False, True], [5, 40, 3, 10]).reshape((2, 29), order="F")
    np.testing.assert_array_equal(mask, expected)


def test_decode_rejects_wrong_total():
    with pytest.raises(ValueError, match="sum to 5"):
        rle_decode({"counts": [2, 3], "size": [2, 2]})


def _entry(**over):
    mask = np.zeros((4, 5), bool)
    mask[1:3, 2:4] = True
    d = detection_from_mask(1, 0, 7, 0.8, mask, time=0.5).to_json()
    d.update(over)
    return d


def test_detections_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    dets = [detection_from_mask(2, i, i + 1, 0.1 * i, rng.random((6, 8)) < 0.3, time=1.25) for i in range(4)]
    path = tmp_path / "dets.json"
    save_detections(path, dets)
    back = load_detections(path)
    assert back == dets
    for d, b in zip(dets, back):
        np.testing.assert_array_equal(b.mask(), d.mask())
    # One detection per line, inside [ ... ].
    lines = path.read_text().splitlines()
    assert lines[0] == "[" and lines[-1] == "]" and len(lines) == len(dets) + 2


def test_detection_bbox_from_mask():
    mask = np.zeros((10, 10), bool)
    mask[2:5, 3:9] = True
    d = detection_from_mask(1, 2, 3, 0.5, mask)
    assert d.bbox == (3.0, 2.0, 5.0, 2.0)  # BOP toolkit convention: max - min
    assert d.obj_id == 3 and d.time == -1.0


@pytest.mark.parametrize(
    "bad, field",
    [
        (_entry(bbox=[0, 1, 2]), "bbox"),
        (_entry(score="high"), "score"),
        (_entry(category_id=1.5), "category_id"),
        (_entry(segmentation={"counts": [1, 2], "size": [4, 5]}), "segmentation"),
        ({k: v for k, v in _entry().items() if k != "image_id"}, "image_id"),
    ],
)
def test_detection_validation_names_entry_and_field(tmp_path, bad, field):
    path = tmp_path / "dets.json"
    path.write_text(json.dumps([_entry(), _entry(), bad]))
    with pytest.raises(BopFormatError) as info:
        load_detections(path)
    msg = str(info.value)
    assert str(path) in msg and "entry 2" in msg and f"field '{field}'" in msg


def test_detections_accept_compressed_counts_and_missing_time(tmp_path):
    entry = _entry()
    entry["segmentation"] = {"counts": rle_counts_to_string(entry["segmentation"]["counts"]), "size": [4, 5]}
    del entry["time"]
    path = tmp_path / "d.json"
    path.write_text(json.dumps([entry]))
    (det,) = load_detections(path)
    assert isinstance(det, Detection) and det.time == -1.0
    assert det.mask().sum() == 4 and det.mask()[1:3, 2:4].all()
