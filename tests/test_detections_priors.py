"""Localisation priors: file variants, category id mapping, merging several prior files."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from pipeline.formats.bop import (
    BopFormatError,
    category_id_problem,
    detection_from_mask,
    load_detections,
    map_category_ids,
    merge_detections,
    rle_counts_to_string,
)
from pipeline.formats.bop.detections import _mask_iou, _MaskGeom
from pipeline.method.segmentation import select_candidates

LMO_OBJ_IDS = [1, 5, 6, 8, 9, 10, 11, 12]
H, W = 40, 50


def _rect(y0: int, y1: int, x0: int, x1: int, shape: tuple[int, int] = (H, W)) -> np.ndarray:
    """(H, W) bool mask, True on rows y0..y1-1 and columns x0..x1-1."""
    m = np.zeros(shape, bool)
    m[y0:y1, x0:x1] = True
    return m


def _canonical_entry() -> dict:
    return detection_from_mask(3, 17, 5, 0.75, _rect(1, 3, 2, 4, (4, 5)), time=0.25).to_json()


def _write(tmp_path, content, name="dets.json"):
    path = tmp_path / name
    path.write_text(json.dumps(content))
    return path


# ---------------------------------------------------------------------------- reading variants


def test_aliases_load_to_the_same_detection(tmp_path):
    canonical = _canonical_entry()
    alias = dict(canonical)
    alias["im_id"] = alias.pop("image_id")
    alias["obj_id"] = alias.pop("category_id")
    both = dict(canonical, im_id=17, obj_id=5)  # both spellings, agreeing
    (ref,) = load_detections(_write(tmp_path, [canonical], "c.json"))
    (a,) = load_detections(_write(tmp_path, [alias], "a.json"))
    (b,) = load_detections(_write(tmp_path, [both], "b.json"))
    assert a == ref and b == ref
    assert (ref.scene_id, ref.image_id, ref.category_id, ref.time, ref.source) == (3, 17, 5, 0.25, "")


def test_integral_floats_and_null_time(tmp_path):
    canonical = _canonical_entry()
    floats = dict(canonical, scene_id=3.0, image_id=17.0, category_id=5.0, time=None)
    floats["segmentation"] = {"counts": [float(c) for c in canonical["segmentation"]["counts"]], "size": [4.0, 5.0]}
    (d,) = load_detections(_write(tmp_path, [floats]))
    (ref,) = load_detections(_write(tmp_path, [canonical], "c.json"))
    assert d.time == -1.0 and replace(d, time=0.25) == ref
    assert all(type(c) is int for c in d.segmentation["counts"]) and d.segmentation["size"] == [4, 5]
    assert d.to_json()["segmentation"] == canonical["segmentation"]


def test_source_is_stored_but_never_written(tmp_path):
    (d,) = load_detections(_write(tmp_path, [_canonical_entry()]), source="cnos")
    assert d.source == "cnos"
    assert "source" not in d.to_json()


def test_disagreeing_aliases_raise_with_file_entry_field(tmp_path):
    bad = dict(_canonical_entry(), obj_id=6)  # category_id is 5
    path = _write(tmp_path, [_canonical_entry(), bad])
    with pytest.raises(BopFormatError) as info:
        load_detections(path)
    msg = str(info.value)
    assert str(path) in msg and "entry 1" in msg and "field 'category_id'" in msg and "'obj_id'" in msg
    bad = dict(_canonical_entry(), im_id=18)
    with pytest.raises(BopFormatError, match=r"entry 0, field 'image_id': 17 disagrees with 'im_id' = 18"):
        load_detections(_write(tmp_path, [bad]))


@pytest.mark.parametrize("drop", [True, False])
def test_missing_segmentation_says_masks_are_needed(tmp_path, drop):
    bad = _canonical_entry()
    if drop:
        del bad["segmentation"]
    else:
        bad["segmentation"] = None
    path = _write(tmp_path, [_canonical_entry(), _canonical_entry(), bad])
    with pytest.raises(BopFormatError) as info:
        load_detections(path)
    msg = str(info.value)
    assert str(path) in msg and "entry 2" in msg and "field 'segmentation'" in msg
    assert "instance mask" in msg and "2D boxes only" in msg


def test_top_level_object_is_rejected(tmp_path):
    path = _write(tmp_path, {"detections": [_canonical_entry()]})
    with pytest.raises(BopFormatError, match=r"dets\.json: expected a JSON list of detections.*'detections'"):
        load_detections(path)


# ---------------------------------------------------------------------------- category ids


def _dets_with_ids(ids):
    return [detection_from_mask(1, 0, c, 0.5, _rect(0, 2, 0, 2, (4, 4))) for c in ids]


def test_map_category_ids_index0_on_lmo():
    dets = _dets_with_ids(range(8))
    mapped = map_category_ids(dets, LMO_OBJ_IDS, mode="index0")
    assert [d.category_id for d in mapped] == LMO_OBJ_IDS
    assert mapped[0].category_id == 1 and mapped[7].category_id == 12
    assert [d.category_id for d in dets] == list(range(8))  # inputs untouched
    with pytest.raises(BopFormatError) as info:
        map_category_ids(_dets_with_ids([0, 3, 8]), LMO_OBJ_IDS, mode="index0", path="x/prior.json")
    msg = str(info.value)
    assert msg.startswith("x/prior.json: entry 2, field 'category_id': 8")


def test_map_category_ids_index1_and_identity():
    assert [d.category_id for d in map_category_ids(_dets_with_ids([1, 8]), LMO_OBJ_IDS, "index1")] == [1, 12]
    with pytest.raises(BopFormatError, match="entry 0, field 'category_id': 0"):
        map_category_ids(_dets_with_ids([0]), LMO_OBJ_IDS, "index1")
    same = map_category_ids(_dets_with_ids([5, 99]), LMO_OBJ_IDS, "obj_id")
    assert [d.category_id for d in same] == [5, 99]
    with pytest.raises(ValueError, match="index0"):
        map_category_ids(_dets_with_ids([5]), LMO_OBJ_IDS, "index2")


def test_category_id_problem():
    assert category_id_problem(_dets_with_ids(LMO_OBJ_IDS), LMO_OBJ_IDS) is None
    assert category_id_problem([], LMO_OBJ_IDS) is None
    msg = category_id_problem(_dets_with_ids(range(8)), LMO_OBJ_IDS)
    assert msg is not None and "'index0'" in msg and "'index1'" not in msg
    assert msg.startswith("5 of 8 detections") and "[0, 2, 3, 4, 7]" in msg  # not LM-O objects
    msg = category_id_problem(_dets_with_ids(range(2, 9)), LMO_OBJ_IDS)  # 2..8 only fits 1-based
    assert "'index1'" in msg and "'index0'" not in msg
    msg = category_id_problem(_dets_with_ids([1, 2, 3]), LMO_OBJ_IDS)  # fits both
    assert "'index0'" in msg and "'index1'" in msg
    msg = category_id_problem(_dets_with_ids([1, 99]), LMO_OBJ_IDS)  # fits neither
    assert "[99]" in msg and "index" not in msg


# ---------------------------------------------------------------------------- merging


def _det(mask, score, obj=1, image=0):
    return detection_from_mask(1, image, obj, score, mask)


A_INST = _rect(5, 25, 5, 25)        # 20 x 20 = 400 px
B_COPY = _rect(6, 26, 5, 25)        # shifted one row: IoU 380 / 420 = 0.905
B_NEW = _rect(30, 38, 30, 46)       # disjoint from everything


def test_mask_iou_known_answer_and_bound():
    a, b = _MaskGeom(_det(A_INST, 1).segmentation), _MaskGeom(_det(B_COPY, 1).segmentation)
    assert a.box == (5, 5, 24, 24) and a.area == 400
    assert _mask_iou(a, b) == pytest.approx(380 / 420)
    assert _mask_iou(a, _MaskGeom(_det(B_NEW, 1).segmentation)) == 0.0
    half = _MaskGeom(_det(_rect(5, 25, 5, 15), 1).segmentation)
    assert _mask_iou(a, half) == 0.5


def test_mask_geometry_matches_numpy_on_random_masks():
    rng = np.random.default_rng(0)
    for trial in range(30):
        shape = (int(rng.integers(1, 30)), int(rng.integers(1, 30)))
        ma = rng.random(shape) < rng.uniform(0.01, 0.9)
        mb = rng.random(shape) < rng.uniform(0.01, 0.9)
        da, db = _det(ma, 1), _det(mb, 1)
        if trial % 2:
            da.segmentation = {"counts": rle_counts_to_string(da.segmentation["counts"]), "size": list(shape)}
        ga, gb = _MaskGeom(da.segmentation), _MaskGeom(db.segmentation)
        ys, xs = np.nonzero(ma)
        if len(xs):
            assert ga.box == (xs.min(), ys.min(), xs.max(), ys.max())
            np.testing.assert_array_equal(ga.crop(), ma[ys.min():ys.max() + 1, xs.min():xs.max() + 1])
        else:
            assert ga.box is None
        union = (ma | mb).sum()
        expected = (ma & mb).sum() / union if union else 0.0
        assert _mask_iou(ga, gb) == pytest.approx(expected)


def test_merge_drops_the_less_confident_cross_source_copy():
    a = [_det(A_INST, 0.9)]
    b = [_det(B_COPY, 0.8), _det(B_NEW, 0.7)]
    merged, report = merge_detections([("A", a), ("B", b)], iou_threshold=0.5)
    assert merged == [replace(a[0], source="A"), replace(b[1], source="B")]
    assert report["iou_threshold"] == 0.5
    assert (report["n_read"], report["n_kept"], report["n_dropped_duplicates"]) == (3, 2, 1)
    assert report["sources"]["A"] == {"n_read": 1, "n_kept": 1, "n_dropped_duplicates": 0, "duplicate_of": {}}
    assert report["sources"]["B"] == {"n_read": 2, "n_kept": 1, "n_dropped_duplicates": 1, "duplicate_of": {"A": 1}}
    json.dumps(report)  # goes into a stage summary
    # Above the copy's IoU nothing is a duplicate.
    merged, report = merge_detections([("A", a), ("B", b)], iou_threshold=0.95)
    assert len(merged) == 3 and report["n_dropped_duplicates"] == 0


def test_merge_keeps_the_more_confident_source():
    a = [_det(A_INST, 0.6)]
    b = [_det(B_COPY, 0.8), _det(B_NEW, 0.7)]
    merged, report = merge_detections([("A", a), ("B", b)])
    assert merged == [replace(b[0], source="B"), replace(b[1], source="B")]
    assert report["sources"]["A"]["n_dropped_duplicates"] == 1 and report["sources"]["A"]["duplicate_of"] == {"B": 1}
    assert report["sources"]["B"]["n_kept"] == 2


def test_merge_tie_goes_to_the_first_source_and_iou_at_threshold_is_a_duplicate():
    a = [_det(A_INST, 0.5)]
    b = [_det(_rect(5, 25, 5, 15), 0.5)]  # IoU exactly 0.5, same score
    merged, _ = merge_detections([("A", a), ("B", b)], iou_threshold=0.5)
    assert [d.source for d in merged] == ["A"]
    merged, _ = merge_detections([("B", b), ("A", a)], iou_threshold=0.5)
    assert [d.source for d in merged] == ["B"]


def test_merge_never_suppresses_within_a_source():
    a = [_det(A_INST, 0.9), _det(B_COPY, 0.8)]  # the detector's own two overlapping instances
    b = [_det(B_NEW, 0.7)]
    merged, report = merge_detections([("A", a), ("B", b)])
    assert merged == [replace(a[0], source="A"), replace(a[1], source="A"), replace(b[0], source="B")]
    assert report["n_dropped_duplicates"] == 0


def test_merge_only_compares_within_scene_image_category():
    a = [_det(A_INST, 0.9, obj=1)]
    b = [_det(A_INST, 0.8, obj=2), _det(A_INST, 0.8, obj=1, image=1)]
    merged, report = merge_detections([("A", a), ("B", b)])
    assert len(merged) == 3 and report["n_dropped_duplicates"] == 0


def test_single_source_comes_back_unchanged():
    rng = np.random.default_rng(1)
    dets = [_det(rng.random((H, W)) < 0.4, float(s), obj=int(o)) for s, o in zip(rng.random(6), [1, 1, 2, 1, 2, 1])]
    merged, report = merge_detections([("cnos", dets)])
    assert merged == [replace(d, source="cnos") for d in dets]
    assert report["sources"]["cnos"] == {"n_read": 6, "n_kept": 6, "n_dropped_duplicates": 0, "duplicate_of": {}}


def test_compressed_rle_merges_like_its_list_form():
    def compressed(d):
        return replace(d, segmentation={"counts": rle_counts_to_string(d.segmentation["counts"]),
                                        "size": d.segmentation["size"]})

    a = [_det(A_INST, 0.9)]
    b = [_det(B_COPY, 0.8), _det(B_NEW, 0.7)]
    _, ref = merge_detections([("A", a), ("B", b)])
    merged, report = merge_detections([("A", a), ("B", [compressed(d) for d in b])])
    assert report == ref
    assert merged[1].segmentation["counts"] == rle_counts_to_string(b[1].segmentation["counts"])  # own mask kept


def test_merge_rejects_bad_arguments():
    a = [_det(A_INST, 0.9)]
    with pytest.raises(ValueError, match="unique"):
        merge_detections([("A", a), ("A", a)])
    with pytest.raises(ValueError, match="iou_threshold"):
        merge_detections([("A", a)], iou_threshold=0.0)
    other_size = [_det(_rect(5, 25, 5, 25, (41, 50)), 0.5)]
    with pytest.raises(BopFormatError, match=r"B: entry 0, field 'segmentation': mask size 41x50 differs"):
        merge_detections([("A", a), ("B", other_size)])


# ---------------------------------------------------------------------------- candidates


class _Target:
    def __init__(self, scene_id, im_id, obj_id, inst_count=1):
        self.scene_id, self.im_id, self.obj_id, self.inst_count = scene_id, im_id, obj_id, inst_count


def test_select_candidates_carries_prior_source():
    merged, _ = merge_detections([("A", [_det(A_INST, 0.9)]), ("B", [_det(B_NEW, 0.7)])])
    table, _ = select_candidates(merged + [_det(B_COPY, 0.1)], [_Target(1, 0, 1, inst_count=3)], top_k=1)
    assert list(table.columns)[-1] == "prior_source"
    assert table["prior_source"].tolist() == ["A", "B", ""]
